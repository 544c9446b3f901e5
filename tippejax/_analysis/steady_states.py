r"""Steady states for a given Jellet: vertical and intermediate, with their stability (Sec. 3-4).

Intermediate states are the roots $x = \cos\theta_0 \in (-1, 1)$ of (eq. define_intstates)

$$f(J^2, x) = \frac{J^2}{m g C R^2\epsilon}\,\tilde B(x) - P(x)^2,\qquad
\tilde B = (a-1)x + e,\quad P = a(1 - x^2) + (x - e)^2,$$

which need $\tilde B > 0$ (eq. Exist). Along the branch $J^2(x) = m g C R^2\epsilon P^2/\tilde B$
and $dJ^2/dx = -g(x) J^2/\tilde B$ (`docs/notes.md`, "Monotonicity along the intermediate branch"), so $J^2(x)$ is monotone between the ends of the
branch and the bifurcation point $x_b$. Each monotone piece holds at most one root, which is
bracketed and found by bisection (`optimistix.Bisection`): at most two intermediate states
(the branch and its roots: `branch.py`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Complex, Float

from .._top import TippeTop
from .branch import branch_pieces, find_branch_root, stability_function
from .laws import drilling_torque_at_rest, slip_coefficient
from .potential import effective_potential_d2_closed_form
from .stability import (
    drilling_rate,
    polynomial_eigenvalues,
    reduced_jacobian_eigenvalues,
    vector_field_eigenvalues,
)


class SteadyStates(eqx.Module):
    r"""Steady states of a top for one Jellet value (fields for one top; batch with `vmap`).

    `print(ss)` shows a table of the states (for concrete values of one top), the same as
    `ss.table()`; `ss.intermediate` lists the filled intermediate states as `(theta, stable)`.

    Vertical states, index 0 for $\theta = 0$ and 1 for $\theta = \pi$:

    - `vertical_theta`: $(0, \pi)$; `vertical_spin`: $n_0 = J/(C(R-\epsilon))$,
      $n_\pi = -J/(C(R+\epsilon))$ (eq. jello).
    - `vertical_d2W`: $W''$ at the pole; `vertical_stable`: $W'' > 0$ (eqs. cond_n1,
      stabpi_muniet0).
    - `vertical_eigenvalues_so3` (4 each), `vertical_eigenvalues_full` (6 each): non-trivial
      eigenvalues of the SO(3) and full vector fields linearised at the pole (a regular chart).

    Intermediate states, up to two slots (`intermediate_valid` says which are filled; empty slots
    hold nan):

    - `intermediate_theta`, `intermediate_spin` ($n = J(R\cos\theta_0 - \epsilon)/D$ on the
      relative equilibrium, $D = R^2 A\sin^2\theta_0 + C(R\cos\theta_0 - \epsilon)^2$),
      `intermediate_d2W` ($W''$, eq. stabilityba), `intermediate_g` ($g(\cos\theta_0)$, eq.
      eq:defg), `intermediate_stable` ($W'' > 0$).
    - `intermediate_eigenvalues_reduced` (3): autodiff Jacobian of the reduced system.
    - `intermediate_eigenvalues_polynomial` (3): the corrected characteristic polynomial.
    - `intermediate_eigenvalues_so3` (3), `intermediate_eigenvalues_full` (5): vector fields
      linearised in the co-rotating frame.

    The reduced Jacobian, the polynomial and the SO(3) field describe the same model (translation
    dropped in the friction), so their three eigenvalues agree; the full model has two more
    modes (the translation) and eigenvalues of its own. `table()` reports both.

    **The friction law.** The states, their spins, $W''$, $g$ and the stability by $W'' > 0$
    do not depend on the law: a steady state needs only $f = 0 \Leftrightarrow v_Q = 0$
    (Friedl 1997, sec. 2.3; Leine & Glocker 2003, eq. 18). The eigenvalues do: a law without
    drilling torque linearises at zero slip to a viscous law of coefficient
    `*_slip_coefficient` ($\mu$ for `Viscous`, $\mu/\delta$ for `Coulomb`; s/m), which the
    reduced routes use, while the SO(3) and full fields use the law itself. A law with a
    drilling torque (`CoulombContensou`) keeps drilling at these states: there the Jellet
    integral drifts at `*_jellet_rate` $= m g\, m(0, \omega_n)(R - \epsilon\cos\theta)$
    (kg m^2/s^2; `jellet_rate`), so they are quasi-steady states that move with $J$ (stable
    ones at frozen $J$ where $W'' > 0$), not fixed points: their eigenvalues and slip
    coefficients are nan, and `drifts` is True.

    - `vertical_jellet_rate`, `intermediate_jellet_rate`: $\dot J$ at each state (0 for a law
      without drilling torque).
    - `vertical_slip_coefficient`, `intermediate_slip_coefficient`: the law's viscous
      coefficient at zero slip at each state's drilling rate (s/m; nan under a drilling torque).
    - `law`: the law's class name; `drifts`: whether the law has a drilling torque.
    """

    jellet: Float[Array, ""]
    vertical_theta: Float[Array, "2"]
    vertical_spin: Float[Array, "2"]
    vertical_d2W: Float[Array, "2"]
    vertical_stable: Bool[Array, "2"]
    vertical_eigenvalues_so3: Complex[Array, "2 4"]
    vertical_eigenvalues_full: Complex[Array, "2 6"]
    intermediate_valid: Bool[Array, "2"]
    intermediate_theta: Float[Array, "2"]
    intermediate_spin: Float[Array, "2"]
    intermediate_d2W: Float[Array, "2"]
    intermediate_g: Float[Array, "2"]
    intermediate_stable: Bool[Array, "2"]
    intermediate_eigenvalues_reduced: Complex[Array, "2 3"]
    intermediate_eigenvalues_polynomial: Complex[Array, "2 3"]
    intermediate_eigenvalues_so3: Complex[Array, "2 3"]
    intermediate_eigenvalues_full: Complex[Array, "2 5"]
    vertical_jellet_rate: Float[Array, "2"]
    intermediate_jellet_rate: Float[Array, "2"]
    vertical_slip_coefficient: Float[Array, "2"]
    intermediate_slip_coefficient: Float[Array, "2"]
    law: str = eqx.field(static=True, default="Viscous")
    drifts: bool = eqx.field(static=True, default=False)

    @property
    def intermediate(self) -> list[tuple[float, bool]]:
        """The filled intermediate states as a list of `(theta, stable)` (concrete values only)."""
        valid = np.asarray(self.intermediate_valid)
        return [
            (float(t), bool(s))
            for t, s, v in zip(
                np.asarray(self.intermediate_theta), np.asarray(self.intermediate_stable), valid
            )
            if v
        ]

    def rows(self) -> list[dict]:
        """The states as a list of dicts, one per state (concrete values of one top only).

        Keys: `state` ("vertical" or "intermediate"), `theta` (rad), `spin` (rad/s), `d2W`,
        `stable` (by $W'' > 0$), `eigenvalues_so3`, `eigenvalues_full` (numpy arrays),
        `max_real_so3`, `max_real_full` (the largest real part: negative for a
        linearly stable state), `routes_agree` (whether the sign of every route's largest real
        part agrees with `stable`; None under a drilling torque, where there are no
        eigenvalues), `jellet_rate`, `slip_coefficient` and, for intermediate states,
        `eigenvalues_reduced`, `eigenvalues_polynomial` and `route_spread`: the largest
        distance between the eigenvalues of the reduced Jacobian, the polynomial and the SO(3)
        field, matched in sorted order (the three describe one model; rounding-level when they
        agree).
        """
        _check_concrete_single(self, "rows")
        out = []
        for i in range(2):
            ev_so3 = np.asarray(self.vertical_eigenvalues_so3[i])
            ev_full = np.asarray(self.vertical_eigenvalues_full[i])
            stable = bool(self.vertical_stable[i])
            out.append(
                dict(
                    state="vertical",
                    theta=float(self.vertical_theta[i]),
                    spin=float(self.vertical_spin[i]),
                    d2W=float(self.vertical_d2W[i]),
                    stable=stable,
                    eigenvalues_so3=ev_so3,
                    eigenvalues_full=ev_full,
                    max_real_so3=float(np.max(ev_so3.real)),
                    max_real_full=float(np.max(ev_full.real)),
                    routes_agree=None if self.drifts else _signs_agree(stable, ev_so3, ev_full),
                    jellet_rate=float(self.vertical_jellet_rate[i]),
                    slip_coefficient=float(self.vertical_slip_coefficient[i]),
                )
            )
        for i in range(2):
            if not bool(self.intermediate_valid[i]):
                continue
            ev = {
                k: np.asarray(getattr(self, f"intermediate_eigenvalues_{k}")[i])
                for k in ("reduced", "polynomial", "so3", "full")
            }
            stable = bool(self.intermediate_stable[i])
            spread = (
                float("nan")
                if self.drifts
                else max(
                    _eigen_distance(ev["so3"], ev["reduced"]),
                    _eigen_distance(ev["so3"], ev["polynomial"]),
                )
            )
            out.append(
                dict(
                    state="intermediate",
                    theta=float(self.intermediate_theta[i]),
                    spin=float(self.intermediate_spin[i]),
                    d2W=float(self.intermediate_d2W[i]),
                    stable=stable,
                    eigenvalues_so3=ev["so3"],
                    eigenvalues_full=ev["full"],
                    eigenvalues_reduced=ev["reduced"],
                    eigenvalues_polynomial=ev["polynomial"],
                    max_real_so3=float(np.max(ev["so3"].real)),
                    max_real_full=float(np.max(ev["full"].real)),
                    routes_agree=None if self.drifts else _signs_agree(stable, *ev.values()),
                    route_spread=spread,
                    jellet_rate=float(self.intermediate_jellet_rate[i]),
                    slip_coefficient=float(self.intermediate_slip_coefficient[i]),
                )
            )
        return out

    def table(self) -> str:
        """The states as a text table: theta, spin, $W''$, stability, and the largest real
        part of the eigenvalues by each route with their agreement (see `rows`)."""
        d2w = "W''"
        if self.drifts:
            last = f"{'dJ/dt':>13}"
        else:
            last = f"{'max Re so3':>12}{'max Re full':>13}  routes"
        lines = [
            f"steady states at J = {float(self.jellet):.6g} kg m^2/s ({self.law} law)",
            f"  {'state':<13}{'theta (rad)':>12}{'spin (rad/s)':>14}{d2w:>12}  {'stable':<9}{last}",
        ]
        for row in self.rows():
            if self.drifts:
                tail = f"{row['jellet_rate']:>13.4g}"
            else:
                routes = "agree" if row["routes_agree"] else "DISAGREE"
                if row["state"] == "intermediate":
                    routes += f" (spread {row['route_spread']:.1e})"
                tail = f"{row['max_real_so3']:>12.4g}{row['max_real_full']:>13.4g}  {routes}"
            lines.append(
                f"  {row['state']:<13}{row['theta']:>12.6g}{row['spin']:>14.6g}"
                f"{row['d2W']:>12.4g}  {'stable' if row['stable'] else 'unstable':<9}{tail}"
            )
        if not np.asarray(self.intermediate_valid).any():
            lines.append("  (no intermediate state at this J)")
        if self.drifts:
            lines.append(
                f"  The {self.law} law's drilling torque does not vanish at these states: J "
                "drifts at dJ/dt (kg m^2/s^2), so they are quasi-steady states that move with "
                "J, 'stable' at frozen J (W'' > 0); no eigenvalues (stability margins)."
            )
        elif self.law != "Viscous":
            k = np.asarray(self.vertical_slip_coefficient)[0]
            lines.append(
                f"  Eigenvalues of the {self.law} law linearised at zero slip: a viscous law of "
                f"coefficient {k:.4g} s/m (mu/slip_scale for Coulomb)."
            )
        return "\n".join(lines)

    def __repr__(self) -> str:
        if _is_concrete_single(self):
            return self.table()
        return eqx.tree_pformat(self)

    __str__ = __repr__


def _is_concrete_single(ss: SteadyStates) -> bool:
    leaves = jax.tree_util.tree_leaves(ss)
    return not any(isinstance(x, jax.core.Tracer) for x in leaves) and jnp.ndim(ss.jellet) == 0


def _check_concrete_single(ss: SteadyStates, what: str) -> None:
    if not _is_concrete_single(ss):
        raise ValueError(
            f"SteadyStates.{what}() needs the concrete steady states of one top and one J "
            "(call it outside jax.jit/vmap; for a batch, index one member first)."
        )


def _signs_agree(stable: bool, *eigenvalue_sets) -> bool:
    """Whether every route's largest real part has the sign that `stable` implies. A real
    part within rounding of 0 (a neutral direction, at a threshold) agrees either way."""
    for ev in eigenvalue_sets:
        if ev.size == 0 or not np.all(np.isfinite(ev)):
            return False
        worst = float(np.max(ev.real))
        scale = float(np.max(np.abs(ev))) or 1.0
        if abs(worst) <= 1e-9 * scale:
            continue
        if (worst < 0) != stable:
            return False
    return True


def _eigen_distance(a, b) -> float:
    """The largest distance between two sets of eigenvalues matched in sorted order."""
    a = np.sort_complex(np.asarray(a))
    b = np.sort_complex(np.asarray(b))
    return float(np.max(np.abs(a - b))) if a.shape == b.shape else float("inf")


def steady_states(top: TippeTop, J) -> SteadyStates:
    r"""All steady states of `top` at Jellet `J`, with their stability by every route.

    **Arguments:**

    - `top`: a single `TippeTop` (use `jax.vmap` for a batch).
    - `J`: the Jellet value (kg m^2/s), e.g. `tj.jellet(top, y0)`.

    **Returns:** a `SteadyStates`. Eigenvalues use `jnp.linalg.eigvals` (CPU).
    """
    return _steady_states(top, jnp.asarray(J, dtype=jnp.result_type(J, top.m)))


@eqx.filter_jit
def _steady_states(top: TippeTop, J) -> SteadyStates:
    J = jnp.asarray(J, dtype=jnp.result_type(J, top.m))
    pieces = branch_pieces(top)
    thetas, valids = [], []
    for lo, hi in pieces:
        theta, ok = find_branch_root(top, J, lo, hi)
        thetas.append(theta)
        valids.append(ok)
    theta_i = jnp.stack(thetas)
    valid = jnp.stack(valids)
    safe = jnp.where(valid, theta_i, 1.0)
    drifts = top.friction.has_drilling_torque
    complex_dtype = jnp.complex128 if jnp.dtype(J.dtype).itemsize == 8 else jnp.complex64

    def eigenvalues(th, count, fn, **kw):  # nan under a drilling torque (no fixed point)
        if drifts:
            return jnp.full((count,), jnp.nan, complex_dtype)
        return fn(top, th, J, **kw)

    def law_at(th):  # (dJ/dt, the slip coefficient) at the state theta = th
        rate = drilling_rate(top, th, J)
        torque = top.m * top.g * drilling_torque_at_rest(top, rate)  # R_n = m g at rest
        jdot = torque * (top.R - top.eps * jnp.cos(th))
        k = jnp.full_like(rate, jnp.nan) if drifts else slip_coefficient(top, rate)
        return jdot, k

    def per_state(th):
        return (
            effective_potential_d2_closed_form(top, th, J),
            stability_function(top, jnp.cos(th)),
            eigenvalues(th, 3, reduced_jacobian_eigenvalues),
            eigenvalues(th, 3, polynomial_eigenvalues),
            eigenvalues(th, 3, vector_field_eigenvalues, model="so3"),
            eigenvalues(th, 5, vector_field_eigenvalues, model="full"),
            *law_at(th),
        )

    d2w, g, ev_red, ev_poly, ev_so3, ev_full, jdot_i, k_i = jax.vmap(per_state)(safe)

    def mask(x):
        shape = (2,) + (1,) * (x.ndim - 1)
        return jnp.where(valid.reshape(shape), x, jnp.nan)

    poles = jnp.array([0.0, jnp.pi], dtype=J.dtype)
    vertical_d2w = effective_potential_d2_closed_form(top, poles, J)
    vertical_so3 = jnp.stack(
        [
            eigenvalues(p, 4, vector_field_eigenvalues, model="so3", pole=True)
            for p in (poles[0], poles[1])
        ]
    )
    vertical_full = jnp.stack(
        [
            eigenvalues(p, 6, vector_field_eigenvalues, model="full", pole=True)
            for p in (poles[0], poles[1])
        ]
    )
    jdot_v, k_v = (jnp.stack(x) for x in zip(*(law_at(p) for p in (poles[0], poles[1]))))
    x = jnp.cos(safe)
    lever = top.R * x - top.eps
    spin_i = J * lever / (top.R**2 * top.A * (1.0 - x**2) + top.C * lever**2)
    return SteadyStates(
        jellet=J,
        vertical_theta=poles,
        vertical_spin=jnp.stack(
            [J / (top.C * (top.R - top.eps)), -J / (top.C * (top.R + top.eps))]
        ),
        vertical_d2W=vertical_d2w,
        vertical_stable=vertical_d2w > 0,
        vertical_eigenvalues_so3=vertical_so3,
        vertical_eigenvalues_full=vertical_full,
        intermediate_valid=valid,
        intermediate_theta=theta_i,
        intermediate_spin=mask(spin_i),
        intermediate_d2W=mask(d2w),
        intermediate_g=mask(g),
        intermediate_stable=valid & (d2w > 0),
        intermediate_eigenvalues_reduced=mask(ev_red),
        intermediate_eigenvalues_polynomial=mask(ev_poly),
        intermediate_eigenvalues_so3=mask(ev_so3),
        intermediate_eigenvalues_full=mask(ev_full),
        vertical_jellet_rate=jdot_v,
        intermediate_jellet_rate=mask(jdot_i),
        vertical_slip_coefficient=k_v,
        intermediate_slip_coefficient=mask(k_i),
        law=type(top.friction).__name__,
        drifts=drifts,
    )


@eqx.filter_jit
def pole_threshold(top: TippeTop, *, pole: str = "north", model: str = "so3") -> Array:
    r"""The spin threshold at a pole, found from the linearised SO(3) or full vector field.

    `pole="north"` ($\theta = 0$): the $|n_0|$ above which the largest real part of the non-trivial
    eigenvalues becomes positive ($n_1$ of eq. n1). `pole="south"` ($\theta = \pi$): the $|n_\pi|$
    above which it becomes negative ($n_2$ of eq. n2). Found by bisection on $\log|n|$ between
    $10^{-2}$ and $10^{3}$ times $\sqrt{m g\epsilon/C}$; nan where the sign does not change
    (Group I at the north pole, Group III at the south pole). Needs $\mu > 0$.
    """
    if pole not in ("north", "south"):
        raise ValueError(f"pole must be 'north' or 'south', got {pole!r}.")
    theta0 = 0.0 if pole == "north" else jnp.pi
    lever = (top.R - top.eps) if pole == "north" else -(top.R + top.eps)
    scale = jnp.sqrt(top.m * top.g * top.eps / top.C)

    def growth(log_n, args):
        J = top.C * lever * jnp.exp(log_n)
        ev = vector_field_eigenvalues(top, theta0, J, model=model, pole=True)
        return jnp.max(jnp.real(ev)) / scale

    lo, hi = jnp.log(1e-2 * scale), jnp.log(1e3 * scale)
    bracketed = jnp.sign(growth(lo, None)) * jnp.sign(growth(hi, None)) < 0
    tol = 1e-14 if jnp.result_type(top.m) == jnp.float64 else 1e-6
    mid = 0.5 * (lo + hi)

    def safe_growth(log_n, args):
        return jnp.where(bracketed, growth(log_n, args), log_n - mid)

    sol = optx.root_find(
        safe_growth,
        optx.Bisection(rtol=tol, atol=tol, flip="detect"),
        0.5 * (lo + hi),
        options=dict(lower=lo, upper=hi),
        throw=False,
        max_steps=512,
    )
    ok = bracketed & (sol.result == optx.RESULTS.successful)
    return jnp.where(ok, jnp.exp(sol.value), jnp.nan)
