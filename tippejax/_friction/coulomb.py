from __future__ import annotations

from typing import ClassVar

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .base import AbstractFriction


def slip_scale_rule(owner, slip_scale):
    return (slip_scale <= 0, f"{owner}.slip_scale (regularisation speed, m/s) must be > 0.")


def coulomb_mu_rule(owner, mu):
    return (mu < 0, f"{owner}.mu (Coulomb friction coefficient, dimensionless) must be >= 0.")


class Coulomb(AbstractFriction):
    r"""Regularised Coulomb sliding friction: $F = -\mu R_n\, v/\sqrt{|v|^2 + \delta^2}$.

    Per unit normal force $f = -\mu v/\sqrt{|v|^2 + \delta^2}$, with $\mu$ dimensionless and
    the slip scale $\delta$ (m/s) below which the law turns viscous (coefficient $\mu/\delta$);
    no drilling torque. As $\delta\to0$ it tends to Coulomb's law $|f| = \mu$ against the slip
    (Cohen 1977; Or 1994, unregularised). It dissipates $f\cdot v \le 0$.

    !!! warning

        With this law alone the inversion time of a top launched spinning about its axis
        does not converge as $\delta\to0$: the top reaches near-rolling within a fraction of
        a second and then rises only by creep below $\delta$, so that the time grows roughly
        like $1/\delta$ and has no limit (`docs/friction.md`; the measured times are in
        `benchmarks/RESULTS.md`, `real_tops.py --slip`). `simulate` and `inversion_time` say
        so with a `UserWarning` and still run. Only the drilling torque of a Contensou law
        (`CoulombContensou`) makes the rise a property of the physics.

    **Arguments:**

    - `mu`: the Coulomb friction coefficient (dimensionless), >= 0.
    - `slip_scale`: the regularisation speed $\delta$ (m/s), > 0.
    """

    mu: Float[Array, "*batch"]
    slip_scale: Float[Array, "*batch"]
    mu_units: ClassVar[str] = "1"
    has_drilling_torque: ClassVar[bool] = False

    def __init__(self, mu: ArrayLike, slip_scale: ArrayLike):
        self._set_checked(dict(mu=mu, slip_scale=slip_scale))

    def _rules(self, values, xp):
        mu, slip_scale = values
        owner = type(self).__name__
        return [coulomb_mu_rule(owner, mu), slip_scale_rule(owner, slip_scale)]

    def components(self, slip_x, slip_y, drilling_rate):
        scale = self.mu / jnp.sqrt(slip_x**2 + slip_y**2 + self.slip_scale**2)
        return -scale * slip_x, -scale * slip_y, jnp.zeros_like(drilling_rate)

    def zero_slip_coefficient(self):
        return self.mu / self.slip_scale

    def inversion_time_caveat(self):
        scales = np.unique(np.asarray(self.slip_scale))
        shown = ", ".join(f"{x:.3g}" for x in scales[:3]) + (", ..." if scales.size > 3 else "")
        return (
            f"tj.Coulomb has no drilling torque: under it the inversion time of a top spinning "
            f"about its axis depends on slip_scale (here {shown} m/s) and grows roughly like "
            "1/slip_scale as slip_scale goes to 0, with no limit, so sol.t_invert and "
            "inversion_time are properties of slip_scale, not of the top. Coulomb-Contensou "
            "friction (tj.CoulombContensou) has a rise that converges (docs/friction.md, 'A "
            "trap: pure Coulomb friction')."
        )
