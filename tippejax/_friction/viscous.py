from __future__ import annotations

from typing import ClassVar

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .base import AbstractFriction


class Viscous(AbstractFriction):
    r"""Viscous sliding friction, the paper's law (eq. viscfric): $F = -\mu R_n v$.

    Per unit normal force, $f = -\mu v$ with $\mu$ in s/m; no drilling torque. The law of
    Ciocci & Langerock and of Rutstam (2012); the default of `TippeTop`, where
    `TippeTop(..., mu=0.3)` means `TippeTop(..., friction=Viscous(mu=0.3))`. Every level of
    model takes it. It dissipates $f\cdot v = -\mu|v|^2 \le 0$.

    **Arguments:**

    - `mu`: the viscous friction coefficient (s/m), >= 0.
    """

    mu: Float[Array, "*batch"]
    mu_units: ClassVar[str] = "s/m"
    has_drilling_torque: ClassVar[bool] = False

    def __init__(self, mu: ArrayLike = 0.3):
        self._set_checked(dict(mu=mu))

    def _rules(self, values, xp):
        (mu,) = values
        return [
            (mu < 0, f"{type(self).__name__}.mu (viscous friction coefficient, s/m) must be >= 0.")
        ]

    def components(self, slip_x, slip_y, drilling_rate):
        return -self.mu * slip_x, -self.mu * slip_y, jnp.zeros_like(drilling_rate)

    def zero_slip_coefficient(self):
        return self.mu
