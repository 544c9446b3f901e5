r"""Mechanics shared by the full and SO(3) models: contact kinematics and the normal force.

The top touches the table at $Q$, with $q = \vec{OQ} = \epsilon a - R e_Z$. The centre of mass is
at height $h = R - \epsilon a_Z$ (so $h = R - \epsilon\cos\theta$), the angular momentum about it is
$L = I\omega = A\omega + (C - A)(\omega\cdot a)a$, and the contact force is
$F = R_n(e_Z + f)$ with the friction law's force per unit normal force $f(v_Q, \omega_n)$
($f = -\mu v_Q$ for the paper's law, eq. viscfric), plus its drilling torque $R_n m\,e_Z$ about
$Q$ ($\omega_n = \omega\cdot e_Z$). The equations of motion are

$$m\ddot{\mathbf r}_O = F - m g e_Z,\qquad \dot L = q\times F + R_n m\,e_Z,\qquad
\dot a = \omega\times a.$$

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


def friction_per_normal_force(top: TippeTop, axis, omega, velocity):
    r"""The friction law's force per unit normal force $f$ (horizontal, 2-vector) and drilling
    torque per unit normal force $m$ (m) at this state: `top.friction` at the slip velocity
    $v_Q$ and the drilling rate $\omega_n = \omega\cdot e_Z$."""
    v_q = contact_velocity(top, axis, omega, velocity)
    return top.friction.force_and_torque(v_q[:2], omega[2])


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
    $\tau_1 = q\times(e_Z + f) + m\,e_Z$ (torque per unit normal force, with the friction
    law's $f(v_Q, \omega_n)$ and $m(v_Q, \omega_n)$, which do not depend on $R_n$), and
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
    friction, drilling = top.friction.force_and_torque(v_q[:2], omega[2])
    force_per_rn = jnp.concatenate([friction, jnp.ones_like(drilling)[None]])
    torque_per_rn = jnp.cross(q, force_per_rn)
    if top.friction.has_drilling_torque:
        torque_per_rn = torque_per_rn.at[2].add(drilling)
    omega_dot_0 = -(top.C - top.A) / top.A * n * axis_dot
    omega_dot_1 = inverse_inertia(top, axis, torque_per_rn)
    h_ddot_0 = -top.eps * (jnp.cross(omega_dot_0, axis)[2] + jnp.cross(omega, axis_dot)[2])
    h_ddot_1 = -top.eps * jnp.cross(omega_dot_1, axis)[2]
    denominator = 1.0 / top.m - h_ddot_1
    normal_force = (top.g + h_ddot_0) / denominator
    omega_dot = omega_dot_0 + normal_force * omega_dot_1
    return normal_force, omega_dot, v_q, denominator


def cross(u, v):
    r"""$u\times v$ of 3-vectors (last axis), written out by components.

    The same numbers as `jnp.cross`, which XLA builds from slices and a concatenation; in a
    batch whose members run as one state (`simulate_batch(..., steps="shared")`) the written-out
    form fuses with the arithmetic around it (see `rigid_body_dynamics_by_components`)."""
    u0, u1, u2 = u[..., 0], u[..., 1], u[..., 2]
    v0, v1, v2 = v[..., 0], v[..., 1], v[..., 2]
    return jnp.stack([u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0], axis=-1)


def rigid_body_dynamics_by_components(top: TippeTop, axis, omega, velocity):
    r"""`rigid_body_dynamics` (same arguments, same returns, same equations) with the algebra
    written out by components (each a scalar, or an array over leading axes),
    with $q = \epsilon a - R e_Z$ and $v_Q = v_O + \omega\times q$ (horizontal; see
    `contact_vector`, `contact_velocity`), and only the returned vectors stacked. In vector form
    (`jnp.cross`, `jnp.dot`, a concatenation for $v_O$) XLA keeps the intermediate 3-vectors as
    concatenations, which do not vectorise when the members of a batch are the fast axis
    (`simulate_batch(..., steps="shared")`): there this form is the faster. Elsewhere the vector
    form stays (`AbstractLevel.by_components`): it is the cheaper for one top, a vmapped batch
    and under `jax.jacfwd`. `tests/test_models.py` checks that both forms give the same
    numbers.
    """
    a0, a1, a2 = axis[..., 0], axis[..., 1], axis[..., 2]
    w0, w1, w2 = omega[..., 0], omega[..., 1], omega[..., 2]
    eps, A, C = top.eps, top.A, top.C
    n = w0 * a0 + w1 * a1 + w2 * a2  # omega . a
    d0, d1, d2 = w1 * a2 - w2 * a1, w2 * a0 - w0 * a2, w0 * a1 - w1 * a0  # a_dot = omega x a
    q0, q1, q2 = eps * a0, eps * a1, eps * a2 - top.R  # q
    # v_Q = v_O + omega x q, horizontal (v_O's vertical part cancels omega x q's)
    vx = velocity[..., 0] + (w1 * q2 - w2 * q1)
    vy = velocity[..., 1] + (w2 * q0 - w0 * q2)
    fx, fy, drilling = top.friction.components(vx, vy, w2)  # f; e_Z + f has Z component 1
    t0, t1, t2 = q1 - q2 * fy, q2 * fx - q0, q0 * fy - q1 * fx  # q x (e_Z + f)
    if top.friction.has_drilling_torque:
        t2 = t2 + drilling  # tau_1 = q x (e_Z + f) + m e_Z
    k0 = -(C - A) / A * n
    o00, o01, o02 = k0 * d0, k0 * d1, k0 * d2  # omega_dot_0
    k1 = (1.0 / C - 1.0 / A) * (a0 * t0 + a1 * t1 + a2 * t2)
    o10, o11, o12 = t0 / A + k1 * a0, t1 / A + k1 * a1, t2 / A + k1 * a2  # I^-1 tau_1
    # h_ddot = -eps (omega_dot x a + omega x a_dot)_Z
    h_ddot_0 = -eps * ((o00 * a1 - o01 * a0) + (w0 * d1 - w1 * d0))
    h_ddot_1 = -eps * (o10 * a1 - o11 * a0)
    denominator = 1.0 / top.m - h_ddot_1
    normal_force = (top.g + h_ddot_0) / denominator
    omega_dot = jnp.stack(
        [o00 + normal_force * o10, o01 + normal_force * o11, o02 + normal_force * o12], axis=-1
    )
    slip_velocity = jnp.stack([vx, vy, jnp.zeros_like(vx)], axis=-1)
    return normal_force, omega_dot, slip_velocity, denominator


def rigid_body_algebra(by_components: bool):
    """`(rigid_body_dynamics, jnp.cross)`, or their forms written out by components
    (`rigid_body_dynamics_by_components`, `cross`; see `AbstractLevel.by_components`)."""
    if by_components:
        return rigid_body_dynamics_by_components, cross
    return rigid_body_dynamics, jnp.cross
