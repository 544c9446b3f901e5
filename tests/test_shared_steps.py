"""simulate_batch(steps="shared"): one solve for the whole batch, every member as its own run.

The shared path takes different steps from a member's own run (the shortest any member needs),
so the two agree to about the tolerances, not to rounding. Contact-loss times are compared
loosely: the grazing dips of R_n before a top leaves the table make them sensitive (at rtol
1e-8 both paths miss the converged time by up to ~1e-4 s for some spins).
"""

import json
import subprocess
import sys

import numpy as np
import pytest
from helpers import host_devices_env

import tippejax as tj

T1 = 8.0
SPINS = np.array([150.0, 155.0, 145.0, 330.0, 400.0, 160.0])  # 3 and 4 lose contact ~6.3 s
LOST = np.array([False, False, False, True, True, False])


def _pair(top, theta0, spin, **kw):
    return tuple(
        tj.simulate_batch(top, theta0, spin, steps=steps, **kw)
        for steps in ("per_member", "shared")
    )


def _close_times(a, b, atol):
    a, b = np.asarray(a), np.asarray(b)
    assert np.array_equal(np.isnan(a), np.isnan(b)), (a, b)
    ok = ~np.isnan(a)
    assert np.max(np.abs(a[ok] - b[ok]), initial=0.0) < atol, (a, b)


@pytest.fixture(scope="module")
def so3_summary():
    return _pair(tj.default_top(), 0.1, SPINS, t1=T1, model="so3", summary=True, grid=("spin",))


@pytest.fixture(scope="module")
def so3_reference():
    """The per-member runs of `so3_summary` converged (rtol 1e-12): the inversion times the
    two paths are held to."""
    return tj.simulate_batch(
        tj.default_top(),
        0.1,
        SPINS,
        t1=T1,
        model="so3",
        summary=True,
        grid=("spin",),
        steps="per_member",
        rtol=1e-12,
        atol=1e-14,
    )


GRAZING = np.array([False, False, False, True, False, False])
"""Members whose inversion falls in the grazing dips of R_n just before they leave the table
(spin 330: inverts at 6.2516 s, loses contact about 0.05 s later). There the per-member run at
the default rtol misses the converged inversion time by microseconds that move with rounding:
over spins 300-360 (16 that invert) by at most 6.0e-6 s with diffrax's stage loop and 1.25e-5 s
with tippejax's (`StageLoopERK`), median 2.2e-6 and 2.9e-6 s; the module docstring's contact-loss
sensitivity. The shared path, whose steps are the fastest member's, is within 1e-8 s of it."""


def _inversion_times_converge(per, shared, reference):
    ref = np.asarray(reference.t_invert)
    # every path against the converged runs: the shared one to 1e-5 s (measured <= 1e-8)
    _close_times(shared.t_invert, ref, 1e-5)
    # the per-member runs to 1e-5 s where the inversion is away from contact loss, to the
    # module's contact-loss tolerance (1e-4 s) in the grazing dips
    per_t = np.asarray(per.t_invert)
    _close_times(per_t[~GRAZING], ref[~GRAZING], 1e-5)
    _close_times(per_t[GRAZING], ref[GRAZING], 1e-4)


@pytest.mark.slow
def test_shared_summary_agrees_with_per_member(so3_summary, so3_reference):
    per, shared = so3_summary
    assert shared.theta.shape == per.theta.shape == (SPINS.size,)  # no save axis
    assert shared.model == "so3"
    # the same outcome per member: inverted tops invert, the fast ones lose contact and stop,
    # while the others go on to t1
    np.testing.assert_array_equal(np.asarray(shared.result._value), np.asarray(per.result._value))
    np.testing.assert_array_equal(np.asarray(shared.result == tj.RESULTS.contact_lost), LOST)
    np.testing.assert_array_equal(np.asarray(shared.outcome), np.asarray(per.outcome))
    t_final = np.asarray(shared.t_final)
    assert np.all(t_final[~LOST] == T1)
    assert np.all(t_final[LOST] < 7.0)
    _close_times(shared.t_final, per.t_final, 1e-3)
    _close_times(shared.t_contact_loss, per.t_contact_loss, 1e-3)
    _inversion_times_converge(per, shared, so3_reference)
    assert np.all(np.isfinite(np.asarray(shared.t_invert)[[0, 1, 2, 3, 5]]))
    # the state where each member ended
    for field in ("theta", "spin", "energy", "jellet"):
        a, b = np.asarray(getattr(per, field)), np.asarray(getattr(shared, field))
        np.testing.assert_allclose(b[~LOST], a[~LOST], rtol=1e-5, atol=1e-6, err_msg=field)
        np.testing.assert_allclose(b[LOST], a[LOST], rtol=1e-2, atol=1e-2, err_msg=field)
    # the steps of its shared solve (one per device's shard)
    assert np.all(np.asarray(shared.num_steps) > 0)


def test_shared_saves_of_different_tops_full_model():
    """grid=("top",) over mu, full model, a save grid: saves after a member's end are nan as on
    the per-member path."""
    top = tj.default_top()
    tops = top.replace(mu=np.array([0.05, 0.3, 0.6, 0.3]))
    spins = np.array([150.0, 150.0, 150.0, 400.0])
    ts = np.linspace(0.0, T1, 41)
    per, shared = _pair(tops, 0.1, spins, t1=T1, model="full", saveat=ts, grid=())
    assert shared.theta.shape == (4, ts.size)
    np.testing.assert_array_equal(np.asarray(shared.result._value), np.asarray(per.result._value))
    th_a, th_b = np.asarray(per.theta), np.asarray(shared.theta)
    assert np.array_equal(np.isnan(th_a), np.isnan(th_b))
    assert np.isnan(th_b[3, -1]) and np.all(np.isfinite(th_b[:3]))
    ok = ~np.isnan(th_a)
    assert np.max(np.abs(th_a[ok] - th_b[ok])) < 1e-5
    pos_a, pos_b = np.asarray(per.position), np.asarray(shared.position)
    assert np.nanmax(np.abs(pos_a - pos_b)) < 1e-6
    _close_times(shared.t_invert, per.t_invert, 1e-5)
    _close_times(shared.t_final, per.t_final, 1e-3)
    np.testing.assert_array_equal(np.asarray(shared.ts), np.broadcast_to(ts, (4, ts.size)))


def test_shared_continue_past_contact_loss():
    per, shared = _pair(
        tj.default_top(),
        0.1,
        np.array([150.0, 400.0]),
        t1=T1,
        model="so3",
        summary=True,
        grid=("spin",),
        on_contact_loss="continue",
    )
    np.testing.assert_array_equal(np.asarray(shared.t_final), [T1, T1])
    np.testing.assert_array_equal(np.asarray(shared.result._value), np.asarray(per.result._value))
    np.testing.assert_array_equal(
        np.asarray(shared.result == tj.RESULTS.contact_lost), [False, True]
    )
    _close_times(shared.t_contact_loss, per.t_contact_loss, 1e-3)


@pytest.mark.slow
def test_shared_member_dead_at_launch():
    """A member with R_n < 0 at launch is not integrated (t_final = t0, contact lost at t0) and
    the others run as usual."""
    per, shared = _pair(
        tj.default_top(),
        np.array([0.1, 2.0]),
        np.array([150.0, 50.0]),
        t1=2.0,
        theta_dot=np.array([0.0, -100.0]),
        grid=(),
        model="so3",
        summary=True,
    )
    np.testing.assert_array_equal(np.asarray(shared.t_final), [2.0, 0.0])
    np.testing.assert_array_equal(np.asarray(shared.t_contact_loss)[1], 0.0)
    np.testing.assert_array_equal(np.asarray(shared.result._value), np.asarray(per.result._value))
    np.testing.assert_allclose(np.asarray(shared.theta), np.asarray(per.theta), atol=1e-6)
    assert int(shared.num_steps[1]) == 0 and int(shared.num_steps[0]) > 0


def test_shared_invariants_so3():
    """Along the saved states of the shared path the Jellet integral is conserved (the SO(3)
    level conserves it exactly) and the energy never increases."""
    top = tj.default_top()
    ts = np.linspace(0.0, T1, 81)
    sol = tj.simulate_batch(
        top, [0.1, 0.5], [150.0, 100.0], T1, model="so3", saveat=ts, steps="shared"
    )
    assert np.all(np.asarray(sol.result == tj.RESULTS.successful))
    J = np.asarray(sol.jellet).reshape(-1, ts.size)
    assert np.max(np.abs(J - J[:, :1]) / np.abs(J[:, :1])) < 1e-6
    E = np.asarray(sol.energy).reshape(-1, ts.size)
    assert np.all(np.diff(E, axis=-1) < 1e-8 * np.abs(E[:, :1]))


@pytest.mark.slow
def test_shared_float32():
    """In float32 the shared path is as accurate as the per-member path, both measured
    against the float64 run: the member at 400 rad/s is mid-inversion at t1, where float32
    (default tolerances) is about 0.3 rad off in theta on BOTH paths (the two float32 answers
    differ by 0.02 there, float64's by 2e-7), so their difference alone says little."""
    spins = np.array([150.0, 400.0, 160.0])
    kw = dict(t1=T1, model="so3", summary=True, grid=("spin",))
    per, shared = _pair(tj.default_top().astype(np.float32), 0.1, spins, **kw)
    ref = tj.simulate_batch(tj.default_top(), 0.1, spins, **kw)  # float64, per member
    assert shared.theta.dtype == np.float32
    np.testing.assert_array_equal(np.asarray(shared.result._value), np.asarray(per.result._value))
    _close_times(shared.t_invert, per.t_invert, 1e-2)
    _close_times(shared.t_final, per.t_final, 3e-2)
    err_per = np.abs(np.asarray(per.theta, float) - np.asarray(ref.theta))
    err_shared = np.abs(np.asarray(shared.theta, float) - np.asarray(ref.theta))
    assert np.all(err_shared <= 1.5 * err_per + 1e-3), (err_shared, err_per)


def test_bad_steps_and_unsupported_options_are_refused():
    top = tj.default_top()
    with pytest.raises(ValueError, match="steps must be 'per_member' or 'shared'"):
        tj.simulate_batch(top, 0.1, 150.0, 1.0, steps="batch")
    with pytest.raises(ValueError, match="runs the models"):
        tj.simulate_batch(top, 0.1, 150.0, 1.0, steps="shared", model="routhian")
    with pytest.raises(ValueError, match="not adjoint, progress"):
        tj.simulate_batch(top, 0.1, 150.0, 1.0, steps="shared", progress=True, adjoint=None)
    import diffrax

    with pytest.raises(ValueError, match="explicit solvers only"):
        tj.simulate_batch(top, 0.1, 150.0, 1.0, steps="shared", solver=diffrax.Kvaerno5())


SCRIPT = r"""
import json, numpy as np, jax
import tippejax as tj
top = tj.default_top()
kw = dict(t1=3.0, model="so3", summary=True, grid=("spin",), steps="shared")
spins = np.array([150.0, 100.0, 60.0, 400.0, 30.0])
sharded = tj.simulate_batch(top, 0.1, spins, **kw)
plain = tj.simulate_batch(top, 0.1, spins, shard=False, **kw)
print(json.dumps(dict(devices=jax.device_count(), shape=list(sharded.theta.shape),
    diff=float(np.max(np.abs(np.asarray(sharded.theta) - np.asarray(plain.theta)))))))
"""


@pytest.mark.slow
def test_shared_steps_sharded_over_two_host_devices():
    env = host_devices_env(2)
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, check=True
    ).stdout
    r = json.loads(out.strip().splitlines()[-1])
    assert r["devices"] == 2
    assert r["shape"] == [5]  # 5 launches padded to 6 and cut back
    assert r["diff"] < 1e-5  # each device shares steps over its own shard only


@pytest.mark.slow
def test_shared_large_batch_is_split_into_blocks(so3_summary, so3_reference, monkeypatch):
    """A batch of more than `SHARED_BLOCK` members per device runs as several shared solves
    (buckets by spin, put back in order): with a block of 2, the six members of
    `so3_summary` give every member the result of its per-member run, in the same order."""
    import jax

    import tippejax._devices as devices

    per, _ = so3_summary
    monkeypatch.setattr(devices, "SHARED_BLOCK", 2)
    blocks = tj.simulate_batch(
        tj.default_top(),
        0.1,
        SPINS,
        t1=T1,
        model="so3",
        summary=True,
        grid=("spin",),
        steps="shared",
    )
    np.testing.assert_array_equal(np.asarray(blocks.result._value), np.asarray(per.result._value))
    _inversion_times_converge(per, blocks, so3_reference)
    _close_times(blocks.t_final, per.t_final, 1e-3)
    # more than one solve: the members' step counts differ between blocks (one per device's
    # shard within a block)
    assert len(set(np.asarray(blocks.num_steps).tolist())) > len(jax.devices())
