r"""The stem level: a top with a stem on two compliant contacts (ball and stem tip), with translation.

State $(x, y, \dot x, \dot y, z_O, \dot z_O, a, \omega)$ and the body vector as in the full
level. Each sphere $i$ (the ball: radius $R$, centre $O + \epsilon a$; the stem's tip: $r_2$,
$O + a_2 a$) pushes on the top at its lowest point $Q_i$, $\rho_i = \vec{OQ_i} = d_i a - r_i e_Z$,
with the Hunt-Crossley normal force of `tj.Stem` and the top's friction law at its slip
$s_i = [v_O + \omega\times\rho_i]_{XY}$ and drilling rate $\omega_Z$:

$$m\dot v_O = \sum_i R_{n,i}(e_Z + f_i) - m g e_Z,\qquad
I\dot\omega = \sum_i\big[\rho_i\times R_{n,i}(e_Z + f_i) + R_{n,i} m_i e_Z\big]
- (C - A)(\omega\cdot a)\,\omega\times a,\qquad \dot a = \omega\times a.$$

The energy with the elastic energy $\sum_i \tfrac25 k_i\delta_i^{5/2}$ never increases
(`contact_energy`). The full level of a top with a stem hands over to this level just before the
stem touches (`FullLevel`, `HAND_OVER_DEFLECTIONS`); it is reached only so, never asked for by
name.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._friction.base import AbstractFriction
from .._state import State
from .._stem import hertz_stiffness
from .._top import TippeTop
from ._rigid_body import e_z, inverse_inertia, rigid_body_dynamics
from ._spin_frame import body_of, spin_frame_rates
from .base import AbstractLevel, Conditions

HAND_OVER_DEFLECTIONS = 20.0
r"""The full level of a top with a stem hands over to the stem level when the stem's gap above
the table falls to this many static deflections of the ball under the top's weight,
$(m g/k_R)^{2/3}$ with $k_R = \tfrac43 E^*\sqrt R$ (5 um for Leine & Glocker's top): the
compliant contacts then meet the stem's impact from its first contact on, and the ball's
contact, rigid until there, is the same to its deflection."""

GAP_ROUNDING = 64.0
r"""The watch's floor of the gap conditions, in ulp of the ball's radius (`condition_floors`):
above the rounding of $z_O + a_2 a_Z - r_2$ and $z_O + \epsilon a_Z - R$, far below any gap
the contacts resolve."""


def _spheres(top: TippeTop):
    """(radius, offset along the axis, Hertz stiffness) of the ball and of the stem's tip."""
    stem = top.stem
    return (
        (top.R, top.eps, hertz_stiffness(stem, top.R)),
        (stem.radius, stem.offset, hertz_stiffness(stem, stem.radius)),
    )


def static_deflection(top: TippeTop):
    r"""$(m g/k_R)^{2/3}$: the ball's compliant contact pressed in by the top's weight (m)."""
    return (top.m * top.g / hertz_stiffness(top.stem, top.R)) ** (2.0 / 3.0)


def stem_gap(top: TippeTop, axis, height):
    r"""The stem tip's height above the table, $z_O + a_2 a_Z - r_2$ (m)."""
    return height + top.stem.offset * axis[..., 2] - top.stem.radius


def rigid_height(top: TippeTop, axis, omega):
    r"""$z_O = R - \epsilon a_Z$ and $\dot z_O = -\epsilon(\omega\times a)_Z$ of the ball's rigid
    contact (the full level)."""
    axis_dot_z = omega[..., 0] * axis[..., 1] - omega[..., 1] * axis[..., 0]
    return top.R - top.eps * axis[..., 2], -top.eps * axis_dot_z


class Contact(eqx.Module):
    """One sphere's contact with the table at one state."""

    depth: Float[Array, ""]  # penetration delta (m; < 0: clear of the table)
    normal_force: Float[Array, ""]  # R_n (N), >= 0
    force: Float[Array, "3"]  # R_n (e_Z + f) (N)
    torque: Float[Array, "3"]  # about the centre of mass, drilling included (N m)
    slip: Float[Array, "2"]  # slip velocity of the lowest point (m/s)
    power: Float[Array, ""]  # friction power F . s + M w_Z (W), <= 0


def sphere_contact(
    top: TippeTop, radius, offset, stiffness, height, height_rate, axis, omega, velocity
) -> Contact:
    r"""The Hunt-Crossley contact of the sphere of `radius` centred at $O + $ `offset` $a$, for
    one state: $\delta = r - z_O - d\,a_Z$, $R_n = \max(0, k\delta^{3/2}(1 + \tfrac32 c
    \dot\delta))$ where $\delta > 0$, and the friction law at the lowest point (`tj.Stem`)."""
    axis_dot = jnp.cross(omega, axis)
    depth = radius - height - offset * axis[2]
    depth_rate = -(height_rate + offset * axis_dot[2])
    pressed = jnp.maximum(depth, 0.0)
    normal = stiffness * pressed**1.5 * (1.0 + 1.5 * top.stem.contact_damping * depth_rate)
    normal = jnp.maximum(normal, 0.0)
    rho = offset * axis - radius * e_z(axis.dtype)
    slip = velocity + jnp.cross(omega, rho)[:2]
    friction, drilling = top.friction.force_and_torque(slip, omega[2])
    force = normal * jnp.concatenate([friction, jnp.ones_like(drilling)[None]])
    torque = jnp.cross(rho, force)
    power = normal * jnp.dot(friction, slip)
    if top.friction.has_drilling_torque:
        torque = torque.at[2].add(normal * drilling)
        power = power + normal * drilling * omega[2]
    return Contact(
        depth=depth, normal_force=normal, force=force, torque=torque, slip=slip, power=power
    )


def contacts(top: TippeTop, state: State) -> tuple[Contact, Contact]:
    """The ball's and the stem's contacts at one common `State` with a height (unbatched)."""
    return tuple(
        sphere_contact(
            top, r, d, k, state.height, state.height_rate, state.axis, state.omega, state.velocity
        )
        for r, d, k in _spheres(top)
    )


def elastic_energy(top: TippeTop, axis, height):
    r"""$\sum_i \tfrac25 k_i\max(\delta_i, 0)^{5/2}$ (J): the energy stored in the compliant
    contacts (zero at the ball's rigid contact, where its penetration is zero)."""
    total = jnp.zeros_like(height)
    for radius, offset, stiffness in _spheres(top):
        depth = jnp.maximum(radius - height - offset * axis[..., 2], 0.0)
        total = total + 0.4 * stiffness * depth**2.5
    return total


def stem_observables(top: TippeTop, states: State) -> dict:
    """`sol.normal_force` and `sol.slip_speed` of states of the stem level (any leading axes):
    the table's whole normal force (ball and stem together, N), and the slip speed of the
    contact that carries more of it (m/s)."""

    def one(state):
        ball, stem = contacts(top, state)
        slip = jnp.where(
            stem.normal_force > ball.normal_force,
            jnp.linalg.norm(stem.slip),
            jnp.linalg.norm(ball.slip),
        )
        return ball.normal_force + stem.normal_force, slip

    fn = one
    for _ in states.axis.shape[:-1]:
        fn = jax.vmap(fn)
    normal, slip = fn(states)
    return dict(normal_force=normal, slip_speed=slip)


class StemLevelState(eqx.Module):
    """State of the stem level: the full level's with the height of the centre of mass and its
    rate; `frame` and `angle` are None for a level without the body vector."""

    position: Float[Array, "2"]
    velocity: Float[Array, "2"]
    height: Float[Array, ""]
    height_rate: Float[Array, ""]
    axis: Float[Array, "3"]
    omega: Float[Array, "3"]
    frame: Float[Array, "3"] | None = None
    angle: Float[Array, ""] | None = None


class StemLevel(AbstractLevel):
    r"""A top with a stem on two compliant contacts (see the module docstring). Takes every
    friction law. No chart: it is the last level of its chain.

    Its own observed events (`observed_events`, in `Conditions.events`): `stem_touch`, the
    stem tip's gap above the table, $z_O + a_2 a_Z - r_2$ (`sol.t_stem`), and `ball_return`,
    the ball's, $z_O + \epsilon a_Z - R$, which falls through zero when the ball touches the
    table again after leaving it (`sol.t_ball_return`). Neither normal force going to zero is
    a failure: a flight, however short, is part of the compliant model's motion.
    """

    name = "stem"
    friction_model = "full"
    friction_laws = (AbstractFriction,)
    observed_events: ClassVar[tuple[str, ...]] = ("stem_touch", "ball_return")

    def from_state(self, top, state):
        # From the rigid ball contact (the hand-over): the ball pressed in by the depth that
        # carries the rigid R_n, at no rate of penetration, so that the motion goes on as it
        # was (the reference model's hand-over too).
        normal_force = rigid_body_dynamics(top, state.axis, state.omega, state.velocity)[0]
        stiffness = hertz_stiffness(top.stem, top.R)
        pressed = jnp.maximum(normal_force, 0.0) / stiffness
        safe = jnp.where(pressed > 0, pressed, 1.0)
        depth = jnp.where(pressed > 0, safe ** (2.0 / 3.0), 0.0)
        height, height_rate = rigid_height(top, state.axis, state.omega)
        frame = angle = None
        if self.body:
            frame, angle = state.body, jnp.zeros((), state.axis.dtype)
        return StemLevelState(
            position=state.position,
            velocity=state.velocity,
            height=height - depth,
            height_rate=height_rate,
            axis=state.axis,
            omega=state.omega,
            frame=frame,
            angle=angle,
        )

    def to_state(self, top, y):
        return State(
            position=y.position,
            velocity=y.velocity,
            axis=y.axis,
            omega=y.omega,
            body=body_of(y.axis, y.frame, y.angle),
            height=y.height,
            height_rate=y.height_rate,
        )

    def vector_field(self, t, y, top):
        del t
        state = State(
            position=y.position,
            velocity=y.velocity,
            axis=y.axis,
            omega=y.omega,
            body=y.axis,
            height=y.height,
            height_rate=y.height_rate,
        )
        ball, stem = contacts(top, state)
        force = ball.force + stem.force
        n = jnp.dot(y.omega, y.axis)
        axis_dot = jnp.cross(y.omega, y.axis)
        omega_dot = (
            inverse_inertia(top, y.axis, ball.torque + stem.torque)
            - (top.C - top.A) / top.A * n * axis_dot
        )
        frame_dot, angle_dot = spin_frame_rates(y.axis, y.omega, y.frame)
        return StemLevelState(
            position=y.velocity,
            velocity=force[:2] / top.m,
            height=y.height_rate,
            height_rate=force[2] / top.m - top.g,
            axis=axis_dot,
            omega=omega_dot,
            frame=frame_dot,
            angle=angle_dot,
        )

    def condition_floors(self, top):
        # The gaps are differences of lengths of the ball's size: rounding of a few ulp of R.
        floor = GAP_ROUNDING * jnp.finfo(jnp.result_type(top.R)).eps * top.R
        return dict(stem_touch=floor, ball_return=floor)

    def conditions(self, top, y):
        one = jnp.ones_like(y.height)
        ball_gap = y.height + top.eps * y.axis[2] - top.R
        return Conditions(
            contact=one,
            singular=one,
            upright=y.axis[2] * one,
            chart=one,
            events=dict(stem_touch=stem_gap(top, y.axis, y.height), ball_return=ball_gap),
        )
