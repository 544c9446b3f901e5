"""Every ```python block of README.md and docs/**/*.md runs, and prints what the page shows.

The blocks of one page run in order in one namespace. What a block prints is checked against
the page: the ```text block right after it, or else the block's own `# prints: ...` comments,
one printed line each. Numbers may differ by one unit in the last digit the page shows
(rounding), printed to as many digits; everything else must match. A block with an HTML comment `<!-- no-test -->` on the
line before it is not run (a GPU, several processes, a run of minutes).

`python tests/test_docs.py PAGE.md` prints what each block of a page prints, to write a page.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import math
import os
import pathlib
import re
import sys
import textwrap

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
SKIP = "<!-- no-test -->"
PRINTS = re.compile(r"#\s*prints:\s?(.*)$")
NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?|\bnan\b|\binf\b")


@dataclasses.dataclass
class Block:
    line: int  # of the opening fence, 1-based
    code: str
    expected: str | None  # the output the page shows; None where it shows none
    skip: bool


def pages() -> list[pathlib.Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def blocks(text: str) -> list[Block]:
    """The ```python blocks of a markdown text, each with the output the page shows for it."""
    lines = text.splitlines()
    found: list[Block] = []
    i = 0
    while i < len(lines):
        if lines[i].strip() != "```python":
            i += 1
            continue
        before = next((s.strip() for s in reversed(lines[:i]) if s.strip()), "")
        end = next(j for j in range(i + 1, len(lines)) if lines[j].strip().startswith("```"))
        code = textwrap.dedent("\n".join(lines[i + 1 : end]))  # a block in a list is indented
        after = end + 1
        while after < len(lines) and not lines[after].strip():
            after += 1
        expected = None
        if after < len(lines) and lines[after].strip() == "```text":
            close = next(
                j for j in range(after + 1, len(lines)) if lines[j].strip().startswith("```")
            )
            expected = textwrap.dedent("\n".join(lines[after + 1 : close]))
        else:
            shown = [m[1] for m in map(PRINTS.search, code.splitlines()) if m]
            expected = "\n".join(shown) if shown else None
        found.append(Block(i + 1, code, expected, before == SKIP))
        i = end + 1
    return found


def _unit(token: str) -> float:
    """One unit in the last digit of a printed number."""
    mantissa, _, exponent = token.lower().partition("e")
    decimals = len(mantissa.partition(".")[2])
    return 10.0 ** (int(exponent or 0) - decimals)


def same_line(actual: str, expected: str) -> bool:
    if NUMBER.sub("#", actual).split() != NUMBER.sub("#", expected).split():
        return False
    for a, e in zip(NUMBER.findall(actual), NUMBER.findall(expected), strict=True):
        if e in ("nan", "inf") or a in ("nan", "inf"):
            if a.lstrip("+-") != e.lstrip("+-") or (e[0] == "-") != (a[0] == "-"):
                return False
        elif _unit(a) != _unit(e) or not math.isclose(
            float(a), float(e), rel_tol=1e-12, abs_tol=1.001 * _unit(e)
        ):
            return False
    return True


def same_output(actual: str, expected: str) -> bool:
    """Whether printed text matches a page's: line by line, numbers to the digits shown."""
    a = [s.rstrip() for s in actual.strip("\n").splitlines()]
    e = [s.rstrip() for s in expected.strip("\n").splitlines()]
    return len(a) == len(e) and all(map(same_line, a, e))


def run_page(path: pathlib.Path, report=None) -> int:
    """Run a page's blocks in order in one namespace; returns how many ran."""
    namespace: dict = {"__name__": "__main__"}
    ran = 0
    for block in blocks(path.read_text()):
        if block.skip:
            continue
        out = io.StringIO()
        where = f"{path.relative_to(ROOT)}:{block.line}"
        with contextlib.redirect_stdout(out):
            exec(compile(block.code, where, "exec"), namespace)  # noqa: S102
        ran += 1
        if report is not None:
            report(where, out.getvalue())
        elif block.expected is not None:
            assert same_output(out.getvalue(), block.expected), (
                f"{where} printed\n{out.getvalue()}\nbut the page shows\n{block.expected}"
            )
    return ran


PAGES_WITH_CODE = [p for p in pages() if any(not b.skip for b in blocks(p.read_text()))]


@pytest.mark.parametrize("path", PAGES_WITH_CODE, ids=lambda p: str(p.relative_to(ROOT)))
def test_page_runs_and_prints_what_it_shows(path, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # whatever a block writes lands here
    monkeypatch.setenv("MPLBACKEND", "Agg")
    assert run_page(path) > 0


def test_pages_have_code():
    """The README and the guide's pages hold code that runs (the extractor finds it)."""
    names = {p.relative_to(ROOT).as_posix() for p in PAGES_WITH_CODE}
    assert {"README.md", "docs/index.md", "docs/simulation.md"} <= names


def test_readme_links_resolve():
    """The README's relative links (to the docs pages, on GitHub) name files that exist."""
    targets = re.findall(r"\]\((?!https?://|#)([^)#\s]+)", (ROOT / "README.md").read_text())
    assert targets and [t for t in targets if not (ROOT / t).exists()] == []


def test_the_extractor_reads_outputs_and_skips():
    page = "\n".join(
        [
            "```python",
            "print(1.25)  # prints: 1.25",
            "```",
            "",
            "<!-- no-test -->",
            "```python",
            "raise SystemExit",
            "```",
            "```python",
            "print('a', 2)",
            "```",
            "",
            "```text",
            "a 2",
            "```",
            "```python",
            "x = 1",
            "```",
        ]
    )
    found = blocks(page)
    assert [(b.skip, b.expected) for b in found] == [
        (False, "1.25"),
        (True, None),
        (False, "a 2"),
        (False, None),
    ]


@pytest.mark.parametrize(
    ("actual", "expected", "same"),
    [
        ("t = 5.701", "t = 5.70", False),  # more digits than shown are still held to them
        ("t = 5.70", "t = 5.70", True),
        ("t = 5.71", "t = 5.70", True),  # one unit in the last digit shown
        ("t = 5.72", "t = 5.70", False),
        ("t = 5.70 s", "t = 5.70", False),  # words must match
        ("1.0e-06", "1.1e-06", True),
        ("1.0e-06", "1.2e-06", False),
        ("nan", "nan", True),
        ("nan", "5.70", False),
        ("IIb", "IIa", False),
        ("a\nb", "a", False),
    ],
)
def test_outputs_are_compared_to_the_digits_shown(actual, expected, same):
    assert same_output(actual, expected) == same


if __name__ == "__main__":  # print what each block of a page prints
    os.environ.setdefault("MPLBACKEND", "Agg")
    for name in sys.argv[1:]:
        run_page(
            pathlib.Path(name).resolve(),
            report=lambda where, text: sys.__stdout__.write(f"--- {where}\n{text}"),
        )
