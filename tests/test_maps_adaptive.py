"""Adaptive outcome maps, maps over any two axes, and their boundaries (`tippejax._maps`)."""

import json
import os
import socket
import subprocess
import sys

import jax
import numpy as np
import pytest
from helpers import host_devices_env

import tippejax as tj
from tippejax._invariants import normal_force_denominator
from tippejax._maps import refine as refine_module
from tippejax._maps.boundaries import box_counting_dimension
from tippejax._maps.refine import refine
from tippejax._outcome import CONTACT_LOST, INTERMEDIATE, UPRIGHT

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# --- the refinement alone, on outcomes given in closed form ---------------------------------


def _plane(n):
    x = np.linspace(-1.0, 1.0, n)
    return np.meshgrid(x, x, indexing="ij")


ISLAND = (-0.671875, 0.578125)  # a quarter of a base cell (n = 129, refine 4) from a corner


def _closed_form(n):
    """A disc (1), a wavy band (2) and an island (3) far smaller than a base cell, with an
    indicator of the island: the distance to its rim (the contact margin's role)."""
    X, Y = _plane(n)
    outcome = np.where(np.hypot(X - 0.2, Y + 0.1) < 0.5, 1, 0)
    outcome = np.where(X + 0.3 * np.sin(3 * Y) > 0.6, 2, outcome)
    rim = np.hypot(X - ISLAND[0], Y - ISLAND[1]) - 0.03
    outcome = np.where(rim < 0, 3, outcome)
    return outcome, rim


def _evaluator(outcome, margin, calls):
    def evaluate(i, j, hint):
        calls.append((i.copy(), j.copy()))
        nan = np.full(i.size, np.nan)
        return dict(
            outcome=outcome[i, j].astype(np.int8),
            num_steps=np.ones(i.size, np.int32),
            contact_margin=margin[i, j],
            decision_margin=np.full(i.size, np.pi),
            theta_max=np.zeros(i.size),
            t_invert=nan,
            t_contact_loss=nan,
            settled=np.ones(i.size, bool),
            result=np.zeros(i.size, np.int8),
        )

    return evaluate


def test_refinement_reproduces_a_map_from_a_small_share_of_it():
    n, levels = 257, 4
    outcome, rim = _closed_form(n)
    calls = []
    out = refine((n, n), levels, _evaluator(outcome, rim, calls), t1=1.0)
    np.testing.assert_array_equal(out.fields["outcome"], outcome)
    # every point simulated once, each call one batch of new points, the base grid first
    simulated = np.zeros((n, n), int)
    for i, j in calls:
        np.add.at(simulated, (i, j), 1)
    assert simulated.max() == 1 and np.array_equal(simulated > 0, out.simulated)
    assert calls[0][0].size == (n // 2**levels + 1) ** 2
    assert [c[0].size for c in calls] == [h[0] for h in out.history]
    assert out.simulated.mean() < 0.1
    assert out.resolved.all() and not out.stopped
    # the launches not simulated hold the fields of none
    assert np.all(np.isnan(out.fields["contact_margin"][~out.simulated]))


def test_island_smaller_than_the_base_grid_is_found_through_its_indicator(monkeypatch):
    """The island (radius 0.03, base cells 0.25 wide) holds no point of the base grid; its
    indicator (the distance to its rim, smallest at the corner it is near, with a spread
    over the corners that points to a zero inside the cell) splits that cell down to the
    island. Without the indicator the cell is kept whole. (An island in the middle of a base
    cell, with an indicator as large at every corner, would not be seen: see
    `outcome_map`'s docstring.)"""
    n, levels = 129, 4
    outcome, rim = _closed_form(n)
    base = refine_module.base_indices(n, 2**levels)
    assert not np.any(outcome[np.ix_(base, base)] == 3)
    found = refine((n, n), levels, _evaluator(outcome, rim, []), t1=1.0)
    np.testing.assert_array_equal(found.fields["outcome"] == 3, outcome == 3)
    monkeypatch.setattr(refine_module, "NEAR_ZERO", 0.0)
    blind = refine((n, n), levels, _evaluator(outcome, rim, []), t1=1.0)
    assert not np.any(blind.fields["outcome"] == 3)


def test_refinement_stops_where_the_boundary_fills_the_region():
    """A square whose outcome flips from point to point (a boundary of dimension 2): the base
    cells inside it stop refining, their dimension is reported above the threshold, and their
    launches are flagged unresolved; the disc's boundary elsewhere is resolved."""
    n, levels = 257, 5
    X, Y = _plane(n)
    outcome = np.where(np.hypot(X + 0.4, Y + 0.4) < 0.3, 1, 0)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    noisy = (X > 0.3) & (Y > 0.3)
    outcome = np.where(noisy, ((i * 7919 + j * 104729) % 13 < 6).astype(int) + 1, outcome)
    out = refine((n, n), levels, _evaluator(outcome, np.ones((n, n)), []), t1=1.0)
    assert out.stopped
    for i0, i1, j0, j1, dimension in out.stopped:
        assert noisy[i0 : i1 + 1, j0 : j1 + 1].any()
        assert dimension > refine_module.DIMENSION_STOP
    inside = np.zeros((n, n), bool)
    for i0, i1, j0, j1, _ in out.stopped:
        inside[i0 : i1 + 1, j0 : j1 + 1] = True
    assert np.all(inside[~out.resolved])
    disc = np.hypot(X + 0.4, Y + 0.4) < 0.6
    np.testing.assert_array_equal(out.fields["outcome"][disc], outcome[disc])
    assert (~out.resolved).sum() > 0 and out.simulated[noisy].mean() < 0.9


def test_box_counting_dimension_of_a_line_a_circle_and_a_square():
    n = 512
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    line = i == j
    circle = np.abs(np.hypot(i - n / 2, j - n / 2) - n / 3) < 0.75
    square = (i > n // 4) & (i < 3 * n // 4) & (j > n // 4) & (j < 3 * n // 4)
    assert box_counting_dimension(line) == pytest.approx(1.0, abs=0.05)
    assert box_counting_dimension(circle) == pytest.approx(1.0, abs=0.1)
    assert box_counting_dimension(square) == pytest.approx(2.0, abs=0.1)


# --- adaptive maps of the full model --------------------------------------------------------

THETA0 = np.linspace(0.05, 1.4, 17)
SPIN = np.linspace(20.0, 220.0, 17)
T1 = 6.0
CHUNK = 8  # one chunk shape: every map of this module runs one compiled program


@pytest.fixture(scope="module")
def dense():
    return tj.outcome_map(tj.default_top(), THETA0, SPIN, t1=T1, chunk_size=CHUNK)


@pytest.fixture(scope="module")
def adaptive():
    return tj.outcome_map(tj.default_top(), THETA0, SPIN, t1=T1, chunk_size=CHUNK, refine=2)


def _near_a_boundary(outcome, cells=1):
    """Points with a point of another outcome within `cells` (chessboard distance)."""
    near = np.zeros(outcome.shape, bool)
    n1, n2 = outcome.shape
    for di in range(-cells, cells + 1):
        for dj in range(-cells, cells + 1):
            a = outcome[max(di, 0) : n1 + min(di, 0), max(dj, 0) : n2 + min(dj, 0)]
            b = outcome[max(-di, 0) : n1 + min(-di, 0), max(-dj, 0) : n2 + min(-dj, 0)]
            near[max(-di, 0) : n1 + min(-di, 0), max(-dj, 0) : n2 + min(-dj, 0)] |= a != b
    return near


def test_adaptive_map_agrees_with_the_dense_map(dense, adaptive):
    simulated = np.asarray(adaptive.simulated)
    assert 0.2 < adaptive.share_simulated < 1.0
    assert sum(points for points, _ in adaptive.levels) == simulated.sum()
    # a simulated launch is the dense map's own run
    for name in ("outcome", "theta_final", "t_final", "num_steps", "contact_margin"):
        np.testing.assert_array_equal(
            np.asarray(getattr(adaptive, name))[simulated],
            np.asarray(getattr(dense, name))[simulated],
        )
    assert np.all(np.isnan(np.asarray(adaptive.theta_final)[~simulated]))
    true, got = np.asarray(dense.outcome), np.asarray(adaptive.outcome)
    differ = true != got
    assert differ.mean() <= 0.02, (true, got)
    assert np.all(_near_a_boundary(true)[differ])
    # the map has the outcomes whose boundaries the refinement follows
    assert {UPRIGHT, INTERMEDIATE, CONTACT_LOST} <= set(np.unique(true).tolist())


def test_boundary_of_the_upright_launches_lies_within_one_cell_of_J1(adaptive):
    """For J < J1 the upright state is the only stable one of the standard top (Group IIb),
    for J > J1 it is not stable: the classification puts the boundary of the upright launches
    on the curve J = J1 (W''(0; J) = 0), and the map must find it within a cell."""
    found = [b for b in adaptive.boundaries() if b.outcomes == ("upright", "intermediate")]
    assert len(found) == 1
    b = found[0]
    assert b.theory == "J1" and b.lines and b.cells >= 10
    assert b.distance_max <= 1.0, b
    # the polylines lie in the map, midway between launches
    points = np.concatenate(b.lines)
    assert np.all((points[:, 0] >= THETA0[0]) & (points[:, 0] <= THETA0[-1]))
    assert np.all((points[:, 1] >= SPIN[0]) & (points[:, 1] <= SPIN[-1]))
    curves = adaptive.theory_curves()
    assert curves["J1"] and curves["J2"]


def test_indicators_are_the_extremes_of_each_run(dense):
    """`contact_margin` and `theta_max` (kept by the engine at the accepted steps' ends) of
    one launch of each outcome against the same launch run by `tj.simulate` with 6001 saved
    states: the smallest $R_n D / g$ (`tippejax._invariants`) and the largest tilt over them.
    The steps' ends are points of the run, so the map's values lie within the saved range,
    up to what falls between saved points; a contact-lost run ends at $R_n = 0$."""
    top = dense.top
    ts = np.linspace(0.0, T1, 6001)
    outcome = np.asarray(dense.outcome)
    for code in (UPRIGHT, INTERMEDIATE, CONTACT_LOST):
        i, j = (int(k[0]) for k in np.nonzero(outcome == code))
        sol = tj.simulate(
            top,
            tj.initial_state(top, THETA0[i], SPIN[j]),
            T1,
            saveat=ts,
            throw=False,
            rtol=dense.rtol,
            atol=dense.atol,
        )
        ran = ts <= float(sol.t_final)
        margin = np.asarray(sol.normal_force * normal_force_denominator(top, sol.states))
        margin = margin[ran] / float(top.g)
        theta = np.asarray(sol.theta)[ran]
        got_margin, got_theta = float(dense.contact_margin[i, j]), float(dense.theta_max[i, j])
        assert got_margin <= np.nanmin(margin) + 0.05, code
        if code == CONTACT_LOST:  # the run ends where R_n reaches 0, after the last saved state
            assert abs(got_margin) < 0.05
            theta = np.r_[theta, float(dense.theta_final[i, j])]
        else:
            assert got_margin >= np.nanmin(margin) - 1e-3, code
        assert np.nanmax(theta) - 0.02 <= got_theta <= np.nanmax(theta) + 1e-3, code
    lost = outcome == CONTACT_LOST
    assert np.all(np.abs(np.asarray(dense.contact_margin)[lost]) < 0.05)


FLOAT32 = """
import json, sys
import numpy as np
import tippejax as tj
th, sp, t1, chunk = json.loads(sys.argv[1])
om = tj.outcome_map(tj.default_top(), np.array(th), np.array(sp), t1=t1, chunk_size=chunk,
                    refine=2)
print(json.dumps(dict(dtype=str(om.theta_final.dtype), outcome=np.asarray(om.outcome).tolist(),
                      simulated=np.asarray(om.simulated).tolist(),
                      theory=[b.theory for b in om.boundaries()])))
"""


@pytest.mark.slow
def test_float32_adaptive_map_differs_from_float64_only_next_to_a_boundary(adaptive):
    """The same adaptive map in a float32 process (TIPPEJAX_ENABLE_X64=0): it runs in float32
    and its outcomes differ from the float64 map's only beside a boundary of that map."""
    env = dict(os.environ, TIPPEJAX_ENABLE_X64="0")
    args = [THETA0.tolist(), SPIN.tolist(), T1, CHUNK]
    out = subprocess.run(
        [sys.executable, "-c", FLOAT32, json.dumps(args)],
        env=env,
        capture_output=True,
        text=True,
        check=True,
        timeout=600,
    ).stdout
    r = json.loads(out.strip().splitlines()[-1])
    assert r["dtype"] == "float32"
    assert not np.all(r["simulated"]) and "J1" in r["theory"]
    ref, got = np.asarray(adaptive.outcome), np.array(r["outcome"])
    differ = ref != got
    assert differ.mean() <= 0.02
    assert np.all(_near_a_boundary(ref)[differ])


def test_any_axes_map_matches_single_simulations():
    """A map over theta_dot x mu (the launch quantity first), each cell one launch of its own
    top, against single runs of `tj.simulate`."""
    top = tj.default_top()
    theta_dot, mu = np.array([-2.0, 0.0, 3.0]), np.array([0.1, 0.6])
    om = tj.outcome_map(
        top, mu=mu, theta_dot=theta_dot, theta0=0.3, spin=120.0, t1=2.0, chunk_size=CHUNK
    )
    assert om.axes == ("theta_dot", "mu") and om.outcome.shape == (3, 2)
    np.testing.assert_array_equal(np.asarray(om.axis_values[1]), mu)
    assert dict(om.fixed) == {"theta0": 0.3, "spin": 120.0}
    for i, td in enumerate(theta_dot):
        for j, m in enumerate(mu):
            one = top.replace(mu=m)
            sol = tj.simulate(
                one,
                tj.initial_state(one, 0.3, 120.0, theta_dot=td),
                2.0,
                summary=True,
                throw=False,
                rtol=om.rtol,
                atol=om.atol,
            )
            assert int(om.outcome[i, j]) == int(sol.outcome)
            assert float(om.theta_final[i, j]) == pytest.approx(float(sol.theta[-1]), abs=1e-6)
            assert float(om.t_final[i, j]) == pytest.approx(float(sol.t_final), abs=1e-9)
    # the order of the axes can be given
    swapped = tj.outcome_map(
        top,
        mu=mu,
        theta_dot=theta_dot,
        theta0=0.3,
        spin=120.0,
        t1=2.0,
        chunk_size=CHUNK,
        axes=("mu", "theta_dot"),
    )
    np.testing.assert_array_equal(np.asarray(swapped.outcome), np.asarray(om.outcome).T)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(omega=1.0), "unknown quantity 'omega'"),
        (dict(theta0=[0.1, 0.3, 0.2]), "strictly increasing or strictly decreasing"),
        (dict(spin=[50.0, 50.0, 60.0]), "strictly increasing"),
        (dict(mu=[0.1, 0.2]), "a map has two axes, but 3"),
        (dict(A=4e-6, A_over_C=0.9), "give A or A_over_C, not both"),
        (dict(axes=("spin", "spin")), "twice"),
        (dict(axes=("spin", "mu")), "give its values"),
        (dict(axes=("spin", "omega"), omega=[1.0]), "unknown quantity"),
        (dict(spin=None), "give spin"),
        (dict(theta0=0.1, spin=50.0, eps_over_R=[0.2, 1.2]), "eps"),
        (dict(spin=[[50.0]]), "1-d list"),
        (dict(refine=-1), "refine must be"),
        (dict(refine=True), "refine must be"),
        (dict(refine=2, model="auto"), "refine runs one level"),
        (dict(theta0=0.1, mu=[0.1, 0.2], model="auto"), "maps theta0 x spin only"),
    ],
)
def test_bad_axes_are_refused(kwargs, match):
    args = dict(theta0=[0.1, 0.2], spin=[50.0, 60.0], t1=1.0)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        tj.outcome_map(tj.default_top(), **args)


def test_a_launch_quantity_on_a_map_of_tops_is_refused():
    with pytest.raises(ValueError, match="maps tops for one launch: theta0 must be a number"):
        tj.outcome_map_tops(
            tj.default_top(), [0.9, 1.0], [0.2, 0.3], theta0=[0.1, 0.2], spin=50.0, t1=1.0
        )


def test_two_processes_spread_each_level_and_give_the_single_process_map(tmp_path):
    """`examples/distributed_map.py --refine 2` in two CPU processes (two devices each) with
    jax.distributed, as the dense map's test runs it: every level is sharded over the four
    devices, and the map is the one process's map."""
    script = os.path.join(ROOT, "examples", "distributed_map.py")
    common = ["--n-theta", "9", "--n-spin", "9", "--t1", "3", "--chunk-size", "4", "--refine", "2"]
    with socket.socket() as s:
        s.bind(("localhost", 0))
        port = s.getsockname()[1]
    env = host_devices_env(2, JAX_PLATFORMS="cpu")
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
    logs = [p.communicate(timeout=500)[0] for p in procs]
    for p, log in zip(procs, logs):
        assert p.returncode == 0, log[-3000:]
    got = np.load(tmp_path / "map0.npz")
    assert int(got["process_count"]) == 2 and int(got["device_count"]) == 4
    assert len(got["levels"]) > 1 and not got["simulated"].all()
    om = tj.outcome_map(
        tj.default_top(),
        got["theta0"],
        got["spin"],
        t1=3.0,
        refine=2,
        chunk_size=4,
        devices=jax.devices()[:1],
    )
    np.testing.assert_array_equal(got["outcome"], np.asarray(om.outcome))
    np.testing.assert_array_equal(got["simulated"], np.asarray(om.simulated))
    np.testing.assert_array_equal(got["levels"], np.array(om.levels))
    np.testing.assert_allclose(
        got["theta_final"], np.asarray(om.theta_final), rtol=1e-9, atol=1e-12
    )


def test_map_command_draws_an_adaptive_map_and_writes_it(tmp_path, capsys):
    from tippejax._cli import main

    code = main(
        [
            "map",
            "--resolution",
            "9",
            "--adaptive",
            "--refine",
            "2",
            "--t1",
            "2",
            "--no-tops",
            "--out",
            str(tmp_path),
        ]
    )
    out = capsys.readouterr().out
    assert code == 0, out
    assert "adaptive, refine = 2" in out and "boundary upright | intermediate" in out
    assert (tmp_path / "outcome_map.png").stat().st_size > 0
    saved = np.load(tmp_path / "outcome_map.npz")  # no pickle needed
    assert list(saved["axes"]) == ["theta0", "spin"] and int(saved["refine"]) == 2
    assert saved["outcome"].shape == saved["simulated"].shape == (9, 9)
    assert saved["simulated"].dtype == bool and not saved["simulated"].all()
    np.testing.assert_array_equal(saved["axis0"], np.linspace(0.02, 1.5, 9))
    # the polylines: every line's points, where each starts, the pair it parts
    starts, points = saved["boundary_starts"], saved["boundary_points"]
    assert points.shape[1] == 2 and len(starts) == len(saved["boundary_pairs"]) >= 1
    assert "upright|intermediate" in set(saved["boundary_pairs"].tolist())
    assert set(saved["theory_pairs"].tolist()) <= {"J1", "J2"}
