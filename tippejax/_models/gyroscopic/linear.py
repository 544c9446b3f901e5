"""The linear projection of a launch: the split into the two modes at the nearer pole."""

from __future__ import annotations

import jax.numpy as jnp

from ..._invariants import jellet
from ..._state import State, euler_angles
from ..._top import TippeTop
from .base import AbstractProjection
from .coordinate import theta_of
from .modes import slow_state, split
from .state import GyroscopicLevelState


def linear_projection(top: TippeTop, state: State):
    r"""$(u, \varphi_s, \psi_s, \ln a_0, J)$ of the linear projection of a (single) state,
    $u = \ln\tan(\theta_s/2)$ (see `LinearProjection`)."""
    J = jellet(top, state)
    theta, _, _ = euler_angles(state)
    north = state.axis[2] >= 0
    pole = jnp.where(north, 0.0, jnp.pi).astype(theta.dtype)
    c_re, c_im = split(top, state, J, pole)
    zero = jnp.zeros_like(c_re)
    # the linear projection keeps phi + psi (at both poles)
    return (*slow_state(state, north, c_re, c_im, zero, zero, zero, 1.0), J)


def project_launch(top: TippeTop, state: State):
    r"""$(\theta_s, \varphi_s, \psi_s, \ln a_0, J)$: a (single) state projected linearly onto the
    slow manifold, with the amplitude $a_0$ of its nutation. Regular at the poles."""
    u, phi_s, psi_s, log_amplitude, J = linear_projection(top, state)
    return theta_of(u), phi_s, psi_s, log_amplitude, J


def linear_state(top: TippeTop, state: State) -> GyroscopicLevelState:
    """The gyroscopic level's state of the linear projection of a (single) state."""
    u, phi, psi, log_amplitude, J = linear_projection(top, state)
    return GyroscopicLevelState(
        log_tan_half_theta=u, phi=phi, psi=psi, nutation=log_amplitude, jellet=J
    )


class LinearProjection(AbstractProjection):
    r"""The linear projection: the slow component of the split into the two modes near a pole,

    $$\xi_s = \frac{w - r_-\xi}{r_+ - r_-},\qquad \sin\theta_s = |\xi_s|,\qquad
    a_0 = |\xi - \xi_s|,$$

    with $\xi = a_X + ia_Y$, $w = \omega_X + i\omega_Y$, $r = \dot\psi + i\dot\theta/\sin\theta$
    of each mode: $r_-$ of the other root of (G2) at the nearer pole, $r_+$ of the slow manifold
    at the launch's tilt. Exact on the slow manifold and, near a pole, the exact linear
    projection; for a spun launch ($\omega = n a$) it misses what the decaying nutation feeds
    into the slow mode, which `AveragedProjection` adds. Derivation:
    `docs/derivations/launch-projection.md`.
    """

    name = "linear"

    def project(self, top, state):
        return linear_state(top, state)
