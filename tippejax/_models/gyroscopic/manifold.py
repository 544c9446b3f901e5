r"""The slow manifold: gyroscopic balance (G1), its roots (G2) and the slow flow (G3) on them."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array

from ..._top import TippeTop
from .coordinate import safe_sqrt, sign_of


def balance_discriminant(top: TippeTop, x, J) -> Array:
    r"""$\Delta = J^2 + 4Ah\,mg\epsilon(Rx - \epsilon)$ of (G2), $x = \cos\theta$,
    $h = R - \epsilon x$; $\Delta < 0$: no gyroscopic balance at this tilt.

    (G2) is the balance (G1), $A\Omega^2\cos\theta - Cn\Omega - mg\epsilon = 0$, with $n$
    eliminated through the Jellet (eq. jello): $Ah\,\Omega^2 - J\Omega - mg\epsilon(Rx -
    \epsilon) = 0$. Derivation: `docs/derivations/gyroscopic-averaging.md`.
    """
    h = top.R - top.eps * x
    return J**2 + 4 * top.A * h * top.m * top.g * top.eps * (top.R * x - top.eps)


def precession_rate(top: TippeTop, x, J, *, branch: int = 1) -> Array:
    r"""A root $\Omega$ of (G2) at $x = \cos\theta$.

    `branch=1` (the slow manifold): $(J + \mathrm{sgn}(J)\sqrt\Delta)/(2Ah)$;
    `branch=-1` (the classical slow precession): $-2mg\epsilon(Rx - \epsilon)/(J + \mathrm{sgn}(J)
    \sqrt\Delta)$, the same root written without cancellation. $\sqrt\Delta$ is taken as 0 where
    $\Delta < 0$.
    """
    h = top.R - top.eps * x
    root = sign_of(J) * safe_sqrt(balance_discriminant(top, x, J))
    if branch == 1:
        return (J + root) / (2 * top.A * h)
    if branch == -1:
        return -2 * top.m * top.g * top.eps * (top.R * x - top.eps) / (J + root)
    raise ValueError(f"branch must be 1 or -1, got {branch!r}.")


class SlowManifold(eqx.Module):
    r"""The slow manifold at one $\theta$ for one $J$.

    - `precession`: $\Omega = \dot\varphi$, a root of (G2).
    - `spin`: $n = (A\Omega^2\cos\theta - mg\epsilon)/(C\Omega)$.
    - `slip`: $p = Rn - \Omega(R\cos\theta - \epsilon)$ (slip across $\Pi$ is $p\sin\theta$).
    - `rate`: $\dot\theta/\sin\theta$ of (G3) (regular at the poles; $= \dot u$).
    - `theta_dot`: $\dot\theta$ of (G3).
    - `discriminant`: $\Delta$ of (G2).
    """

    precession: Array
    spin: Array
    slip: Array
    rate: Array
    theta_dot: Array
    discriminant: Array


def slow_manifold_at(top: TippeTop, x, s, J, branch: int = 1) -> SlowManifold:
    r"""`slow_manifold` at $x = \cos\theta$, $s = \sin\theta$ (the form the level evaluates)."""
    m, g, eps, R, A, C = top.m, top.g, top.eps, top.R, top.A, top.C
    weight = m * g * eps  # m g eps
    h = R - eps * x
    lever = R * x - eps
    discriminant = J**2 + 4 * A * h * weight * lever
    root = sign_of(J) * safe_sqrt(discriminant)
    if branch == 1:
        omega = (J + root) / (2 * A * h)
    elif branch == -1:
        omega = -2 * weight * lever / (J + root)
    else:
        raise ValueError(f"branch must be 1 or -1, got {branch!r}.")
    spin = (A * omega**2 * x - weight) / (C * omega)
    slip = R * spin - omega * lever
    f_omega = 2 * A * h * omega - J
    denominator = A * omega * f_omega + eps * (A * omega**2 + m * g * R) * (
        A * x + weight / omega**2
    )
    rate = top.mu * m * g * R * slip * f_omega / denominator
    return SlowManifold(
        precession=omega,
        spin=spin,
        slip=slip,
        rate=rate,
        theta_dot=rate * s,
        discriminant=discriminant,
    )


def slow_manifold(top: TippeTop, theta, J, *, branch: int = 1) -> SlowManifold:
    r"""Precession, spin, slip and the slow flow (G3) at $\theta$ on one root of (G2):

    $$\dot\theta = \frac{\mu m g R\,\sin\theta\; p\, F_\Omega}
    {A\Omega F_\Omega + \epsilon(A\Omega^2 + m g R)\,(A\cos\theta + m g\epsilon/\Omega^2)},
    \qquad F_\Omega = 2Ah\Omega - J.$$

    `branch=1` is the level's slow manifold; `branch=-1` (the other root) is singular at
    $\cos\theta = \epsilon/R$ and serves the launch projection and the analysis. Derivation:
    `docs/derivations/gyroscopic-averaging.md`.
    """
    theta = jnp.asarray(theta, dtype=jnp.result_type(theta, top.m))
    return slow_manifold_at(top, jnp.cos(theta), jnp.sin(theta), J, branch)


def gyroscopic_theta_dot(top: TippeTop, theta, J) -> Array:
    r"""$\dot\theta$ of the slow flow (G3) on the level's root of (G2)."""
    return slow_manifold(top, theta, J).theta_dot


def limit_theta_dot(top: TippeTop, theta) -> Array:
    r"""The $J \to \infty$ limit of (G3): $(\mu mgR^2/A)(1 - \tfrac\epsilon R\cos\theta)
    \sin\theta\,((\tfrac AC - 1)\cos\theta + \tfrac\epsilon R)$; its sign is that of eq. Exist."""
    x, s = jnp.cos(theta), jnp.sin(theta)
    a, e = top.A / top.C, top.eps / top.R
    return top.mu * top.m * top.g * top.R**2 / top.A * (1 - e * x) * s * ((a - 1) * x + e)
