"""`tippejax diagram`: the six bifurcation diagrams (the paper's Fig. 1) and the group map."""

from __future__ import annotations

import os

from .._plot import bifurcation_diagrams
from .common import REPRESENTATIVES, representative_tops, save, use_agg, write_group_map


def write_diagrams(out: str) -> list[str]:
    """Write `bifurcation_diagrams.png` and `group_map.png` to the folder `out`."""
    use_agg()
    fig = bifurcation_diagrams(representative_tops())
    paths = [save(fig, os.path.join(out, "bifurcation_diagrams.png"))]
    paths.append(write_group_map(out, points=REPRESENTATIVES))
    return paths


def run(args) -> int:
    os.makedirs(args.out, exist_ok=True)
    for name, (a, e) in REPRESENTATIVES.items():
        print(f"Group {name:3s}: A/C = {a:g}, eps/R = {e:g}")
    for path in write_diagrams(args.out):
        print(f"wrote {path}")
    return 0
