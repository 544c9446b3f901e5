"""`tippejax map`: where a grid of launches ends, and a map over (A/C, eps/R) beside the groups."""

from __future__ import annotations

import os
import sys
import time

import jax
import numpy as np

from .._analysis.groups import classify, thresholds
from .._maps import OUTCOMES, outcome_map, outcome_map_tops
from .._plot import outcome_map_figure
from .common import REPRESENTATIVES, mu_text, save, top_from_options, use_agg

MAP_GROUP_TOPS = ("standard", *REPRESENTATIVES)


def _map_top(args):
    """The top of `tippejax map`: `--group` (a representative of a group, or the standard top),
    then the fields given on the command line (as `top_from_options`)."""
    if args.group not in (None, "standard"):
        a_over_c, eps_over_r = REPRESENTATIVES[args.group]
        args.A_over_C = a_over_c if args.A_over_C is None else args.A_over_C
        args.eps_over_R = eps_over_r if args.eps_over_R is None else args.eps_over_R
    for name in ("m", "R", "eps"):
        setattr(args, name, getattr(args, name, None))
    top = top_from_options(args)
    return top, classify(top)


def run(args) -> int:
    """Outcome maps of one top: launch plane (theta0 x spin) and the plane of (A/C, eps/R)."""
    use_agg()
    try:
        top, group = _map_top(args)
        if min(args.n_theta, args.n_spin) < 2:
            raise ValueError("--n-theta and --n-spin must be at least 2.")
        theta0 = np.linspace(args.theta_min, args.theta_max, args.n_theta)
        spin_max = args.spin_max if args.spin_max is not None else 6.0 * float(thresholds(top).n1)
        spin = np.linspace(args.spin_min, spin_max, args.n_spin)
        os.makedirs(args.out, exist_ok=True)
        print(f"top: Group {group}, A/C = {float(top.A_over_C):.4g}, "
              f"eps/R = {float(top.eps_over_R):.4g}, {mu_text(top)}")
        start = time.perf_counter()
        om = outcome_map(top, theta0, spin, t1=args.t1, model=args.model,
                         tolerance=args.tolerance)
        elapsed = time.perf_counter() - start
        n = theta0.size * spin.size
        print(om.summary())
        print(f"{n} launches in {elapsed:.1f} s ({n / elapsed:.1f} launches/s, compilation "
              f"included) on {len(jax.devices())} device(s)")
        paths = [save(outcome_map_figure(om), os.path.join(args.out, "outcome_map.png"), dpi=110)]
        np.savez(
            os.path.join(args.out, "outcome_map.npz"), theta0=theta0, spin=spin,
            outcome=np.asarray(om.outcome), settled=np.asarray(om.settled),
            theta_final=np.asarray(om.theta_final), t_invert=np.asarray(om.t_invert),
            jellet=np.asarray(om.jellet), outcomes=np.array(OUTCOMES),
        )
        paths.append(os.path.join(args.out, "outcome_map.npz"))
        if args.tops:
            a = np.linspace(0.55, 1.6, args.n_tops)
            e = np.linspace(0.04, 0.7, max(2, (3 * args.n_tops) // 4))
            spin_tops = args.spin_tops if args.spin_tops is not None else float(spin[len(spin) // 2])
            start = time.perf_counter()
            omt = outcome_map_tops(top, a, e, theta0=args.theta0_tops, spin=spin_tops,
                                   t1=args.t1, model="full" if args.model == "auto" else args.model)
            print(omt.summary())
            print(f"{a.size * e.size} tops in {time.perf_counter() - start:.1f} s")
            paths.append(save(outcome_map_figure(omt),
                              os.path.join(args.out, "outcome_map_tops.png"), dpi=110))
    except (ValueError, TypeError, OSError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for path in paths:
        print(f"wrote {path}")
    return 0

