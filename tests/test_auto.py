"""model="auto": the regime of a launch, the level chooser, its table against
benchmarks/LEVELS.md, and the promise itself (a launch the table did not contain stays within
the tolerance it asked for)."""

import pathlib
import re

import jax.numpy as jnp
import numpy as np
import pytest

import tippejax as tj
from tippejax._auto import COST_MARGIN, MEASURED, choose_model, launch_regime

LEVELS_MD = pathlib.Path(__file__).parents[1] / "benchmarks" / "LEVELS.md"


def test_measured_table_matches_levels_md():
    text = LEVELS_MD.read_text()
    block = re.search(r"```python\n(MEASURED = \{.*?\n\})\n```", text, re.S).group(1)
    namespace = {}
    exec(block, namespace)
    assert namespace["MEASURED"] == MEASURED


def test_launch_regimes_follow_the_thresholds():
    top = tj.default_top()
    th = tj.thresholds(top)
    assert launch_regime(top, tj.initial_state(top, 0.1, 100.0)) == "inverts"
    assert launch_regime(top, tj.initial_state(top, 0.1, 0.5 * float(th.n1))) == "stays upright"
    # J between J1 and J2 (IIb): neither pole is stable
    J = 0.5 * (float(th.J1) + float(th.J2))
    n = J / float(tj.jellet(top, tj.initial_state(top, 0.1, 1.0)))
    assert launch_regime(top, tj.initial_state(top, 0.1, n)) == "intermediate"
    assert launch_regime(top, tj.initial_state(top, 0.1, 100.0, vx=0.1)) == "moving"
    stiff = tj.TippeTop.from_ratios(0.9, 0.3, mu=300.0)
    assert launch_regime(stiff, tj.initial_state(stiff, 0.1, 100.0)) == "stiff"


def test_choose_model():
    top = tj.default_top()
    y0 = tj.initial_state(top, 0.1, 100.0)
    assert choose_model(top, y0, tolerance=None) == "full"
    err, cost = MEASURED["inverts"]["so3"]
    assert cost < COST_MARGIN
    assert choose_model(top, y0, tolerance=0.5 * err) == "full"
    assert choose_model(top, y0, tolerance=2 * err) == "so3"
    # a level whose measured cost is not below the margin is never chosen
    for level, (err, cost) in MEASURED["inverts"].items():
        if cost >= COST_MARGIN:
            assert choose_model(top, y0, tolerance=10 * err) != level
    # a group the benchmark did not measure keeps the full model
    group_iii = tj.TippeTop.from_ratios(1.5, 0.2)
    assert choose_model(group_iii, tj.initial_state(group_iii, 0.1, 100.0), tolerance=10.0) == "full"
    with pytest.raises(ValueError, match="tolerance"):
        choose_model(top, y0, tolerance=-1.0)


def test_auto_keeps_its_promise_on_a_new_launch():
    """A launch not among the benchmark's scenes (same regime): auto picks the cheaper level
    for a tolerance above its measured error, says so, and the run is within that tolerance
    of the full model."""
    top = tj.default_top()
    y0 = tj.initial_state(top, 0.15, 120.0)
    assert launch_regime(top, y0) == "inverts"
    tolerance = 0.05
    ts = jnp.linspace(0.0, 8.0, 801)
    auto = tj.simulate(top, y0, 8.0, model="auto", tolerance=tolerance, saveat=ts)
    full = tj.simulate(top, y0, 8.0, model="full", saveat=ts)
    assert auto.model == "so3"
    err = float(np.max(np.abs(np.asarray(auto.theta) - np.asarray(full.theta))))
    print(f"auto (so3) vs full on a new inverting launch: max |dtheta| = {err:.3g} rad "
          f"(tolerance {tolerance}); t_invert {float(auto.t_invert):.4f} vs {float(full.t_invert):.4f}")
    assert err < tolerance
    # and the full model is what a tight tolerance gets
    tight = tj.simulate(top, y0, 8.0, model="auto", tolerance=1e-3, saveat=ts)
    assert tight.model == "full"
