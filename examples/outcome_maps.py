"""Outcome maps of the standard top and of a Group IIa top, and a map over (A/C, eps/R).

Runs `tj.outcome_map` over a grid of launch tilt x spin for two tops, and
`tj.outcome_map_tops` over the plane of (A/C, eps/R) for one launch, and writes the figures
`examples/figures/outcome_map_standard.png`, `outcome_map_IIa.png` and `outcome_map_tops.png`
(the same figures as `tippejax map`). Prints each map's counts and its launches per second.

    python examples/outcome_maps.py [--n-theta 24 --n-spin 48 --t1 30]
"""

from __future__ import annotations

import argparse
import os
import time

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import tippejax as tj
from tippejax._plot import outcome_map_figure

HERE = os.path.dirname(os.path.abspath(__file__))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--n-theta", type=int, default=24)
    p.add_argument("--n-spin", type=int, default=48)
    p.add_argument("--t1", type=float, default=30.0)
    p.add_argument("--out", default=os.path.join(HERE, "figures"))
    args = p.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    theta0 = np.linspace(0.02, 1.5, args.n_theta)
    tops = {
        "standard": tj.default_top(),  # Group IIb: A/C = 0.9, eps/R = 0.3
        "IIa": tj.TippeTop.from_ratios(0.69, 0.38),  # bistable: upright and intermediate
    }
    for name, top in tops.items():
        spin = np.linspace(10.0, 220.0, args.n_spin)
        start = time.perf_counter()
        om = tj.outcome_map(top, theta0, spin, t1=args.t1, model="full")
        elapsed = time.perf_counter() - start
        print(f"--- {name} top (Group {tj.classify(top)})")
        print(om.summary())
        n = theta0.size * spin.size
        print(
            f"{n} launches in {elapsed:.1f} s: {n / elapsed:.1f} launches/s (compilation included)"
        )
        fig = outcome_map_figure(om)
        path = os.path.join(args.out, f"outcome_map_{name}.png")
        fig.savefig(path, dpi=100)
        plt.close(fig)
        print(f"wrote {path}")
    a = np.linspace(0.55, 1.6, 2 * args.n_theta)
    e = np.linspace(0.04, 0.7, (3 * args.n_theta) // 2)
    start = time.perf_counter()
    omt = tj.outcome_map_tops(tj.default_top(), a, e, theta0=0.1, spin=120.0, t1=args.t1)
    print("--- tops over (A/C, eps/R), launch theta0 = 0.1 rad, spin = 120 rad/s")
    print(omt.summary())
    print(f"{a.size * e.size} tops in {time.perf_counter() - start:.1f} s")
    fig = outcome_map_figure(omt)
    path = os.path.join(args.out, "outcome_map_tops.png")
    fig.savefig(path, dpi=100)
    plt.close(fig)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
