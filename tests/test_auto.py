"""model="auto": the regime of a launch, the level chooser, its table against the levels
suite's blocks of benchmarks/RESULTS.md, and the promise itself (launches the table did not
contain, in several groups, stay within the tolerance they asked for)."""

import pathlib
import re

import jax.numpy as jnp
import numpy as np
import pytest

import tippejax as tj
from tippejax._analysis.groups import GROUPS
from tippejax._auto import COST_MARGIN, MEASURED, choose_model, launch_regime

RESULTS_MD = pathlib.Path(__file__).parents[1] / "benchmarks" / "RESULTS.md"


def _block(name):
    """The table `name` of RESULTS.md: a row per (group,) regime, "error / cost" per level."""
    text = RESULTS_MD.read_text()
    lines = re.search(rf"^`{name}`.*\n\n((?:\|.*\n?)+)", text, re.M).group(1).splitlines()
    head = [c.strip() for c in lines[0].strip("|").split("|")]
    n_keys = head.index("regime") + 1
    out = {}
    for line in lines[2:]:
        cells = [c.strip() for c in line.strip("|").split("|")]
        at = out.setdefault(cells[0], {}) if n_keys > 1 else out
        at[cells[n_keys - 1]] = {
            level: tuple(float(x) for x in cell.split(" / "))
            for level, cell in zip(head[n_keys:], cells[n_keys:])
        }
    return out


def test_measured_table_matches_results_md():
    assert _block("MEASURED") == MEASURED


def test_every_group_is_measured_and_iib_keeps_its_own_scenes():
    assert set(MEASURED) == set(GROUPS)
    for group, regimes in MEASURED.items():
        assert regimes, group
    # group IIb: the worst error and highest cost of its per-group scenes and of the main
    # section's IIb scenes (stiff friction, moving centre of mass, nutating launches)
    for regime, table in _block("MEASURED_IIB_SCENES").items():
        for level, (error, cost) in table.items():
            merged_error, merged_cost = MEASURED["IIb"][regime][level]
            assert merged_error >= error and merged_cost >= cost


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
    # group I: theta = 0 is stable at every spin; above J2 theta = pi is stable too
    group_i = tj.TippeTop.from_ratios(0.7, 0.2)
    n2 = float(tj.thresholds(group_i).n2)
    assert launch_regime(group_i, tj.initial_state(group_i, 0.1, 0.5 * n2)) == "stays upright"
    assert launch_regime(group_i, tj.initial_state(group_i, 0.1, 5 * n2)) == "bistable"


def test_choose_model():
    top = tj.default_top()
    y0 = tj.initial_state(top, 0.1, 100.0)
    assert choose_model(top, y0, tolerance=None) == "full"
    # below every level's measured error: the full model; above: the cheapest qualifying level
    # levels that refused a scene of the regime have error inf: never chosen there
    finite = {lv: ec for lv, ec in MEASURED["IIb"]["inverts"].items() if np.isfinite(ec[0])}
    errors = [err for err, _ in finite.values()]
    assert choose_model(top, y0, tolerance=0.5 * min(errors)) == "full"
    cost, level = min((c, lv) for lv, (e, c) in finite.items())
    expected = level if cost < COST_MARGIN else "full"
    assert choose_model(top, y0, tolerance=2 * max(errors)) == expected
    stiff = tj.TippeTop.from_ratios(0.9, 0.3, mu=300.0)
    y_stiff = tj.initial_state(stiff, 0.1, 100.0)
    cost, level = min((c, lv) for lv, (e, c) in MEASURED["IIb"]["stiff"].items() if np.isfinite(e))
    err = MEASURED["IIb"]["stiff"][level][0]
    assert choose_model(stiff, y_stiff, tolerance=2 * err) == (
        level if cost < COST_MARGIN else "full"
    )
    # a level whose measured cost is not below the margin is never chosen
    for level, (err, cost) in MEASURED["IIb"]["inverts"].items():
        if cost >= COST_MARGIN:
            assert choose_model(top, y0, tolerance=10 * err) != level
    # a regime the benchmark did not measure in a group keeps the full model (stiff friction
    # and a moving centre of mass are measured in group IIb only)
    group_iii = tj.TippeTop.from_ratios(1.5, 0.2)
    assert "moving" not in MEASURED["III"] and "stiff" not in MEASURED["III"]
    moving = tj.initial_state(group_iii, 0.1, 100.0, vx=0.1)
    assert choose_model(group_iii, moving, tolerance=10.0) == "full"
    stiff_iii = tj.TippeTop.from_ratios(1.5, 0.2, mu=300.0)
    assert (
        choose_model(stiff_iii, tj.initial_state(stiff_iii, 0.1, 100.0), tolerance=10.0) == "full"
    )
    # every group is measured: a loose tolerance gets a cheaper level where one is measured
    # cheaper (group III, a fast launch: "intermediate")
    y_iii = tj.initial_state(group_iii, 0.1, 100.0)
    table = MEASURED["III"][launch_regime(group_iii, y_iii)]
    cheaper = [lv for lv, (e, c) in table.items() if np.isfinite(e) and c < COST_MARGIN]
    assert (choose_model(group_iii, y_iii, tolerance=10.0) != "full") == bool(cheaper)
    with pytest.raises(ValueError, match="tolerance"):
        choose_model(top, y0, tolerance=-1.0)


@pytest.mark.slow
def test_auto_keeps_its_promise_on_a_new_launch():
    """A launch not among the benchmark's scenes (same regime): auto picks the level the table
    says, says so, and the run is within the tolerance it asked for of the full model. Slow: one
    launch; `test_auto_keeps_its_promise_on_random_launches` holds the promise on seeded random
    launches."""
    top = tj.default_top()
    y0 = tj.initial_state(top, 0.15, 120.0)
    assert launch_regime(top, y0) == "inverts"
    tolerance = 1.25 * max(
        err for err, _ in MEASURED["IIb"]["inverts"].values() if np.isfinite(err)
    )
    expected = choose_model(top, y0, tolerance=tolerance)
    cheaper = [
        lv
        for lv, (e, c) in MEASURED["IIb"]["inverts"].items()
        if e <= tolerance and c < COST_MARGIN
    ]
    assert (expected != "full") == bool(cheaper)
    # 201 save points, as in test_reference.py: the compiled runs are shared (rtol, t1 traced)
    ts = jnp.linspace(0.0, 8.0, 201)
    auto = tj.simulate(top, y0, 8.0, model="auto", tolerance=tolerance, saveat=ts)
    assert auto.model.startswith(expected)
    full = tj.simulate(top, y0, 8.0, model="full", saveat=ts)
    # whichever the table picks (and the cheap levels it could pick), the promise holds
    for level in dict.fromkeys(
        ("so3", "routhian", expected) if expected != "full" else ("so3", "routhian")
    ):
        sol = tj.simulate(top, y0, 8.0, model=level, saveat=ts)
        err = float(np.max(np.abs(np.asarray(sol.theta) - np.asarray(full.theta))))
        print(
            f"{level} vs full on a new inverting launch: max |dtheta| = {err:.3g} rad "
            f"(tolerance {tolerance:.3g})"
        )
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
        top, GyroscopicLevelState.from_theta(0.1, phi=0.0, psi=0.0, nutation=-30.0, jellet=J)
    )
    assert launch_regime(top, y0) == "inverts"
    error, cost = MEASURED["IIb"]["inverts"]["gyroscopic"]
    assert np.isfinite(error) and cost < COST_MARGIN
    loose = 1.5 * error
    ts = jnp.linspace(0.0, 8.0, 201)
    auto = tj.simulate(top, y0, 8.0, model="auto", tolerance=loose, saveat=ts)
    # the slow flow, handing over to the full model where the manifold starts to repel
    assert auto.model in ("gyroscopic", "gyroscopic->full")
    full = tj.simulate(top, y0, 8.0, model="full", saveat=ts)
    err = float(np.max(np.abs(np.asarray(auto.theta) - np.asarray(full.theta))))
    print(
        f"gyroscopic (auto) vs full, on-manifold launch n0 = 150: max |dtheta| = {err:.3g} rad "
        f"(tolerance {loose:.3g})"
    )
    assert err < loose
    tight = tj.simulate(top, y0, 8.0, model="auto", tolerance=1e-3, saveat=ts)
    assert tight.model == "full"
    nutating = tj.initial_state(top, 0.5, 80.0, theta_dot=2.0)
    assert not bool(GyroscopicLevel().in_chart(top, nutating))
    assert choose_model(top, nutating, tolerance=10.0) != "gyroscopic"


# (A/C, eps/R) of the benchmark's top of each group (`benchmarks/levels.py --groups`), and the
# ranges of its launches: spin 0.7-10 x n1 (n2 in group I), mu 0.05-2 s/m, theta0 0.05-0.5, 8 s
BENCHMARK_TOPS = {
    "Ia": (0.96, 0.02),
    "Ib": (0.7, 0.2),
    "IIa": (0.8, 0.3),
    "IIb": (0.9, 0.3),
    "IIc": (0.99, 0.02),
    "III": (1.5, 0.2),
}
RANDOM_LAUNCHES = 5


def _random_launch(group, rng):
    a, e = BENCHMARK_TOPS[group]
    mu = float(np.exp(rng.uniform(np.log(0.05), np.log(2.0))))
    top = tj.TippeTop.from_ratios(a, e, mu=mu)
    th = tj.thresholds(top)
    reference = float(th.n1) if np.isfinite(float(th.n1)) else float(th.n2)
    spin = float(np.exp(rng.uniform(np.log(0.7), np.log(10.0)))) * reference
    theta0 = float(rng.uniform(0.05, 0.5))
    return (
        top,
        tj.initial_state(top, theta0, spin),
        f"theta0={theta0:.3f}, spin={spin:.1f}, mu={mu:.3f}",
    )


@pytest.mark.parametrize("group", ["Ia", "IIa", "IIc", "III"])
def test_auto_keeps_its_promise_on_random_launches(group):
    """Seeded random launches of the group's benchmark top, none of them a benchmark scene:
    wherever auto picks a cheaper level, at the tightest tolerance at which it picks it, the
    run stays within that tolerance of the full model (max |dtheta| over the save times where
    both are defined, the benchmark's metric)."""
    rng = np.random.default_rng(1000 + GROUPS.index(group))
    ts = jnp.linspace(0.0, 8.0, 201)
    checked = 0
    for _ in range(RANDOM_LAUNCHES):
        top, y0, launch = _random_launch(group, rng)
        assert tj.classify(top) == group
        table = MEASURED[group].get(launch_regime(top, y0), {})
        # auto's choice changes only where the tolerance crosses a measured error
        tightest = {}
        for tolerance in sorted(e for e, _ in table.values() if np.isfinite(e)):
            level = choose_model(top, y0, tolerance=tolerance)
            if level != "full":
                tightest.setdefault(level, tolerance)
        if not tightest:
            continue
        full = np.asarray(tj.simulate(top, y0, 8.0, saveat=ts, throw=False).theta)
        for level, tolerance in tightest.items():
            sol = tj.simulate(
                top, y0, 8.0, model="auto", tolerance=tolerance, saveat=ts, throw=False
            )
            assert sol.model.startswith(level)
            theta = np.asarray(sol.theta)
            both = np.isfinite(theta) & np.isfinite(full)
            assert both.sum() > 10
            err = float(np.max(np.abs(theta - full)[both]))
            print(
                f"{group} {launch_regime(top, y0)} ({launch}): {sol.model} at tolerance "
                f"{tolerance:.3g}: max |dtheta| = {err:.3g}"
            )
            assert err <= tolerance
            checked += 1
    assert checked, f"auto picked the full model for every launch of group {group}"
