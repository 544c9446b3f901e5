"""Figures have one home, `benchmarks/RESULTS.md`: code, tests, README, docs pages and examples
give guidance, not measurement logs (ratios such as "0.93x", dates, machine names, before/after
figures such as "13.5 -> 8.4 s")."""

import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).parents[1]

PATTERNS = {
    "a measured ratio": re.compile(r"\b\d+\.\d+x\b|\b\d+(\.\d+)?-\d+(\.\d+)?x\b"),
    "a date": re.compile(r"\b20\d\d-\d\d-\d\d\b"),
    "a machine": re.compile(r"\bGHz\b|\bEPYC\b|\bXeon\b|\bH100\b|\bH200\b|\bA100\b"),
    "a before/after figure": re.compile(r"(?<![\w.])\d+(\.\d+)?( ?[a-zA-Z/%]+)? -> \d"),
}

ALLOWED: dict[str, tuple[str, ...]] = {
    # (file, text on the line that makes it guidance, not a log)
    "tests/test_no_measurement_logs.py": ("re.compile", '"0.93x"', '"13.5 -> 8.4 s"'),
}


def _files():
    out = []
    for folder, pattern in (
        ("tippejax", "*.py"),
        ("tests", "*.py"),
        ("docs", "*.md"),
        ("examples", "*.py"),
        ("examples", "*.md"),
    ):
        out += sorted((ROOT / folder).rglob(pattern))
    out += [ROOT / "README.md", ROOT / "CONTRIBUTING.md"]
    # the performance page includes RESULTS.md, the one home of the figures
    return [p for p in out if p.exists() and p.name != "performance.md"]


@pytest.mark.parametrize("path", _files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_measurement_logs(path):
    rel = str(path.relative_to(ROOT))
    found = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if any(text in line for text in ALLOWED.get(rel, ())):
            continue
        for what, pattern in PATTERNS.items():
            if pattern.search(line):
                found.append(f"{rel}:{number}: {what}: {line.strip()}")
    assert not found, (
        "measured figures belong in benchmarks/RESULTS.md (the section its benchmark writes); "
        "here give guidance and link to the performance page:\n" + "\n".join(found)
    )
