"""`model="auto"`: the cheapest level whose measured error is below what the caller asks.

The numbers below are copied from `benchmarks/LEVELS.md`, made by `python benchmarks/levels.py`:
the worst error in theta(t) of each level against the full model over the benchmark's scenes, and
the median cost (wall time relative to the full model in the same run). Re-run the benchmark and
update them together when a model or solver changes.
"""

from __future__ import annotations

import numpy as np

from ._engine.solver_choice import STIFF_RATE, friction_rate
from ._state import State
from ._top import TippeTop

# Worst theta error (rad) against the full model and median cost relative to it, per regime,
# from benchmarks/LEVELS.md. "stiff": friction_rate(top) > STIFF_RATE (the mu = 300 scene);
# "moving": launches with horizontal centre-of-mass velocity included (all non-stiff scenes).
MEASURED = {
    "non-stiff": {"so3": (0.366, 0.98), "routhian": (0.366, 1.08)},
    "moving": {"so3": (0.366, 0.98), "routhian": (0.366, 1.08)},
    "stiff": {"so3": (0.536, 0.79), "routhian": (0.536, 0.46)},
}

COST_MARGIN = 0.9
"""A cheaper level is used only if its measured cost is below this fraction of the full model's.

Costs are wall-time ratios on a shared 2-core machine; two runs of the benchmark gave 1.075 and
0.98 for the same entry, so a level within ~10% of the full model is not measurably cheaper."""


def choose_model(top: TippeTop, y0: State, *, tolerance: float | None) -> str:
    """The level `model="auto"` uses for this launch and `tolerance` (max theta error, rad).

    `tolerance=None` means "as accurate as the package can": the full model. Otherwise, in the
    regime of this launch (stiff friction, or centre-of-mass velocity, or neither), the level
    with the lowest measured cost among those whose measured worst error is at most `tolerance`
    and whose cost is below `COST_MARGIN` (the full model, cost 1, always qualifies).
    """
    if tolerance is None:
        return "full"
    if not tolerance > 0:
        raise ValueError(f"tolerance must be a positive error in theta (rad), got {tolerance}.")
    try:
        moving = bool(np.any(np.asarray(y0.velocity) != 0))
        stiff = bool(np.max(np.asarray(friction_rate(top))) > STIFF_RATE)
    except Exception:  # traced values: no regime can be read, stay with the full model
        return "full"
    regime = "stiff" if stiff else ("moving" if moving else "non-stiff")
    candidates = [(1.0, 0.0, "full")]
    for level, (error, cost) in MEASURED[regime].items():
        if error <= tolerance and cost < COST_MARGIN:
            candidates.append((cost, error, level))
    return min(candidates)[2]
