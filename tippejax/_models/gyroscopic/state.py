"""The state of the gyroscopic level."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .coordinate import log_tan_half, theta_of


class GyroscopicLevelState(eqx.Module):
    r"""State of the gyroscopic level: $u = \ln\tan(\theta/2)$, the precession and spin angles,
    the log of the nutation amplitude, and $J$.

    Only $u$ is dynamic: $\dot u = \dot\theta/\sin\theta$, the `rate` of (G3), regular and
    nearly constant near the poles, where $\theta$ itself grows or decays exponentially ("The
    level's coordinate", `docs/derivations/gyroscopic-averaging.md`). $\varphi$ and $\psi$ are
    integrated from $\dot\varphi = \Omega$ and $\dot\psi = n - \Omega\cos\theta$ to report the
    orientation, and `nutation` $= \ln a$ from $\sigma$ to watch the nutation that is dropped;
    none of them feeds back. $J$ is constant. `nutation_rate` (None by default): a constant
    $\dot{\ln a}$ that replaces $\sigma$, for a run whose nutation is not the SO(3) model's (the
    full model's rolling mode, `tippejax/_maps/slow_entry.py`).
    """

    log_tan_half_theta: Float[Array, ""]
    phi: Float[Array, ""]
    psi: Float[Array, ""]
    nutation: Float[Array, ""]
    jellet: Float[Array, ""]
    nutation_rate: Float[Array, ""] | None = None

    @property
    def theta(self) -> Array:
        return theta_of(self.log_tan_half_theta)

    @classmethod
    def from_theta(cls, theta, phi, psi, nutation, jellet) -> GyroscopicLevelState:
        """The state at tilt `theta` (the other fields as given)."""
        return cls(
            log_tan_half_theta=log_tan_half(theta),
            phi=jnp.asarray(phi),
            psi=jnp.asarray(psi),
            nutation=jnp.asarray(nutation),
            jellet=jnp.asarray(jellet),
        )
