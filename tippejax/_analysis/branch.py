r"""The branch of intermediate states: $J(\theta)$ along it, its stability and its roots at a Jellet."""

from __future__ import annotations

import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array

from .._top import TippeTop
from .groups import thresholds


def intermediate_condition(top: TippeTop, J, x) -> Array:
    r"""$f(J^2, x)$ of eq. define_intstates; zero at an intermediate state $x = \cos\theta_0$."""
    a, e = top.A / top.C, top.eps / top.R
    b = (a - 1.0) * x + e
    p = a * (1.0 - x**2) + (x - e) ** 2
    return J**2 / (top.m * top.g * top.C * top.R**2 * top.eps) * b - p**2


def stability_function(top: TippeTop, x) -> Array:
    r"""$g(x) = (a - 1) + 4\tilde B(x)^2/(a(1-x^2) + (x-e)^2)$ (eq. eq:defg).

    An intermediate state at $x = \cos\theta_0$ is stable iff $g(x) > 0$.
    """
    a, e = top.A / top.C, top.eps / top.R
    b = (a - 1.0) * x + e
    return (a - 1.0) + 4 * b**2 / (a * (1.0 - x**2) + (x - e) ** 2)


def branch_jellet(top: TippeTop, theta) -> Array:
    r"""$J(\theta) \ge 0$ on the branch of intermediate states, $J^2 = m g C R^2\epsilon P^2/\tilde B$.

    nan where no intermediate state exists ($\tilde B \le 0$).
    """
    a, e = top.A / top.C, top.eps / top.R
    x = jnp.cos(theta)
    b = (a - 1.0) * x + e
    p = a * (1.0 - x**2) + (x - e) ** 2
    j2 = top.m * top.g * top.C * top.R**2 * top.eps * p**2 / jnp.where(b > 0, b, 1.0)
    return jnp.where(b > 0, jnp.sqrt(j2), jnp.nan)


def branch_pieces(top: TippeTop):
    """Theta-intervals of the branch on which J^2 is monotone: ((lo1, hi1), (lo2, hi2))."""
    a, e = top.A / top.C, top.eps / top.R
    th = thresholds(top)
    group_i = a - 1.0 < -e
    group_iii = a - 1.0 > e
    theta_lo = jnp.where(group_iii, 0.0, jnp.where(group_i, th.theta_c, 0.0))
    theta_hi = jnp.where(group_iii, th.theta_c, jnp.pi)
    theta_lo = jnp.where(group_iii, 0.0, theta_lo)
    split = jnp.where(
        jnp.isfinite(th.theta_b) & (th.theta_b > theta_lo) & (th.theta_b < theta_hi),
        th.theta_b,
        theta_hi,
    )
    return (theta_lo, split), (split, theta_hi)


def find_branch_root(top: TippeTop, J, lo, hi):
    """Root of f(J^2, cos theta) in [lo, hi] by bisection, if the bracket changes sign."""
    dtype = jnp.result_type(top.m)
    tol = 1e-13 if dtype == jnp.float64 else 1e-6

    a, e = top.A / top.C, top.eps / top.R
    k = J**2 / (top.m * top.g * top.C * top.R**2 * top.eps)

    def fn(theta, args):
        # f / (k + P^2): the same roots, but O(1), so that Bisection's |f| < atol test can be
        # met in floating point however large J is.
        x = jnp.cos(theta)
        p = a * (1.0 - x**2) + (x - e) ** 2
        return intermediate_condition(top, J, x) / (k + p**2)

    # Nudge off the ends: at theta_c, f is finite; at a pole it is the vertical state.
    width = hi - lo
    lo_in, hi_in = lo + 1e-12 * width, hi - 1e-12 * width
    f_lo, f_hi = fn(lo_in, None), fn(hi_in, None)
    bracketed = (jnp.sign(f_lo) * jnp.sign(f_hi) < 0) & (width > 0)
    # Without a sign change, solve a dummy problem on [0, 1] (Bisection requires a bracket).
    lo_in = jnp.where(bracketed, lo_in, 0.0)
    hi_in = jnp.where(bracketed, hi_in, 1.0)

    def safe_fn(theta, args):
        return jnp.where(bracketed, fn(theta, args), theta - 0.5)

    solver = optx.Bisection(rtol=tol, atol=tol, flip="detect")
    sol = optx.root_find(
        safe_fn,
        solver,
        0.5 * (lo_in + hi_in),
        options=dict(lower=lo_in, upper=hi_in),
        throw=False,
        max_steps=256,
    )
    ok = bracketed & (sol.result == optx.RESULTS.successful)
    return jnp.where(ok, sol.value, jnp.nan), ok
