"""One page per `examples/*.py`: its docstring, its figures from `examples/figures/` and its
source. The scripts are read, never run, at build time."""

from __future__ import annotations

import ast
import pathlib

from mkdocs.structure.files import File

ROOT = pathlib.Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"
SECTION = "Examples"


def scripts() -> list[pathlib.Path]:
    return sorted(EXAMPLES.glob("*.py"))


def split_docstring(source: str) -> tuple[str, str]:
    """The script's first docstring line (its title) and the rest of its docstring."""
    doc = ast.get_docstring(ast.parse(source)) or ""
    first, _, rest = doc.partition("\n\n")
    return " ".join(first.split()).rstrip("."), rest.strip()


def figures(source: str) -> list[str]:
    """The figures of `examples/figures/` that the script names."""
    return [f.name for f in sorted((EXAMPLES / "figures").iterdir()) if f.name in source]


def page(path: pathlib.Path) -> str:
    source = path.read_text()
    title, rest = split_docstring(source)
    parts = [f"# {path.name}", "", f"*{title}.*", "", rest, ""]
    for name in figures(source):
        parts += [f"![{name}](figures/{name})", ""]
    parts += [
        "## Source",
        "",
        f"Run from the repository root: `python examples/{path.name}`.",
        "",
        "```python",
        source.rstrip(),
        "```",
        "",
    ]
    return "\n".join(parts)


def index() -> str:
    parts = [
        "# Examples",
        "",
        "Scripts in `examples/` that use the public API. Each page shows the script's "
        "description, the figure it writes to `examples/figures/` and its source. Run "
        "one from the repository root, after `pip install -e .`, with "
        "`python examples/<name>.py`.",
        "",
    ]
    for path in scripts():
        title, _ = split_docstring(path.read_text())
        parts.append(f"- [`{path.name}`]({path.stem}.md): {title}.")
    return "\n".join(parts) + "\n"


def on_config(config):
    """Expand the nav entry `Examples: examples/index.md` into the section of pages."""
    entries = [{"Overview": "examples/index.md"}]
    entries += [{path.name: f"examples/{path.stem}.md"} for path in scripts()]
    for i, item in enumerate(config["nav"] or []):
        if isinstance(item, dict) and SECTION in item:
            config["nav"][i] = {SECTION: entries}
    return config


def on_files(files, config):
    files.append(File.generated(config, "examples/index.md", content=index()))
    for path in scripts():
        files.append(File.generated(config, f"examples/{path.stem}.md", content=page(path)))
    return files
