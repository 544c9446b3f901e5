"""Outcome maps (`tippejax._maps`): every launch ends where the analysis level says it can."""

import os
import subprocess
import sys

import jax
import numpy as np
import pytest
from helpers import host_devices_env

import tippejax as tj
from tippejax._auto import choose_model
from tippejax._maps.auto import auto_models
from tippejax._maps.stages import staged_outcomes
from tippejax._models.levels import LEVELS
from tippejax._outcome import INTERMEDIATE, INVERTED, UPRIGHT

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
THETA0 = np.array([0.1, 0.6, 1.2])
SPIN = np.array([20.0, 70.0, 120.0, 220.0])
T1 = 30.0


@pytest.fixture(scope="module")
def standard_map():
    return tj.outcome_map(tj.default_top(), THETA0, SPIN, t1=T1, model="full")


def _stable_by_analysis(top, J):
    """(theta, outcome code) of the states `tj.steady_states` calls stable at J."""
    ss = tj.steady_states(top, J)
    out = [(0.0, UPRIGHT)] if bool(ss.vertical_stable[0]) else []
    if bool(ss.vertical_stable[1]):
        out.append((np.pi, INVERTED))
    for theta, stable in ss.intermediate:
        if stable:
            out.append((theta, INTERMEDIATE))
    return out


def test_every_launch_ends_on_a_state_stable_for_its_jellet(standard_map):
    om = standard_map
    top = om.top
    outcome = np.asarray(om.outcome)
    ended = outcome <= INTERMEDIATE
    assert ended.sum() >= 8, om.summary()  # the grid is mostly launches that stay on the table
    for i, j in zip(*np.nonzero(ended)):
        J = tj.jellet(top, tj.initial_state(top, THETA0[i], SPIN[j]))
        np.testing.assert_allclose(float(om.jellet[i, j]), float(J), rtol=1e-12)
        stable = _stable_by_analysis(top, J)
        theta_f = float(om.theta_final[i, j])
        # Settled at t1, on a state the analysis level calls stable, of the kind reported.
        dist = [abs(theta_f - th) for th, _ in stable]
        k = int(np.argmin(dist))
        assert dist[k] < 0.1, (THETA0[i], SPIN[j], theta_f, stable)
        assert stable[k][1] == outcome[i, j]
        assert bool(om.settled[i, j])


def test_map_holds_all_three_end_states_and_inversion_times(standard_map):
    outcome = np.asarray(standard_map.outcome)
    for code in (UPRIGHT, INVERTED, INTERMEDIATE):
        assert np.any(outcome == code), standard_map.summary()
    # Below n1 nothing inverts; an inverted launch has crossed pi/2 once, before t1.
    n1 = float(tj.thresholds(standard_map.top).n1)
    assert np.all(outcome[:, SPIN < n1] == UPRIGHT)
    t_inv = np.asarray(standard_map.t_invert)
    assert np.all((t_inv[outcome == INVERTED] > 0) & (t_inv[outcome == INVERTED] < T1))


def test_intermediate_launches_end_on_the_predicted_intermediate_tilt(standard_map):
    om = standard_map
    found = 0
    for i, j in zip(*np.nonzero(np.asarray(om.outcome) == INTERMEDIATE)):
        J = float(om.jellet[i, j])
        predicted = [th for th, st in tj.steady_states(om.top, J).intermediate if st]
        assert len(predicted) == 1
        np.testing.assert_allclose(float(om.theta_expected[i, j]), predicted[0], atol=1e-9)
        # Nutation decays slowly on the intermediate state: a few hundredths of a radian.
        assert abs(float(om.theta_final[i, j]) - predicted[0]) < 0.05
        found += 1
    assert found >= 1


def test_contact_loss_matches_a_single_simulation(standard_map):
    om = standard_map
    lost = np.argwhere(np.asarray(om.outcome) == tj.OUTCOMES.index("contact_lost"))
    assert lost.size, om.summary()  # the fastest launches leave the table
    i, j = lost[0]
    top = om.top
    sol = tj.simulate(
        top,
        tj.initial_state(top, THETA0[i], SPIN[j]),
        T1,
        summary=True,
        throw=False,
        rtol=om.rtol,
        atol=om.atol,
    )
    assert sol.result == tj.RESULTS.contact_lost
    np.testing.assert_allclose(float(om.t_contact_loss[i, j]), float(sol.t_contact_loss), rtol=1e-6)


def test_auto_picks_per_launch_what_simulate_would():
    top = tj.default_top()
    theta = np.array([0.05, 0.1, 0.5, 1.0, 1.4, 0.1, 0.3])
    spin = np.array([10.0, 40.0, 60.0, 100.0, 150.0, 300.0, 30.0])
    for tolerance in (None, 0.05, 0.5, 2.0):
        models, index = auto_models(top, theta, spin, tolerance)
        for k in range(theta.size):
            y0 = tj.initial_state(top, theta[k], spin[k])
            assert models[index[k]] == choose_model(top, y0, tolerance=tolerance)


def test_tops_map_classifies_each_top_against_its_own_states():
    base = tj.default_top()
    a = np.array([0.7, 1.3])
    e = np.array([0.2, 0.4])
    om = tj.outcome_map_tops(base, a, e, theta0=0.1, spin=120.0, t1=20.0)
    assert om.axes == ("A_over_C", "eps_over_R") and om.outcome.shape == (2, 2)
    for i in range(2):
        for j in range(2):
            top = tj.TippeTop.from_ratios(a[i], e[j], m=base.m, R=base.R, mu=base.mu, C=base.C)
            code = int(om.outcome[i, j])
            if code > INTERMEDIATE:
                continue
            J = tj.jellet(top, tj.initial_state(top, 0.1, 120.0))
            stable = _stable_by_analysis(top, J)
            theta_f = float(om.theta_final[i, j])
            k = int(np.argmin([abs(theta_f - th) for th, _ in stable]))
            assert stable[k][1] == code
    # Group III (A/C > 1 + eps/R): theta = pi is never stable, the top does not invert.
    assert tj.classify(tj.TippeTop.from_ratios(1.3, 0.2, m=base.m, R=base.R, C=base.C)) == "III"
    assert int(om.outcome[1, 0]) in (UPRIGHT, INTERMEDIATE)


@pytest.mark.slow
def test_map_in_blocks_is_each_launchs_single_run(monkeypatch):
    """On CPU devices a map's launches run in blocks (`run_in_blocks`, as in simulate_batch):
    with blocks of 2, a map of 3 x 2 tops (their fields split into the blocks) holds each
    top's own single run, the padding cut off."""
    from tippejax import _devices
    from tippejax._maps import runs

    monkeypatch.setattr(_devices, "PER_MEMBER_BLOCK", 2)
    calls = []
    run = runs._run_chunk_cpu
    monkeypatch.setattr(runs, "_run_chunk_cpu", lambda *a: calls.append(a) or run(*a))
    base = tj.default_top()
    a, e = np.array([0.7, 1.0, 1.3]), np.array([0.2, 0.4])
    om = tj.outcome_map_tops(base, a, e, theta0=0.1, spin=120.0, t1=2.0)
    assert calls and {c[-1] for c in calls} == {2}
    for i in range(a.size):
        for j in range(e.size):
            top = tj.TippeTop.from_ratios(a[i], e[j], m=base.m, R=base.R, mu=base.mu, C=base.C)
            sol = tj.simulate(
                top,
                tj.initial_state(top, 0.1, 120.0),
                2.0,
                summary=True,
                throw=False,
                rtol=om.rtol,
                atol=om.atol,
            )
            assert abs(float(om.theta_final[i, j]) - float(sol.theta[-1])) < 1e-8
            assert float(om.t_final[i, j]) == pytest.approx(float(sol.t_final), abs=1e-12)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(model="fast"), "unknown model"),
        (dict(t1=-1.0), "t1 must be"),
        (dict(theta0=[0.1, 4.0]), "theta0 must lie"),
        (dict(spin=[np.nan]), "spin must be finite"),
        (dict(chunk_size=0), "chunk_size"),
        (dict(settle_tol=0.0), "settle_tol"),
    ],
)
def test_bad_arguments_are_refused(kwargs, match):
    args = dict(theta0=[0.1], spin=[50.0], t1=1.0)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        tj.outcome_map(tj.default_top(), **args)


def test_tops_map_refuses_impossible_bodies():
    with pytest.raises(ValueError, match="A/C < 1/2"):
        tj.outcome_map_tops(tj.default_top(), [0.4], [0.3], theta0=0.1, spin=50.0, t1=1.0)
    with pytest.raises(ValueError, match="eps_over_R"):
        tj.outcome_map_tops(tj.default_top(), [0.9], [1.0], theta0=0.1, spin=50.0, t1=1.0)


@pytest.mark.slow
def test_two_processes_with_jax_distributed_give_the_single_process_map(tmp_path):
    """Two CPU processes (two devices each: four shards) with jax.distributed."""
    script = os.path.join(ROOT, "examples", "distributed_map.py")
    common = ["--n-theta", "2", "--n-spin", "3", "--t1", "4", "--chunk-size", "4"]
    env = host_devices_env(2, JAX_PLATFORMS="cpu")
    import socket

    with socket.socket() as s:
        s.bind(("localhost", 0))
        port = s.getsockname()[1]
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                script,
                "--coordinator",
                f"localhost:{port}",
                "--num-processes",
                "2",
                "--process-id",
                str(pid),
                "--out",
                str(tmp_path / f"map{pid}.npz"),
                *common,
            ],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for pid in (0, 1)
    ]
    outs = [p.communicate(timeout=500)[0] for p in procs]
    for p, out in zip(procs, outs):
        assert p.returncode == 0, out[-3000:]
    got = np.load(tmp_path / "map0.npz")
    assert int(got["process_count"]) == 2 and int(got["device_count"]) == 4
    # chunk 4 over 4 devices: two chunks, one padded; every process ran its own shards.
    om = tj.outcome_map(
        tj.default_top(),
        got["theta0"],
        got["spin"],
        t1=4.0,
        model="full",
        devices=jax.devices()[:1],
    )
    np.testing.assert_array_equal(got["outcome"], np.asarray(om.outcome))
    np.testing.assert_allclose(
        got["theta_final"], np.asarray(om.theta_final), rtol=1e-9, atol=1e-12
    )
    np.testing.assert_array_equal(got["num_steps"], np.asarray(om.num_steps))


@pytest.mark.slow
def test_map_command_writes_both_maps(tmp_path, capsys):
    from tippejax._cli import main

    # Grid shapes as in the tests above (2 x 3 launches, 2 x 2 tops): no new compilation.
    code = main(
        [
            "map",
            "--n-theta",
            "2",
            "--n-spin",
            "3",
            "--t1",
            "2",
            "--n-tops",
            "2",
            "--group",
            "IIa",
            "--out",
            str(tmp_path),
        ]
    )
    out = capsys.readouterr().out
    assert code == 0, out
    assert "Group IIa" in out and "launches/s" in out
    for name in ("outcome_map.png", "outcome_map.npz", "outcome_map_tops.png"):
        assert (tmp_path / name).stat().st_size > 0
    saved = np.load(tmp_path / "outcome_map.npz")
    assert saved["outcome"].shape == (2, 3)
    assert set(saved["outcomes"].tolist()) == set(tj.OUTCOMES)


def test_map_command_rejects_a_degenerate_grid(tmp_path, capsys):
    from tippejax._cli import main

    assert main(["map", "--n-theta", "1", "--out", str(tmp_path)]) == 2
    assert "at least 2" in capsys.readouterr().err


def test_map_messages_are_read_elementwise(standard_map):
    om = standard_map
    msgs = om.message()
    assert msgs.shape == om.outcome.shape
    np.testing.assert_array_equal(msgs, tj.RESULTS.message(om.result))
    ok = np.asarray(om.result) == 0
    assert np.all(msgs[ok] == "successful")
    lost = np.asarray(om.outcome) == tj.OUTCOMES.index("contact_lost")
    assert lost.any()
    assert np.all(msgs[lost] == tj.RESULTS[tj.RESULTS.contact_lost])


@pytest.mark.parametrize(
    "tops",
    [
        tj.default_top().replace(mu=[0.1, 0.3]),
        tj.TippeTop.from_ratios([0.9, 1.1], 0.3),
    ],
)
def test_map_of_a_batch_of_tops_is_refused_clearly(tops):
    with pytest.raises(ValueError, match="maps one top, but this TippeTop is a batch"):
        tj.outcome_map(tops, THETA0, SPIN, t1=T1)
    with pytest.raises(ValueError, match="maps one top"):
        tj.outcome_map_tops(tops, [0.9], [0.3], theta0=0.1, spin=100.0, t1=T1)


@pytest.fixture(scope="module")
def auto_map():
    """The grid of `standard_map` with `model="auto"`: staged, see
    `tippejax/_maps/stages.py`."""
    return tj.outcome_map(tj.default_top(), THETA0, SPIN, t1=T1, model="auto")


@pytest.mark.slow
def test_auto_map_gives_the_full_models_outcomes(standard_map, auto_map):
    """The staged auto map ends every launch where the full model does, on a grid with contact
    losses, launches the gyroscopic level refuses (tilted 0.6 and 1.2 rad) and runs it hands
    back to the full model; a contact loss is the full model's own (a replay; the windows
    restart the solver, so its steps and the located time differ at the level of rtol 1e-6:
    a restart from the slow manifold was off by 0.1-0.7 s)."""
    full, auto = standard_map, auto_map
    np.testing.assert_array_equal(np.asarray(auto.outcome), np.asarray(full.outcome))
    lost = np.asarray(full.outcome) == tj.OUTCOMES.index("contact_lost")
    assert lost.any()
    np.testing.assert_allclose(
        np.asarray(auto.t_contact_loss)[lost], np.asarray(full.t_contact_loss)[lost], rtol=1e-4
    )
    routes = np.asarray(auto.models)[np.asarray(auto.model_index)]
    top = full.top
    refused = ~np.array(
        [
            [bool(LEVELS["gyroscopic"].in_chart(top, tj.initial_state(top, th, sp))) for sp in SPIN]
            for th in THETA0
        ]
    )
    assert refused.any() and (~refused).any()
    # a refused launch starts in the full model; an accepted one in the slow flow
    assert all(r.startswith("full") for r in routes[refused])
    assert all(r.startswith("gyroscopic") for r in routes[~refused])
    # the slow flow ran somewhere, and some run went back to the full model after it
    assert any("gyroscopic" in r for r in routes.ravel())
    assert any("gyroscopic->full" in r for r in routes.ravel())
    # the slow flow takes tens of steps where the full model takes hundreds or thousands
    assert np.sum(np.asarray(auto.num_steps)) < np.sum(np.asarray(full.num_steps))


@pytest.mark.slow
def test_auto_map_stages_are_organised_as_claimed():
    """Each stage is a batch of its own: the slow stages take few steps; the first full stage
    holds exactly the launches the gyroscopic level refuses; a launch is in a full stage after
    a slow stage only if that slow stage handed it back, and a launch the slow stage finished
    (or that lost contact) is in no later stage."""
    top = tj.default_top()
    th, sp = np.meshgrid(THETA0, SPIN, indexing="ij")
    y0 = tj.initial_state(top, th.ravel(), sp.ravel())
    refused = ~np.asarray(jax.vmap(lambda y: LEVELS["gyroscopic"].in_chart(top, y))(y0))
    run = staged_outcomes(
        top,
        y0,
        8.0,
        rtol=1e-6,
        atol=1e-9,
        solver=tj.default_solver(top),
        slow_solver=tj.default_solver(top, slow_flow=True),
        max_steps=200_000,
        devices=jax.devices(),
    )
    stages = run["stages"]
    level, members, _, _ = stages[0]
    assert level == "full" and set(members) == set(np.flatnonzero(refused))
    handed_back = tj.RESULTS.no_gyroscopic_balance._value
    finished, pending, slow_seen = set(), set(), set()
    for level, members, steps, codes in stages:
        assert not finished & set(members), "a finished run came back"
        if level == "gyroscopic":
            assert steps.max() < 100, steps.max()
            slow_seen |= set(members)
            pending |= set(members[codes == handed_back])
            finished |= set(members[codes != handed_back])
        else:
            # back in the full model after the slow flow only if the slow flow handed it back
            assert set(members) & slow_seen <= pending
            finished |= set(members[codes != 0])
    assert pending, "no run was handed back on this grid"
    assert np.all(run["hand_overs"][sorted(pending)] >= 1)
