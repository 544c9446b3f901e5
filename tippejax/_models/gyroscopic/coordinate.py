r"""The gyroscopic level's coordinate $u = \ln\tan(\theta/2)$, and elementary functions safe at 0."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array

POLE = 750.0
r"""$|u| \geq$ `POLE` ($u = \ln\tan(\theta/2)$) is a pole: $e^{-|u|}$ is then exactly zero (in
float32 and float64), $\theta$ is exactly $0$ or $\pi$, and $u$ does not move."""


def sign_of(J) -> Array:
    """+1 where `J >= 0`, else -1, in the dtype of `J`."""
    return jnp.where(J >= 0, 1.0, -1.0).astype(jnp.result_type(J))


def safe_sqrt(x) -> Array:
    """sqrt(x) for x > 0, else 0, with a finite derivative everywhere."""
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def safe_log(x, floor) -> Array:
    """log(x) for x > 0, else `floor`, with a finite derivative everywhere."""
    positive = x > 0
    return jnp.where(positive, jnp.log(jnp.where(positive, x, 1.0)), floor)


def cos_sin(u) -> tuple[Array, Array]:
    r"""$(\cos\theta, \sin\theta) = (-\tanh u, 1/\cosh u)$ for $u = \ln\tan(\theta/2)$; exact
    (and with finite derivatives) at the poles $|u| \geq$ `POLE`."""
    e = jnp.exp(-jnp.abs(u))
    return -jnp.tanh(u), 2 * e / (1 + e * e)


def theta_of(u) -> Array:
    r"""$\theta = 2\arctan e^u$ of $u = \ln\tan(\theta/2)$."""
    x, s = cos_sin(u)
    return jnp.arctan2(s, x)


def log_tan_half(theta) -> Array:
    r"""$u = \ln\tan(\theta/2)$, clipped to $[-$`POLE`$, $`POLE`$]$ (the poles)."""
    theta = jnp.asarray(theta, dtype=jnp.result_type(theta, float))
    x, s = jnp.cos(theta), jnp.abs(jnp.sin(theta))
    north = x >= 0
    # tan(theta/2) = s/(1 + x) = (1 - x)/s: the form without cancellation on each side
    tangent = jnp.where(north, s / (1 + x), s / (1 - x))
    u = safe_log(tangent, -POLE)
    return jnp.clip(jnp.where(north, u, -u), -POLE, POLE)
