r"""Mechanics shared by the full and SO(3) models: contact kinematics and the normal force.

The top touches the table at $Q$, with $q = \vec{OQ} = \epsilon a - R e_Z$. The centre of mass is
at height $h = R - \epsilon a_Z$ (so $h = R - \epsilon\cos\theta$), the angular momentum about it is
$L = I\omega = A\omega + (C - A)(\omega\cdot a)a$, and the contact force is
$F = R_n e_Z + R_f$ with $R_f = -\mu R_n v_Q$ (eq. viscfric). The equations of motion are

$$m\ddot{\mathbf r}_O = F - m g e_Z,\qquad \dot L = q\times F,\qquad \dot a = \omega\times a.$$

$R_n$ is not a state variable: it is fixed by the contact constraint, i.e. by the vertical Newton
equation $m\ddot h = R_n - m g$ solved together with the other equations. Since $\dot\omega$ is
affine in $R_n$, so is $\ddot h$, and the solve is a scalar division.
"""

from __future__ import annotations

import jax.numpy as jnp

from .._top import TippeTop


def e_z(dtype):
    return jnp.array([0.0, 0.0, 1.0], dtype=dtype)


def contact_vector(top: TippeTop, axis):
    r"""$q = \epsilon a - R e_Z$, from the centre of mass to the contact point."""
    return top.eps * axis - top.R * e_z(axis.dtype)


def inverse_inertia(top: TippeTop, axis, x):
    r"""$I^{-1}x = x/A + (1/C - 1/A)(a\cdot x)a$."""
    return x / top.A + (1.0 / top.C - 1.0 / top.A) * jnp.dot(axis, x) * axis


def centre_of_mass_velocity(top: TippeTop, axis, omega, velocity):
    r"""$v_O = (\dot x, \dot y, \dot h)$ with $\dot h = -\epsilon(\omega\times a)_Z$."""
    axis_dot = jnp.cross(omega, axis)
    return jnp.concatenate([velocity, (-top.eps * axis_dot[2])[None]])


def contact_velocity(top: TippeTop, axis, omega, velocity):
    r"""Slip velocity $v_Q = v_O + \omega\times q$ of the contact point (horizontal).

    Its vertical component vanishes identically; it is set to exactly zero.
    """
    v_o = centre_of_mass_velocity(top, axis, omega, velocity)
    v_q = v_o + jnp.cross(omega, contact_vector(top, axis))
    return v_q.at[2].set(0.0)


def rigid_body_dynamics(top: TippeTop, axis, omega, velocity):
    r"""Normal force, angular acceleration and slip velocity for a given horizontal velocity.

    `velocity` is the horizontal centre-of-mass velocity used in the friction law: the real one
    for the full model, zero for the SO(3) model.

    Writing $\dot\omega = \dot\omega_0 + R_n\, I^{-1}\tau_1$ with
    $\dot\omega_0 = -(C-A)/A\,(\omega\cdot a)(\omega\times a)$ (gyroscopic term) and
    $\tau_1 = q\times(e_Z - \mu v_Q)$ (torque per unit normal force), and
    $\ddot h = -\epsilon\ddot a_Z = \ddot h_0 + R_n \ddot h_1$, the vertical Newton equation gives

    $$R_n = \frac{g + \ddot h_0}{1/m - \ddot h_1}.$$

    The denominator $1/m - \ddot h_1$ is the one of eq. reactie; it can vanish (`docs/notes.md`, The R_n singularity),
    where the model with friction proportional to $R_n$ has no solution.

    **Returns:** `(normal_force, omega_dot, slip_velocity, denominator)`.
    """
    n = jnp.dot(omega, axis)
    axis_dot = jnp.cross(omega, axis)
    q = contact_vector(top, axis)
    v_q = contact_velocity(top, axis, omega, velocity)
    force_per_rn = e_z(axis.dtype) - top.mu * v_q
    torque_per_rn = jnp.cross(q, force_per_rn)
    omega_dot_0 = -(top.C - top.A) / top.A * n * axis_dot
    omega_dot_1 = inverse_inertia(top, axis, torque_per_rn)
    h_ddot_0 = -top.eps * (jnp.cross(omega_dot_0, axis)[2] + jnp.cross(omega, axis_dot)[2])
    h_ddot_1 = -top.eps * jnp.cross(omega_dot_1, axis)[2]
    denominator = 1.0 / top.m - h_ddot_1
    normal_force = (top.g + h_ddot_0) / denominator
    omega_dot = omega_dot_0 + normal_force * omega_dot_1
    return normal_force, omega_dot, v_q, denominator
