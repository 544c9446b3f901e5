r"""Linear stability of the steady states, by four independent routes.

1. $W''(\theta_0) > 0$ (Sec. 4; the Hurwitz argument of App. B).
2. Eigenvalues of the autodiff Jacobian of the reduced vector field at $(\theta_0, \dot\theta = 0,
   \dot{\bar\varphi} = 0)$, in the variables $(\theta, \dot\theta, \dot{\bar\varphi})$ (the cyclic
   $\bar\varphi$ only adds the zero eigenvalue of the residual symmetry, which is removed).
3. Roots of the characteristic polynomial of Sec. 4,
   $\lambda^3 + (\alpha+\gamma)\lambda^2 + (\alpha\gamma + \beta^2 + \delta)\lambda + \delta\gamma$,
   with $\alpha = \mu m g h^2/M_\theta$, $\gamma = \mu m g\sin^2\theta_0/M_{\bar\varphi}$,
   $\beta^2 = \beta'^2/(M_\theta M_{\bar\varphi})$, $\delta = W''/M_\theta$ and the *full* inertia
   coefficients $M_\theta$, $M_{\bar\varphi}$ (`docs/notes.md`, "The factor 2 in the linearised equations"). `corrected=False` evaluates the
   polynomial as printed, with $T_{\theta\theta} = M_\theta/2$ and $T_{\bar\varphi\bar\varphi} =
   M_{\bar\varphi}/2$, which gives wrong eigenvalues.
4. Eigenvalues of the SO(3) or full vector field linearised in the frame co-rotating with the
   relative equilibrium at rate $\dot\varphi_0 = RJ/D$. These charts are regular at the poles,
   where the reduced chart is singular (`docs/notes.md`, "The singular chart at the poles"). The trivial eigenvalues are removed
   exactly: the zeros of the conserved $|a|^2$ and $J$ by restricting to the invariant subspace
   $\nabla|a|^2\cdot\delta = \nabla J\cdot\delta = 0$, the zero of the rotation symmetry (away from
   the poles) by quotienting out its generator $e_Z\times y_0$.

Routes 1-3 are derived for the viscous law; a law without drilling torque enters them through
its viscous coefficient at zero slip (`laws.linearised_top`: $\mu/\delta$ for the regularised
Coulomb law), route 4 through the law itself. Under a drilling torque there is no fixed point to
linearise about (`laws.drifting_message`): each route raises `ValueError`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Complex

from .._models._rigid_body import rigid_body_dynamics
from .._models.routhian import RouthianState, _single as _routhian_single
from .._top import TippeTop
from .laws import drifting_message, linearised_top
from .potential import effective_potential_d2_closed_form, routhian_terms


def drilling_rate(top: TippeTop, theta0, J):
    r"""$\omega_n = \omega\cdot e_Z$ at the relative equilibrium $\theta_0$ with Jellet $J$."""
    return relative_equilibrium(top, theta0, J)[1][2]


def reduced_jacobian_eigenvalues(top: TippeTop, theta0, J) -> Complex[Array, "3"]:
    r"""Eigenvalues of the reduced system's Jacobian at the relative equilibrium $\theta_0$.

    Variables $(\theta, \dot\theta, \dot{\bar\varphi})$; the Jacobian is by `jax.jacfwd` of the
    Routhian vector field, with the law's viscous coefficient at zero slip
    (`laws.linearised_top`). Not defined at $\sin\theta_0 = 0$.
    """
    top = linearised_top(top, drilling_rate(top, theta0, J))

    def field(z):
        y = RouthianState(
            theta=z[0],
            phibar=jnp.zeros_like(z[0]),
            c=jnp.zeros_like(z[0]),
            theta_dot=z[1],
            phibar_dot=z[2],
        )
        dy = _routhian_single(top, y, J)
        return jnp.stack([dy.theta, dy.theta_dot, dy.phibar_dot])

    z0 = jnp.stack(
        [jnp.asarray(theta0, dtype=jnp.result_type(theta0, top.m)), 0.0 * top.m, 0.0 * top.m]
    )
    return jnp.linalg.eigvals(jax.jacfwd(field)(z0))


def characteristic_polynomial(top: TippeTop, theta0, J, *, corrected: bool = True) -> Array:
    r"""Coefficients $[1, c_2, c_1, c_0]$ of the cubic of Sec. 4 at $\theta_0$ (zero root removed).

    `corrected=True` uses the full inertia coefficients (`docs/notes.md`, "The factor 2"); `False` the printed ones.
    $\mu$ is the law's viscous coefficient at zero slip (`laws.linearised_top`).
    """
    top = linearised_top(top, drilling_rate(top, theta0, J))
    terms = routhian_terms(top, theta0, J)
    dbeta = jax.grad(lambda th: routhian_terms(top, th, J).gyroscopic)(
        jnp.asarray(theta0, dtype=jnp.result_type(theta0, top.m))
    )
    w2 = effective_potential_d2_closed_form(top, theta0, J)
    factor = 1.0 if corrected else 0.5
    t_theta = factor * terms.inertia_theta
    t_phibar = factor * terms.inertia_phibar
    h = top.R - top.eps * jnp.cos(theta0)
    mgmu = top.mu * top.m * top.g
    alpha = mgmu * h**2 / t_theta
    gamma = mgmu * jnp.sin(theta0) ** 2 / t_phibar
    beta2 = dbeta**2 / (t_theta * t_phibar)
    delta = w2 / t_theta
    one = jnp.ones_like(alpha)
    return jnp.stack([one, alpha + gamma, alpha * gamma + beta2 + delta, delta * gamma])


def polynomial_eigenvalues(
    top: TippeTop, theta0, J, *, corrected: bool = True
) -> Complex[Array, "3"]:
    """Roots of `characteristic_polynomial` (see there)."""
    return jnp.roots(
        characteristic_polynomial(top, theta0, J, corrected=corrected), strip_zeros=False
    )


def relative_equilibrium(top: TippeTop, theta0, J):
    r"""The relative equilibrium at $\theta_0$ with Jellet $J$ as a vector state, and its rate.

    $\dot\theta = 0$, $\dot\varphi_0 = RJ/D$, $\dot\psi_0 = -\epsilon J/D$ (pure rolling), centre of
    mass at rest, $\varphi = 0$. **Returns:** `(axis, omega, precession_rate)`.
    """
    theta0 = jnp.asarray(theta0, dtype=jnp.result_type(theta0, top.m))
    s, c = jnp.sin(theta0), jnp.cos(theta0)
    d = top.R**2 * top.A * s**2 + top.C * (top.R * c - top.eps) ** 2
    phi_dot = top.R * J / d
    psi_dot = -top.eps * J / d
    axis = jnp.stack([0.0 * s, -s, c])
    omega = phi_dot * jnp.array([0.0, 0.0, 1.0], dtype=axis.dtype) + psi_dot * axis
    return axis, omega, phi_dot


def _jellet_vec(top, axis, omega):
    n = jnp.dot(omega, axis)
    lvec = top.A * omega + (top.C - top.A) * n * axis
    q = top.eps * axis - top.R * jnp.array([0.0, 0.0, 1.0], dtype=axis.dtype)
    return -jnp.dot(lvec, q)


def vector_field_eigenvalues(
    top: TippeTop, theta0, J, *, model: str = "so3", pole: bool = False
) -> Complex[Array, " k"]:
    r"""Non-trivial eigenvalues of the SO(3) or full model at a relative equilibrium.

    Linearised in the frame rotating about $e_Z$ at $\dot\varphi_0$, where the relative
    equilibrium is a fixed point. `pole=True` (static) for $\theta_0 \in \{0, \pi\}$: there the
    rotation symmetry fixes the equilibrium and gives no zero eigenvalue.
    SO(3): 4 eigenvalues at a pole, 3 elsewhere; full: 6 at a pole, 5 elsewhere. The friction
    is the top's law itself (its force and its effect on $R_n$); a law with a drilling torque
    raises `ValueError` (the relative equilibrium is not a fixed point: `laws.drifting_message`).
    """
    if model not in ("so3", "full"):
        raise ValueError(f"model must be 'so3' or 'full', got {model!r}.")
    if top.friction.has_drilling_torque:
        raise ValueError(drifting_message(top, "A linearisation at a steady state"))
    axis0, omega0, rate = relative_equilibrium(top, theta0, J)
    if pole:
        # At a pole the steady state is a true fixed point: use the inertial frame.
        rate = jnp.zeros_like(rate)
    ez = jnp.array([0.0, 0.0, 1.0], dtype=axis0.dtype)
    full = model == "full"

    def split(y):
        if full:
            return y[0:2], y[2:5], y[5:8]
        return jnp.zeros(2, y.dtype), y[0:3], y[3:6]

    def field(y):
        velocity, axis, omega = split(y)
        rn, omega_dot, v_q, _ = rigid_body_dynamics(top, axis, omega, velocity)
        axis_dot = jnp.cross(omega, axis) - rate * jnp.cross(ez, axis)
        omega_dot = omega_dot - rate * jnp.cross(ez, omega)
        parts = [axis_dot, omega_dot]
        if full:
            force, _ = top.friction.force_and_torque(v_q[:2], omega[2])  # per unit R_n
            velocity_dot = rn * force / top.m - rate * jnp.stack([-velocity[1], velocity[0]])
            parts = [velocity_dot] + parts
        return jnp.concatenate(parts)

    parts0 = [axis0, omega0]
    if full:
        parts0 = [jnp.zeros(2, axis0.dtype)] + parts0
    y0 = jnp.concatenate(parts0)
    jac = jax.jacfwd(field)(y0)

    def norm_axis(y):
        return jnp.dot(split(y)[1], split(y)[1])

    def jellet_y(y):
        _, axis, omega = split(y)
        return _jellet_vec(top, axis, omega)

    rows = [jax.grad(norm_axis)(y0), jax.grad(jellet_y)(y0)]
    if not pole:
        sym = [jnp.cross(ez, axis0), jnp.cross(ez, omega0)]
        if full:
            sym = [jnp.zeros(2, axis0.dtype)] + sym
        rows.append(jnp.concatenate(sym))
    constraints = jnp.stack(rows)
    _, _, vt = jnp.linalg.svd(constraints, full_matrices=True)
    basis = vt[len(rows) :].T
    return jnp.linalg.eigvals(basis.T @ jac @ basis)


def max_real_part(eigenvalues) -> Array:
    """Largest real part: < 0 means linearly stable (all non-trivial eigenvalues decay)."""
    return jnp.max(jnp.real(eigenvalues), axis=-1)


def is_stable_by_potential(top: TippeTop, theta0, J) -> Array:
    r"""$W''(\theta_0) > 0$ (closed form, eq. stabilityba)."""
    return effective_potential_d2_closed_form(top, theta0, J) > 0
