"""The Performance page includes `benchmarks/RESULTS.md` as it is at build time: its headings one
level down, its figures and relative links named as repository files (the figures stay in
`benchmarks/`, out of the site)."""

from __future__ import annotations

import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parents[2]
RESULTS = ROOT / "benchmarks" / "RESULTS.md"
MARKER = "<!-- include: benchmarks/RESULTS.md -->"
IMAGE = re.compile(r"!\[([^\]]*)\]\(([^)\s]+)[^)]*\)")
LINK = re.compile(r"(?<!!)\[([^\]]+)\]\((?!https?://|#)([^)\s]+)[^)]*\)")


def include(text: str) -> str:
    out, fence = [], False
    for line in text.splitlines():
        if line.lstrip().startswith(("```", "~~~")):
            fence = not fence
        elif not fence:
            if line.startswith("#"):
                line = "#" + line
            line = IMAGE.sub(lambda m: f"*(figure `benchmarks/{m[2]}` in the repository)*", line)
            line = LINK.sub(lambda m: f"{m[1]} (`benchmarks/{m[2]}`)", line)
        out.append(line)
    return "\n".join(out) + "\n"


def on_page_markdown(markdown, page, config, files):
    if MARKER in markdown:
        markdown = markdown.replace(MARKER, include(RESULTS.read_text()))
    return markdown
