"""The stem of a real tippe top: a second sphere on the axis, and its contact with the table."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._friction.base import array_module, as_float, broadcast_fields, checked, finite_rules

CONTACT_MODULUS = 5.0e9
"""Default effective modulus $E^*$ of the compliant contacts (Pa): a hard plastic top on a
hard table (Leine & Glocker's top is of wood or plastic; steel on steel would be about 1e11)."""

CONTACT_DAMPING = 200.0
"""Default Hunt-Crossley damping $c$ (s/m): nearly plastic impacts, a coefficient of restitution
of about $1/(\\tfrac32 c v)$ at an impact speed $v$ well above $1/c$ (0.08 at 4 cm/s)."""

_FIELDS = ("radius", "offset", "contact_modulus", "contact_damping")


class Stem(eqx.Module):
    r"""The stem of a tippe top: a sphere of radius $r_2$ centred on the axis at $O + a_2 a$.

    $O$ is the centre of mass and $a$ the symmetry axis, which points from $O$ to the centre of
    the ball, $O + \epsilon a$; the stem lies on the same side, beyond it ($a_2 > \epsilon$):
    Leine & Glocker 2003's geometry, and cardillo's. With the ball on the table the stem's tip
    touches it where $z_O + a_2\cos\theta - r_2 = 0$, that is at the tilt

    $$\cos\theta_s = \frac{r_2 - R}{a_2 - \epsilon}$$

    (`TippeTop.stem_angle`; about 2.45 rad for Leine & Glocker's top). From the touch on the top
    moves on two compliant contacts, then on the stem alone, possibly back on the ball: the
    stem level (`docs/friction.md`, "The stem"). Each contact, sphere $i$ of radius $r_i$ whose
    centre is at $O + d_i a$ (the ball: $R$, $\epsilon$; the stem: $r_2$, $a_2$), is a
    Hunt-Crossley contact with penetration $\delta_i = r_i - z_O - d_i a_Z$,

    $$R_{n,i} = \max\big(0,\ k_i\,\delta_i^{3/2}(1 + \tfrac32 c\,\dot\delta_i)\big),\qquad
    k_i = \tfrac43 E^*\sqrt{r_i}\quad(\delta_i > 0),$$

    with the friction law of the top at each contact, with its own normal force, slip and
    drilling rate. $E^*$ (`contact_modulus`) and $c$ (`contact_damping`) are the parameters of
    that switch; the motion after the touch depends on them only weakly (the measured
    sensitivity is in `benchmarks/RESULTS.md`, `real_tops.py --contact`).

    Every field is a JAX array: a `Stem` can be batched (a leading axis on its fields) and
    differentiated like the other fields of a `TippeTop`. Rules that involve the ball
    ($R$, $\epsilon$) are checked by `TippeTop`. A top with a stem runs in float64 only (its
    contacts' penetrations, about $10^{-7}$ m, are below what float32 resolves at a top's
    size) and at the full level, which hands over to the stem level.

    **Arguments:**

    - `radius`: the radius $r_2$ of the stem's tip (m), > 0.
    - `offset`: the distance $a_2$ from the centre of mass to the centre of the tip (m), along
      the axis on the ball centre's side, $a_2 > \epsilon$, with a tip that reaches out of the
      ball ($a_2 - \epsilon + r_2 > R$) and touches the table only once the top has tilted
      ($r_2 - R < a_2 - \epsilon$).
    - `contact_modulus`: the effective modulus $E^*$ of both compliant contacts (Pa), > 0
      (keyword only; default `CONTACT_MODULUS`).
    - `contact_damping`: the Hunt-Crossley damping $c$ (s/m), >= 0 (keyword only; default
      `CONTACT_DAMPING`).
    """

    radius: Float[Array, "*batch"]
    offset: Float[Array, "*batch"]
    contact_modulus: Float[Array, "*batch"]
    contact_damping: Float[Array, "*batch"]

    def __init__(
        self,
        radius: ArrayLike,
        offset: ArrayLike,
        *,
        contact_modulus: ArrayLike = CONTACT_MODULUS,
        contact_damping: ArrayLike = CONTACT_DAMPING,
    ):
        values = [as_float(v) for v in (radius, offset, contact_modulus, contact_damping)]
        values = broadcast_fields("Stem", _FIELDS, values)
        values = checked("Stem", _FIELDS, values, _own_rules)
        self.radius, self.offset, self.contact_modulus, self.contact_damping = values

    def ball_rules(self, R, eps, xp) -> list:
        """(failed, message) for the rules on the stem and the ball together (`TippeTop`)."""
        del xp
        r2, a2 = self.radius, self.offset
        return [
            (
                a2 <= eps,
                "TippeTop.stem: Stem.offset a2 (from the centre of mass to the centre of the tip, "
                "m) must be > eps: the stem sits on the ball centre's side, beyond it.",
            ),
            (
                a2 - eps + r2 <= R,
                "TippeTop.stem: the stem lies inside the ball and can never reach the table: "
                "a2 - eps + r2 <= R (cos theta_s = (r2 - R)/(a2 - eps) < -1). Allowed: "
                "a2 - eps + r2 > R.",
            ),
            (
                r2 - R >= a2 - eps,
                "TippeTop.stem: the tip would touch the table at every tilt, upright too: "
                "r2 - R >= a2 - eps (cos theta_s = (r2 - R)/(a2 - eps) >= 1). Allowed: "
                "r2 - R < a2 - eps.",
            ),
        ]

    def __repr__(self) -> str:
        parts = []
        try:
            for k in _FIELDS:
                v = np.asarray(getattr(self, k))
                if v.ndim == 0:
                    parts.append(f"{k}={v.item():.6g}")
                elif v.size and np.all(v == v.flat[0]):
                    parts.append(f"{k}={v.flat[0].item():.6g}")
                else:
                    parts.append(f"{k}={np.array2string(v, precision=6, threshold=8)}")
        except Exception:  # noqa: BLE001 - traced fields have no values to show
            return super().__repr__()
        return f"Stem({', '.join(parts)})"


def _own_rules(radius, offset, modulus, damping):
    xp = array_module(radius, offset, modulus, damping)
    return finite_rules("Stem", _FIELDS, (radius, offset, modulus, damping), xp) + [
        (radius <= 0, "Stem.radius (radius r2 of the stem's tip, m) must be > 0."),
        (
            offset <= 0,
            "Stem.offset (distance a2 from the centre of mass to the tip's centre, m) must be > 0.",
        ),
        (
            modulus <= 0,
            "Stem.contact_modulus (effective modulus E* of the contacts, Pa) must be > 0.",
        ),
        (damping < 0, "Stem.contact_damping (Hunt-Crossley damping c, s/m) must be >= 0."),
    ]


def stem_angle(R, eps, stem: Stem):
    r"""$\theta_s = \arccos\big((r_2 - R)/(a_2 - \epsilon)\big)$: the tilt at which the stem
    touches the table with the ball on it."""
    return jnp.arccos((stem.radius - R) / (stem.offset - eps))


def hertz_stiffness(stem: Stem, radius):
    r"""$k = \tfrac43 E^*\sqrt{r}$ (N/m^{3/2}) of a sphere of radius `radius` on the table."""
    return (4.0 / 3.0) * stem.contact_modulus * jnp.sqrt(radius)
