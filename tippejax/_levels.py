"""`model="auto"`: the cheapest level whose measured error is below what the caller asks.

The numbers below are copied from `benchmarks/LEVELS.md`, made by `python benchmarks/levels.py`:
the worst error in theta(t) of each level against the full model over the benchmark's scenes, and
the median cost (wall time relative to the full model in the same run). Re-run the benchmark and
update them together when a model or solver changes.
"""

from __future__ import annotations

import numpy as np

from ._state import State
from ._top import TippeTop

# level: (worst theta error with initial CM velocity, worst without, median cost vs full)
MEASURED = {
    "full": (0.0, 0.0, 1.0),
    "so3": (float("nan"), float("nan"), float("nan")),
    "routhian": (float("nan"), float("nan"), float("nan")),
}


def choose_model(top: TippeTop, y0: State, *, tolerance: float | None) -> str:
    """The level `model="auto"` uses for this launch and `tolerance` (max theta error, rad).

    `tolerance=None` means "as accurate as the package can": the full model. Otherwise the
    level with the lowest measured cost among those whose measured worst error (over scenes
    with initial centre-of-mass velocity if `y0` has some) is at most `tolerance`.
    """
    del top
    if tolerance is None:
        return "full"
    if not tolerance > 0:
        raise ValueError(f"tolerance must be a positive error in theta (rad), got {tolerance}.")
    try:
        moving = bool(np.any(np.asarray(y0.velocity) != 0))
    except Exception:  # traced: assume the worst case
        moving = True
    candidates = []
    for level, (err_v, err, cost) in MEASURED.items():
        error = err_v if moving else err
        if np.isfinite(error) and error <= tolerance and np.isfinite(cost):
            candidates.append((cost, error, level))
    return min(candidates)[2]
