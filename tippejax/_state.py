r"""State of the top in the global vector form, and conversions to and from Euler angles.

Conventions (paper, Sec. 2, and `docs/notes.md`): inertial frame with $Z$ up, ZXZ Euler angles
$(\varphi, \theta, \psi)$; symmetry axis $a = (\sin\theta\sin\varphi, -\sin\theta\cos\varphi,
\cos\theta)$, pointing from the centre of mass $O$ to the centre of the sphere; line of nodes
$N = (\cos\varphi, \sin\varphi, 0)$; $\omega = \dot\varphi e_Z + \dot\theta N + \dot\psi a$;
spin $n = \omega\cdot a = \dot\psi + \dot\varphi\cos\theta$ (eq. omega).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._errors import error_if
from ._plausibility import warn_if_implausible_spin
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
    - `height`, `height_rate`: the height $z_O$ of the centre of mass (m) and its rate (m/s)
      for a top with a stem (`tj.Stem`), whose contacts with the table are compliant from just
      before the stem touches (the stem level): there the height is a state of its own. Before
      that they are the ball's rigid contact's, $R - \epsilon a_Z$ and its rate. None (the
      default) for a top without a stem.

    Leading batch dimensions are allowed on every field.
    """

    position: Float[Array, "*batch 2"]
    velocity: Float[Array, "*batch 2"]
    axis: Float[Array, "*batch 3"]
    omega: Float[Array, "*batch 3"]
    body: Float[Array, "*batch 3"]
    height: Float[Array, "*batch"] | None = None
    height_rate: Float[Array, "*batch"] | None = None


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
        *[
            jnp.asarray(x, dtype=jnp.result_type(x, float))
            for x in (theta, phi, psi, theta_dot, phi_dot, psi_dot)
        ]
    )
    axis, nodes, m_vec = _frame(theta, phi)
    e_z = jnp.zeros_like(axis).at[..., 2].set(1.0)
    omega = phi_dot[..., None] * e_z + theta_dot[..., None] * nodes + psi_dot[..., None] * axis
    body = jnp.cos(psi)[..., None] * nodes + jnp.sin(psi)[..., None] * m_vec
    batch = theta.shape
    position = jnp.broadcast_to(jnp.asarray(position, dtype=axis.dtype), batch + (2,))
    velocity = jnp.broadcast_to(jnp.asarray(velocity, dtype=axis.dtype), batch + (2,))
    return State(position=position, velocity=velocity, axis=axis, omega=omega, body=body)


def _pole_tolerance(dtype):
    """Horizontal length of the axis below which it is taken to be vertical (rounding level)."""
    return 8 * jnp.finfo(dtype).eps


def _tilt_and_nodes(y: State):
    r"""$\theta$, $\varphi$ and whether the axis is at a pole, with $\varphi$ read from the motion there.

    Away from the poles $\varphi = \operatorname{atan2}(a_X, -a_Y)$. At a pole
    ($|a_{XY}| \le 8\,\varepsilon_{\rm mach}$) the axis has no horizontal direction, and
    $\varphi$ is the direction in which it is leaving the pole: the line of nodes $N$ is taken
    along the horizontal part of $\dot a = \omega \times a$, so that $\varphi$ at the pole is
    the limit of $\varphi(t)$ along the motion. A state that does not tilt ($\omega \parallel a$)
    gets $\varphi = 0$. Nothing depends on the sign of a zero.
    """
    a = y.axis
    dtype = jnp.result_type(a)
    tol = _pole_tolerance(dtype)
    h2 = a[..., 0] ** 2 + a[..., 1] ** 2
    at_pole = h2 <= tol**2
    horizontal = jnp.where(at_pole, 0.0, jnp.sqrt(jnp.where(at_pole, 1.0, h2)))
    theta = jnp.arctan2(horizontal, a[..., 2])
    phi_away = jnp.arctan2(a[..., 0], -a[..., 1])
    # Horizontal part of the axis's velocity, omega x a.
    w = y.omega
    tilt_x = w[..., 1] * a[..., 2] - w[..., 2] * a[..., 1]
    tilt_y = w[..., 2] * a[..., 0] - w[..., 0] * a[..., 2]
    tilting = tilt_x**2 + tilt_y**2 > 0
    # (x == 0 -> +0.0: atan2 must not see the sign of a zero.)
    tilt_x = jnp.where(tilting & (tilt_x != 0), tilt_x, 0.0)
    tilt_y = jnp.where(tilting, jnp.where(tilt_y != 0, -tilt_y, 0.0), 1.0)
    phi_pole = jnp.where(tilting, jnp.arctan2(tilt_x, tilt_y), 0.0)
    phi = jnp.where(at_pole, phi_pole, phi_away)
    return theta, phi, at_pole


def euler_angles(y: State) -> tuple[Array, Array, Array]:
    r"""ZXZ Euler angles $(\theta, \varphi, \psi)$ of a state, each in $(-\pi, \pi]$ ($\theta$ in $[0, \pi]$).

    At the poles $\sin\theta = 0$ only $\varphi \pm \psi$ is defined by the axis; there
    $\varphi$ is the direction in which the axis leaves the pole ($\omega \times a$), which is
    the limit of $\varphi(t)$ along the motion (0 for a top that does not tilt), and $\psi$
    follows from the body vector. Use `jnp.unwrap` on time series.
    """
    theta, phi, _ = _tilt_and_nodes(y)
    _, nodes, m_vec = _frame(theta, phi)
    psi = jnp.arctan2(jnp.sum(y.body * m_vec, -1), jnp.sum(y.body * nodes, -1))
    return theta, phi, psi


def spin(y: State) -> Array:
    r"""Spin $n = \omega\cdot a = \dot\psi + \dot\varphi\cos\theta$ (eq. omega)."""
    return jnp.sum(y.omega * y.axis, -1)


def euler_rates(y: State) -> tuple[Array, Array, Array]:
    r"""Euler rates $(\dot\theta, \dot\varphi, \dot\psi)$ of a state.

    $\dot\theta = \omega\cdot N$, $\dot\varphi = \omega\cdot M/\sin\theta$,
    $\dot\psi = n - \dot\varphi\cos\theta$, with $N$ the line of nodes and $M = a\times N$.

    At a pole the rates are read from the motion, never from the sign of a zero: $N$ points
    where the axis is going (see `euler_angles`), so $\dot\theta = \omega\cdot N =
    \pm|\omega_\perp|$, the speed of the axis ($\omega_\perp$ the part of $\omega$
    perpendicular to $a$), positive at $\theta = 0$ (where $\theta$ can only grow) and
    negative at $\theta = \pi$. The split of the rotation about the vertical between
    $\dot\varphi$ and $\dot\psi$ is not fixed by the state there (it depends on the axis's
    acceleration); the pole convention is $\dot\varphi = 0$, $\dot\psi = n$, so that
    $\omega = \dot\varphi e_Z + \dot\theta N + \dot\psi a$ still holds.
    """
    theta, phi, at_pole = _tilt_and_nodes(y)
    _, nodes, m_vec = _frame(theta, phi)
    theta_dot = jnp.sum(y.omega * nodes, -1)
    sin_theta = jnp.where(at_pole, 1.0, jnp.sin(theta))
    phi_dot = jnp.where(at_pole, 0.0, jnp.sum(y.omega * m_vec, -1) / sin_theta)
    psi_dot = spin(y) - phi_dot * jnp.cos(theta)
    return theta_dot, phi_dot, psi_dot


def check_theta0(name: str, theta) -> None:
    """A concrete launch tilt must lie in [0, pi] rad; say so, with the degrees hint."""
    theta = np.asarray(theta, dtype=float)
    if np.any(theta < 0) or np.any(theta > np.pi):
        bad = theta[(theta < 0) | (theta > np.pi)].ravel()[0]
        hint = (
            f" It looks like degrees: pass np.deg2rad({bad:g}) = {np.deg2rad(bad):.6g} rad."
            if np.pi < bad <= 180
            else ""
        )
        raise ValueError(
            f"{name} must lie in [0, pi] rad (the tilt of the axis from the vertical, in "
            f"radians); got {bad:g}.{hint}"
        )


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
    raw = (theta, spin, theta_dot, phi_dot, phi, psi, vx, vy)
    names = ("theta", "spin", "theta_dot", "phi_dot", "phi", "psi", "vx", "vy")
    concrete = not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(raw))
    if concrete:
        # Concrete values: say what is wrong in Python, before any jit.
        for name, value in zip(names, raw):
            try:
                value = np.asarray(value, dtype=float)
            except (TypeError, ValueError):
                raise ValueError(
                    f"initial_state: {name} must be a number or an array of numbers, got "
                    f"{type(value).__name__}."
                ) from None
            if not np.all(np.isfinite(value)):
                raise ValueError(f"initial_state: {name} must be finite (got NaN or inf).")
        check_theta0("initial_state: theta", theta)
        if not any(isinstance(v, jax.core.Tracer) for v in (top.m, top.R, top.C, top.g)):
            warn_if_implausible_spin(top.m, top.R, top.C, top.g, spin)
    args = [jnp.asarray(x, dtype=dtype) for x in raw]
    if not concrete:  # (concrete values were checked above; no runtime check to compile)
        args = [
            error_if(v, ~jnp.isfinite(v), f"initial_state: {name} must be finite (got NaN or inf).")
            for name, v in zip(names, args)
        ]
        args[0] = error_if(
            args[0], (args[0] < 0) | (args[0] > jnp.pi), "initial_state: theta must lie in [0, pi]."
        )
    theta, spin_, theta_dot, phi_dot, phi, psi, vx, vy = args
    psi_dot = spin_ - phi_dot * jnp.cos(theta)
    velocity = jnp.stack(jnp.broadcast_arrays(vx, vy), axis=-1)
    y = state_from_euler(theta, phi, psi, theta_dot, phi_dot, psi_dot)
    velocity = jnp.broadcast_to(velocity, y.axis.shape[:-1] + (2,))
    return eqx.tree_at(lambda s: s.velocity, y, velocity)
