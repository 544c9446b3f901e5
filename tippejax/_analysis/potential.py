"""The effective potential $W$ and its derivatives (Sec. 4); its terms are the Routhian
reduction's (`tippejax._models.reduction`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._models.reduction import (
    RouthianTerms as RouthianTerms,
    effective_potential as effective_potential,
    inertia_denominator,
    routhian_terms as routhian_terms,
)
from .._top import TippeTop


def _scalar_derivative(fn, theta, order):
    for _ in range(order):
        fn = jax.grad(fn)
    return jnp.vectorize(fn)(theta)


def effective_potential_derivative(
    top: TippeTop, theta: ArrayLike, J: ArrayLike, *, order: int = 1
) -> Float[Array, "..."]:
    r"""$\partial^k W/\partial\theta^k$ by automatic differentiation (`order` = k = 1 or 2)."""
    theta = jnp.asarray(theta, dtype=jnp.result_type(theta, top.m))
    return _scalar_derivative(lambda th: effective_potential(top, th, J), theta, order)


def effective_potential_d2_closed_form(
    top: TippeTop, theta: ArrayLike, J: ArrayLike
) -> Float[Array, "..."]:
    r"""$\partial^2W/\partial\theta^2$ in closed form (eq. stabilityba), for comparison with autodiff.

    $$W'' = m g\epsilon\cos\theta - \frac{J^2R^2C}{D^2}\Big(-(A/C-1)\sin^2\theta
    + \frac{\mathcal B}{C}\cos\theta - 4\frac{\mathcal B^2}{C^2}
    \frac{\sin^2\theta}{(A/C)\sin^2\theta + (\cos\theta-\epsilon/R)^2}\Big),$$
    $\mathcal B = (A - C)\cos\theta + C\epsilon/R$. Valid for every $\theta$, not only at critical points.
    """
    theta = jnp.asarray(theta, dtype=jnp.result_type(theta, top.m))
    s, c = jnp.sin(theta), jnp.cos(theta)
    a_c, e = top.A / top.C, top.eps / top.R
    b_c = (a_c - 1.0) * c + e  # B / C
    d = inertia_denominator(top, theta)
    bracket = -(a_c - 1.0) * s**2 + b_c * c - 4 * b_c**2 * s**2 / (a_c * s**2 + (c - e) ** 2)
    return top.m * top.g * top.eps * c - J**2 * top.R**2 * top.C / d**2 * bracket
