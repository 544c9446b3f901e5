"""The gyroscopic level's chain (`tippejax/_engine/chain.py`): on a scene the slow flow owns it
takes the slow flow's few steps and runs no full-model segment at all; where it hands over, the
hand-over time (`sol.t_hand_over`) is where the switch condition (the nutation about the slow
manifold stops decaying, `nutation_damping`) says, and the full model runs only after it.

The chain runs through one jitted program with a counting full model (`CountingFull`), compiled
once for every launch of the standard top at theta0 = 0.1."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tippejax as tj
from tippejax._engine.chain import run_chain
from tippejax._models.full import FullLevel
from tippejax._models.gyroscopic import (
    HAND_OVER_MARGIN,
    GyroscopicLevel,
    nutation_damping,
    nutation_frequency,
)

T1 = 20.0
TS = jnp.linspace(0.0, T1, 201)
RTOL = 1e-8

FIELD_CALLS = []
"""Host-side record of the full model's field evaluations in `CountingFull`'s runs."""


class CountingFull(FullLevel):
    """The full model, counting its vector-field evaluations on the host."""

    def vector_field(self, t, y, top):
        jax.debug.callback(lambda: FIELD_CALLS.append(1))
        return super().vector_field(t, y, top)


class CountingGyroscopic(GyroscopicLevel):
    """The gyroscopic level handing over to `CountingFull`."""

    def fallback(self):
        return CountingFull(body=self.body)


@pytest.fixture(scope="module")
def top():
    return tj.default_top()


@pytest.fixture(scope="module")
def chain(top):
    """The counting chain from a launch at spin n0: its `ChainOutput` and the number of the
    full model's field evaluations it made."""
    program = jax.jit(
        lambda y0: run_chain(
            CountingGyroscopic(),
            top,
            y0,
            0.0,
            T1,
            TS,
            stop_on_contact=False,
            solver=(diffrax.Dopri5(), diffrax.Dopri8()),
            rtol=RTOL,
            atol=1e-10,
            max_steps=100_000,
            adjoint=diffrax.RecursiveCheckpointAdjoint(),
            progress_meter=diffrax.NoProgressMeter(),
            pieces=1,
        )
    )

    def run(n0):
        FIELD_CALLS.clear()
        out = jax.block_until_ready(program(tj.initial_state(top, 0.1, n0)))
        jax.effects_barrier()
        return out, len(FIELD_CALLS)

    return run


def nutation_periods(top, n0, t1):
    """The number of nutation periods 2 pi A / (C n) in a run of length t1 at spin n0."""
    return t1 * float(top.C) * n0 / (2 * np.pi * float(top.A))


def test_the_slow_flow_owns_a_moderate_spin(top, chain):
    """n0 = 100: the slow manifold attracts throughout (sigma < 0 on the whole rise), so the
    run is the slow flow's alone. The full model needs a few steps per nutation period; the
    slow flow, which has averaged the nutation out, follows the rise alone: fewer steps than a
    quarter of the nutation periods in the run. No full-model segment runs: its field is not
    evaluated once (a segment of zero length would still evaluate it at its start)."""
    out, full_calls = chain(100.0)
    assert bool(out.result == tj.RESULTS.successful)
    assert np.isnan(float(out.t_chart_switch))
    assert np.isfinite(float(out.t_invert))
    assert 0 < int(out.num_steps) < nutation_periods(top, 100.0, T1) / 4
    assert full_calls == 0
    # every save time carries the slow flow's state
    assert np.all(np.isfinite(np.asarray(out.states.axis)))


def test_the_hand_over_is_where_the_slow_manifold_starts_to_repel(top, chain):
    """n0 = 150: the nutation about the slow manifold stops decaying during the rise
    (-sigma/nu falls through `HAND_OVER_MARGIN`): the run hands over to the full model there.
    At the save times before the hand-over -sigma/nu (from the tilt saved there and the
    launch's Jellet) is above the margin; it falls through it within one save interval of the
    hand-over time. The full model then runs from the hand-over to t1, and only there."""
    y0 = tj.initial_state(top, 0.1, 150.0)
    J = tj.jellet(top, y0)
    out, full_calls = chain(150.0)
    t_hand = float(out.t_chart_switch)
    assert 0.0 < t_hand < T1 and float(out.t_final) == T1
    assert full_calls > 0
    theta = np.asarray(tj.euler_angles(out.states)[0])
    ts = np.asarray(TS)
    before = ts < t_hand
    sigma = np.array([float(nutation_damping(top, th, J)) for th in theta[before]])
    nu = np.array([float(nutation_frequency(top, th, J)) for th in theta[before]])
    margin = -sigma / nu - HAND_OVER_MARGIN
    assert np.all(margin > 0)
    dt = float(ts[1] - ts[0])
    # where the margin, continued past the last save time before the hand-over at its rate
    # between the last two, crosses zero
    t_cross = ts[before][-1] + margin[-1] / (margin[-2] - margin[-1]) * dt
    assert abs(t_cross - t_hand) < dt
    # the slow flow's steps before the hand-over are few (as on a scene it owns), the full
    # model's after it resolve the nutation: fewer in all than the full model from t0 needs
    # for the nutation periods of the whole run
    assert int(out.num_steps) < 4 * nutation_periods(top, 150.0, T1)


def test_t_hand_over_on_the_solution(top):
    """`sol.t_hand_over` is the gyroscopic run's `t_chart_switch` (nan where it does not hand
    over), and nan for a level that has no hand-over to the full model, also under `vmap`."""
    spins = jnp.array([100.0, 150.0])
    sols = jax.vmap(
        lambda n0: tj.simulate(
            top, tj.initial_state(top, 0.1, n0), T1, model="gyroscopic", summary=True, throw=False
        )
    )(spins)
    t_hand = np.asarray(sols.t_hand_over)
    assert t_hand.shape == (2,)
    assert np.isnan(t_hand[0]) and 0.0 < t_hand[1] < T1
    np.testing.assert_array_equal(t_hand, np.asarray(sols.t_chart_switch))
    so3 = tj.simulate(top, tj.initial_state(top, 0.1, 150.0), 0.1, model="so3", summary=True)
    assert np.isnan(float(so3.t_hand_over))
