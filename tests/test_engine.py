"""The engine: events exact on any save grid and with any solver, summary mode, long tight runs,
and clear errors for bad input (in Python where values are concrete, `error_if` under jit).

All runs here share one save-grid length and the default tolerances, so each (model, solver,
summary) combination compiles once for the module.
"""

from typing import ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tippejax as tj

N = 201
COARSE = np.array([0.0, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0])


@pytest.fixture(scope="module")
def top():
    return tj.default_top()


@pytest.fixture(scope="module")
def inverting(top):
    """Standard top, theta0 = 0.1, spin 150: inverts at ~5.7 s (ERRATA: 5.70 s)."""
    y0 = tj.initial_state(top, 0.1, 150.0)
    fine = tj.simulate(top, y0, 20.0, saveat=np.linspace(0.0, 20.0, N))
    return y0, fine


@pytest.mark.slow
def test_inversion_time_does_not_depend_on_the_save_grid(top, inverting):
    y0, fine = inverting
    coarse = tj.simulate(top, y0, 20.0, saveat=COARSE)
    # summary mode integrates no body vector unless asked: body=True is the same solve
    summary = tj.simulate(top, y0, 20.0, summary=True, body=True)
    lean = tj.simulate(top, y0, 20.0, summary=True)
    t_fine = float(fine.t_invert)
    print(
        f"t_invert: fine grid {t_fine:.10f}, 7-point grid {float(coarse.t_invert):.10f}, "
        f"summary {float(summary.t_invert):.10f}, summary without body "
        f"{float(lean.t_invert):.10f}"
    )
    assert 5.6 < t_fine < 5.8
    # the same solve (the save grid does not change the steps): equal to root-finder precision
    assert abs(float(coarse.t_invert) - t_fine) < 1e-9
    assert abs(float(summary.t_invert) - t_fine) < 1e-9
    # theta really is pi/2 there: a tight run, saved at its own event time
    t_tight = float(tj.simulate(top, y0, 20.0, summary=True, rtol=1e-12, atol=1e-14).t_invert)
    # without the body vector the solve takes other steps; its error is the solver's, as with it
    assert abs(float(lean.t_invert) - t_tight) < 3 * max(abs(t_fine - t_tight), 1e-8)
    tight = tj.simulate(top, y0, 20.0, saveat=[0.0, t_tight], rtol=1e-12, atol=1e-14)
    print(f"theta(t_invert) - pi/2 = {float(tight.theta[-1]) - np.pi / 2:.1e} (rtol 1e-12)")
    assert abs(float(tight.theta[-1]) - np.pi / 2) < 1e-9
    # and it is the first upward crossing: on the fine grid, theta < pi/2 before it
    before = np.asarray(fine.ts) < t_fine
    assert np.all(np.asarray(fine.theta)[before] < np.pi / 2)


@pytest.mark.slow
def test_inversion_time_agrees_across_solvers_and_tolerances(top, inverting):
    y0, fine = inverting
    ref = tj.simulate(top, y0, 20.0, summary=True, rtol=1e-12, atol=1e-14)
    t_ref = float(ref.t_invert)
    errors = {}
    for solver in (diffrax.Tsit5(), diffrax.Dopri8()):
        for rtol in (1e-6, 1e-8):
            sol = tj.simulate(
                top, y0, 20.0, summary=True, solver=solver, rtol=rtol, atol=rtol * 1e-2
            )
            errors[(type(solver).__name__, rtol)] = abs(float(sol.t_invert) - t_ref)
    print("t_invert error vs rtol-1e-12 run:", {k: f"{v:.1e}" for k, v in errors.items()})
    for (name, rtol), err in errors.items():
        assert err < 1e4 * rtol, (name, rtol, err)  # the error follows the tolerance


def test_summary_mode_is_the_end_of_the_trajectory(top, inverting):
    y0, fine = inverting
    summary = tj.simulate(top, y0, 20.0, summary=True, body=True)
    assert summary.ts.shape == (1,) and summary.theta.shape == (1,)
    assert float(summary.ts[0]) == pytest.approx(20.0)
    for name in ("theta", "theta_dot", "spin", "jellet", "energy", "normal_force"):
        a, b = float(getattr(summary, name)[0]), float(getattr(fine, name)[-1])
        assert a == pytest.approx(b, rel=1e-9, abs=1e-12), name
    # psi: one saved value, the fine grid's is unwrapped
    turn = float(summary.psi[0]) - float(fine.psi[-1])
    assert abs(np.angle(np.exp(1j * turn))) < 1e-7
    assert int(summary.num_steps) == int(fine.num_steps)


@pytest.mark.slow
@pytest.mark.parametrize("model", ["so3", "full"])
def test_a_run_without_the_body_vector(top, inverting, model):
    """`body=False` (summary mode's default) drops the 4 body components: psi and the body
    vector are nan, nothing else depends on them, and the motion agrees with the run that
    carries them to the solver's own error (a tight run is the reference)."""
    y0, _ = inverting
    ts = np.linspace(0.0, 8.0, 9)
    opts = dict(model=model, saveat=ts)
    lean = tj.simulate(top, y0, 8.0, body=False, **opts)
    full = tj.simulate(top, y0, 8.0, **opts)
    tight = tj.simulate(top, y0, 8.0, rtol=1e-12, atol=1e-14, **opts)
    assert np.all(np.isnan(np.asarray(lean.psi))) and np.all(np.isnan(np.asarray(lean.states.body)))
    assert np.all(np.isfinite(np.asarray(full.psi)))
    assert np.all(np.isnan(np.asarray(tj.simulate(top, y0, 8.0, model=model, summary=True).psi)))
    for name in ("theta", "phi", "theta_dot", "phi_dot", "psi_dot", "spin", "normal_force"):
        err_lean = np.max(
            np.abs(np.asarray(getattr(lean, name)) - np.asarray(getattr(tight, name)))
        )
        err_full = np.max(
            np.abs(np.asarray(getattr(full, name)) - np.asarray(getattr(tight, name)))
        )
        scale = 1.0 + np.max(np.abs(np.asarray(getattr(tight, name))))
        print(f"{model} {name}: error without body {err_lean:.1e}, with {err_full:.1e}")
        assert err_lean < 3 * max(err_full, 1e-9 * scale), name
    assert abs(float(lean.t_invert) - float(tight.t_invert)) < 1e-6
    # 6 (so3) or 10 (full) components instead of 10 or 14: about the same steps
    assert 0.8 < int(lean.num_steps) / int(full.num_steps) < 1.2


def test_dopri8_at_loose_tolerance_finds_the_brief_contact_loss(top):
    """ERRATA 6: at spin 200 R_n first dips below 0 at 5.1865 s, briefly. Dopri8 at rtol 1e-6
    takes steps of ~1/3 of a nutation period, long enough to hold the whole dip; the watch on
    the dense output finds it."""
    y0 = tj.initial_state(top, 0.1, 200.0)
    ref = tj.simulate(
        top, y0, 7.0, summary=True, throw=False, solver=diffrax.Tsit5(), rtol=1e-10, atol=1e-12
    )
    loose = tj.simulate(
        top, y0, 7.0, summary=True, throw=False, solver=diffrax.Dopri8(), rtol=1e-6, atol=1e-8
    )
    for sol in (ref, loose):
        assert bool(sol.result == tj.RESULTS.contact_lost)
    t_ref, t_loose = float(ref.t_contact_loss), float(loose.t_contact_loss)
    print(
        f"contact loss: Tsit5 rtol 1e-10 {t_ref:.6f} s, Dopri8 rtol 1e-6 {t_loose:.6f} s "
        f"({int(loose.num_steps)} steps)"
    )
    assert abs(t_ref - 5.1865) < 5e-4
    assert abs(t_loose - t_ref) < 1e-4
    # the run stops there, and R_n is (to root-finding precision) zero at the end
    assert float(loose.t_final) == pytest.approx(t_loose)
    assert abs(float(loose.normal_force[0])) < 1e-6


def test_long_tight_run_of_a_fast_top_finishes():
    """40 s at rtol 1e-10 of a 300 rad/s top: no max_steps (issue: 200 000 used to stop it).

    This launch leaves the table during its rise (as spin 200 does, ERRATA 6); the run goes on
    past the loss (`on_contact_loss="continue"`) so that all 40 s are integrated."""
    top = tj.default_top()
    y0 = tj.initial_state(top, 0.1, 300.0)
    sol = tj.simulate(
        top, y0, 40.0, summary=True, rtol=1e-10, atol=1e-12, throw=False, on_contact_loss="continue"
    )
    print(
        f"40 s at rtol 1e-10, spin 300: {int(sol.num_steps)} steps, result {sol.result}, "
        f"t_contact_loss {float(sol.t_contact_loss):.4f} s"
    )
    assert bool(sol.result == tj.RESULTS.contact_lost)  # flagged, not max_steps
    assert float(sol.t_final) == pytest.approx(40.0)
    J0 = float(tj.jellet(top, y0))
    assert abs(float(sol.jellet[0]) / J0 - 1) < 1e-8  # J conserved over 40 s


def test_routhian_level_finds_events_on_a_coarse_grid(top):
    y0 = tj.initial_state(top, 0.3, 150.0)
    a = tj.simulate(top, y0, 20.0, model="routhian", saveat=COARSE)
    b = tj.simulate(top, y0, 20.0, model="so3", saveat=COARSE)
    print(f"routhian t_invert {float(a.t_invert):.8f} ({a.model}), so3 {float(b.t_invert):.8f}")
    assert np.isfinite(float(a.t_invert))
    assert abs(float(a.t_invert) - float(b.t_invert)) < 1e-5


# ------------------------------------------------------------------------------------------------
# Bad input, as a new user would try it


def test_saveat_beyond_t1_is_an_error(top):
    y0 = tj.initial_state(top, 0.1, 100.0)
    with pytest.raises(ValueError, match=r"within \[t0, t1\]"):
        tj.simulate(top, y0, 1.0, saveat=[0.0, 0.5, 2.0])
    with pytest.raises(ValueError, match="non-decreasing"):
        tj.simulate(top, y0, 1.0, saveat=[0.0, 0.7, 0.5])
    with pytest.raises(ValueError, match="either saveat or summary"):
        tj.simulate(top, y0, 1.0, saveat=[0.0, 1.0], summary=True)


def test_saveat_beyond_t1_under_jit_is_an_error(top):
    y0 = tj.initial_state(top, 0.1, 100.0)
    run = jax.jit(lambda ts: tj.simulate(top, y0, 1.0, saveat=ts, summary=False).theta)
    with pytest.raises(Exception, match=r"within \[t0, t1\]"):
        jax.block_until_ready(run(jnp.array([0.0, 0.5, 2.0])))


@pytest.mark.parametrize(
    "rtol, atol", [(-1e-8, 1e-10), (0.0, 1e-10), (1e-8, -1.0), (np.nan, 1e-10)]
)
def test_bad_tolerances(top, rtol, atol):
    y0 = tj.initial_state(top, 0.1, 100.0)
    with pytest.raises(ValueError, match="rtol|atol"):
        tj.simulate(top, y0, 1.0, rtol=rtol, atol=atol)


def test_state_that_is_not_a_rotation_is_an_error(top):
    y0 = tj.initial_state(top, 0.1, 100.0)
    not_unit = eqx.tree_at(lambda s: s.axis, y0, 2.0 * y0.axis)
    with pytest.raises(ValueError, match="unit vectors"):
        tj.simulate(top, not_unit, 1.0)
    skew = eqx.tree_at(lambda s: s.body, y0, y0.axis)  # body along the axis
    with pytest.raises(ValueError, match="perpendicular"):
        tj.simulate(top, skew, 1.0)
    nan_spin = eqx.tree_at(lambda s: s.omega, y0, y0.omega.at[2].set(jnp.nan))
    with pytest.raises(ValueError, match="finite"):
        tj.simulate(top, nan_spin, 1.0)
    run = jax.jit(lambda y: tj.simulate(top, y, 1.0, summary=True).theta)
    with pytest.raises(Exception, match="unit vectors"):
        jax.block_until_ready(run(not_unit))


def test_batched_top_or_state_is_an_error(top):
    tops = jax.tree_util.tree_map(lambda x: jnp.stack([x, x]), top)
    y0 = tj.initial_state(top, 0.1, 100.0)
    with pytest.raises(ValueError, match="one top.*jax.vmap"):
        tj.simulate(tops, y0, 1.0)
    with pytest.raises(ValueError, match="one state"):
        tj.simulate(top, tj.initial_state(top, jnp.array([0.1, 0.2]), 100.0), 1.0)
    with pytest.raises(TypeError, match="State"):
        tj.simulate(top, (0.1, 100.0), 1.0)


def test_other_bad_options(top):
    y0 = tj.initial_state(top, 0.1, 100.0)
    with pytest.raises(ValueError, match="Unknown model"):
        tj.simulate(top, y0, 1.0, model="euler")
    with pytest.raises(ValueError, match="max_steps"):
        tj.simulate(top, y0, 1.0, max_steps=0)
    with pytest.raises(ValueError, match="event_pieces"):
        tj.simulate(top, y0, 1.0, event_pieces=0)
    with pytest.raises(ValueError, match="on_contact_loss"):
        tj.simulate(top, y0, 1.0, on_contact_loss="ignore")


def test_simulate_batch_bad_grids(top):
    with pytest.raises(ValueError, match="spin is empty"):
        tj.simulate_batch(top, [0.1], [], 1.0)
    with pytest.raises(ValueError, match="theta0 must be finite"):
        tj.simulate_batch(top, [np.nan], [100.0], 1.0)


# ----------------------------------------------------------------------------------------------
# Issue 18: the body vector as a frame and a spin angle, the state's leaves, every core
# ----------------------------------------------------------------------------------------------


def _random_states(key, n=8):
    from tippejax._state import state_from_euler

    k1, k2, k3 = jax.random.split(key, 3)
    angles = jax.random.uniform(k1, (n, 3), minval=-3.0, maxval=3.0)
    theta = jnp.abs(angles[:, 0]) % jnp.pi
    omega = jax.random.normal(k2, (n, 3)) * 60.0
    velocity = jax.random.normal(k3, (n, 2)) * 0.3
    states = []
    for i in range(n):
        s = state_from_euler(theta[i], angles[i, 1], angles[i, 2], 0.0, 0.0, 1.0)
        states.append(
            s.__class__(
                position=jnp.zeros(2),
                velocity=velocity[i],
                axis=s.axis,
                omega=omega[i],
                body=s.body,
            )
        )
    return states


@pytest.mark.parametrize("name", ["so3", "full"])
def test_spin_frame_carries_the_body_vector_exactly(top, name):
    """b = cos(s) c + sin(s) a x c obeys db/dt = omega x b along the level's vector field
    (checked by autodiff of the level's to_state along its own field, at random states and
    nonzero spin angles), c stays perpendicular to a, the other components have the rates of
    the common vector field, and to_state(from_state(x)) = x."""
    from tippejax._models.full import full_vector_field
    from tippejax._models.levels import LEVELS
    from tippejax._models.so3 import so3_vector_field

    level = LEVELS[name]
    common_field = {"so3": so3_vector_field, "full": full_vector_field}[name]
    for i, state in enumerate(_random_states(jax.random.PRNGKey(3))):
        y = level.from_state(top, state)
        back = level.to_state(top, y)
        for leaf in ("axis", "omega", "body", "velocity"):
            expected = getattr(state, leaf) if (name == "full" or leaf != "velocity") else 0.0
            assert np.allclose(getattr(back, leaf), expected, atol=1e-14), leaf
        y = eqx.tree_at(lambda s: s.angle, y, jnp.asarray(0.7 * i - 2.0))
        dy = level.vector_field(0.0, y, top)
        state_i, dstate = jax.jvp(lambda z: level.to_state(top, z), (y,), (dy,))
        reference = common_field(0.0, state_i, top)
        for leaf in ("axis", "omega", "body"):
            scale = 1.0 + np.max(np.abs(getattr(reference, leaf)))
            assert np.max(np.abs(getattr(dstate, leaf) - getattr(reference, leaf))) < 1e-12 * scale
        assert abs(float(jnp.dot(dy.frame, y.axis) + jnp.dot(y.frame, dy.axis))) < 1e-12


@pytest.mark.parametrize(
    "solver",
    [
        diffrax.Dopri8(),
        diffrax.Dopri5(),
        diffrax.Tsit5(),
        diffrax.Kvaerno5(root_finder=diffrax.VeryChord(rtol=1e-10, atol=1e-12)),
    ],
    ids=lambda s: type(s).__name__,
)
def test_the_watch_reads_the_dense_output_in_normalised_time(top, solver):
    """The event watch evaluates a step's dense output and its time derivative at the middle on
    [0, 1] (constant weights) and divides by h: the same as the interpolation on the step's own
    times and its derivative in t (diffrax's interpolations are polynomials in (t - t0)/h with
    coefficients k_i = h f_i)."""
    from tippejax._engine.packing import FlatField, ravel_state
    from tippejax._engine.watch import _midpoint
    from tippejax._models.levels import LEVELS

    level = LEVELS["so3"]
    y0 = level.from_state(top, tj.initial_state(top, 0.3, 120.0, theta_dot=1.0))
    flat, unravel = ravel_state(y0)
    term = diffrax.ODETerm(FlatField(level, unravel))
    t0, t1 = jnp.asarray(1.25), jnp.asarray(1.25 + 0.004)
    state = solver.init(term, t0, t1, flat, top)
    _, _, dense, _, _ = solver.step(term, t0, t1, flat, top, state, False)
    y_mid, y_dot = _midpoint(solver, dense, t1 - t0)
    interp = solver.interpolation_cls(t0=t0, t1=t1, **dense)
    middle = t0 + 0.5 * (t1 - t0)
    ref, ref_dot = jax.jvp(interp.evaluate, (middle,), (jnp.ones_like(middle),))
    for a, b in zip(
        jax.tree_util.tree_leaves((y_mid, y_dot)), jax.tree_util.tree_leaves((ref, ref_dot))
    ):
        assert np.allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=1e-9 * np.max(np.abs(b)))
    # and it is the motion: the derivative is the vector field there, to the interpolant's order
    field = term.vf(middle, y_mid, top)
    for a, b in zip(jax.tree_util.tree_leaves(y_dot), jax.tree_util.tree_leaves(field)):
        assert np.allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-4 * np.max(np.abs(b)))


def test_ravel_state_round_trip_and_leaves():
    from tippejax._engine.packing import ravel_state
    from tippejax._models.so3 import RigidState

    y = RigidState(
        axis=jnp.arange(3.0),
        omega=jnp.arange(3.0, 6.0),
        frame=jnp.arange(6.0, 9.0),
        angle=jnp.asarray(9.0),
    )
    flat, unravel = ravel_state(y)
    # whole leaves, in order, at most PACK_WIDTH (6) to a vector: axis + omega, frame + angle
    assert [x.shape for x in flat] == [(6,), (4,)]
    assert np.array_equal(np.concatenate(flat), np.arange(10.0))
    back = unravel(flat)
    for leaf in ("axis", "omega", "frame", "angle"):
        assert np.array_equal(getattr(back, leaf), getattr(y, leaf))

    from tippejax._models.full import FullLevelState

    names = ("position", "velocity", "axis", "omega", "frame", "angle")
    sizes = (2, 2, 3, 3, 3, 1)
    starts = np.cumsum((0,) + sizes)
    z = FullLevelState(
        **{
            k: jnp.arange(float(a), float(a + n)).reshape((n,) if n > 1 else ())
            for k, a, n in zip(names, starts, sizes)
        }
    )
    flat, unravel = ravel_state(z)
    assert [x.shape for x in flat] == [(4,), (6,), (4,)]  # position + velocity | axis + omega | ...
    assert np.array_equal(np.concatenate(flat), np.arange(14.0))
    back = unravel(flat)
    for leaf in names:
        assert np.array_equal(getattr(back, leaf), getattr(z, leaf))


@pytest.mark.slow
def test_one_top_is_packed_in_one_vector_and_a_batch_in_narrow_ones(top):
    """A run of one top carries its state in one vector, a vmapped batch in vectors of at most
    `PACK_WIDTH`, one top differentiated in forward mode in vectors of at most
    `FORWARD_MODE_PACK_WIDTH` (one vector as well; only the speed depends on it,
    `ravel_state`): the layout is picked inside and outside `vmap` as documented, and the full
    model's end state and inversion time of one top are the same either way (the same
    arithmetic, to rounding; the derivatives in both modes are checked against each other and
    against finite differences in `test_grad.py`)."""
    from tippejax._engine.packing import (
        FORWARD_MODE_PACK_WIDTH,
        ONE_TOP_PACK_WIDTH,
        PACK_WIDTH,
        pack_width_for,
        ravel_state,
    )
    from tippejax._models.full import FullLevelState

    z = FullLevelState(
        position=jnp.zeros(2),
        velocity=jnp.ones(2),
        axis=jnp.arange(3.0),
        omega=jnp.arange(3.0, 6.0),
        frame=jnp.arange(6.0, 9.0),
        angle=jnp.asarray(9.0),
    )
    flat, unravel = ravel_state(z, ONE_TOP_PACK_WIDTH)
    assert [x.shape for x in flat] == [(14,)]
    assert np.array_equal(unravel(flat).omega, z.omega)

    seen = []
    jax.vmap(lambda x: seen.append(pack_width_for(x)) or x)(jnp.ones(2))
    jax.jit(lambda x: seen.append(pack_width_for(x)) or x)(jnp.ones(2))
    assert seen == [PACK_WIDTH, ONE_TOP_PACK_WIDTH]
    assert pack_width_for(jnp.ones(2), 1.0) == ONE_TOP_PACK_WIDTH
    forward = diffrax.ForwardMode()
    jax.vmap(lambda x: seen.append(pack_width_for(x, adjoint=forward)) or x)(jnp.ones(2))
    jax.jacfwd(lambda x: seen.append(pack_width_for(x, adjoint=forward)) or x)(jnp.ones(2))
    assert seen[2:] == [PACK_WIDTH, FORWARD_MODE_PACK_WIDTH]
    flat, _ = ravel_state(z, FORWARD_MODE_PACK_WIDTH)
    assert [x.shape for x in flat] == [(14,)]

    y0 = tj.initial_state(top, 0.1, 150.0)
    one = tj.simulate(top, y0, 6.0, summary=True, model="full")
    batch = jax.vmap(
        lambda s: tj.simulate(
            top, tj.initial_state(top, 0.1, s), 6.0, summary=True, model="full", throw=False
        )
    )(jnp.array([150.0]))
    assert np.isfinite(float(one.t_invert))
    np.testing.assert_allclose(float(batch.t_invert[0]), float(one.t_invert), rtol=1e-9)
    np.testing.assert_allclose(
        np.asarray(batch.states.omega[0, -1]),
        np.asarray(one.states.omega[-1]),
        rtol=1e-7,
        atol=1e-7,
    )


@pytest.mark.slow
def test_batches_compiled_with_the_cpu_options_match_a_users_vmap(top):
    """tippejax's own CPU batch programs (`CpuProgram`: its compile options, blocks under
    `lax.map`, sharding) change the speed only: `simulate_batch` and the user's `vmap` of
    `simulate` in the user's `jit` (XLA's defaults; an eager `vmap` gets tippejax's options)
    end at the same state and inversion time."""
    spins = jnp.array([140.0, 160.0])
    own = tj.simulate_batch(top, 0.1, spins, 6.0, grid=(), summary=True, model="full")
    user = jax.jit(
        jax.vmap(
            lambda s: tj.simulate(
                top, tj.initial_state(top, 0.1, s), 6.0, summary=True, model="full", throw=False
            )
        )
    )(spins)
    assert np.all(np.isfinite(np.asarray(own.t_invert)))
    np.testing.assert_allclose(np.asarray(own.t_invert), np.asarray(user.t_invert), rtol=1e-8)
    # (a summary batch has no save axis; the user's vmap of single summaries keeps theirs)
    np.testing.assert_allclose(
        np.asarray(own.states.omega), np.asarray(user.states.omega[:, -1]), rtol=1e-6, atol=1e-6
    )


def test_body_vector_of_a_fast_top_against_a_plain_solve(top, inverting):
    """The SO(3) level's body vector (frame and spin angle) against a plain diffrax solve of
    db/dt = omega x b on the 9-component state (axis, omega, body) at tight tolerance: the
    new form reproduces the old one, through the inversion and the pole."""
    from tippejax._models.so3 import so3_vector_field

    y0 = tj.initial_state(top, 0.1, 150.0)
    ts = np.linspace(0.0, 8.0, 9)
    sol = tj.simulate(top, y0, 8.0, model="so3", saveat=ts, rtol=1e-11, atol=1e-13)
    ref = diffrax.diffeqsolve(
        diffrax.ODETerm(so3_vector_field),
        diffrax.Dopri8(),
        0.0,
        8.0,
        None,
        y0,
        top,
        saveat=diffrax.SaveAt(ts=jnp.asarray(ts)),
        max_steps=100_000,
        stepsize_controller=diffrax.PIDController(rtol=1e-12, atol=1e-14),
    ).ys
    assert np.max(np.abs(np.asarray(sol.states.body) - np.asarray(ref.body))) < 1e-7
    assert np.max(np.abs(np.asarray(sol.states.axis) - np.asarray(ref.axis))) < 1e-7


def test_fast_top_steps_match_a_solve_without_body_vector(top):
    """The body vector no longer sets the steps: the SO(3) level takes within 5% of the steps
    of a plain Dopri8 solve of (axis, omega) alone with the same step-size controller (the
    spinning body vector in the state would set the steps), at rtol 1e-8."""
    from tippejax._engine.segment import STEP_CONTROL
    from tippejax._models.so3 import so3_vector_field

    y0 = tj.initial_state(top, 0.1, 150.0)
    sol = tj.simulate(top, y0, 20.0, model="so3", summary=True)

    def rigid(t, y, args):
        a, w = y[:3], y[3:]
        s = so3_vector_field(
            t, tj.State(position=jnp.zeros(2), velocity=jnp.zeros(2), axis=a, omega=w, body=a), args
        )
        return jnp.concatenate([s.axis, s.omega])

    plain = diffrax.diffeqsolve(
        diffrax.ODETerm(rigid),
        diffrax.Dopri8(),
        0.0,
        20.0,
        None,
        jnp.concatenate([y0.axis, y0.omega]),
        top,
        max_steps=100_000,
        stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-10, **STEP_CONTROL),
    )
    ratio = int(sol.num_steps) / int(plain.stats["num_steps"])
    assert 0.9 < ratio < 1.05, ratio


@pytest.mark.parametrize("model", ["full", "so3"])
def test_step_control_rejects_few_steps(top, model):
    """The PI step-size controller (`STEP_CONTROL`): the standard top's 20 s summary run rejects
    under 1% of its steps. With diffrax's default I controller in its place it rejected 134 of
    1997 at the full level (6.7%, oscillating between accepted and rejected steps) and 23 of
    2021 at the SO(3) level (1.1%); with the PI controller 13 of 2077 and 5 of 2217."""
    from tippejax._engine.segment import STEP_CONTROL

    assert STEP_CONTROL["pcoeff"] > 0  # a PI controller, not diffrax's I controller
    sol = tj.simulate(top, tj.initial_state(top, 0.1, 150.0), 20.0, model=model, summary=True)
    assert sol.result == tj.RESULTS.successful
    assert int(sol.num_rejected_steps) < 0.01 * int(sol.num_steps), (
        int(sol.num_rejected_steps),
        int(sol.num_steps),
    )


COUNT_SCRIPT = r"""
import json, os
import tippejax as tj, jax
print(json.dumps(dict(devices=jax.device_count(), flags=os.environ.get("XLA_FLAGS", ""),
                      option=getattr(jax.config, "jax_num_cpu_devices", None))))
"""


def _devices_run(script=COUNT_SCRIPT, **env_changes):
    import json
    import os
    import subprocess
    import sys

    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("XLA_FLAGS", "TIPPEJAX_HOST_DEVICES", "TIPPEJAX_CPU_SCHEDULER")
    }
    env.update(env_changes)
    out = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True
    ).stdout
    return json.loads(out.strip().splitlines()[-1])


def test_every_core_is_a_device_by_default():
    """Importing tippejax makes os.cpu_count() host devices (here forced to 2 through
    TIPPEJAX_HOST_DEVICES, as on a 2-core machine); TIPPEJAX_HOST_DEVICES=1 keeps one device;
    a flag the user set is kept. That `simulate_batch` shards over every device by default
    with the same results is `tests/test_batch.py`'s four-device test."""
    import os

    two = _devices_run(TIPPEJAX_HOST_DEVICES="2")
    assert two["devices"] == 2
    # JAX's own option where this JAX has it, the XLA flag otherwise
    if two["option"] is not None:
        assert two["option"] == 2 and "device_count" not in two["flags"]
    else:
        assert "--xla_force_host_platform_device_count=2" in two["flags"]
    assert _devices_run(TIPPEJAX_HOST_DEVICES="1")["devices"] == 1
    user = _devices_run(XLA_FLAGS="--xla_force_host_platform_device_count=3")
    assert user["devices"] == 3
    assert user["flags"].split()[0] == "--xla_force_host_platform_device_count=3"
    assert _devices_run(JAX_NUM_CPU_DEVICES="3")["devices"] == 3
    default = _devices_run()
    assert default["devices"] == (os.cpu_count() or 1)


@pytest.mark.slow
def test_sequential_cpu_scheduler_by_default_and_its_opt_outs():
    """XLA:CPU's concurrency-optimised scheduler is turned off where this jaxlib knows the
    flag (`_devices.use_sequential_scheduler`); TIPPEJAX_CPU_SCHEDULER=concurrent and a flag
    the user set keep XLA's choice; a bad setting is refused."""
    import os
    import subprocess
    import sys

    from tippejax import _devices

    def flags(**env_changes):  # XLA_FLAGS after importing tippejax in a new process
        env = {
            k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "TIPPEJAX_CPU_SCHEDULER")
        }
        env.update(env_changes)
        script = "import os, tippejax; print(os.environ.get('XLA_FLAGS', ''))"
        out = (
            subprocess.run(
                [sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True
            )
            .stdout.strip()
            .splitlines()
        )
        return out[-1] if out else ""

    flag = _devices.SCHEDULER_FLAG
    known = _devices._jaxlib_version() in _devices.SCHEDULER_JAXLIB
    assert (f"{flag}=false" in flags()) == known
    assert flag not in flags(TIPPEJAX_CPU_SCHEDULER="concurrent")
    user = flags(XLA_FLAGS=f"{flag}=true")
    assert user.count(flag) == 1 and f"{flag}=true" in user
    with pytest.raises(ValueError, match="TIPPEJAX_CPU_SCHEDULER must be"):
        _devices.use_sequential_scheduler({"TIPPEJAX_CPU_SCHEDULER": "fast"})


def test_every_core_bad_setting_and_late_import():
    from tippejax import _devices

    with pytest.raises(ValueError, match="TIPPEJAX_HOST_DEVICES must be a positive integer"):
        _devices.requested_devices({"TIPPEJAX_HOST_DEVICES": "zero"})
    with pytest.raises(ValueError, match="positive integer"):
        _devices.requested_devices({"TIPPEJAX_HOST_DEVICES": "0"})
    # This process's backends run already: the flag could not take effect, nothing is changed.
    jax.devices()
    env = {"TIPPEJAX_HOST_DEVICES": "4"}
    assert _devices.use_every_core(env) is None and "XLA_FLAGS" not in env


@pytest.mark.parametrize("pieces", [1, 2, 3])
def test_bernstein_polygon_is_the_quintic(pieces):
    """The watch's Bernstein coefficients (`_bernstein_polygon`) describe the quintic Hermite
    interpolant of the step's data (`_quintic_samples`, built independently from the power
    basis): on each part the Bernstein sum equals the quintic, its end coefficients are the
    quintic's values at the part's ends, and the sign changes of the coefficients are never
    fewer than the quintic's own on a fine grid (the bound the watch relies on)."""
    from math import comb

    from tippejax._engine.bernstein import _bernstein_polygon, _quintic_samples

    rng = np.random.default_rng(pieces)
    weights = _bernstein_polygon(pieces)
    assert weights.shape == (5 * pieces + 1, 6)
    fine = 600
    on_grid = np.concatenate([[[1, 0, 0, 0, 0, 0]], _quintic_samples(fine), [[0, 0, 0, 0, 1, 0]]])
    u = np.linspace(0.0, 1.0, fine // pieces + 1)
    basis = np.stack([comb(5, i) * u**i * (1 - u) ** (5 - i) for i in range(6)], axis=1)
    fewer = 0
    for _ in range(300):
        data = rng.normal(size=6) * np.array([1, 3, 1, 3, 1, 3]) + rng.normal() * 0.5
        b = weights @ data
        values = on_grid @ data  # the quintic at s = k / fine, k = 0..fine
        for k in range(pieces):
            part = b[5 * k : 5 * k + 6]
            bern = basis @ part
            assert np.allclose(
                bern,
                values[k * fine // pieces : (k + 1) * fine // pieces + 1],
                atol=1e-12 * np.max(np.abs(data)) * 100,
            )
        positive = values > 0
        crossings = np.sum(positive[1:] != positive[:-1])
        variations = np.sum((b[1:] > 0) != (b[:-1] > 0))
        assert variations >= crossings
        fewer += variations > crossings
    assert fewer < 300  # the bound is not trivially loose


def test_signs_within_a_conditions_rounding_do_not_count():
    """`settled_signs`: coefficients inside a condition's rounding floor take the nearest
    significant sign, so a condition at zero to rounding (signs flipping at random) shows no
    hidden crossing and no fall, while a dip out of the band and back is still a hidden
    crossing, and a condition with no significant coefficient changes no sign."""
    from tippejax._engine.bernstein import fell, hidden_crossing, settled_signs

    rng = np.random.default_rng(0)
    floor = 1e-15
    noise = floor * 0.1 * rng.standard_normal((11, 1))
    leaving = np.concatenate([noise[:6], -np.linspace(1e-9, 1e-8, 5)[:, None]])  # 0, then down
    dip = np.array([1e-9, 5e-10, -1e-10, -5e-10, -1e-10, 3e-10, 1e-9, 2e-9, 3e-9, 4e-9, 5e-9])
    for coefficients, hidden in ((noise, False), (leaving, False), (dip[:, None], True)):
        raw = jnp.asarray(coefficients > 0)
        settled = settled_signs(raw, jnp.asarray(np.abs(coefficients) > floor))
        assert bool(hidden_crossing(settled)) == hidden
    assert bool(hidden_crossing(jnp.asarray(noise > 0)))  # (the raw signs of the noise do)
    settled = settled_signs(jnp.asarray(noise > 0), jnp.asarray(np.abs(noise) > floor))
    assert np.all(np.asarray(settled) == bool(noise[0, 0] > 0))  # nothing significant
    leaving_settled = settled_signs(jnp.asarray(leaving > 0), jnp.asarray(np.abs(leaving) > floor))
    assert not bool(fell(leaving_settled, [0])[0])  # from zero down is not a fall


def test_a_recorded_event_that_chatters_does_not_hold_the_steps_back():
    """Once an observed event is recorded its later crossings are not split into steps of their
    own (a compliant contact's chatter after the ball's return stalled a run at `max_steps`):
    a condition that crosses zero every 3e-5 s is recorded at its first downward crossing,
    after which the steps grow to the cap of 2 ms, while a second observed event, a dip later
    in the run, is still found on a step of its own. Without the rule the run needs a step per
    pair of crossings, tens of thousands."""
    from tippejax._engine.watch import WatchedSolver

    omega, centre, width = 1e5, 0.7, 4e-3

    def watch(y, args):
        dip = 1.0 - 2.0 * jnp.exp(-(((y[0] - centre) / width) ** 2))
        return jnp.stack([jnp.cos(omega * y[0]), dip])

    solver = WatchedSolver(diffrax.Tsit5(), watch, observed=(0, 1))
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(lambda t, y, args: jnp.ones_like(y)),
        solver,
        0.0,
        1.0,
        1e-3,
        jnp.zeros(1),
        stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-10, dtmax=2e-3),
        saveat=diffrax.SaveAt(t1=True, solver_state=True),
        max_steps=1000,
        throw=False,
    )
    assert sol.result == diffrax.RESULTS.successful
    records = sol.solver_state.records()
    assert np.all(np.asarray(records.found))
    first = (np.pi / 2) / omega  # y = t: cos(omega t) first falls through zero here
    dip_start = centre - width * np.sqrt(np.log(2.0))
    for k, when in enumerate((first, dip_start)):
        assert float(records.step_t0[k]) <= when <= float(records.step_t1[k])
        assert float(records.step_t1[k] - records.step_t0[k]) < width


class _Overflowing(diffrax.AbstractAdaptiveSolver):
    """Heun's method whose steps longer than 1 overflow (end at +inf with an infinite error),
    as an explicit step of a stiff contact does when it presses the ball in too far."""

    term_structure: ClassVar = diffrax.AbstractTerm
    interpolation_cls: ClassVar = diffrax.LocalLinearInterpolation

    def order(self, terms):
        return 2

    def error_order(self, terms):
        return 2

    def init(self, terms, t0, t1, y0, args):
        return None

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        h = t1 - t0
        k1 = terms.vf(t0, y0, args)
        k2 = terms.vf(t1, y0 + h * k1, args)
        too_long = h > 1.0
        y1 = jnp.where(too_long, jnp.inf, y0 + 0.5 * h * (k1 + k2))
        y_error = jnp.where(too_long, jnp.inf, 0.5 * h * (k2 - k1))
        return y1, y_error, dict(y0=y0, y1=y1), None, diffrax.RESULTS.successful


def test_a_step_that_overflows_is_shrunk_not_stuck():
    """A trial step whose stages overflow ends at an infinite state with an infinite error:
    diffrax's controller scales it by `inf`, takes the nan for its next step size and rejects
    every step after (a batch member of Leine & Glocker's top stalled so as its ball landed).
    `overflow_safe` makes the norm infinite there, so the step shrinks and the run goes on."""
    from tippejax._engine.packing import overflow_safe

    def rms(x):
        return jnp.sqrt(jnp.mean(x**2))

    def solve(norm):
        return diffrax.diffeqsolve(
            diffrax.ODETerm(lambda t, y, args: -y),
            _Overflowing(),
            0.0,
            3.0,
            2.0,
            jnp.ones(1),
            stepsize_controller=diffrax.PIDController(rtol=1e-4, atol=1e-6, norm=norm),
            max_steps=2000,
            throw=False,
        )

    assert solve(rms).result == diffrax.RESULTS.max_steps_reached  # (the trap)
    sol = solve(overflow_safe(rms))
    assert sol.result == diffrax.RESULTS.successful
    assert abs(float(sol.ys[-1, 0]) - np.exp(-3.0)) < 1e-3


def test_a_dip_between_sample_points_is_seen():
    """A top of group IIa drawn at random (seed 0 of benchmarks' random tops) whose first
    contact loss, at 3.5387 s by a solve at rtol 1e-12, is a dip of R_n that fell between the
    8 points per step at which the watch used to check each condition: at rtol 1e-6 and 1e-8
    it reported the next loss, 37 ms later, as the first. The Bernstein check bounds the
    quintic's crossings from above and finds it at every tolerance."""
    top = tj.TippeTop.from_ratios(
        0.9172633358743316, 0.1827716467919303, m=0.02, R=0.025, mu=0.5799224581958591
    )
    y0 = tj.initial_state(top, 0.6216352983872274, 190.60865108208873)

    def first_loss(rtol):
        sol = tj.simulate(
            top,
            y0,
            4.0,
            model="full",
            summary=True,
            rtol=rtol,
            atol=rtol * 1e-2,
            throw=False,
            on_contact_loss="continue",
        )
        return float(sol.t_contact_loss)

    reference = first_loss(1e-12)
    assert abs(reference - 3.5387) < 1e-3  # (the value in the docstring, not an answer key)
    for rtol in (1e-6, 1e-8):
        assert abs(first_loss(rtol) - reference) < 1e-4


def test_compiler_options_are_tippejaxs_own_and_reach_xla():
    """`tj.compiler_options()`: the options tippejax compiles its own CPU programs with, as a
    new dict for a user's top-level `jax.jit`; None on other backends."""
    from tippejax._engine.cpu import own_compiler_options

    options = tj.compiler_options()
    assert options == own_compiler_options()  # the CPU options here (CI runs on a CPU)
    options["xla_backend_optimization_level"] = 3  # a copy: tippejax's own stay as they are
    assert tj.compiler_options() == own_compiler_options() != options
    assert tj.compiler_options("gpu") is None
    with pytest.raises(TypeError, match="platform name"):
        tj.compiler_options(jax.devices()[0])

    # XLA takes them (a misspelt option fails to compile) and they change no number
    def f(x):
        return jnp.sum(jnp.sin(x) * jnp.cross(x, x[::-1]))

    x = jnp.linspace(0.1, 0.3, 3)
    want = jax.jit(jax.grad(f))(x)
    got = jax.jit(jax.grad(f), compiler_options=tj.compiler_options())(x)
    np.testing.assert_allclose(got, want, rtol=1e-14)
    with pytest.raises(Exception, match="xla_no_such_option"):
        jax.jit(f, compiler_options={"xla_no_such_option": 1})(x)
