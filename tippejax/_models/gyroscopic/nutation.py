r"""The nutation about the slow manifold: its frequency $\nu$ and averaged growth rate $\sigma$."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array

from ..._top import TippeTop
from .manifold import SlowManifold, slow_manifold_at


class Nutation(eqx.Module):
    r"""The nutation about the slow manifold at one $\theta$: `frequency_squared` $\nu^2$ and
    `damping` $\sigma$ (see `nutation_frequency`, `nutation_damping`)."""

    frequency_squared: Array
    damping: Array


def nutation_at(top: TippeTop, x, s, J, sm: SlowManifold) -> Nutation:
    r"""$\nu^2$ and $\sigma$ at $x = \cos\theta$, $s = \sin\theta$, in closed form.

    The derivatives in $x$ (at fixed $\dot{\bar\varphi} = p$, and along the manifold) are
    written out; `tests/test_gyroscopic.py` checks them against autodiff of the definitions.
    """
    m, g, eps, R, A, C, mu = top.m, top.g, top.eps, top.R, top.A, top.C, top.mu
    weight = m * g * eps
    omega, n, p = sm.precession, sm.spin, sm.slip
    s2 = s * s
    big_s = eps**2 + R**2
    lever = R * x - eps
    h = R - eps * x
    # D, kappa (eq. routh1) and their x-derivatives
    d = R**2 * A * s2 + C * lever**2
    d_x = -2 * R**2 * A * x + 2 * C * R * lever
    kappa = R * A * eps * s2 + C * lever * (R + eps * x)
    kappa_x = -2 * R * A * eps * x + C * (R**2 - eps**2 + 2 * R * eps * x)
    # R'_n at rest as a function of (x, p) with phi_dot, n from eq. routh1:
    # R'_n = m N / Q, N = g + eps s^2 w (w x - C n/A), Q = 1 + m eps^2 s^2/A
    c_dot = R * omega - eps * (n - omega * x)  # the cyclic rate, c = R phi - eps psi
    gyro = omega * x - C * n / A
    q = 1 + m * eps**2 * s2 / A
    numerator = g + eps * s2 * omega * gyro
    rn = m * numerator / q  # = m g on the manifold
    w_p = (eps - R * kappa / d) / big_s
    n_p = (R + eps * kappa / d) / big_s + w_p * x
    rn_p = m * eps * s2 * (w_p * gyro + omega * (w_p * x - C * n_p / A)) / q
    c_x = -(kappa_x * p + c_dot * d_x) / d
    w_x = R * c_x / big_s
    n_x = -eps * c_x / big_s + w_x * x + omega
    numerator_x = eps * (
        -2 * x * omega * gyro + s2 * (w_x * gyro + omega * (w_x * x + omega - C * n_x / A))
    )
    q_x = -2 * x * m * eps**2 / A
    rn_x = m * (numerator_x * q - numerator * q_x) / q**2
    # M_phibar / sin^2 = A C / D, and B_p / sin(theta) = -(dM_phibar/dx p + dbeta/dx)
    inertia_phibar = A * C / d
    dm_x = A * C * (-2 * x * d - s2 * d_x) / d**2
    dbeta_x = J / big_s * (kappa_x * d - kappa * d_x) / d**2
    coupling = -(dm_x * p + dbeta_x)
    inertia = A + m * eps**2 * s2  # M_theta
    # nu^2 = P/(A M_theta), P = (C n - 2 A Omega x)^2 + A^2 Omega^2 sin^2, along the manifold
    omega_x = (weight * R + A * eps * omega**2) / (2 * A * h * omega - J)  # from (G2)
    n_x_manifold = A / C * (omega + x * omega_x) + weight * omega_x / (C * omega**2)
    lead = C * n - 2 * A * omega * x
    lead_x = C * n_x_manifold - 2 * A * (omega + x * omega_x)
    big_p = lead**2 + (A * omega) ** 2 * s2
    big_p_x = 2 * lead * lead_x + A**2 * (2 * omega * omega_x * s2 - 2 * x * omega**2)
    nu2 = big_p / (A * inertia)
    inertia_x = -2 * x * m * eps**2
    log_m_nu_x = 0.5 * (inertia_x / inertia + big_p_x / big_p)  # d ln(M_theta nu)/dx
    drive = (
        mu * (rn + p * rn_p) * coupling / inertia_phibar + mu * s2 * p * rn_x - 2 * mu * p * rn * x
    )  # alpha / sin(theta)
    friction = -(mu * rn * h**2 + coupling * drive / (inertia_phibar * nu2)) / (2 * inertia)
    adiabatic = 0.5 * sm.rate * s2 * log_m_nu_x  # -(1/2) d ln(M_theta nu)/dt
    return Nutation(frequency_squared=nu2, damping=friction + adiabatic)


def momentum_coupling(top: TippeTop, x, s, J, p) -> Array:
    r"""$K/\sin\theta$, $K = \partial_\theta(M_{\bar\varphi}p + \beta)$ at fixed $p$: the force
    $(K/M_{\bar\varphi})\,q$ with which the momentum $q$ drives the nutation (as in
    `nutation_at`)."""
    eps, R, A, C = top.eps, top.R, top.A, top.C
    big_s = eps**2 + R**2
    lever = R * x - eps
    d = R**2 * A * s * s + C * lever**2
    d_x = -2 * R**2 * A * x + 2 * C * R * lever
    kappa = R * A * eps * s * s + C * lever * (R + eps * x)
    kappa_x = -2 * R * A * eps * x + C * (R**2 - eps**2 + 2 * R * eps * x)
    dm_x = A * C * (-2 * x * d - s * s * d_x) / d**2
    dbeta_x = J / big_s * (kappa_x * d - kappa * d_x) / d**2
    return -(dm_x * p + dbeta_x)


def nutation_frequency(top: TippeTop, theta, J, *, branch: int = 1) -> Array:
    r"""$\nu$ of the nutation about the slow manifold:
    $\nu^2 = ((Cn - 2A\Omega\cos\theta)^2 + A^2\Omega^2\sin^2\theta)/(A M_\theta)$.

    $M_\theta = A + m\epsilon^2\sin^2\theta$. `branch=-1`: about the other root of (G2)
    ($\nu_-$ of the launch projection, `docs/derivations/launch-projection.md`)."""
    theta = jnp.asarray(theta, dtype=jnp.result_type(theta, top.m))
    x, s = jnp.cos(theta), jnp.sin(theta)
    sm = slow_manifold_at(top, x, s, J, branch)
    return jnp.sqrt(nutation_at(top, x, s, J, sm).frequency_squared)


def nutation_damping(top: TippeTop, theta, J, *, branch: int = 1) -> Array:
    r"""$\sigma$: growth rate of the amplitude of the nutation about the slow manifold (negative:
    it decays), averaged over a nutation period:

    $$\sigma = -\frac{\mu R'_n h^2 + c_q}{2M_\theta} - \frac12\frac{d\ln(M_\theta\nu)}{dt},$$

    with $c_q$ the damping through the momentum the nutation drives. Derivation ("The nutation
    it drops"): `docs/derivations/gyroscopic-averaging.md`.

    `branch=-1`: about the other root of (G2) ($\sigma_-$ of the launch projection: the growth
    rate of a launch's slow component while its nutation decays)."""
    theta = jnp.asarray(theta, dtype=jnp.result_type(theta, top.m))
    x, s = jnp.cos(theta), jnp.sin(theta)
    return nutation_at(top, x, s, J, slow_manifold_at(top, x, s, J, branch)).damping
