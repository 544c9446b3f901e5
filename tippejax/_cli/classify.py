"""`tippejax classify`: the group and thresholds of a top, and the map of the groups."""

from __future__ import annotations

import os

from .._top import TippeTop, default_top
from .common import print_top, write_group_map


def run(args) -> int:
    if (args.A_over_C is None) != (args.eps_over_R is None):
        raise SystemExit("classify: give both --A-over-C and --eps-over-R, or neither.")
    if args.A_over_C is None:
        top = default_top()
    else:
        top = TippeTop.from_ratios(args.A_over_C, args.eps_over_R)
    group = print_top(top)
    os.makedirs(args.out, exist_ok=True)
    point = {f"this top ({group})": (float(top.A / top.C), float(top.eps / top.R))}
    print(f"wrote {write_group_map(args.out, points=point)}")
    return 0
