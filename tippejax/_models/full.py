r"""The full model: rolling and sliding with translation (the paper's eq. thesystem), global form.

State $(x, y, \dot x, \dot y, a, \omega)$ and, for $\psi$, the body vector in the form of
`SpinFrame` (a slowly turning frame vector and the spin angle, see below). Regular at
$\theta = 0, \pi$.

$$\dot{\mathbf r} = v,\quad m\dot v = R_n f,\quad \dot a = \omega\times a,
\quad I\dot\omega = q\times F + R_n m\,e_Z - (C-A)(\omega\cdot a)\,\omega\times a,$$
with the friction law's force $f$ (horizontal; $f = -\mu v_Q$ for the paper's law) and
drilling torque $m$ per unit normal force at $(v_Q, \omega\cdot e_Z)$, $F = R_n(e_Z + f)$,
$R_n$ from the contact constraint (see `rigid_body_dynamics`) and
$v_Q = v_O + \omega\times q$ including the horizontal velocity. Takes every friction law.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._friction.base import AbstractFriction
from .._state import State
from .._top import TippeTop
from ._rigid_body import rigid_body_algebra, rigid_body_dynamics
from ._spin_frame import body_of as body_of, spin_frame_rates as spin_frame_rates
from .base import AbstractLevel, Conditions
from .stem import (
    HAND_OVER_DEFLECTIONS,
    StemLevel,
    rigid_height,
    static_deflection,
    stem_gap,
)


def translation_rate(top: TippeTop, normal_force, omega, v_q):
    r"""$\dot v = R_n f(v_Q, \omega_n)/m$: the horizontal acceleration of the centre of mass."""
    friction, _ = top.friction.force_and_torque(v_q[:2], omega[..., 2])
    return normal_force * friction / top.m


def _single(top: TippeTop, y: State) -> State:
    normal_force, omega_dot, v_q, _ = rigid_body_dynamics(top, y.axis, y.omega, y.velocity)
    velocity_dot = translation_rate(top, normal_force, y.omega, v_q)
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


def vector_conditions(
    top: TippeTop, axis, omega, velocity, *, by_components: bool = False
) -> Conditions:
    """Event conditions of the vector form (full and SO(3) levels); `by_components`: see
    `AbstractLevel.by_components`."""
    dynamics, _ = rigid_body_algebra(by_components)
    normal_force, _, _, denominator = dynamics(top, axis, omega, velocity)
    one = jnp.ones_like(denominator)
    return Conditions(
        contact=normal_force * denominator,
        singular=denominator,
        upright=axis[2] * one,
        chart=one,
    )


def pole_linearisation(top: TippeTop, J, *, north: bool = True) -> Array:
    r"""The full model linearised at the vertical state of Jellet `J`, in complex horizontal
    components: $\dot z = M z$ with $z = (\dot x + i\dot y,\; a_X + ia_Y,\;
    \omega_X + i\omega_Y)$.

    The vertical state spins at $n = J/(C(R - \epsilon))$ at $\theta = 0$ (`north`), $n =
    -J/(C(R + \epsilon))$ at $\theta = \pi$ (eq. jello). It is invariant under turns about
    the vertical, so the real $6\times6$ linearisation in the horizontal components is
    $\begin{pmatrix}P & -Q\\ Q & P\end{pmatrix}$ (x components first) and $M = P + iQ$
    ($3\times3$, complex). Its three eigenvalues are the three modes about the vertical state: the
    slow manifold's (the two roots of (G2) of the gyroscopic level: the fast precession) and, where
    the SO(3) model has the other root's mode alone, two: one that decays several times faster
    than the SO(3) model's, and one that barely decays -- the centre of mass rolls round with
    the contact point (standard top at 200 rad/s: $-0.06 \pm 0.53i$/s against the SO(3)
    model's $-5.1$/s). Needs concrete or traced values alike; the eigen-decomposition is the
    caller's (`numpy.linalg.eig`).
    """
    dtype = jnp.result_type(top.m, J)
    J = jnp.asarray(J, dtype)
    sign = 1.0 if north else -1.0
    omega_z = J / (top.C * (top.R - top.eps)) if north else J / (top.C * (top.R + top.eps))

    def field(z):  # z = (vx, ax, wx, vy, ay, wy)
        velocity = jnp.stack([z[0], z[3]])
        axis = jnp.stack([z[1], z[4], jnp.asarray(sign, dtype)])
        omega = jnp.stack([z[2], z[5], omega_z])
        normal_force, omega_dot, v_q, _ = rigid_body_dynamics(top, axis, omega, velocity)
        velocity_dot = translation_rate(top, normal_force, omega, v_q)
        axis_dot = jnp.cross(omega, axis)
        return jnp.stack(
            [velocity_dot[0], axis_dot[0], omega_dot[0], velocity_dot[1], axis_dot[1], omega_dot[1]]
        )

    jac = jax.jacfwd(field)(jnp.zeros(6, dtype))
    return jax.lax.complex(jac[:3, :3], jac[3:, :3])


class FullLevelState(eqx.Module):
    """State of the full level: the common state with the body vector as (frame, angle), both
    None for a level without it (`body=False`)."""

    position: Float[Array, "2"]
    velocity: Float[Array, "2"]
    axis: Float[Array, "3"]
    omega: Float[Array, "3"]
    frame: Float[Array, "3"] | None = None
    angle: Float[Array, ""] | None = None


class FullLevel(AbstractLevel):
    r"""The full model with translation; the common `State`, with the body vector carried as a
    frame vector and a spin angle (`spin_frame_rates`), so that it does not set the steps.
    Takes every friction law.

    **Static option:** `stem` (default False; `for_top` sets it for a top with a `tj.Stem`).
    The level then has a chart: the ball's rigid contact, until the stem's gap above the table,
    $z_O + a_2 a_Z - r_2$ with $z_O = R - \epsilon a_Z$, falls to `HAND_OVER_DEFLECTIONS`
    static deflections of the ball, just before the stem touches, or until the ball's $R_n$
    falls to 0 (a lift-off before the touch: no contact loss then). There the run goes on in the
    stem level (`StemLevel`: two compliant contacts), and the chain's common states carry the
    height of the centre of mass (`State.height`, here the rigid contact's)."""

    name = "full"
    friction_model = "full"
    friction_laws = (AbstractFriction,)
    stem: bool = eqx.field(static=True, default=False, kw_only=True)

    # -- a top with a stem (see the class docstring); nothing changes without one ----------

    @property
    def has_chart(self) -> bool:  # (a class attribute of the other levels)
        return self.stem

    def for_top(self, top):
        return dataclasses.replace(self, stem=top.stem is not None)

    def common_state(self, top, state):
        if not self.stem:
            return state
        height, height_rate = rigid_height(top, state.axis, state.omega)
        return dataclasses.replace(state, height=height, height_rate=height_rate)

    def _stem_chart(self, top, axis):
        """Positive while the stem is clear of the hand-over gap (`HAND_OVER_DEFLECTIONS`)."""
        gap = stem_gap(top, axis, rigid_height(top, axis, jnp.zeros_like(axis))[0])
        return gap - HAND_OVER_DEFLECTIONS * static_deflection(top)

    def in_chart(self, top, state):
        if not self.stem:
            return jnp.array(True)
        return self._stem_chart(top, state.axis) > 0

    def fallback(self):
        return StemLevel(body=self.body) if self.stem else None

    def from_state(self, top, state):
        if not self.body:
            return FullLevelState(
                position=state.position, velocity=state.velocity, axis=state.axis, omega=state.omega
            )
        return FullLevelState(
            position=state.position,
            velocity=state.velocity,
            axis=state.axis,
            omega=state.omega,
            frame=state.body,
            angle=jnp.zeros((), state.axis.dtype),
        )

    def to_state(self, top, y):
        state = State(
            position=y.position,
            velocity=y.velocity,
            axis=y.axis,
            omega=y.omega,
            body=body_of(y.axis, y.frame, y.angle),
        )
        return self.common_state(top, state)

    def vector_field(self, t, y, top):
        dynamics, cross_ = rigid_body_algebra(self.by_components)
        normal_force, omega_dot, v_q, _ = dynamics(top, y.axis, y.omega, y.velocity)
        frame_dot, angle_dot = spin_frame_rates(y.axis, y.omega, y.frame)
        return FullLevelState(
            position=y.velocity,
            velocity=translation_rate(top, normal_force, y.omega, v_q),
            axis=cross_(y.omega, y.axis),
            omega=omega_dot,
            frame=frame_dot,
            angle=angle_dot,
        )

    def conditions(self, top, y):
        conditions = vector_conditions(
            top, y.axis, y.omega, y.velocity, by_components=self.by_components
        )
        if self.stem:
            # The chart also ends where the ball would leave the table (R_n falling through
            # 0): the stem level's compliant contacts carry the flight, so the run hands over
            # there instead of stopping at a contact loss (the reference model does the same).
            lift = conditions.contact / (top.m * top.g)
            gap = self._stem_chart(top, y.axis) / top.R
            conditions = dataclasses.replace(
                conditions, chart=jnp.minimum(gap, lift), contact=jnp.ones_like(lift)
            )
        return conditions
