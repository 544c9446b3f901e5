"""The averaged projection of a launch: first-order averaging over its decaying nutation."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..._invariants import jellet
from ..._state import State, euler_angles, euler_rates
from ..._top import TippeTop
from .base import AbstractProjection
from .chart import NUTATION_LAUNCH_MAX
from .coordinate import POLE, safe_log, safe_sqrt, sign_of
from .linear import linear_projection
from .manifold import slow_manifold_at
from .modes import slow_state, split
from .nutation import momentum_coupling, nutation_at
from .state import GyroscopicLevelState

AVERAGING_NODES = 6
r"""Gauss-Legendre nodes of the averaged projection's integrals over the decay of a launch's
nutation ($I$, $\Phi$, $\Psi$ of `launch_transient`). The integrands are smooth and nearly
linear in the tilt, so a few nodes suffice."""


class LaunchTransient(eqx.Module):
    r"""What the decay of a launch's nutation does to its slow component: the integrals over the
    other root's mode decaying from the tilt $\vartheta_f$ to the pole (see `launch_transient`).

    - `gain`: $I = \int (\sigma_-(\vartheta) - \sigma_-(0))\,dt$, the log of the factor by
      which the slow component's amplitude ends up changed.
    - `turn`: $\Phi$, the extra turn of its phase ($\varphi_s$).
    - `spin_turn`: $\Psi$, the extra turn of the body about the vertical ($\varphi + \psi$).
    - `valid`: the other root's mode decays along the whole path (else the integrals are 0).
    """

    gain: Array
    turn: Array
    spin_turn: Array
    valid: Array


def launch_transient(
    top: TippeTop, shed, J, *, north=True, nodes: int = AVERAGING_NODES
) -> LaunchTransient:
    r"""The integrals $I$, $\Phi$, $\Psi$ over the decay of the other root's mode from a tilt
    `shed` $= \vartheta_f$ (from the pole: $\theta = \vartheta$ at the north pole,
    $\pi - \vartheta$ at the south pole) to the pole, at Jellet `J`:

    $$I = \int_0^{\vartheta_f}\frac{\sigma_-(\vartheta) - \sigma_-(0)}{|\dot\vartheta_-|}\,
    d\vartheta,\quad
    \Phi = \int_0^{\vartheta_f}\frac{\mathrm{sgn}(J)(\nu_- - \nu_-(0)) + \Omega_- -
    \Omega_-(0)}{|\dot\vartheta_-|}\,d\vartheta,\quad
    \Psi = \int_0^{\vartheta_f}\frac{\Omega_-(1 \mp \cos\theta) \pm (n_- - n_-(0))}
    {|\dot\vartheta_-|}\,d\vartheta,$$

    with $\sigma_-$, $\nu_-$ the nutation about the other root, $\Omega_-$, $n_-$ its precession
    and spin, $\dot\vartheta_- = \mp$ (G3) its decay (upper signs at the north pole), by
    Gauss-Legendre quadrature on `nodes` nodes. Derivation:
    `docs/derivations/launch-projection.md`.
    """
    dtype = jnp.result_type(shed, top.m)
    shed = jnp.asarray(shed, dtype)
    nodes, weights = np.polynomial.legendre.leggauss(nodes)
    tilt = 0.5 * shed[..., None] * (1 + jnp.asarray(nodes, dtype))
    weight = 0.5 * shed[..., None] * jnp.asarray(weights, dtype)
    north = jnp.asarray(north)[..., None]
    side = jnp.where(north, 1.0, -1.0).astype(dtype)
    s = jnp.sin(tilt)
    x = side * jnp.cos(tilt)
    J = jnp.asarray(J, dtype)[..., None]
    other = slow_manifold_at(top, x, s, J, -1)
    nutation = nutation_at(top, x, s, J, other)
    at_pole = slow_manifold_at(top, side, jnp.zeros_like(side), J, -1)
    nutation_pole = nutation_at(top, side, jnp.zeros_like(side), J, at_pole)
    decay = -side * other.rate * s  # -d(vartheta)/dt along the other root
    moving = s > 0
    decays = decay > 0
    safe = jnp.where(decays, decay, 1.0)

    def integral(rate):
        return jnp.sum(weight * jnp.where(decays, rate / safe, 0.0), axis=-1)

    sign = sign_of(J)
    gain = integral(nutation.damping - nutation_pole.damping)
    turn = integral(
        sign * (safe_sqrt(nutation.frequency_squared) - safe_sqrt(nutation_pole.frequency_squared))
        + other.precession
        - at_pole.precession
    )
    spin_turn = integral(other.precession * (1 - side * x) + side * (other.spin - at_pole.spin))
    valid = jnp.all((decays | ~moving) & (other.discriminant > 0), axis=-1)
    valid = valid & jnp.isfinite(gain) & jnp.isfinite(turn) & jnp.isfinite(spin_turn)
    zero = jnp.zeros_like(gain)
    return LaunchTransient(
        gain=jnp.where(valid, gain, zero),
        turn=jnp.where(valid, turn, zero),
        spin_turn=jnp.where(valid, spin_turn, zero),
        valid=valid,
    )


def kept_amplitude(top: TippeTop, state: State, J, theta_b):
    r"""$(a_0, \theta_c)$: the amplitude (in $\theta$) of the nutation of a state about the other
    root's state at tilt `theta_b` with the same $J$, and the $\theta$ of its centre (reduced
    chart, conservative linearisation): $\theta_c = \theta_b + K\delta p/(M_\theta\nu^2)$,
    $a_0^2 = (\theta - \theta_c)^2 + (\delta\dot\theta/\nu)^2$."""
    theta, _, _ = euler_angles(state)
    theta_dot, phi_dot, psi_dot = euler_rates(state)
    x, s = jnp.cos(theta_b), jnp.sin(theta_b)
    base = slow_manifold_at(top, x, s, J, -1)
    nutation = nutation_at(top, x, s, J, base)
    nu2 = jnp.where(nutation.frequency_squared > 0, nutation.frequency_squared, 1.0)
    inertia = top.A + top.m * top.eps**2 * s * s  # M_theta
    slip = top.R * psi_dot + top.eps * phi_dot  # p of the state
    coupling = s * momentum_coupling(top, x, s, J, base.slip)  # K
    centre = theta_b + coupling * (slip - base.slip) / (inertia * nu2)
    velocity = (theta_dot - base.theta_dot) / jnp.sqrt(nu2)
    return safe_sqrt((theta - centre) ** 2 + velocity**2), centre


def averaged_projection(top: TippeTop, state: State, nodes: int = AVERAGING_NODES):
    r"""$(u, \varphi_s, \psi_s, \ln a_0, J)$ of `average_launch`."""
    J = jellet(top, state)
    theta, _, _ = euler_angles(state)
    north = state.axis[2] >= 0
    # the launch's tilt from the nearer pole, at most NUTATION_LAUNCH_MAX (a launch with more
    # nutation is refused; one tilted further is taken only near the slow manifold)
    tilt = jnp.minimum(jnp.where(north, theta, jnp.pi - theta), NUTATION_LAUNCH_MAX)
    theta_b = jnp.where(north, tilt, jnp.pi - tilt)
    # the split with the other root's mode frozen at the launch's tilt
    c_re, c_im = split(top, state, J, theta_b)
    a = state.axis
    kept2 = c_re**2 + c_im**2
    shed2 = (a[0] - c_re) ** 2 + (a[1] - c_im) ** 2
    # where the launch's nutation dominates: the slow component's amplitude about the other
    # root's state (reduced chart) and what the nutation's decay feeds into it; where the slow
    # component dominates, the split (exact on the slow manifold)
    weight = jnp.where(shed2 > 0, shed2 / jnp.where(shed2 > 0, shed2 + kept2, 1.0), 0.0)
    amplitude, centre = kept_amplitude(top, state, J, theta_b)
    # the nutation decays from its centre (from the pole) to the pole
    shed = jnp.clip(jnp.where(north, centre, jnp.pi - centre), 0.0, 2 * NUTATION_LAUNCH_MAX)
    transient = launch_transient(top, shed, J, north=north, nodes=nodes)
    log_split = 0.5 * safe_log(kept2, -2 * POLE)
    log_reduced = safe_log(amplitude, -2 * POLE)
    log_gain = jnp.where(kept2 > 0, weight * (log_reduced + transient.gain - log_split), 0.0)
    side = jnp.where(north, 1.0, -1.0).astype(c_re.dtype)
    averaged = slow_state(
        state,
        north,
        c_re,
        c_im,
        log_gain,
        weight * transient.turn,
        weight * transient.spin_turn,
        side,
    )
    linear = linear_projection(top, state)[:4]
    use = transient.valid & jnp.isfinite(c_re) & jnp.isfinite(c_im) & jnp.isfinite(log_gain)
    return (*(jnp.where(use, p, q) for p, q in zip(averaged, linear)), J)


def average_launch(
    top: TippeTop, state: State, *, nodes: int = AVERAGING_NODES
) -> GyroscopicLevelState:
    """The averaged projection of a (single) state (see `AveragedProjection`)."""
    u, phi, psi, log_amplitude, J = averaged_projection(top, state, nodes)
    return GyroscopicLevelState(
        log_tan_half_theta=u, phi=phi, psi=psi, nutation=log_amplitude, jellet=J
    )


class AveragedProjection(AbstractProjection):
    r"""The averaged projection (the default): first-order averaging over the launch's
    nutation, in closed form,

    $$\ln\sin\theta_s = \ln a_0 + I(\vartheta_c),\qquad
    I(\vartheta) = \int_0^{\vartheta}\frac{\sigma_-(\vartheta') - \sigma_-(0)}
    {|\dot\vartheta_-(\vartheta')|}\,d\vartheta',$$

    with $a_0$ the launch's slow content and $\vartheta_c$ its nutation's centre, both read
    about the other root's state at the launch's tilt, and $I$ what the nutation feeds into the
    slow component while it decays (`launch_transient`); where the slow component is not small
    against the nutation, the split of `LinearProjection` (exact on the slow manifold). No
    solve: a few evaluations of (G3) and $\sigma$. Falls back to the linear projection where
    the other root's mode does not decay from the launch's tilt to the pole. Derivation:
    `docs/derivations/launch-projection.md`.

    Use it for spun launches ($\omega = n a$) and for batches: it costs about what the linear
    projection costs. `FibreProjection` is the more exact for launches that mix both modes or
    are tilted far, at the cost of two short solves per launch (see the performance page).

    **Static option:** `nodes` (default `AVERAGING_NODES`), the Gauss-Legendre nodes of the
    integrals.
    """

    name = "averaged"
    nodes: int = eqx.field(static=True, default=AVERAGING_NODES)

    def __check_init__(self):
        if not (isinstance(self.nodes, (int, np.integer)) and self.nodes >= 1):
            raise ValueError(
                f"AveragedProjection: nodes must be a positive integer, got {self.nodes!r}."
            )

    def project(self, top, state):
        return average_launch(top, state, nodes=self.nodes)
