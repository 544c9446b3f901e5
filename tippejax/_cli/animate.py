"""`tippejax animate`: simulate a launch and write a 3-D animation (GIF, or MP4 with ffmpeg)."""

from __future__ import annotations

import os
import sys
import time

import numpy as np

from .._animate import animate
from .._simulate import simulate
from .._state import initial_state
from .common import DEFAULT_OUT, default_spin, fmt, top_from_options

ANIMATE_DEFAULT_OUT = os.path.join(DEFAULT_OUT, "animation.gif")
ANIMATE_SAVES_PER_SECOND = 200  # save times of the simulation (frames are resampled from them)


def run(args) -> int:
    """Simulate one launch (the top of the options, default: the demo's) and render it."""
    try:
        top = top_from_options(args)
        spin = args.spin if args.spin is not None else default_spin(top)
        y0 = initial_state(top, args.theta0, spin)
        ts = np.linspace(0.0, args.t1, max(2, int(round(args.t1 * ANIMATE_SAVES_PER_SECOND)) + 1))
        print(
            f"simulating: theta0 = {args.theta0:g} rad, spin = {spin:g} rad/s, "
            f"t1 = {args.t1:g} s, model {args.model} ..."
        )
        sol = simulate(top, y0, args.t1, model=args.model, saveat=ts, throw=False)
        print(f"  model used: {sol.model}; inversion time: {fmt(sol.t_invert, '.4g')} s")
        start = time.perf_counter()
        path = animate(
            sol,
            top,
            args.out,
            fps=args.fps,
            speed=args.speed,
            duration=args.duration,
            frames=args.frames,
            t_start=args.t_start,
            t_end=args.t_end,
            dpi=args.dpi,
            follow=args.follow,
        )
    except (ValueError, TypeError, OSError, RuntimeError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(
        f"wrote {path} ({os.path.getsize(path) / 1e6:.2f} MB, "
        f"{time.perf_counter() - start:.1f} s to render)"
    )
    return 0
