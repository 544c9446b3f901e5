r"""The Routhian reduced system in $(\theta, \bar\varphi)$ with the Jellet $J$ as parameter.

Equations (reducedeqs, reducedeqs2) with $\mathcal R = T_2 + T_1 - W$ (see `routhian_terms`):

$$M_\theta\ddot\theta = -\tfrac12 M_\theta'\dot\theta^2 + \tfrac12 M_{\bar\varphi}'\dot{\bar\varphi}^2
 + \beta'\dot{\bar\varphi} - W' - \mu R'_n h^2\dot\theta,$$
$$M_{\bar\varphi}\ddot{\bar\varphi} = -M_{\bar\varphi}'\dot\theta\dot{\bar\varphi} - \beta'\dot\theta
 - \mu R'_n\sin^2\theta\,\dot{\bar\varphi},$$

and the cyclic coordinate is reconstructed from eq. routh1,
$\dot c = \big(J S - (R A\epsilon\sin^2\theta + C(R\cos\theta-\epsilon)(R+\epsilon\cos\theta))
\dot{\bar\varphi}\big)/D$. $R'_n$ is eq. reactie with $\dot x = \dot y = 0$.

The chart is singular where $\sin\theta = 0$ ($M_{\bar\varphi} \propto \sin^2\theta$): a simulation
must leave it before reaching a pole.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._invariants import jellet
from .._state import State, euler_angles, euler_rates, state_from_euler
from .._top import TippeTop
from .base import AbstractLevel, Conditions
from .reduction import routhian_terms
from .so3 import SO3Level

CHART_SIN_MIN = 0.05
"""A Routhian run leaves its chart (for the SO(3) level) when $|\\sin\\theta|$ falls below this."""


class RouthianState(eqx.Module):
    r"""State of the reduced system: $(\theta, \bar\varphi, c, \dot\theta, \dot{\bar\varphi})$.

    $\bar\varphi = \epsilon\varphi + R\psi$, $c = R\varphi - \epsilon\psi$. The Jellet $J$ is a
    parameter of the flow, not part of the state.
    """

    theta: Float[Array, "*batch"]
    phibar: Float[Array, "*batch"]
    c: Float[Array, "*batch"]
    theta_dot: Float[Array, "*batch"]
    phibar_dot: Float[Array, "*batch"]


def routhian_rates(top: TippeTop, theta, phibar_dot, J):
    r"""$(\dot c, \dot\varphi, \dot\psi, n)$ from $\theta$, $\dot{\bar\varphi}$ and $J$ (eq. routh1).

    $\dot\varphi = (\epsilon\dot{\bar\varphi} + R\dot c)/S$, $\dot\psi = (R\dot{\bar\varphi} -
    \epsilon\dot c)/S$, $n = \dot\psi + \dot\varphi\cos\theta$.
    """
    s, c = jnp.sin(theta), jnp.cos(theta)
    big_s = top.eps**2 + top.R**2
    d = top.R**2 * top.A * s**2 + top.C * (top.R * c - top.eps) ** 2
    coupling = top.R * top.A * top.eps * s**2 + top.C * (top.R * c - top.eps) * (
        top.R + top.eps * c
    )
    c_dot = (J * big_s - coupling * phibar_dot) / d
    phi_dot = (top.eps * phibar_dot + top.R * c_dot) / big_s
    psi_dot = (top.R * phibar_dot - top.eps * c_dot) / big_s
    return c_dot, phi_dot, psi_dot, psi_dot + phi_dot * c


def routhian_normal_force(top: TippeTop, theta, theta_dot, phi_dot, n):
    r"""$R'_n$: eq. reactie with $\dot x = \dot y = 0$,

    $$R'_n = \frac{g + \dot\theta^2 h'' + h'\dot\varphi\sin\theta(\dot\varphi\cos\theta - C n/A)}
    {1/m + h'(h' + \mu h^2\dot\theta)/A},$$
    $h = R - \epsilon\cos\theta$. **Returns:** `(normal_force, denominator)`.
    """
    s, c = jnp.sin(theta), jnp.cos(theta)
    h = top.R - top.eps * c
    h1, h2 = top.eps * s, top.eps * c
    numerator = top.g + theta_dot**2 * h2 + h1 * phi_dot * s * (phi_dot * c - top.C * n / top.A)
    denominator = 1.0 / top.m + h1 * (h1 + top.mu * h**2 * theta_dot) / top.A
    return numerator / denominator, denominator


def _single(top: TippeTop, y: RouthianState, J) -> RouthianState:
    def terms(theta):
        t = routhian_terms(top, theta, J)
        return t.inertia_theta, t.inertia_phibar, t.gyroscopic, t.potential

    (m_th, m_pb, beta, _), (dm_th, dm_pb, dbeta, dw) = jax.jvp(
        terms, (y.theta,), (jnp.ones_like(y.theta),)
    )
    c_dot, phi_dot, _, n = routhian_rates(top, y.theta, y.phibar_dot, J)
    normal_force, _ = routhian_normal_force(top, y.theta, y.theta_dot, phi_dot, n)
    h = top.R - top.eps * jnp.cos(y.theta)
    thd, pbd = y.theta_dot, y.phibar_dot
    theta_ddot = (
        -0.5 * dm_th * thd**2
        + 0.5 * dm_pb * pbd**2
        + dbeta * pbd
        - dw
        - top.mu * normal_force * h**2 * thd
    ) / m_th
    phibar_ddot = (
        -dm_pb * thd * pbd - dbeta * thd - top.mu * normal_force * jnp.sin(y.theta) ** 2 * pbd
    ) / m_pb
    return RouthianState(
        theta=thd, phibar=pbd, c=c_dot, theta_dot=theta_ddot, phibar_dot=phibar_ddot
    )


def routhian_vector_field(t, y: RouthianState, args) -> RouthianState:
    r"""Time derivative of the reduced state; `args = (top, J)` (diffrax signature).

    Singular at $\sin\theta = 0$. See the module docstring for the equations.
    """
    del t
    top, J = args
    fn = _single
    for _ in jnp.shape(y.theta):
        fn = jax.vmap(fn, in_axes=(None, 0, 0 if jnp.ndim(J) else None))
    return fn(top, y, J)


def routhian_from_state(top: TippeTop, y: State) -> tuple[RouthianState, Array]:
    r"""Reduced coordinates of a vector state and its Jellet $J$. Singular at the poles."""
    theta, phi, psi = euler_angles(y)
    theta_dot, phi_dot, psi_dot = euler_rates(y)
    r = RouthianState(
        theta=theta,
        phibar=top.eps * phi + top.R * psi,
        c=top.R * phi - top.eps * psi,
        theta_dot=theta_dot,
        phibar_dot=top.eps * phi_dot + top.R * psi_dot,
    )
    return r, jellet(top, y)


def state_from_routhian(top: TippeTop, r: RouthianState, J) -> State:
    r"""Vector state of a reduced state with Jellet $J$ (horizontal velocity zero).

    $\varphi = (\epsilon\bar\varphi + Rc)/S$, $\psi = (R\bar\varphi - \epsilon c)/S$,
    rates from eq. routh1.
    """
    big_s = top.eps**2 + top.R**2
    phi = (top.eps * r.phibar + top.R * r.c) / big_s
    psi = (top.R * r.phibar - top.eps * r.c) / big_s
    _, phi_dot, psi_dot, _ = routhian_rates(top, r.theta, r.phibar_dot, J)
    return state_from_euler(r.theta, phi, psi, r.theta_dot, phi_dot, psi_dot)


class RouthianLevelState(eqx.Module):
    r"""State of the Routhian level: the reduced state and the (constant) Jellet $J$."""

    reduced: RouthianState
    jellet: Float[Array, ""]


class RouthianLevel(AbstractLevel):
    r"""The Routhian reduced system in $(\theta, \bar\varphi)$ with $J$ fixed.

    The step size is controlled on $(\theta, \dot\theta, \dot{\bar\varphi})$ only: the cyclic
    angles $\bar\varphi$ and $c$ do not feed back into the motion (they only serve to report
    $\varphi, \psi$), so the solver need not resolve the phase of the spin. Near the poles
    ($|\sin\theta| <$ `CHART_SIN_MIN`) the chart ends and the run continues at the SO(3)
    level, which is the same physics in a form regular there.
    """

    name = "routhian"
    unmodelled = ("position", "velocity")
    friction_model = "so3"
    has_chart = True

    def from_state(self, top, state):
        reduced, J = routhian_from_state(top, state)
        return RouthianLevelState(reduced=reduced, jellet=J)

    def to_state(self, top, y):
        return state_from_routhian(top, y.reduced, y.jellet)

    def vector_field(self, t, y, top):
        return RouthianLevelState(
            reduced=_single(top, y.reduced, y.jellet), jellet=jnp.zeros_like(y.jellet)
        )

    def conditions(self, top, y):
        r = y.reduced
        _, phi_dot, _, n = routhian_rates(top, r.theta, r.phibar_dot, y.jellet)
        normal_force, denominator = routhian_normal_force(top, r.theta, r.theta_dot, phi_dot, n)
        return Conditions(
            contact=normal_force * denominator,
            singular=denominator,
            upright=jnp.cos(r.theta),
            chart=jnp.abs(jnp.sin(r.theta)) - CHART_SIN_MIN,
        )

    def in_chart(self, top, state):
        horizontal = jnp.sqrt(state.axis[0] ** 2 + state.axis[1] ** 2)
        return horizontal > CHART_SIN_MIN

    def fallback(self):
        return SO3Level(body=self.body)

    def error_norm(self, scaled_error):
        r = scaled_error.reduced
        dynamic = jnp.stack([r.theta, r.theta_dot, r.phibar_dot])
        return jnp.sqrt(jnp.mean(dynamic**2))
