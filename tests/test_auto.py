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
    # below every level's measured error: the full model; above: the cheapest qualifying level
    # levels that refused a scene of the regime have error inf: never chosen there
    finite = {lv: ec for lv, ec in MEASURED["inverts"].items() if np.isfinite(ec[0])}
    errors = [err for err, _ in finite.values()]
    assert choose_model(top, y0, tolerance=0.5 * min(errors)) == "full"
    cost, level = min((c, lv) for lv, (e, c) in finite.items())
    expected = level if cost < COST_MARGIN else "full"
    assert choose_model(top, y0, tolerance=2 * max(errors)) == expected
    stiff = tj.TippeTop.from_ratios(0.9, 0.3, mu=300.0)
    y_stiff = tj.initial_state(stiff, 0.1, 100.0)
    cost, level = min((c, lv) for lv, (e, c) in MEASURED["stiff"].items() if np.isfinite(e))
    err = MEASURED["stiff"][level][0]
    assert choose_model(stiff, y_stiff, tolerance=2 * err) == (level if cost < COST_MARGIN else "full")
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
    """A launch not among the benchmark's scenes (same regime): auto picks the level the table
    says, says so, and the run is within the tolerance it asked for of the full model."""
    top = tj.default_top()
    y0 = tj.initial_state(top, 0.15, 120.0)
    assert launch_regime(top, y0) == "inverts"
    tolerance = 1.25 * max(err for err, _ in MEASURED["inverts"].values() if np.isfinite(err))
    expected = choose_model(top, y0, tolerance=tolerance)
    cheaper = [lv for lv, (e, c) in MEASURED["inverts"].items() if e <= tolerance and c < COST_MARGIN]
    assert (expected != "full") == bool(cheaper)
    # 201 save points, as in test_reference.py: the compiled runs are shared (rtol, t1 traced)
    ts = jnp.linspace(0.0, 8.0, 201)
    auto = tj.simulate(top, y0, 8.0, model="auto", tolerance=tolerance, saveat=ts)
    assert auto.model.startswith(expected)
    full = tj.simulate(top, y0, 8.0, model="full", saveat=ts)
    # whichever the table picks (and the cheap levels it could pick), the promise holds
    for level in dict.fromkeys(("so3", "routhian", expected) if expected != "full" else ("so3", "routhian")):
        sol = tj.simulate(top, y0, 8.0, model=level, saveat=ts)
        err = float(np.max(np.abs(np.asarray(sol.theta) - np.asarray(full.theta))))
        print(f"{level} vs full on a new inverting launch: max |dtheta| = {err:.3g} rad "
              f"(tolerance {tolerance:.3g})")
        assert err < tolerance
    # and the full model is what a tight tolerance gets
    tight = tj.simulate(top, y0, 8.0, model="auto", tolerance=1e-3, saveat=ts)
    assert tight.model == "full"


def test_auto_picks_the_gyroscopic_level_for_a_fast_launch_on_its_manifold():
    """A fast launch on the gyroscopic slow manifold (no nutation to drop): at a tolerance above
    the level's measured error auto runs the slow flow, says so, and keeps within it of the full
    model; at a tight tolerance it runs the full model; a launch the level refuses (much
    nutation) never gets it."""
    from tippejax._models.gyroscopic import GyroscopicLevel, GyroscopicLevelState

    top = tj.default_top()
    J = tj.jellet(top, tj.initial_state(top, 0.1, 150.0))
    y0 = GyroscopicLevel().to_state(
        top, GyroscopicLevelState.from_theta(0.1, phi=0.0, psi=0.0, nutation=-30.0, jellet=J))
    assert launch_regime(top, y0) == "inverts"
    error, cost = MEASURED["inverts"]["gyroscopic"]
    assert np.isfinite(error) and cost < COST_MARGIN
    loose = 1.5 * error
    ts = jnp.linspace(0.0, 8.0, 201)
    auto = tj.simulate(top, y0, 8.0, model="auto", tolerance=loose, saveat=ts)
    # the slow flow, handing over to the full model where the manifold starts to repel
    assert auto.model in ("gyroscopic", "gyroscopic->full")
    full = tj.simulate(top, y0, 8.0, model="full", saveat=ts)
    err = float(np.max(np.abs(np.asarray(auto.theta) - np.asarray(full.theta))))
    print(f"gyroscopic (auto) vs full, on-manifold launch n0 = 150: max |dtheta| = {err:.3g} rad "
          f"(tolerance {loose:.3g})")
    assert err < loose
    tight = tj.simulate(top, y0, 8.0, model="auto", tolerance=1e-3, saveat=ts)
    assert tight.model == "full"
    nutating = tj.initial_state(top, 0.5, 80.0, theta_dot=2.0)
    assert not bool(GyroscopicLevel().in_chart(top, nutating))
    assert choose_model(top, nutating, tolerance=10.0) != "gyroscopic"
