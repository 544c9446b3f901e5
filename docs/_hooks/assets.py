"""Static files the site takes from elsewhere: MathJax from its PyPI package, example figures."""

from __future__ import annotations

import pathlib

from mkdocs.structure.files import File

ROOT = pathlib.Path(__file__).resolve().parents[2]
MATHJAX = "tex-svg-full.js"  # SVG output: no web fonts to fetch, so maths renders offline


def mathjax_script() -> pathlib.Path:
    """MathJax 3's combined TeX-to-SVG script, from the `django-static-mathjax` package (an
    import named `mathjax` holding MathJax's own distribution; no Django needed)."""
    import mathjax

    path = pathlib.Path(mathjax.__file__).parent / "static" / "mathjax" / "es5" / MATHJAX
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: pip install -e '.[docs]'")
    return path


def on_files(files, config):
    files.append(
        File.generated(config, f"assets/mathjax/{MATHJAX}", abs_src_path=str(mathjax_script()))
    )
    for figure in sorted((ROOT / "examples" / "figures").iterdir()):
        if figure.suffix in (".png", ".gif", ".svg", ".jpg"):
            files.append(
                File.generated(config, f"examples/figures/{figure.name}", abs_src_path=str(figure))
            )
    return files
