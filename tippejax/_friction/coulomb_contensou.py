from __future__ import annotations

import math
from typing import ClassVar, Literal

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .base import AbstractFriction
from .coulomb import coulomb_mu_rule, slip_scale_rule

PRESSURES = ("hertz", "ellipse")

PATCH_FRACTION = 0.1
"""The largest patch radius a `TippeTop` accepts, as a fraction of its ball's radius."""

REFERENCE_DRILLING_RATE = 100.0
"""The drilling rate (rad/s) at which `CoulombContensou.stiffness_coefficient` takes the slope
of the law at zero slip: a spinning tippe top's (the launches of the literature spin at
100-200 rad/s about the axis)."""

_SERIES_FROM = 2.0
"""From this $u$ on, the Hertz profiles are summed as series in $1/u^2$ (their closed forms
lose digits to cancellation at large $u$)."""

_SERIES_TERMS = 20
"""Terms of the series in $z = 1/u^2 \\le 1/4$: the last one is below float64's rounding."""


def _hypergeometric_coefficients(a, b, c, n):
    coefficients = [1.0]
    for k in range(n - 1):
        coefficients.append(coefficients[-1] * (a + k) * (b + k) / ((c + k) * (k + 1)))
    return tuple(coefficients)


_FORCE_SERIES = _hypergeometric_coefficients(-0.5, 0.5, 2.5, _SERIES_TERMS)
_TORQUE_SERIES = _hypergeometric_coefficients(0.5, 0.5, 3.5, _SERIES_TERMS)


def _polynomial(coefficients, z):
    out = coefficients[-1] * jnp.ones_like(z)
    for c in reversed(coefficients[:-1]):
        out = out * z + c
    return out


def hertz_profiles(u):
    r"""The force and torque profiles $(\varphi_F(u), \varphi_M(u))$ of Coulomb friction over a
    Hertz pressure disc, with $u = |v|/(\rho|\omega_n|)$ (see `CoulombContensou`).

    For $u \le 1$: $\varphi_F = \tfrac{3\pi}{32}u(4 - u^2)$,
    $\varphi_M = \tfrac{3\pi}{128}(8 - 8u^2 + 3u^4)$. For $u > 1$:
    $\varphi_F = \tfrac{3}{16u}\big[(4u^2 - u^4)\arcsin\tfrac1u + (u^2 + 2)\sqrt{u^2-1}\big]
    = {}_2F_1(-\tfrac12, \tfrac12; \tfrac52; u^{-2})$,
    $\varphi_M = \tfrac{3}{64}\big[(3u^4 - 8u^2 + 8)\arcsin\tfrac1u + (6 - 3u^2)\sqrt{u^2-1}\big]
    = \tfrac1{5u}\,{}_2F_1(\tfrac12, \tfrac12; \tfrac72; u^{-2})$,
    summed as series for $u \ge 2$. Each branch is evaluated at a safe argument where it is not
    selected, so gradients are finite everywhere (also at $u = 1$).
    """
    inside = u <= 1.0
    far = u >= _SERIES_FROM
    u_in = jnp.where(inside, u, 0.5)
    u2 = u_in**2
    force_in = (3 * math.pi / 32) * u_in * (4.0 - u2)
    torque_in = (3 * math.pi / 128) * (8.0 - 8.0 * u2 + 3.0 * u2**2)
    u_mid = jnp.where(inside | far, 1.5, u)
    u2 = u_mid**2
    # arcsin(1/u) = arctan(1/sqrt(u^2 - 1)), with u^2 - 1 = (u - 1)(u + 1): accurate values and
    # derivatives near u = 1, where 1 - 1/u^2 would lose digits.
    root = jnp.sqrt((u_mid - 1.0) * (u_mid + 1.0))
    arc = jnp.arctan2(1.0, root)
    force_mid = 3.0 / (16.0 * u_mid) * ((4.0 * u2 - u2**2) * arc + (u2 + 2.0) * root)
    torque_mid = 3.0 / 64.0 * ((3.0 * u2**2 - 8.0 * u2 + 8.0) * arc + (6.0 - 3.0 * u2) * root)
    u_far = jnp.where(far, u, _SERIES_FROM)
    z = 1.0 / u_far**2
    force_far = _polynomial(_FORCE_SERIES, z)
    torque_far = _polynomial(_TORQUE_SERIES, z) / (5.0 * u_far)
    force = jnp.where(inside, force_in, jnp.where(far, force_far, force_mid))
    torque = jnp.where(inside, torque_in, jnp.where(far, torque_far, torque_mid))
    return force, torque


class CoulombContensou(AbstractFriction):
    r"""Coulomb friction over a small contact disc: a sliding force and a drilling torque.

    The contact is a disc of radius $\rho$ (`patch_radius`) about $Q$; each of its elements,
    at $r$ from $Q$, slides at $v + \omega_n e_Z\times r$ and feels Coulomb friction
    $-\mu\,p\,\hat w\,dA$ against its own sliding direction $\hat w$. Integrated over the disc
    this gives a force $F$ against $v$ and a drilling torque $M e_Z$ against $\omega_n$, both
    proportional to $R_n$ (the Contensou coupling: spin softens the sliding friction and slip
    softens the drilling friction). $\mu$ is dimensionless.

    **`pressure="hertz"`** (default): the exact law for the Hertz pressure
    $p = \tfrac{3R_n}{2\pi\rho^2}\sqrt{1 - r^2/\rho^2}$ (Zhuravlev 1998; Leine & Glocker
    2003, eq. 7). With $u = |v|/(\rho|\omega_n|)$,
    $$F = -\mu R_n\,\varphi_F(u)\,\frac{v}{|v|},\qquad
    M = -\mu R_n\,\rho\,\varphi_M(u)\,\operatorname{sign}\omega_n,$$
    where $\varphi_F, \varphi_M$ are closed forms with branches $u \le 1$ (the
    instantaneous centre of the patch's motion lies in the disc) and $u > 1$
    (`hertz_profiles`; derived in `docs/friction.md`). Limits: pure slip $|F| = \mu R_n$; pure
    spin $|M| = \tfrac{3\pi}{16}\mu R_n\rho$; small slip
    $F \approx -\tfrac{3\pi}{8}\mu R_n\,v/(\rho|\omega_n|)$ (Leine & Glocker, eq. 17: the
    slip is damped as by a stiff viscous law).

    Regularised with the slip scale $\delta$: the law is evaluated at the regularised speeds
    $s = \sqrt{|v|^2 + \delta^2}$ and $w = \sqrt{\rho^2\omega_n^2 + \delta^2}$,
    $$f = -\mu\,\varphi_F(s/w)\,\frac{v}{s},\qquad
    m = -\mu\,\rho\,\varphi_M(s/w)\,\frac{\rho\,\omega_n}{w}$$
    (per unit normal force). It is smooth in $(v, \omega_n)$ (the profiles join with two
    continuous derivatives at $u = 1$), dissipates
    $f\cdot v + m\,\omega_n = -\mu(\varphi_F|v|^2/s + \varphi_M\rho^2\omega_n^2/w) \le 0$
    (both profiles are positive), and tends to the exact law as $\delta \to 0$ at every
    $(v, \omega_n) \ne 0$, with a relative error of order $\delta^2/|v|^2 + \delta^2/(\rho\omega_n)^2$.

    **`pressure="ellipse"`**: the ellipsoidal approximation of Moeller, Leine & Glocker
    (2009), used by cardillo (`Sphere2PlaneCoulombContensouMoeller`): the generalised velocity
    $(v, R_b\omega_n)$ with $R_b = 3\pi\rho/16$ meets the friction ball
    $|(F, M/R_b)| \le \mu R_n$; regularised,
    $$D = \sqrt{|v|^2 + R_b^2\omega_n^2 + \delta^2},\qquad F = -\mu R_n\,v/D,\qquad
    M = -\mu R_n R_b^2\,\omega_n/D.$$
    It has the exact limits of pure slip and pure spin, not the small-slip one.

    With either pressure the Jellet integral is not conserved: $\dot J = M(R - \epsilon\cos
    \theta)$ (`jellet_rate`). The full and SO(3) levels take this law.

    **Arguments:**

    - `mu`: the Coulomb friction coefficient (dimensionless), >= 0.
    - `patch_radius`: the radius $\rho$ of the contact disc (m), > 0 and well below the ball's
      radius (a `TippeTop` takes $\rho < R/10$).
    - `slip_scale`: the regularisation speed $\delta$ (m/s), > 0.
    - `pressure`: `"hertz"` (the exact law) or `"ellipse"` (Moeller, Leine & Glocker).
    """

    mu: Float[Array, "*batch"]
    patch_radius: Float[Array, "*batch"]
    slip_scale: Float[Array, "*batch"]
    pressure: Literal["hertz", "ellipse"] = eqx.field(static=True, default="hertz")
    mu_units: ClassVar[str] = "1"
    has_drilling_torque: ClassVar[bool] = True

    def __init__(
        self,
        mu: ArrayLike,
        patch_radius: ArrayLike,
        slip_scale: ArrayLike,
        pressure: Literal["hertz", "ellipse"] = "hertz",
    ):
        if pressure not in PRESSURES:
            raise ValueError(
                f"CoulombContensou.pressure must be one of {PRESSURES} (the exact law for a "
                f"Hertz pressure disc, or Moeller, Leine & Glocker's ellipse), got {pressure!r}."
            )
        self.pressure = pressure
        self._set_checked(dict(mu=mu, patch_radius=patch_radius, slip_scale=slip_scale))

    def _rules(self, values, xp):
        mu, patch_radius, slip_scale = values
        owner = type(self).__name__
        return [
            coulomb_mu_rule(owner, mu),
            (
                patch_radius <= 0,
                f"{owner}.patch_radius (radius of the contact disc, m) must be > 0.",
            ),
            slip_scale_rule(owner, slip_scale),
        ]

    def ball_rules(self, R, xp):
        return [
            (
                self.patch_radius >= PATCH_FRACTION * R,
                f"CoulombContensou.patch_radius (radius of the contact disc, m) must be well below "
                f"the ball's radius R: patch_radius < {PATCH_FRACTION:g} R (the law is for a small "
                "flat contact).",
            )
        ]

    @property
    def drilling_radius(self) -> Float[Array, "*batch"]:
        r"""The ellipse law's $R_b = 3\pi\rho/16$ (m): $|M| = \mu R_n R_b$ in pure spin."""
        return (3 * math.pi / 16) * self.patch_radius

    def components(self, slip_x, slip_y, drilling_rate):
        delta2 = self.slip_scale**2
        if self.pressure == "ellipse":
            rb = self.drilling_radius
            scale = self.mu / jnp.sqrt(slip_x**2 + slip_y**2 + (rb * drilling_rate) ** 2 + delta2)
            return -scale * slip_x, -scale * slip_y, -scale * rb**2 * drilling_rate
        rho = self.patch_radius
        slip = jnp.sqrt(slip_x**2 + slip_y**2 + delta2)
        spin = jnp.sqrt((rho * drilling_rate) ** 2 + delta2)
        force, torque = hertz_profiles(slip / spin)
        scale = self.mu * force / slip
        return (-scale * slip_x, -scale * slip_y, -self.mu * rho**2 * torque * drilling_rate / spin)

    def _slope_at_zero_slip(self, drilling_rate):
        delta = self.slip_scale
        if self.pressure == "ellipse":
            return self.mu / jnp.sqrt((self.drilling_radius * drilling_rate) ** 2 + delta**2)
        spin = jnp.sqrt((self.patch_radius * drilling_rate) ** 2 + delta**2)
        return self.mu * hertz_profiles(delta / spin)[0] / delta

    def _with_slip_floor(self, floor):
        # (the motion converges as delta -> 0: docs/friction.md)
        return eqx.tree_at(lambda law: law.slip_scale, self, jnp.maximum(self.slip_scale, floor))

    def zero_slip_coefficient(self):
        r"""The slope at zero slip and zero drilling (s/m): $\tfrac{9\pi}{32}\mu/\delta$ for
        the Hertz law (there the regularised speeds are equal, $u = 1$), $\mu/\delta$ for the
        ellipse."""
        return self._slope_at_zero_slip(jnp.zeros_like(self.mu))

    def stiffness_coefficient(self):
        r"""The slope at zero slip while the contact drills at `REFERENCE_DRILLING_RATE` (s/m).

        Drilling softens the sliding friction: at zero slip the slope is
        $\mu\varphi_F'(0)/\sqrt{\rho^2\omega_n^2 + \delta^2}$ ($\varphi_F'(0) = 3\pi/8$ for the
        Hertz law, 1 for the ellipse with $R_b$ for $\rho$), which does not depend on $\delta$
        while $\rho|\omega_n| \gg \delta$. A spinning top therefore meets the regularised
        bound `zero_slip_coefficient` only where it stops drilling, and an explicit solver is
        the cheaper at small slip scales (`benchmarks/RESULTS.md`, `real_tops.py --wp`). A top
        that drills much slower is stiffer than this says: pass `solver=diffrax.Kvaerno5()` if
        its steps run into `max_steps`."""
        return self._slope_at_zero_slip(REFERENCE_DRILLING_RATE * jnp.ones_like(self.mu))
