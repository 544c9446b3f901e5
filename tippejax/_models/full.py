r"""The full model: rolling and sliding with translation (the paper's eq. thesystem), global form.

State $(x, y, \dot x, \dot y, a, \omega)$ (+ a body vector for $\psi$): the common `State`
itself. Regular at $\theta = 0, \pi$.

$$\dot{\mathbf r} = v,\quad m\dot v = -\mu R_n v_{Q,\text{hor}},\quad \dot a = \omega\times a,
\quad I\dot\omega = q\times F - (C-A)(\omega\cdot a)\,\omega\times a,$$
with $R_n$ from the contact constraint (see `rigid_body_dynamics`) and
$v_Q = v_O + \omega\times q$ including the horizontal velocity.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._state import State
from .._top import TippeTop
from ._rigid_body import rigid_body_dynamics
from .base import AbstractLevel, Conditions


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

    See the module docstring for the equations. Batched states are handled with `jax.vmap`
    over leading axes of `y` (with `top` shared).
    """
    del t
    fn = _single
    for _ in y.axis.shape[:-1]:
        fn = jax.vmap(fn, in_axes=(None, 0))
    return fn(top, y)


def vector_conditions(top: TippeTop, axis, omega, velocity) -> Conditions:
    """Event conditions of the vector form (full and SO(3) levels)."""
    normal_force, _, _, denominator = rigid_body_dynamics(top, axis, omega, velocity)
    one = jnp.ones_like(denominator)
    return Conditions(
        contact=normal_force * denominator,
        singular=denominator,
        upright=axis[2] * one,
        chart=one,
    )


class FullLevel(AbstractLevel):
    """The full model with translation; its state is the common `State`."""

    name = "full"
    friction_model = "full"

    def from_state(self, top, state):
        return state

    def to_state(self, top, y):
        return y

    def vector_field(self, t, y, top):
        return _single(top, y)

    def conditions(self, top, y):
        return vector_conditions(top, y.axis, y.omega, y.velocity)
