r"""The body vector carried as a slowly turning frame vector and a spin angle (full, SO(3) and
stem levels)."""

from __future__ import annotations

import jax.numpy as jnp


def spin_frame_rates(axis, omega, frame):
    r"""$(\dot c, \dot\sigma)$ of the body vector $b = \cos\sigma\, c + \sin\sigma\, a\times c$.

    The body vector obeys $\dot b = \omega\times b$; it turns about the axis at the spin
    rate $n = \omega\cdot a$ (150 rad/s for a fast top), much faster than anything else in
    the state, and an error-controlled solver would take its steps for it. Split
    $\omega = n a + \omega_\perp$: the frame vector $c \perp a$ follows the slow part,
    $\dot c = \omega_\perp\times c$, and the angle takes the fast one, $\dot\sigma = n$, a
    smooth quadrature. Then $b$ above obeys $\dot b = \omega\times b$: with $\dot a =
    \omega\times a = \omega_\perp\times a$, the $\sin\sigma$ terms agree by the Jacobi identity
    $\omega_\perp\times(a\times c) = a\times(\omega_\perp\times c) + \dot a\times c$, and
    $c\cdot a$ stays 0 (checked against $\dot b = \omega\times b$ in `tests/test_engine.py`).
    """
    if frame is None:  # a level without the body vector
        return None, None
    n = jnp.dot(omega, axis)
    return jnp.cross(omega - n * axis, frame), n


def body_of(axis, frame, angle):
    r"""$b = \cos\sigma\, c + \sin\sigma\, a\times c$ (see `spin_frame_rates`); nan for a level
    without the body vector (`frame` None)."""
    if frame is None:
        return jnp.full_like(axis, jnp.nan)
    return jnp.cos(angle) * frame + jnp.sin(angle) * jnp.cross(axis, frame)
