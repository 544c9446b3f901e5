r"""The Routhian of the reduced system and the effective potential $W$ (Sec. 2.2 and 4).

After the change of variables $\bar\varphi = \epsilon\varphi + R\psi$, $c = R\varphi - \epsilon\psi$
the coordinate $c$ is cyclic with momentum $J/(\epsilon^2+R^2)$, and the Routhian is
$\mathcal R = T_2 + T_1 - W$ with

$$T_2 = \tfrac12 M_\theta\dot\theta^2 + \tfrac12 M_{\bar\varphi}\dot{\bar\varphi}^2,\quad
M_\theta = m\epsilon^2\sin^2\theta + A,\quad M_{\bar\varphi} = \frac{AC\sin^2\theta}{D},$$
$$T_1 = \beta(\theta)\dot{\bar\varphi},\quad
\beta = \frac{J}{S}\,\frac{R\epsilon A\sin^2\theta + C(R+\epsilon\cos\theta)(R\cos\theta-\epsilon)}{D},$$
$$W = \frac{J^2}{2D} - m g\epsilon\cos\theta,$$

where $S = \epsilon^2 + R^2$ and $D = R^2A\sin^2\theta + C(R\cos\theta - \epsilon)^2$.

Note on the factor 2 (`docs/notes.md`, "The factor 2 in the linearised equations"): the paper writes $T_2 = T_{\theta\theta}\dot\theta^2 + \dots$
with $T_{\theta\theta} = M_\theta/2$, but its linearised equations need the full inertia
coefficients $M_\theta$, $M_{\bar\varphi}$. Here the `inertia_*` fields are the full coefficients.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._top import TippeTop


def inertia_denominator(top: TippeTop, theta):
    r"""$D = R^2A\sin^2\theta + C(R\cos\theta - \epsilon)^2$, the denominator of the reduced
    system's terms (Sec. 2.2)."""
    s, c = jnp.sin(theta), jnp.cos(theta)
    return top.R**2 * top.A * s**2 + top.C * (top.R * c - top.eps) ** 2


def effective_potential(top: TippeTop, theta: ArrayLike, J: ArrayLike) -> Float[Array, "..."]:
    r"""Effective potential $W(\theta; J) = \frac{J^2}{2D(\theta)} - m g\epsilon\cos\theta$ (Sec. 2.2).

    $D = R^2A\sin^2\theta + C(R\cos\theta - \epsilon)^2$. Defined up to the constant $m g R$.
    Its critical points are the steady states; $W'' > 0$ is their linear stability.
    """
    theta = jnp.asarray(theta, dtype=jnp.result_type(theta, top.m))
    return 0.5 * J**2 / inertia_denominator(top, theta) - top.m * top.g * top.eps * jnp.cos(theta)


class RouthianTerms(eqx.Module):
    r"""Coefficients of the Routhian $\mathcal R = T_2 + T_1 - W$ at one angle $\theta$.

    - `inertia_theta`: $M_\theta = m\epsilon^2\sin^2\theta + A$ (twice the paper's $T_{\theta\theta}$).
    - `inertia_phibar`: $M_{\bar\varphi} = AC\sin^2\theta/D$ (twice the paper's $T_{\bar\varphi\bar\varphi}$).
    - `gyroscopic`: $\beta = \partial T_1/\partial\dot{\bar\varphi}$.
    - `potential`: $W$.
    """

    inertia_theta: Array
    inertia_phibar: Array
    gyroscopic: Array
    potential: Array


def routhian_terms(top: TippeTop, theta: ArrayLike, J: ArrayLike) -> RouthianTerms:
    r"""The coefficients $M_\theta$, $M_{\bar\varphi}$, $\beta$ and $W$ of the Routhian at $\theta$."""
    theta = jnp.asarray(theta, dtype=jnp.result_type(theta, top.m))
    s, c = jnp.sin(theta), jnp.cos(theta)
    d = inertia_denominator(top, theta)
    big_s = top.eps**2 + top.R**2
    numerator = top.R * top.eps * top.A * s**2 + top.C * (top.R + top.eps * c) * (
        top.R * c - top.eps
    )
    return RouthianTerms(
        inertia_theta=top.m * top.eps**2 * s**2 + top.A,
        inertia_phibar=top.A * top.C * s**2 / d,
        gyroscopic=J / big_s * numerator / d,
        potential=effective_potential(top, theta, J),
    )
