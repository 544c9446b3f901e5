"""`model="auto"`: the cheapest level whose measured error is below what the caller asks.

The levels it can pick: `"full"`, `"so3"`, `"routhian"` and `"gyroscopic"` (the slow flow for
theta alone; it is only picked for a launch it accepts, i.e. inside its own chart: gyroscopic
balance holds and the launch's nutation is small enough to project, see `choose_model`).

The numbers in `MEASURED` are copied from `benchmarks/RESULTS.md`, made by
`python benchmarks/levels.py --groups`: for each group of tops (`classify`) and each regime of
launch in it, the worst error in theta(t) of each level against the full model over the
benchmark's scenes of that group and regime, and the median cost (wall time relative to the
full model in the same run). The scenes: one top per group, launches (omega = n a, 8 s) on a
grid of spins 0.7 to 10 times n1 (n2 in group I), mu 0.05, 0.3, 2 s/m and theta0 0.15, 0.3,
0.5, plus the most tilted launch the gyroscopic level accepts at each spin and mu; group IIb
also has the scenes of `python benchmarks/levels.py` (stiff friction, a moving centre of mass,
nutating launches; worst error and highest cost of the two sets). For the gyroscopic level,
which refuses launches it cannot describe, both are over the scenes of the regime it accepts,
since auto only picks it for a launch it accepts; a scene where it was accepted and then
stopped on the way counts as error `inf` (never picked in that regime), and so does a regime
where it accepted none. Re-run the benchmark and update them together when a model or solver
changes (`tests/test_auto.py` checks they agree).

The worst error of a regime is met at mu = 2 almost everywhere (0.2-0.43 rad where the top
stays upright or is bistable, 0.6-2.5 rad where it rises), so below ~0.2 rad auto keeps the
full model, and the cheaper levels are picked mostly for launches that stay upright or are
bistable. The numbers hold for 8 s runs of the benchmark's top of each group; other tops of a
group, other launches and longer runs are extrapolations (`tests/test_auto.py` checks seeded
random launches of four groups against them).

**What `tolerance` means.** The largest acceptable max |theta(t) - theta_full(t)| over the run
(rad), the same metric for every level. The gyroscopic level drops the nutation, so its error
on this metric is mostly the nutation amplitude of the full model's motion (0.1-0.3 rad for the
benchmark's launches with omega = n a, which carry nutation); its slow drift alone (theta
against the nutation-averaged full model, and t_invert) is far closer (`benchmarks/RESULTS.md`).
Auto therefore uses it only where a caller accepts an error of the size of the nutation (or in
the stiff regime, where the others err as much); a caller who wants the averaged motion
cheaply asks for `model="gyroscopic"` directly.

A launch's regime is read off the algebra level, before anything is integrated: stiff friction,
a moving centre of mass, or else where the Jellet $J$ of the launch sends the top (which of the
vertical states is stable for that $J$, by the sign of $W''$ at the poles).
"""

from __future__ import annotations

from collections.abc import Collection

import numpy as np

from ._analysis.groups import classify
from ._analysis.potential import effective_potential_derivative
from ._engine.solver_choice import STIFF_RATE, friction_rate
from ._friction.viscous import Viscous
from ._invariants import jellet
from ._models.levels import LEVELS
from ._state import State
from ._top import TippeTop

MEASURED = {
    "Ia": {
        "stays upright": {
            "so3": (0.289, 0.80),
            "routhian": (0.289, 0.86),
            "gyroscopic": (0.43, 0.20),
        },
        "bistable": {"so3": (0.266, 0.89), "routhian": (0.266, 0.81), "gyroscopic": (0.323, 0.11)},
    },
    "Ib": {
        "stays upright": {
            "so3": (0.233, 0.84),
            "routhian": (0.233, 0.83),
            "gyroscopic": (0.231, 0.16),
        },
        "bistable": {"so3": (0.202, 1.00), "routhian": (0.202, 0.98), "gyroscopic": (0.246, 0.07)},
    },
    "IIa": {
        "stays upright": {
            "so3": (0.218, 0.85),
            "routhian": (0.218, 0.86),
            "gyroscopic": (0.222, 0.11),
        },
        "intermediate": {"so3": (1.28, 0.82), "routhian": (1.28, 0.81), "gyroscopic": (2.27, 0.07)},
        "inverts": {"so3": (1.36, 0.92), "routhian": (1.36, 0.94), "gyroscopic": (2.53, 0.05)},
    },
    "IIb": {
        "stays upright": {
            "so3": (0.231, 0.87),
            "routhian": (0.231, 1.06),
            "gyroscopic": (0.207, 0.14),
        },
        "intermediate": {"so3": (0.74, 0.82), "routhian": (0.74, 0.80), "gyroscopic": (1.43, 0.11)},
        "inverts": {"so3": (0.882, 0.88), "routhian": (0.882, 0.89), "gyroscopic": (1.98, 0.38)},
        "stiff": {"so3": (0.536, 0.53), "routhian": (0.536, 0.26), "gyroscopic": (1, 0.01)},
        "moving": {"so3": (0.311, 0.83), "routhian": (0.311, 0.83), "gyroscopic": (0.291, 0.06)},
    },
    "IIc": {
        "bistable": {"so3": (0.25, 0.78), "routhian": (0.25, 0.81), "gyroscopic": (0.303, 0.12)},
        "stays upright": {
            "so3": (0.267, 0.84),
            "routhian": (0.267, 0.73),
            "gyroscopic": (float("inf"), float("inf")),
        },
        "inverts": {"so3": (1.41, 0.82), "routhian": (1.41, 0.74), "gyroscopic": (2.27, 0.05)},
    },
    "III": {
        "stays upright": {
            "so3": (0.276, 0.77),
            "routhian": (0.276, 0.82),
            "gyroscopic": (0.255, 0.23),
        },
        "intermediate": {"so3": (0.62, 0.80), "routhian": (0.62, 0.81), "gyroscopic": (1.1, 0.21)},
    },
}
"""Per group, regime and level: (worst theta error in rad, median cost relative to the full
model); for the gyroscopic level over the scenes it accepts (`inf`: it stopped on one, or
accepted none). A group and regime not listed keeps the full model."""

MEASURED_FRICTION = Viscous
"""The friction law `MEASURED` was measured for; for any other law auto keeps the full model."""

COST_MARGIN = 0.9
"""A cheaper level is used only if its measured cost is below this fraction of the full model's.

Costs are wall-time ratios on a shared 2-core machine that move by ~0.1 between runs, so a level
within ~10% of the full model is not measurably cheaper."""


def launch_regime(top: TippeTop, y0: State) -> str:
    """The regime of a launch, as keyed in `MEASURED` (needs concrete values).

    "stiff" if `friction_rate(top)` exceeds `STIFF_RATE`; else "moving" if the centre of mass
    has a horizontal velocity; else, from $W''(\\theta; J)$ at the poles for the launch's $J$:
    "inverts" ($\\theta = \\pi$ the only stable vertical state), "stays upright" ($\\theta = 0$
    the only one), "intermediate" (neither: an intermediate state attracts) or "bistable".
    """
    if float(np.max(np.asarray(friction_rate(top)))) > STIFF_RATE:
        return "stiff"
    if bool(np.any(np.asarray(y0.velocity) != 0)):
        return "moving"
    J = jellet(top, y0)
    up = float(effective_potential_derivative(top, 0.0, J, order=2)) > 0
    down = float(effective_potential_derivative(top, np.pi, J, order=2)) > 0
    return {
        (False, True): "inverts",
        (True, False): "stays upright",
        (False, False): "intermediate",
        (True, True): "bistable",
    }[(up, down)]


def accepts(level: str, top: TippeTop, y0: State) -> bool:
    """Whether `level` describes this launch: False for a level with a chart of its own (the
    gyroscopic level) when the launch is outside it (needs concrete values)."""
    lvl = LEVELS[level]
    return lvl.chart_end_result is None or bool(np.asarray(lvl.in_chart(top, y0)))


def cheapest_level(table: dict, tolerance: float, *, refused: Collection[str] = ()) -> str:
    """The level with the lowest measured cost among those of `table` ({level: (worst error,
    cost)}) whose error is at most `tolerance` and whose cost is below `COST_MARGIN`, leaving
    out the levels `refused` (those that do not accept the launch); `"full"` if none."""
    candidates = [(1.0, 0.0, "full")]
    for level, (error, cost) in table.items():
        if not (np.isfinite(error) and error <= tolerance and cost < COST_MARGIN):
            continue
        if level in refused:
            continue
        candidates.append((cost, error, level))
    return min(candidates)[2]


def choose_model(top: TippeTop, y0: State, *, tolerance: float | None) -> str:
    """The level `model="auto"` uses for this launch and `tolerance` (max theta error, rad).

    `tolerance=None` means "as accurate as the package can": the full model. Otherwise, in the
    group of the top (`classify`) and the regime of this launch (`launch_regime`), the level
    with the lowest measured cost among those whose measured worst error is at most `tolerance`
    and whose cost is below `COST_MARGIN` (the full model, cost 1, always qualifies;
    `cheapest_level`). The gyroscopic level qualifies only if it accepts this launch
    (`accepts`: `in_chart` of the launch); a launch outside its chart would run in the full
    model from the start (`"gyroscopic->full"`). On the way it may still hand over to the full
    model where the slow manifold repels or balance is lost. A group and regime the benchmark
    did not measure, a friction law other than the viscous one (`MEASURED_FRICTION`), and
    traced arguments (no regime can be read), keep the full model.
    """
    if tolerance is None:
        return "full"
    if not tolerance > 0:
        raise ValueError(f"tolerance must be a positive error in theta (rad), got {tolerance}.")
    if not isinstance(top.friction, MEASURED_FRICTION):  # (no measured error for this law)
        return "full"
    try:
        regime = launch_regime(top, y0)
        group = str(classify(top))
    except Exception:  # traced values: no regime can be read, stay with the full model
        return "full"
    table = MEASURED.get(group, {}).get(regime)
    if table is None:
        return "full"
    refused = [level for level in table if not accepts(level, top, y0)]
    return cheapest_level(table, tolerance, refused=refused)
