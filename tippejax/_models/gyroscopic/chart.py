r"""Where the gyroscopic level holds: gyroscopic balance, a decaying nutation, a small one."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array

from ..._top import TippeTop
from .coordinate import POLE, safe_log, safe_sqrt
from .manifold import slow_manifold_at
from .nutation import Nutation, nutation_at

BALANCE_MARGIN = 0.01
r"""The level stops where $\Delta/(J^2 + 4Ahmg\epsilon|R\cos\theta - \epsilon|)$ falls below
this."""

NUTATION_MAX = 0.05
r"""The level stops where the nutation amplitude it drops exceeds this (rad) while growing."""

NUTATION_LAUNCH_MAX = 0.25
r"""A launch with more nutation than this (rad) is refused: its projection is not trusted."""

HAND_OVER_MARGIN = 0.0
r"""With `hand_over`, the level hands over to the full model where $-\sigma/\nu$ falls below
this: where the nutation about the slow manifold stops decaying fast."""


def contact_proximity(top: TippeTop, s, log_amplitude, nutation: Nutation, fraction) -> Array:
    r"""$\ln(f g) - \ln(\epsilon\sin\theta\,a\nu^2)$: positive while the nutation of
    amplitude $a = e^{\ln a}$ takes less than the fraction $f$ of $g$ off the normal force."""
    lift = top.eps * s * nutation.frequency_squared
    return jnp.log(fraction * top.g) - safe_log(lift, -2 * POLE) - log_amplitude


def chart_condition(
    top: TippeTop,
    x,
    J,
    log_amplitude,
    nutation: Nutation,
    *,
    hand_over: bool = False,
    margin: float = HAND_OVER_MARGIN,
    sin_theta=None,
    contact_margin: float | None = None,
) -> Array:
    r"""`Conditions.chart` at $x = \cos\theta$ (see `validity`; with `hand_over`, the level's
    options of `GyroscopicLevel`)."""
    h = top.R - top.eps * x
    lever = top.R * x - top.eps
    weight = top.m * top.g * top.eps
    scale = J**2 + 4 * top.A * h * weight * jnp.abs(lever)
    balance = (J**2 + 4 * top.A * h * weight * lever) / scale - BALANCE_MARGIN
    decaying = -nutation.damping / jnp.sqrt(nutation.frequency_squared)
    small = jnp.log(NUTATION_MAX) - log_amplitude
    projectable = jnp.log(NUTATION_LAUNCH_MAX) - log_amplitude
    if hand_over:
        # hand over to the full model as soon as the slow manifold repels: the full model then
        # grows its own nutation (and finds its own contact loss) from the slow state
        chart = jnp.minimum(jnp.minimum(balance, decaying - margin), projectable)
        if contact_margin is not None:
            proximity = contact_proximity(top, sin_theta, log_amplitude, nutation, contact_margin)
            chart = jnp.minimum(chart, proximity)
        return chart
    return jnp.minimum(jnp.minimum(balance, jnp.maximum(small, decaying)), projectable)


def validity(top: TippeTop, theta, J, log_amplitude) -> Array:
    r"""`Conditions.chart` of the level: $\min(\Delta_{\rm rel} - $ `BALANCE_MARGIN`$,
    \max(\ln(a_{\max}/a), -\sigma/\nu), \ln(a_{\rm launch}/a))$, with $\ln a$ = `log_amplitude`.

    Positive where (G2) has a real root with margin and the nutation is small or decaying; the
    level stops where it falls through zero ("Where the level ends",
    `docs/derivations/gyroscopic-averaging.md`).
    """
    theta = jnp.asarray(theta, dtype=jnp.result_type(theta, top.m))
    x, s = jnp.cos(theta), jnp.sin(theta)
    nutation = nutation_at(top, x, s, J, slow_manifold_at(top, x, s, J))
    return chart_condition(top, x, J, log_amplitude, nutation)


def entry_margin(
    top: TippeTop, theta, J, log_amplitude, *, nutation_max, decay_min, balance_min, contact_max
) -> Array:
    r"""How far inside the level's chart the slow state at `theta` (Jellet `J`) with a
    nutation of amplitude $e^{\ln a}$ (`log_amplitude`) is, with margins:
    $\min(\Delta_{\rm rel} -$ `BALANCE_MARGIN` $-$ `balance_min`, $-\sigma/\nu -$
    `decay_min`, $\ln$ `nutation_max` $- \ln a$, $\ln$(`contact_max` $g) -
    \ln(\epsilon\sin\theta\,a\nu^2))$ (see `contact_margin` of `GyroscopicLevel`). Positive:
    the level may take over a run of the full model there (`outcome_map(model="auto")`,
    `tippejax/_maps/stages.py`). The margins above those at which the level hands over
    (`BALANCE_MARGIN`, `HAND_OVER_MARGIN`) keep a run from handing back and forth."""
    theta = jnp.asarray(theta, dtype=jnp.result_type(theta, top.m))
    x, s = jnp.cos(theta), jnp.sin(theta)
    sm = slow_manifold_at(top, x, s, J)
    nutation = nutation_at(top, x, s, J, sm)
    h = top.R - top.eps * x
    lever = top.R * x - top.eps
    weight = top.m * top.g * top.eps
    scale = J**2 + 4 * top.A * h * weight * jnp.abs(lever)
    balance = (J**2 + 4 * top.A * h * weight * lever) / scale - BALANCE_MARGIN
    frequency = safe_sqrt(nutation.frequency_squared)
    decaying = -nutation.damping / jnp.where(frequency > 0, frequency, 1.0)
    small = jnp.log(nutation_max) - log_amplitude
    margin = jnp.minimum(jnp.minimum(balance - balance_min, decaying - decay_min), small)
    margin = jnp.minimum(margin, contact_proximity(top, s, log_amplitude, nutation, contact_max))
    return jnp.where(jnp.isfinite(margin), margin, -1.0)
