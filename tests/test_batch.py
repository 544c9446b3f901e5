"""simulate_batch: a grid of launches in one compiled batch, and sharding over devices."""

import json
import subprocess
import sys

import numpy as np
import pytest
from helpers import host_devices_env

import tippejax as tj

TS = np.linspace(0.0, 1.0, 21)


def test_batch_equals_single_runs():
    top = tj.default_top()
    thetas, spins = [0.1, 0.4], [30.0, 90.0]
    batch = tj.simulate_batch(top, thetas, spins, 1.0, saveat=TS)
    assert batch.theta.shape == (2, 2, TS.size)
    assert np.all(np.asarray(batch.result == tj.RESULTS.successful))
    for i, th in enumerate(thetas):
        for j, n in enumerate(spins):
            single = tj.simulate(top, tj.initial_state(top, th, n), 1.0, saveat=TS)
            assert np.max(np.abs(np.asarray(batch.theta[i, j]) - np.asarray(single.theta))) < 1e-9
    # A second call with the same shapes reuses the compiled batch (no new trace).
    from tippejax._batch import _batch_run_cpu

    run = _batch_run_cpu.jitted
    before = run._cached._cache_size() if hasattr(run, "_cached") else None
    tj.simulate_batch(top, [0.2, 0.3], [40.0, 80.0], 1.0, saveat=TS)
    if before is not None:
        assert before >= 1 and run._cached._cache_size() == before


SCRIPT = r"""
import json, numpy as np, jax
import tippejax as tj
top = tj.default_top()
ts = np.linspace(0.0, 0.5, 11)
sharded = tj.simulate_batch(top, [0.1, 0.2, 0.3], [50.0, 100.0], 0.5, saveat=ts)
plain = tj.simulate_batch(top, [0.1, 0.2, 0.3], [50.0, 100.0], 0.5, saveat=ts, shard=False)
# The compiled program of the sharded batch: each device runs its own members' loops, with no
# reduction across the devices (jit's automatic partitioning put an all-reduce of the loop
# condition into every while loop of the solve).
from tippejax import _batch
calls = []
run = _batch._batch_run_cpu
_batch._batch_run_cpu = lambda *args: calls.append(args) or run(*args)
tj.simulate_batch(top, [0.1, 0.2, 0.3], [50.0, 100.0], 0.5, saveat=ts)
hlo = run.lower(*calls[0]).compile().compiled.as_text()
print(json.dumps(dict(devices=jax.device_count(),
    diff=float(np.max(np.abs(np.asarray(sharded.theta) - np.asarray(plain.theta)))),
    shape=list(sharded.theta.shape), whiles=hlo.count(" while("),
    collectives=sum(hlo.count(op) for op in ("all-reduce", "all-gather", "collective-permute",
                                             "all-to-all")))))
"""


@pytest.mark.slow
def test_sharded_batch_on_four_host_devices():
    """The same numbers as one device; every device loops over its own members alone. Slow:
    every batch test runs sharded over the default run's host devices; this is the four-device
    route."""
    env = host_devices_env(4)
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, check=True
    ).stdout
    r = json.loads(out.strip().splitlines()[-1])
    assert r["devices"] == 4
    assert r["shape"] == [3, 2, 11]  # 6 launches padded to 8 and cut back
    assert r["diff"] < 1e-12
    assert r["whiles"] > 0 and r["collectives"] == 0


@pytest.mark.slow
def test_bucketed_batch_equals_unbucketed():
    """buckets > 1 sorts launches by spin into equal-size batches and puts results back. Slow: a
    second route of the batch against itself."""
    top = tj.default_top()
    thetas, spins = [0.1, 0.4], [90.0, 30.0]  # spins out of order: the sort must be undone
    plain = tj.simulate_batch(top, thetas, spins, 1.0, saveat=TS)
    for buckets in (2, 3):  # 3 buckets of 2: padded from 4 launches to 6
        bucketed = tj.simulate_batch(top, thetas, spins, 1.0, saveat=TS, buckets=buckets)
        assert bucketed.theta.shape == plain.theta.shape == (2, 2, TS.size)
        assert np.all(np.asarray(bucketed.result == tj.RESULTS.successful))
        # equal to about rtol: a member's rounding can depend on the size of its batch
        diff = np.max(np.abs(np.asarray(bucketed.theta) - np.asarray(plain.theta)))
        assert diff < 1e-6, diff
        np.testing.assert_allclose(
            np.asarray(bucketed.spin[..., 0]), np.asarray(plain.spin[..., 0]), rtol=1e-12
        )


@pytest.mark.slow
def test_blocks_of_members_equal_single_runs(monkeypatch):
    """A CPU device's shard runs in blocks of at most PER_MEMBER_BLOCK members (`lax.map` over
    `vmap`, padded to equal blocks): with blocks of 2, a sweep of 2 tops x 3 spins (the tops'
    fields split into the blocks with the launches) is every member's single run, the padding
    cut off. Slow: a second route of the batch against single runs
    (`test_batch_equals_single_runs`)."""
    from tippejax import _batch, _devices

    monkeypatch.setattr(_devices, "PER_MEMBER_BLOCK", 2)
    calls = []
    run = _batch._batch_run_cpu
    monkeypatch.setattr(_batch, "_batch_run_cpu", lambda *a: calls.append(a) or run(*a))
    top = tj.default_top()
    tops = top.replace(mu=[0.1, 0.6], A_over_C=[0.9, 1.2])
    spins = [30.0, 60.0, 90.0]
    batch = tj.simulate_batch(tops, 0.3, spins, 1.0, grid=("top", "spin"), saveat=TS)
    assert [a[-1] for a in calls] == [2]  # blocks of 2 members
    assert batch.theta.shape == (2, 3, TS.size)
    assert np.all(batch.message() == "successful")
    for i, (mu, ac) in enumerate([(0.1, 0.9), (0.6, 1.2)]):
        one = top.replace(mu=mu, A_over_C=ac)
        for j, n in enumerate(spins):
            single = tj.simulate(one, tj.initial_state(one, 0.3, n), 1.0, saveat=TS)
            assert np.max(np.abs(np.asarray(batch.theta[i, j]) - np.asarray(single.theta))) < 1e-9
            assert int(batch.num_steps[i, j]) == int(single.num_steps)


def test_sweep_of_tops_and_launch_rates_equals_single_runs():
    """grid=("top", "spin") over a batch of tops (mu and A/C both vary), with theta_dot
    broadcast along the spin axis and a common phi_dot: every member is its single run."""
    top = tj.default_top()
    tops = top.replace(mu=[0.1, 0.6], A_over_C=[0.9, 1.2])
    spins = [30.0, 90.0]
    theta_dot = [0.0, 1.5]  # broadcasts along the spin axis (the last one)
    batch = tj.simulate_batch(
        tops, 0.3, spins, 1.0, theta_dot=theta_dot, phi_dot=2.0, grid=("top", "spin"), saveat=TS
    )
    assert batch.theta.shape == (2, 2, TS.size)
    assert np.all(batch.message() == "successful")
    for i, (mu, ac) in enumerate([(0.1, 0.9), (0.6, 1.2)]):
        one = top.replace(mu=mu, A_over_C=ac)
        for j, n in enumerate(spins):
            y0 = tj.initial_state(one, 0.3, n, theta_dot=theta_dot[j], phi_dot=2.0)
            single = tj.simulate(one, y0, 1.0, saveat=TS)
            assert np.max(np.abs(np.asarray(batch.theta[i, j]) - np.asarray(single.theta))) < 1e-9
            assert (
                np.max(np.abs(np.asarray(batch.phi_dot[i, j]) - np.asarray(single.phi_dot))) < 1e-7
            )
            assert int(batch.outcome[i, j]) == int(single.outcome)
    np.testing.assert_allclose(
        np.asarray(batch.theta_dot[:, :, 0]), [theta_dot, theta_dot], atol=1e-12
    )


def test_batch_shapes_broadcast_and_bad_sweeps_are_refused():
    top = tj.default_top()
    # Shapes only: the member count is checked before anything runs.
    with pytest.raises(ValueError, match="do not broadcast"):
        tj.simulate_batch(top.replace(mu=[0.1, 0.2, 0.3]), [0.1, 0.2], [50.0, 60.0], 1.0)
    with pytest.raises(ValueError, match="grid names must be among"):
        tj.simulate_batch(top, 0.1, 50.0, 1.0, grid=("theta",))
    with pytest.raises(ValueError, match="must be 1-d"):
        tj.simulate_batch(top, [[0.1, 0.2]], 50.0, 1.0)
    with pytest.raises(ValueError, match="must be finite"):
        tj.simulate_batch(top, 0.1, 50.0, 1.0, phi_dot=float("nan"), grid=())
    with pytest.raises(ValueError, match="not y0="):
        tj.simulate_batch(top, 0.1, 50.0, 1.0, y0=None)


@pytest.mark.parametrize("theta0", [5.7, [0.1, 90.0], -0.2])
def test_batch_in_degrees_is_a_value_error(theta0):
    top = tj.default_top()
    with pytest.raises(ValueError, match=r"theta0 must lie in \[0, pi\] rad") as info:
        tj.simulate_batch(top, theta0, [50.0], 1.0)
    if theta0 != -0.2:
        assert "np.deg2rad" in str(info.value)


# --------------------------------------------------------------------------------------------
# A batch keeps its inputs and exports itself (CSV, npz, xarray)
# --------------------------------------------------------------------------------------------

THETAS, SPINS_X = np.array([0.05, 0.1]), np.array([60.0, 100.0, 150.0])


@pytest.fixture(scope="module")
def summary_batch():
    return tj.simulate_batch(tj.default_top(), THETAS, SPINS_X, 1.0, summary=True)


def test_a_summary_batch_has_the_batch_shape_and_its_inputs(summary_batch):
    sol = summary_batch
    assert sol.theta.shape == (2, 3) and sol.position.shape == (2, 3, 2)
    assert sol.states.axis.shape == (2, 3, 3)
    assert sol.grid == ("theta0", "spin")
    np.testing.assert_array_equal(sol.coords()["theta0"], THETAS)
    np.testing.assert_array_equal(sol.coords()["spin"], SPINS_X)
    np.testing.assert_array_equal(sol.inputs["theta0"], np.repeat(THETAS[:, None], 3, 1))
    np.testing.assert_array_equal(sol.inputs["spin0"], np.repeat(SPINS_X[None], 2, 0))
    assert np.all(sol.inputs["mu"] == 0.3) and sol.inputs["A_over_C"].shape == (2, 3)
    # each member is the single run of its inputs (independent of the batch's bookkeeping)
    top = tj.default_top()
    one = tj.simulate(
        top,
        tj.initial_state(top, float(sol.inputs["theta0"][1, 2]), float(sol.inputs["spin0"][1, 2])),
        1.0,
        summary=True,
    )
    assert float(sol.theta[1, 2]) == pytest.approx(float(one.theta[-1]), abs=1e-7)
    with pytest.raises(ValueError, match="no grid"):
        one.coords()


def test_exports_round_trip(summary_batch, tmp_path):
    import csv

    sol = summary_batch
    sol.to_csv(tmp_path / "b.csv")
    with open(tmp_path / "b.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 6  # one row per member, in C order
    for k, row in enumerate(rows):
        i, j = divmod(k, 3)
        assert float(row["theta0"]) == THETAS[i] and float(row["spin0"]) == SPINS_X[j]
        assert float(row["theta_end"]) == float(sol.theta[i, j])
        assert row["outcome"] == tj.OUTCOMES[int(sol.outcome[i, j])]
        assert row["settled"] == str(bool(sol.settled[i, j]))
        assert row["message"] == "successful"
    sol.to_npz(tmp_path / "b.npz")
    z = np.load(tmp_path / "b.npz")
    np.testing.assert_array_equal(z["theta"], np.asarray(sol.theta))
    np.testing.assert_array_equal(z["inputs.spin0"], sol.inputs["spin0"])
    assert list(z["grid"]) == ["theta0", "spin"] and str(z["model"]) == "full"
    xr = pytest.importorskip("xarray")
    ds = sol.to_xarray()
    assert isinstance(ds, xr.Dataset) and ds.theta.dims == ("theta0", "spin0")
    assert float(ds.theta.sel(theta0=0.1, spin0=60.0)) == float(sol.theta[1, 0])
    assert float(ds.mu.sel(theta0=0.05, spin0=150.0)) == 0.3


def test_a_saved_batch_exports_its_series_over_time(tmp_path):
    pytest.importorskip("xarray")
    ts = np.linspace(0.0, 0.5, 6)
    mus = np.array([0.1, 1.0])
    sol = tj.simulate_batch(tj.default_top().replace(mu=mus), 0.1, 60.0, 0.5, grid=(), saveat=ts)
    ds = sol.to_xarray()
    assert ds.theta.dims == ("member_0", "time")
    np.testing.assert_allclose(ds.time.values, ts)
    np.testing.assert_array_equal(ds.mu.values, mus)
    sol.to_csv(tmp_path / "s.csv")
    z = np.genfromtxt(tmp_path / "s.csv", delimiter=",", names=True, dtype=None, encoding=None)
    np.testing.assert_allclose(z["theta_end"], np.asarray(sol.theta)[:, -1])


def test_a_batch_of_tops_with_a_friction_law_keeps_its_law():
    """Any law: the batch's tops carry the law's batched fields, and each member is its
    single run."""
    law = tj.CoulombContensou(mu=0.3, patch_radius=5e-4, slip_scale=1e-5)
    top = tj.TippeTop(m=0.006, R=0.015, eps=0.003, A=8e-7, C=7e-7, friction=law)
    mus = np.array([0.2, 0.4])
    sol = tj.simulate_batch(top.replace(mu=mus), 0.1, 180.0, 0.3, grid=(), summary=True)
    np.testing.assert_array_equal(sol.inputs["mu"], mus)
    assert np.all(sol.inputs["patch_radius"] == 5e-4)
    one = top.replace(mu=0.4)
    ref = tj.simulate(one, tj.initial_state(one, 0.1, 180.0), 0.3, summary=True)
    assert float(sol.theta[1]) == pytest.approx(float(ref.theta[-1]), abs=1e-6)
    assert float(sol.jellet[1]) == pytest.approx(float(ref.jellet[-1]), rel=1e-6)
