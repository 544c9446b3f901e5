r"""The SO(3) model: the paper's approximation with translation dropped in the friction law.

As in Sec. 2.2 (Routhian reduction), the horizontal velocity of the centre of mass is neglected in
the friction force and in $R_n$ ($R'_n$); the vertical motion of the centre of mass (the
$m\epsilon^2\sin^2\theta\,\dot\theta^2$ term of $L'$) is kept. In vector form this is the full model
with $v_O = (0, 0, \dot h)$: state $(a, \omega)$ (+ the body vector for $\psi$, carried as a frame
vector and a spin angle, `full.spin_frame_rates`), regular at the poles. For a friction force alone the Jellet $J$ is conserved exactly; the energy
$E' = T_{\rm rot} + \tfrac12 m\dot h^2 + m g h$ never increases:
$\dot E' = R_n(f\cdot v_Q + m\,\omega_n) \le 0$ ($-\mu R_n|v_Q|^2$ for the viscous law). Takes
every friction law; under a drilling torque $m$ the Jellet is not conserved,
$\dot J = R_n m(R - \epsilon\cos\theta)$.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._friction.base import AbstractFriction
from .._state import State
from .._top import TippeTop
from ._rigid_body import rigid_body_algebra, rigid_body_dynamics
from .base import AbstractLevel
from .full import body_of, spin_frame_rates, vector_conditions


def _single(top: TippeTop, y: State) -> State:
    zero = jnp.zeros_like(y.velocity)
    _, omega_dot, _, _ = rigid_body_dynamics(top, y.axis, y.omega, zero)
    return State(
        position=zero,
        velocity=zero,
        axis=jnp.cross(y.omega, y.axis),
        omega=omega_dot,
        body=jnp.cross(y.omega, y.body),
    )


def so3_vector_field(t, y: State, top: TippeTop) -> State:
    r"""Time derivative of a common `State` under the SO(3) model (diffrax signature).

    Same as `full_vector_field` with the horizontal velocity set to zero in
    $v_Q = v_O + \omega\times q$ and in $R'_n$; position and velocity are frozen.
    """
    del t
    fn = _single
    for _ in y.axis.shape[:-1]:
        fn = jax.vmap(fn, in_axes=(None, 0))
    return fn(top, y)


class RigidState(eqx.Module):
    r"""State of the SO(3) level: axis, angular velocity, and the body vector as a frame vector
    and a spin angle, $b = \cos\sigma\, c + \sin\sigma\, a\times c$ (no translation); `frame`
    and `angle` are None for a level without the body vector (`body=False`)."""

    axis: Float[Array, "3"]
    omega: Float[Array, "3"]
    frame: Float[Array, "3"] | None = None
    angle: Float[Array, ""] | None = None


class SO3Level(AbstractLevel):
    """The SO(3) model: rotation only (10 ODEs: axis, omega, and the body vector as a frame
    vector and a spin angle; 6 with `body=False`); position and velocity are reported as
    zero."""

    name = "so3"
    unmodelled = ("position", "velocity")
    friction_model = "so3"
    friction_laws = (AbstractFriction,)

    def from_state(self, top, state):
        if not self.body:
            return RigidState(axis=state.axis, omega=state.omega)
        return RigidState(
            axis=state.axis,
            omega=state.omega,
            frame=state.body,
            angle=jnp.zeros((), state.axis.dtype),
        )

    def to_state(self, top, y):
        zero = jnp.zeros(2, y.axis.dtype)
        return State(
            position=zero,
            velocity=zero,
            axis=y.axis,
            omega=y.omega,
            body=body_of(y.axis, y.frame, y.angle),
        )

    def vector_field(self, t, y, top):
        zero = jnp.zeros(2, y.axis.dtype)
        dynamics, cross_ = rigid_body_algebra(self.by_components)
        _, omega_dot, _, _ = dynamics(top, y.axis, y.omega, zero)
        frame_dot, angle_dot = spin_frame_rates(y.axis, y.omega, y.frame)
        return RigidState(
            axis=cross_(y.omega, y.axis),
            omega=omega_dot,
            frame=frame_dot,
            angle=angle_dot,
        )

    def conditions(self, top, y):
        return vector_conditions(
            top, y.axis, y.omega, jnp.zeros(2, y.axis.dtype), by_components=self.by_components
        )
