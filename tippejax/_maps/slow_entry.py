"""Where the gyroscopic level takes over a run of the full model: the modes of each state, and the entry test."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._bucket import bucket
from .._models.full import pole_linearisation
from .._models.gyroscopic import (
    GyroscopicLevel,
    GyroscopicLevelState,
    _projection,
    entry_margin,
    log_tan_half,
    theta_of,
)
from .._state import State
from .._top import TippeTop

POLE_SPLIT_SIN = 0.5
r"""A state with $\sin\theta$ above this is split with the linear projection (SO(3) modes)
instead of the full model's modes at the pole."""


ENTRY_NUTATION = 0.25
r"""The gyroscopic level takes over a run of the full model where the nutation (the two
modes of the full model other than the slow manifold's, at the pole) is below this (rad), as
it accepts a launch (`NUTATION_LAUNCH_MAX`)..."""


ENTRY_DECAY = 0.005
r"""... where the nutation about its slow manifold decays at $-\sigma/\nu$ above this (it
hands over where $-\sigma/\nu$ falls below `HAND_OVER_MARGIN` = 0)..."""


ENTRY_BALANCE = 0.01
r"""... where $\Delta_{\rm rel}$ is above `BALANCE_MARGIN` by this..."""


ENTRY_CONTACT = 0.25
r"""... and where the nutation takes less than this fraction of $g$ off the normal force
($\epsilon\sin\theta\,a\nu^2 <$ `ENTRY_CONTACT` $g$)."""


@eqx.filter_jit
def _accepted(top, states):
    """Whether the gyroscopic level takes each launch (its `in_chart`)."""
    return jax.vmap(lambda y: GyroscopicLevel().in_chart(top, y))(states)


@eqx.filter_jit
def _launch_states(top, states, log_nutation, rate):
    """The gyroscopic level's states of launches (its projection), carrying the nutation
    `log_nutation` with its own growth `rate`."""

    def one(y, la, r):
        z = GyroscopicLevel().from_state(top, y)
        return GyroscopicLevelState(
            log_tan_half_theta=z.log_tan_half_theta,
            phi=z.phi,
            psi=z.psi,
            nutation=la,
            jellet=z.jellet,
            nutation_rate=r,
        )

    return jax.vmap(one)(states, log_nutation, rate)


@eqx.filter_jit
def _linearisations(top, J):
    north = jax.vmap(lambda j: pole_linearisation(top, j, north=True))(J)
    south = jax.vmap(lambda j: pole_linearisation(top, j, north=False))(J)
    return north, south


@eqx.filter_jit
def _linear_split(top, states):
    """(theta_s, phi_s, ln a) of the linear projection (SO(3) modes) of each state."""

    def one(y):
        u, phi, _, log_amplitude, _ = _projection(top, y)
        return theta_of(u), phi, log_amplitude

    return jax.vmap(one)(states)


@eqx.filter_jit
def _entry(top, theta, phi, J, log_amplitude, rate):
    """`entry_margin` of each slow state, and the gyroscopic level's state there (carrying
    the nutation `log_amplitude` with its growth `rate`) with its common state."""
    level = GyroscopicLevel()

    def one(th, ph, j, la, r):
        margin = entry_margin(
            top,
            th,
            j,
            la,
            nutation_max=ENTRY_NUTATION,
            decay_min=ENTRY_DECAY,
            balance_min=ENTRY_BALANCE,
            contact_max=ENTRY_CONTACT,
        )
        y = GyroscopicLevelState(
            log_tan_half_theta=log_tan_half(th),
            phi=ph,
            psi=jnp.zeros_like(th),
            nutation=la,
            jellet=j,
            nutation_rate=r,
        )
        return margin, y, level.to_state(top, y)

    return jax.vmap(one)(theta, phi, J, log_amplitude, rate)


def _bucketed(fn, top, *trees):
    """`fn(top, *trees)` with the leading axis of `trees` padded to its `bucket` (copies of the
    last member), cut back after: one compilation per bucket, not per size."""
    size = np.asarray(jax.tree_util.tree_leaves(trees[0])[0]).shape[0]
    padded = bucket(size)

    def pad(x):
        x = np.asarray(x)
        return np.concatenate([x, np.repeat(x[-1:], padded - size, axis=0)]) if padded > size else x

    out = fn(top, *(jax.tree_util.tree_map(pad, t) for t in trees))
    return jax.tree_util.tree_map(lambda x: np.asarray(x)[:size], out)


def split_state(top: TippeTop, states: State, J: np.ndarray):
    r"""Each state split into the full model's three modes at the nearer pole (host-side,
    batched; see `staged_outcomes`): `(theta_s, phi_s, a, rate)`, the tilt and phase of the slow
    manifold's component, the amplitude (rad) of the other two (the nutation), and the
    growth rate (1/s, at most 0) of the rolling mode, which outlives the other. Away from the
    poles ($\sin\theta >$ `POLE_SPLIT_SIN`): the linear projection, and rate 0."""
    north_m, south_m = _bucketed(_linearisations, top, np.asarray(J))
    axis = np.asarray(states.axis)
    north = axis[:, 2] >= 0
    m = np.where(north[:, None, None], north_m, south_m)
    values, vectors = np.linalg.eig(m)
    # the slow manifold's mode precesses fastest; of the other two the rolling one decays least
    slow = np.argmax(np.abs(values.imag), axis=1)
    real = np.where(np.arange(3)[None, :] == slow[:, None], -np.inf, values.real)
    rolling = np.argmax(real, axis=1)
    rows = np.arange(axis.shape[0])
    velocity, omega = np.asarray(states.velocity), np.asarray(states.omega)
    z = np.stack(
        [
            velocity[:, 0] + 1j * velocity[:, 1],
            axis[:, 0] + 1j * axis[:, 1],
            omega[:, 0] + 1j * omega[:, 1],
        ],
        axis=1,
    )
    with np.errstate(all="ignore"):
        coefficients = np.linalg.solve(vectors, z[..., None])[..., 0]
    tilt = coefficients * vectors[:, 1, :]  # each mode's part of a_X + i a_Y
    xi_slow = tilt[rows, slow]
    rest = np.abs(z[:, 1] - xi_slow)
    sin_s = np.minimum(np.abs(xi_slow), 1.0)
    theta_s = np.where(north, np.arcsin(sin_s), np.pi - np.arcsin(sin_s))
    # xi = -i sin(theta) e^{i phi} (either pole)
    phi_s = np.arctan2(xi_slow.real, -xi_slow.imag)
    rate = np.minimum(values[rows, rolling].real, 0.0)
    lin_theta, lin_phi, lin_log_a = _bucketed(_linear_split, top, states)
    near = np.hypot(axis[:, 0], axis[:, 1]) <= POLE_SPLIT_SIN
    ok = near & np.isfinite(theta_s) & np.isfinite(rest) & np.isfinite(rate)
    return (
        np.where(ok, theta_s, lin_theta),
        np.where(ok, phi_s, lin_phi),
        np.where(ok, rest, np.exp(lin_log_a)),
        np.where(ok, rate, 0.0),
    )
