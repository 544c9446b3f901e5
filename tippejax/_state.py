r"""State of the top in the global vector form, and conversions to and from Euler angles.

Conventions (paper, Sec. 2, and ERRATA.md): inertial frame with $Z$ up, ZXZ Euler angles
$(\varphi, \theta, \psi)$; symmetry axis $a = (\sin\theta\sin\varphi, -\sin\theta\cos\varphi,
\cos\theta)$, pointing from the centre of mass $O$ to the centre of the sphere; line of nodes
$N = (\cos\varphi, \sin\varphi, 0)$; $\omega = \dot\varphi e_Z + \dot\theta N + \dot\psi a$;
spin $n = \omega\cdot a = \dot\psi + \dot\varphi\cos\theta$ (eq. omega).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._top import TippeTop


class State(eqx.Module):
    r"""State of the top in a form that is regular at $\theta = 0, \pi$.

    **Fields:**

    - `position`: horizontal position $(x, y)$ of the centre of mass (m). Its height is fixed
      by contact, $h = R - \epsilon\, a_Z$.
    - `velocity`: horizontal velocity $(\dot x, \dot y)$ of the centre of mass (m/s).
    - `axis`: unit symmetry axis $a$ (from the centre of mass to the centre of the sphere).
    - `omega`: angular velocity $\omega$ in the inertial frame (rad/s).
    - `body`: a unit vector fixed in the body and perpendicular to `axis`. It does not enter
      the dynamics; it only serves to read off the Euler angle $\psi$.

    Leading batch dimensions are allowed on every field.
    """

    position: Float[Array, "*batch 2"]
    velocity: Float[Array, "*batch 2"]
    axis: Float[Array, "*batch 3"]
    omega: Float[Array, "*batch 3"]
    body: Float[Array, "*batch 3"]


def _frame(theta, phi):
    """Axis a, line of nodes N and M = a x N... (right-handed (N, M, a)) for Euler angles."""
    st, ct = jnp.sin(theta), jnp.cos(theta)
    sp, cp = jnp.sin(phi), jnp.cos(phi)
    axis = jnp.stack([st * sp, -st * cp, ct], axis=-1)
    nodes = jnp.stack([cp, sp, jnp.zeros_like(phi)], axis=-1)
    m_vec = jnp.stack([-sp * ct, cp * ct, st], axis=-1)
    return axis, nodes, m_vec


def state_from_euler(
    theta: ArrayLike,
    phi: ArrayLike,
    psi: ArrayLike,
    theta_dot: ArrayLike,
    phi_dot: ArrayLike,
    psi_dot: ArrayLike,
    *,
    position: ArrayLike = (0.0, 0.0),
    velocity: ArrayLike = (0.0, 0.0),
) -> State:
    r"""The vector state for given ZXZ Euler angles and rates.

    $a = (\sin\theta\sin\varphi, -\sin\theta\cos\varphi, \cos\theta)$,
    $\omega = \dot\varphi e_Z + \dot\theta N + \dot\psi a$ and
    body $= \cos\psi\, N + \sin\psi\, M$ with $M = a \times N$.
    """
    theta, phi, psi, theta_dot, phi_dot, psi_dot = jnp.broadcast_arrays(
        *[jnp.asarray(x, dtype=jnp.result_type(x, float)) for x in
          (theta, phi, psi, theta_dot, phi_dot, psi_dot)]
    )
    axis, nodes, m_vec = _frame(theta, phi)
    e_z = jnp.zeros_like(axis).at[..., 2].set(1.0)
    omega = (
        phi_dot[..., None] * e_z + theta_dot[..., None] * nodes + psi_dot[..., None] * axis
    )
    body = jnp.cos(psi)[..., None] * nodes + jnp.sin(psi)[..., None] * m_vec
    batch = theta.shape
    position = jnp.broadcast_to(jnp.asarray(position, dtype=axis.dtype), batch + (2,))
    velocity = jnp.broadcast_to(jnp.asarray(velocity, dtype=axis.dtype), batch + (2,))
    return State(position=position, velocity=velocity, axis=axis, omega=omega, body=body)


def euler_angles(y: State) -> tuple[Array, Array, Array]:
    r"""ZXZ Euler angles $(\theta, \varphi, \psi)$ of a state, each in $(-\pi, \pi]$ ($\theta$ in $[0, \pi]$).

    $\varphi$ and $\psi$ are undefined at the poles $\sin\theta = 0$ (only $\varphi \pm \psi$ is);
    there they are returned by the `atan2` convention. Use `jnp.unwrap` on time series.
    """
    a = y.axis
    horizontal = jnp.sqrt(a[..., 0] ** 2 + a[..., 1] ** 2)
    theta = jnp.arctan2(horizontal, a[..., 2])
    phi = jnp.arctan2(a[..., 0], -a[..., 1])
    _, nodes, m_vec = _frame(theta, phi)
    psi = jnp.arctan2(jnp.sum(y.body * m_vec, -1), jnp.sum(y.body * nodes, -1))
    return theta, phi, psi


def spin(y: State) -> Array:
    r"""Spin $n = \omega\cdot a = \dot\psi + \dot\varphi\cos\theta$ (eq. omega)."""
    return jnp.sum(y.omega * y.axis, -1)


def euler_rates(y: State) -> tuple[Array, Array, Array]:
    r"""Euler rates $(\dot\theta, \dot\varphi, \dot\psi)$ of a state.

    $\dot\theta = \omega\cdot N$, $\dot\varphi = \omega\cdot M/\sin\theta$,
    $\dot\psi = n - \dot\varphi\cos\theta$. $\dot\varphi$ and $\dot\psi$ are singular at the poles.
    """
    theta, phi, _ = euler_angles(y)
    _, nodes, m_vec = _frame(theta, phi)
    theta_dot = jnp.sum(y.omega * nodes, -1)
    phi_dot = jnp.sum(y.omega * m_vec, -1) / jnp.sin(theta)
    psi_dot = spin(y) - phi_dot * jnp.cos(theta)
    return theta_dot, phi_dot, psi_dot


def initial_state(
    top: TippeTop,
    theta: ArrayLike,
    spin: ArrayLike,
    *,
    theta_dot: ArrayLike = 0.0,
    phi_dot: ArrayLike = 0.0,
    phi: ArrayLike = 0.0,
    psi: ArrayLike = 0.0,
    vx: ArrayLike = 0.0,
    vy: ArrayLike = 0.0,
) -> State:
    r"""The state of a top launched at tilt `theta` with spin `spin` $= n$ about its axis.

    The centre of mass starts at $x = y = 0$ with horizontal velocity $(v_x, v_y)$.
    $\dot\psi = n - \dot\varphi\cos\theta$. Broadcasts over arrays of arguments.

    **Arguments:**

    - `top`: the `TippeTop` (used for its dtype and to check the arguments).
    - `theta`: angle between the vertical and the symmetry axis (rad), in $[0, \pi]$.
    - `spin`: spin $n$ about the symmetry axis (rad/s).
    - `theta_dot`, `phi_dot`, `phi`, `psi`: the other Euler angles and rates (default 0).
    - `vx`, `vy`: horizontal velocity of the centre of mass (m/s, default 0).

    **Returns:** a `State`.
    """
    dtype = jnp.result_type(top.m)
    args = [jnp.asarray(x, dtype=dtype) for x in (theta, spin, theta_dot, phi_dot, phi, psi, vx, vy)]
    names = ("theta", "spin", "theta_dot", "phi_dot", "phi", "psi", "vx", "vy")
    checked = []
    for name, value in zip(names, args):
        value = eqx.error_if(value, ~jnp.isfinite(value), f"initial_state: {name} must be finite (got NaN or inf).")
        checked.append(value)
    theta, spin_, theta_dot, phi_dot, phi, psi, vx, vy = checked
    theta = eqx.error_if(
        theta, (theta < 0) | (theta > jnp.pi), "initial_state: theta must lie in [0, pi]."
    )
    psi_dot = spin_ - phi_dot * jnp.cos(theta)
    velocity = jnp.stack(jnp.broadcast_arrays(vx, vy), axis=-1)
    y = state_from_euler(theta, phi, psi, theta_dot, phi_dot, psi_dot)
    velocity = jnp.broadcast_to(velocity, y.axis.shape[:-1] + (2,))
    return eqx.tree_at(lambda s: s.velocity, y, velocity)
