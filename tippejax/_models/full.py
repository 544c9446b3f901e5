r"""The full model: rolling and sliding with translation (the paper's eq. thesystem), global form.

State $(x, y, \dot x, \dot y, a, \omega)$ (+ a body vector for $\psi$). Regular at $\theta = 0, \pi$.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._state import State
from .._top import TippeTop
from ._rigid_body import rigid_body_dynamics


def _single(top: TippeTop, y: State) -> State:
    normal_force, omega_dot, v_q, _ = rigid_body_dynamics(top, y.axis, y.omega, y.velocity)
    velocity_dot = -top.mu * normal_force * v_q[:2] / top.m
    return State(
        position=y.velocity,
        velocity=velocity_dot,
        axis=jnp.cross(y.omega, y.axis),
        omega=omega_dot,
        body=jnp.cross(y.omega, y.body),
    )


def full_vector_field(t, y: State, top: TippeTop) -> State:
    r"""Time derivative of the state under the full model (diffrax signature `f(t, y, args)`).

    $$\dot{\mathbf r} = v,\quad m\dot v = -\mu R_n v_{Q,\text{hor}},\quad \dot a = \omega\times a,
    \quad I\dot\omega = q\times F - (C-A)(\omega\cdot a)\,\omega\times a,$$
    with $R_n$ from the contact constraint (see `rigid_body_dynamics`) and
    $v_Q = v_O + \omega\times q$ including the horizontal velocity.
    Batched states are handled with `jax.vmap` over leading axes of `y` (with `top` shared).
    """
    del t
    batch = y.axis.shape[:-1]
    fn = _single
    for _ in batch:
        fn = jax.vmap(fn, in_axes=(None, 0))
    return fn(top, y)
