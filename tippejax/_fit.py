r"""Fitting physical parameters and launch quantities to a measured tilt $\theta(t_k)$.

The fit is a weighted nonlinear least-squares problem,

$$\min_p \tfrac12 \sum_k w_k\,\big(\theta(t_k; p) - \theta^{obs}_k\big)^2
        \;[+\; \tfrac12 \sum_k w^\varphi_k \sin^2\theta^{obs}_k\,
        \mathrm{wrap}\big(\varphi(t_k; p) - \varphi^{obs}_k\big)^2],$$

where $\theta(t; p)$ comes from `simulate` at the chosen level of model. The free parameters $p$
are mapped to unconstrained coordinates $u$ (logarithms, logits) so that positivity, $0 < \epsilon
< R$, $A/C > 1/2$ and $0 < \theta_0 < \pi$ hold at every trial without clipping. Jacobians are
taken in forward mode (few parameters, many residuals) through the ODE solve
(`diffrax.ForwardMode`), in one pass that yields the residuals and all columns together.

Inversion makes $\theta(t; p)$ very sensitive: a 30% change of $\mu$ moves the inversion of the
standard top by more than a second, and a least-squares fit over the whole record then stalls in
a flat, curved valley. The default strategy (`"levels"`) first fits slow observables: the times
at which the kernel-smoothed tilt first crosses a ladder of levels, the same smoothing applied to
data and model. Time residuals are nearly linear in the parameters (a 1 s shift is a 1 s
residual, not a flat plateau), so this stage converges from far. The nutation is the second
trap: its phase error grows with time and with the error in the spin (1% in the spin slips it
by a cycle over the standard top's rise), so the record is then fitted in windows that double
from 1/64 of its length, the level times kept in the loss, and last the whole record alone (the
loss the covariance describes). `benchmarks/fitting.py` measures this against plain fits and
window continuation without levels (`"windows"`).

Each optimiser step costs one simulation with $p$ tangents: the residual function has a custom
JVP that returns the materialised Jacobian, so `jax.linearize` inside optimistix does not run
the ODE solve again for each Jacobian-vector product.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

import diffrax
import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._simulate import MODELS, simulate
from ._state import State, euler_angles, euler_rates, spin, state_from_euler
from ._top import TippeTop, _checks

TOP_FIELDS = ("m", "R", "eps", "A", "C", "g", "mu")
LAUNCH_FIELDS = ("theta0", "spin", "theta_dot", "phi_dot", "vx", "vy")
FREE_NAMES = TOP_FIELDS + LAUNCH_FIELDS
METHODS = ("levenberg_marquardt", "gauss_newton", "adam")
STRATEGIES = ("levels", "windows", "plain")
NUM_LEVELS = 12
# A save time at which the trial's simulation has stopped (contact lost, singularity, max steps)
# gets this residual (rad): the largest error a tilt can have. It is finite and constant, so the
# loss of such a trial is large, its gradient stays finite, and the optimiser rejects the step.
FAILED_RESIDUAL = math.pi
_LEVEL_TIME_SCALE = 0.05  # s: level-crossing residuals are divided by this
_STAGE_TOL = 1e-4  # optimiser tolerance of the intermediate stages (the last one uses `tol`)
_U_MAX = 30.0  # |u| bound: sigmoid(30) = 1 - 1e-13 < 1, exp(30) = 1e13


class FIT_RESULTS(eqxi.Enumeration):
    """Outcome of a fit. `successful` is the empty message."""

    successful = ""
    max_steps_reached = (
        "The optimiser used max_steps without meeting its tolerance. The fit may still be "
        "usable (look at loss_history); raise max_steps or try another strategy."
    )
    optimiser_failed = (
        "The optimiser stopped on a non-finite loss or a singular linear system."
    )
    simulation_failed = (
        "At the fitted parameters the simulation fails before the end of the record (contact "
        "lost, the R_n singularity or max steps): those save times carry the failure residual."
    )


class FitResult(eqx.Module):
    r"""The result of `fit`. Batched fits (several recordings) carry a leading batch axis.

    **Fields:**

    - `top`, `y0`: the fitted `TippeTop` and initial `State` (free quantities replaced).
    - `free`: the names of the free parameters, in the order of `values`.
    - `values`: fitted values of the free parameters.
    - `std_errors`: their standard errors, $\sqrt{\mathrm{diag}\,\Sigma}$.
    - `covariance`: $\Sigma = s^2 (J^\top J)^{-1}$, the Gauss-Newton covariance in the physical
      parameters, with $J$ the Jacobian of the weighted residuals at the fit and $s^2 =
      \mathrm{RSS}/(N - p)$ the residual variance ($N$ used points, $p$ free parameters). It
      assumes independent errors of equal variance and a model that describes the data; it is
      linear, so it understates the uncertainty of badly determined parameters.
    - `correlation`: $\Sigma_{ij}/\sqrt{\Sigma_{ii}\Sigma_{jj}}$.
    - `loss_history`: $\tfrac12\sum r_k^2$ after each optimiser step, all stages one after the
      other (nan-padded to a fixed length).
    - `stage_ends`: index in `loss_history` where each stage ended.
    - `ts`, `theta_obs`: the data (nan where masked); `ts` carries the batch axis too, so
      `jax.tree_util.tree_map(lambda x: x[b], result)` picks recording `b`.
    - `theta_fit`: the fitted model's tilt at `ts` (nan past a failure).
    - `residuals`: `theta_fit - theta_obs` (nan where masked or failed).
    - `rms`: root mean square of the theta residuals over the used points (rad).
    - `noise`: the noise level the residuals are judged against: `sigma` if given, else the
      10th percentile of the moving RMS of the residuals over 5% of the record (the residual
      of the best-described stretches). `rms` well above `noise` says the model does not
      describe the whole record, whatever `converged` says.
    - `describes_until`: the end of the initial part of the record that the model describes:
      the last time before the moving RMS of the residuals first exceeds `3 * noise`. For data
      the model made, the whole record.
    - `fitted_until`: the end of the part of the record the fit used (`trim`; else the end).
    - `phi_fit`, `phi_residuals`: the fitted precession angle and its wrapped residual (nan
      unless `phi_obs` was given).
    - `converged`: whether the last stage met its tolerance.
    - `result`: a `FIT_RESULTS` code; `message` gives its text.
    - `num_steps`: optimiser steps, all stages.
    - `model`, `method`, `strategy`: the level of model, optimiser and strategy used.
    """

    top: TippeTop
    y0: State
    values: Float[Array, "*batch p"]
    std_errors: Float[Array, "*batch p"]
    covariance: Float[Array, "*batch p p"]
    correlation: Float[Array, "*batch p p"]
    loss_history: Float[Array, "*batch steps"]
    stage_ends: Int[Array, "*batch stages"]
    ts: Float[Array, "*batch N"]
    theta_obs: Float[Array, "*batch N"]
    theta_fit: Float[Array, "*batch N"]
    residuals: Float[Array, "*batch N"]
    rms: Float[Array, "*batch"]
    noise: Float[Array, "*batch"]
    describes_until: Float[Array, "*batch"]
    fitted_until: Float[Array, "*batch"]
    phi_fit: Float[Array, "*batch N"]
    phi_residuals: Float[Array, "*batch N"]
    converged: Bool[Array, "*batch"]
    result: FIT_RESULTS
    num_steps: Int[Array, "*batch"]
    free: tuple[str, ...] = eqx.field(static=True)
    model: str = eqx.field(static=True)
    method: str = eqx.field(static=True)
    strategy: str = eqx.field(static=True)

    @property
    def params(self) -> dict[str, Array]:
        """The fitted free parameters by name."""
        return {name: self.values[..., i] for i, name in enumerate(self.free)}

    @property
    def message(self) -> str | list[str]:
        """Why the fit stopped ("converged" when it did)."""
        size = int(np.size(np.asarray(self.result._value)))
        texts = [
            FIT_RESULTS[jax.tree_util.tree_map(lambda x: jnp.ravel(x)[i], self.result)] or "converged"
            for i in range(size)
        ]
        return texts[0] if np.ndim(np.asarray(self.result._value)) == 0 else texts

    def table(self) -> str:
        """The fitted values with standard errors, one line per free parameter."""
        values, errors = np.asarray(self.values), np.asarray(self.std_errors)
        lines = []
        if values.ndim == 1:
            lines.append(f"{'parameter':>10}  {'value':>13}  {'std error':>11}  {'rel':>8}")
            for name, v, e in zip(self.free, values, errors):
                rel = abs(e / v) if v != 0 else np.inf
                lines.append(f"{name:>10}  {v:13.6g}  {e:11.3g}  {rel:8.2%}")
            lines.append(
                f"rms residual {float(self.rms):.4g} rad (noise level {float(self.noise):.3g}); "
                f"describes the record until t = {float(self.describes_until):.4g} s of "
                f"{float(self.ts[-1]):.4g} s; {int(self.num_steps)} optimiser steps; {self.message}"
            )
        else:
            for b in range(values.shape[0]):
                row = ", ".join(
                    f"{n} = {v:.6g} +- {e:.2g}" for n, v, e in zip(self.free, values[b], errors[b])
                )
                lines.append(
                    f"[{b}] {row}; rms {float(self.rms[b]):.3g}; {int(self.num_steps[b])} steps; "
                    f"{self.message[b]}"
                )
        return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# Parameters: physical values <-> unconstrained coordinates.


def _logit(x):
    return jnp.log(x) - jnp.log1p(-x)


class _Base(eqx.Module):
    """The guess: every top field and launch quantity, free or not (arrays, maybe batched)."""

    top: dict[str, Array]
    launch: dict[str, Array]


def _launch_of(y0: State) -> dict[str, Array]:
    theta, phi, psi = euler_angles(y0)
    theta_dot, phi_dot, _ = euler_rates(y0)
    return dict(
        theta0=theta, spin=spin(y0), theta_dot=theta_dot, phi_dot=phi_dot, phi=phi, psi=psi,
        vx=y0.velocity[..., 0], vy=y0.velocity[..., 1], x=y0.position[..., 0],
        y=y0.position[..., 1],
    )


def _physical(u: Float[Array, " p"], base: _Base, free: tuple[str, ...]) -> dict[str, Array]:
    """Physical values of the free parameters for unconstrained `u` (u = 0 is the guess)."""
    t, lau = base.top, base.launch
    # Bounded arguments keep sigmoids below 1 and exponentials finite in float64 (a guard on
    # the unconstrained coordinates, not a clip of the physical values).
    bound = _U_MAX if u.dtype == jnp.float64 else 15.0  # float32: sigmoid(15) < 1 still
    z = dict(zip(free, jnp.clip(u, -bound, bound)))
    out = {}
    for name in ("m", "R", "g", "mu"):
        if name in z:
            out[name] = t[name] * jnp.exp(z[name])
    if "C" in z and "A" not in z:
        out["C"] = 2 * t["A"] * jax.nn.sigmoid(z["C"] + _logit(t["C"] / (2 * t["A"])))
    elif "C" in z:
        out["C"] = t["C"] * jnp.exp(z["C"])
    C = out.get("C", t["C"])
    if "A" in z:
        out["A"] = C * (0.5 + (t["A"] / t["C"] - 0.5) * jnp.exp(z["A"]))
    if "eps" in z:
        R = out.get("R", t["R"])
        out["eps"] = R * jax.nn.sigmoid(z["eps"] + _logit(t["eps"] / t["R"]))
    if "theta0" in z:
        out["theta0"] = jnp.pi * jax.nn.sigmoid(z["theta0"] + _logit(lau["theta0"] / jnp.pi))
    if "spin" in z:
        out["spin"] = lau["spin"] * jnp.exp(z["spin"])
    for name, floor in (("theta_dot", 1.0), ("phi_dot", 1.0), ("vx", 0.01), ("vy", 0.01)):
        if name in z:
            out[name] = lau[name] + jnp.maximum(jnp.abs(lau[name]), floor) * z[name]
    # The coordinates u are in the optimiser's precision (float64 when enabled); the physical
    # values in the top's (float32 tops simulate in float32).
    dtype = jnp.result_type(t["m"])
    return {k: jnp.asarray(v, dtype) for k, v in out.items()}


def _assemble(values: dict[str, Array], base: _Base) -> tuple[TippeTop, State]:
    """The top and initial state with `values` replacing the guess's fields."""
    lau = {**base.launch, **{k: v for k, v in values.items() if k in LAUNCH_FIELDS}}
    # The guess is a checked top; trial values are valid by construction (reparametrised), so
    # they replace its fields without TippeTop's runtime checks: a trial that overflows to
    # inf makes a non-finite simulation, which gets the failure residual, instead of raising.
    top = TippeTop(**base.top)
    changed = [k for k in TOP_FIELDS if k in values]
    if changed:
        top = eqx.tree_at(
            lambda tp: [getattr(tp, k) for k in changed], top, [values[k] for k in changed]
        )
    y0 = state_from_euler(
        lau["theta0"], lau["phi"], lau["psi"], lau["theta_dot"], lau["phi_dot"],
        lau["spin"] - lau["phi_dot"] * jnp.cos(lau["theta0"]),
        position=jnp.stack([lau["x"], lau["y"]], -1),
        velocity=jnp.stack([lau["vx"], lau["vy"]], -1),
    )
    return top, y0


# ---------------------------------------------------------------------------------------------
# Residuals.


class _Config(eqx.Module):
    """Static settings of one fit (hashable: one compilation per configuration)."""

    free: tuple[str, ...]
    model: str
    method: str
    max_steps: int
    sim_max_steps: int
    has_phi: bool
    solver: diffrax.AbstractSolver | None
    learning_rate: float


class _Data(eqx.Module):
    """Everything a stage needs that is an array (batched along with the recording)."""

    base: _Base
    ts: Float[Array, " N"]
    t0: Float[Array, ""]
    t_end: Float[Array, ""]
    theta_obs: Float[Array, " N"]  # 0 where masked
    weights: Float[Array, " N"]  # 0 where masked or outside the window
    mask: Float[Array, " N"]  # 1 where a sample exists (for the smoothing), whatever the stage
    phi_obs: Float[Array, " N"]
    phi_weights: Float[Array, " N"]
    smoother_index: Int[Array, "G M"]  # samples near each grid point (a band of the kernel)
    smoother_weight: Float[Array, "G M"]  # their Gaussian weights (0 for padding)
    grid: Float[Array, " G"]
    levels: Float[Array, " L"]
    t_levels: Float[Array, " L"]
    level_weight: Float[Array, ""]
    rtol: Float[Array, ""]
    atol: Float[Array, ""]
    tol: Float[Array, ""]  # the optimiser's tolerance in this stage


def _simulated(values, data: _Data, cfg: _Config):
    # A trial with a non-finite value (an optimiser step that overflowed) runs the guess
    # instead, and all its samples are marked failed: simulate must not see a NaN state.
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(v)) for v in values.values()]))
    guess = {k: data.base.top[k] if k in TOP_FIELDS else data.base.launch[k] for k in values}
    safe = {k: jnp.where(finite, v, guess[k]) for k, v in values.items()}
    top, y0 = _assemble(safe, data.base)
    saves = jnp.minimum(data.ts, data.t_end)
    sol = simulate(
        top, y0, data.t_end, t0=data.t0, saveat=saves, model=cfg.model, rtol=data.rtol,
        atol=data.atol, solver=cfg.solver, max_steps=cfg.sim_max_steps, throw=False,
        adjoint=diffrax.ForwardMode(), on_contact_loss="continue",
    )
    return eqx.tree_at(lambda s: s.theta, sol, jnp.where(finite, sol.theta, jnp.nan))


def _first_crossings(smooth, grid, levels):
    """Differentiable first time `smooth` (sampled on `grid`) reaches each level."""

    def one(level):
        above = smooth >= level
        k = jnp.maximum(jnp.argmax(above), 1)
        lo, hi = smooth[k - 1], smooth[k]
        frac = jnp.clip((level - lo) / jnp.where(hi > lo, hi - lo, 1.0), 0.0, 1.0)
        t_hit = grid[k - 1] + frac * (grid[k] - grid[k - 1])
        # Never reached: past the end by the missing height, at the mean rate pi per record.
        t_miss = grid[-1] + (level - jnp.max(smooth)) * (grid[-1] - grid[0]) / jnp.pi
        return jnp.where(jnp.any(above), t_hit, t_miss)

    return jax.vmap(one)(levels)


def _smoothed(y, mask, index, weight):
    """Kernel regression onto the grid: sum_k w_gk m_k y_k / sum_k w_gk m_k over the band."""
    numerator = jnp.sum(weight * (mask * y)[index], axis=-1)
    return numerator / jnp.maximum(jnp.sum(weight * mask[index], axis=-1), 1e-300)


def _residuals_of_values(values, data: _Data, cfg: _Config):
    sol = _simulated(values, data, cfg)
    theta = sol.theta
    finite = jnp.isfinite(theta)
    theta_safe = jnp.where(finite, theta, 0.0)
    # Past a contact loss the hard-table model does not hold: those samples get the failure
    # residual. The run itself goes on (on_contact_loss="continue") with the same equations, so
    # the level-crossing times below stay smooth functions of the parameters through the loss.
    lost = sol.ts > sol.t_contact_loss  # False when contact is never lost (nan)
    ok = finite & ~lost
    used = data.weights > 0
    r = jnp.where(used, jnp.where(ok, theta_safe - data.theta_obs, FAILED_RESIDUAL), 0.0)
    parts = [jnp.sqrt(data.weights) * r]
    if cfg.has_phi:
        phi = jnp.where(ok, sol.phi, 0.0)
        dphi = jnp.arctan2(jnp.sin(phi - data.phi_obs), jnp.cos(phi - data.phi_obs))
        used_phi = data.phi_weights > 0
        rphi = jnp.where(used_phi, jnp.where(ok, dphi, FAILED_RESIDUAL), 0.0)
        parts.append(jnp.sqrt(data.phi_weights) * jnp.sin(data.theta_obs) * rphi)
    # Slow observables: level-crossing times of the smoothed tilt (model against data).
    smooth = _smoothed(theta_safe, data.mask, data.smoother_index, data.smoother_weight)
    t_cross = _first_crossings(smooth, data.grid, data.levels)
    parts.append(data.level_weight * (t_cross - data.t_levels) / _LEVEL_TIME_SCALE)
    return jnp.concatenate(parts), sol


def _residuals(u, data: _Data, cfg: _Config):
    r = _residuals_of_values(_physical(u, data.base, cfg.free), data, cfg)[0]
    return r.astype(u.dtype)  # the optimiser works in its own precision


def _value_and_jacobian(u, data, cfg):
    """Residuals and their Jacobian in one forward-mode pass (primal plus p tangents)."""
    jac, value = jax.jacfwd(lambda v: (_residuals(v, data, cfg),) * 2, has_aux=True)(u)
    return value, jac


def _residual_fn(cfg: _Config):
    """The residual function for optimistix: a custom JVP so that `jax.linearize` keeps the
    Jacobian as a matrix (one solve per step) instead of re-running the ODE per product."""

    @jax.custom_jvp
    def fn(u, data):
        return _residuals(u, data, cfg)

    @fn.defjvp
    def _jvp(primals, tangents):
        u, data = primals
        value, jac = _value_and_jacobian(u, data, cfg)
        return value, jac @ tangents[0]

    return fn


# ---------------------------------------------------------------------------------------------
# Optimisers: one stage, run inside jit (and vmap over recordings).


def _optimistix_stage(u0, data: _Data, cfg: _Config):
    if cfg.method == "levenberg_marquardt":
        solver = optx.LevenbergMarquardt(rtol=data.tol, atol=data.tol)
    else:
        solver = optx.GaussNewton(rtol=data.tol, atol=data.tol)
    residuals = _residual_fn(cfg)

    def fn(u, data):  # optimistix's solvers take functions returning (output, aux)
        return residuals(u, data), None

    options, tags = {"jac": "fwd"}, frozenset()
    f_struct = jax.eval_shape(lambda: residuals(u0, data))
    state0 = solver.init(fn, u0, data, options, f_struct, None, tags)
    # The solver state holds a jaxpr (the linearised residuals): carry only its arrays.
    dynamic0, static = eqx.partition(state0, eqx.is_array)
    history0 = jnp.full(cfg.max_steps, jnp.nan, u0.dtype)

    def cond(carry):
        u, dynamic, _, k = carry
        state = eqx.combine(dynamic, static)
        done, _ = solver.terminate(fn, u, data, options, state, tags)
        return (~done) & (k < cfg.max_steps)

    def body(carry):
        u, dynamic, history, k = carry
        u, state, _ = solver.step(fn, u, data, options, eqx.combine(dynamic, static), tags)
        loss = 0.5 * jnp.sum(state.f_info.residual**2)
        return u, eqx.filter(state, eqx.is_array), history.at[k].set(loss), k + 1

    u, dynamic, history, k = jax.lax.while_loop(cond, body, (u0, dynamic0, history0, 0))
    state = eqx.combine(dynamic, static)
    done, result = solver.terminate(fn, u, data, options, state, tags)
    code = FIT_RESULTS.where(
        done & (result == optx.RESULTS.successful),
        FIT_RESULTS.successful,
        FIT_RESULTS.where(done, FIT_RESULTS.optimiser_failed, FIT_RESULTS.max_steps_reached),
    )
    return u, history, k, code


def _optax_stage(u0, data: _Data, cfg: _Config):
    optimiser = optax.adam(cfg.learning_rate)
    history0 = jnp.full(cfg.max_steps, jnp.nan, u0.dtype)

    def loss_and_grad(u):
        r, jac = _value_and_jacobian(u, data, cfg)
        return 0.5 * jnp.sum(r**2), jac.T @ r

    def cond(carry):
        *_, k, done = carry
        return (~done) & (k < cfg.max_steps)

    def body(carry):
        u, opt_state, best, history, k, _ = carry
        loss, grad = loss_and_grad(u)
        updates, opt_state = optimiser.update(grad, opt_state, u)
        u_new = optax.apply_updates(u, updates)
        # Stop when the step is small relative to the coordinates (as optimistix's Cauchy test).
        done = jnp.max(jnp.abs(updates) / (data.tol + data.tol * jnp.abs(u))) < 1.0
        best = jnp.where(loss < best[0], jnp.concatenate([loss[None], u]), best)
        return u_new, opt_state, best, history.at[k].set(loss), k + 1, done

    best0 = jnp.concatenate([jnp.array([jnp.inf], u0.dtype), u0])
    carry = (u0, optimiser.init(u0), best0, history0, 0, jnp.array(False))
    u, _, best, history, k, done = jax.lax.while_loop(cond, body, carry)
    u = jnp.where(jnp.isfinite(best[0]), best[1:], u)
    code = FIT_RESULTS.where(done, FIT_RESULTS.successful, FIT_RESULTS.max_steps_reached)
    return u, history, k, code


def _stage(u0, data, cfg):
    if cfg.method == "adam":
        return _optax_stage(u0, data, cfg)
    return _optimistix_stage(u0, data, cfg)


def _finish(u, code, data: _Data, cfg: _Config):
    """Covariance, residuals and the fitted curve at the final coordinates."""
    value, jac_u = _value_and_jacobian(u, data, cfg)
    values = _physical(u, data.base, cfg.free)
    dp_du = jax.jacfwd(lambda v: jnp.stack([_physical(v, data.base, cfg.free)[n] for n in cfg.free]))(u)
    n_used = jnp.sum(data.weights > 0) + (jnp.sum(data.phi_weights > 0) if cfg.has_phi else 0)
    p = len(cfg.free)
    rss = jnp.sum(value**2)
    s2 = rss / jnp.maximum(n_used - p, 1)
    # J_p = J_u (du/dp); Sigma = s2 (J_p^T J_p)^{-1} = s2 G (J_u^T J_u)^{-1} G^T with G = dp/du.
    jtj = jac_u.T @ jac_u
    scale = 1.0 / jnp.sqrt(jnp.maximum(jnp.diag(jtj), 1e-300))
    inv_scaled = jnp.linalg.inv(scale[:, None] * jtj * scale[None, :])
    cov_u = s2 * scale[:, None] * inv_scaled * scale[None, :]
    cov = dp_du @ cov_u @ dp_du.T
    std = jnp.sqrt(jnp.maximum(jnp.diag(cov), 0.0))
    std = jnp.where(jnp.isfinite(std), std, jnp.inf)
    corr = cov / (std[:, None] * std[None, :])
    _, sol = _residuals_of_values(values, data, cfg)
    used = data.weights > 0
    theta_fit = jnp.where(sol.ts > sol.t_contact_loss, jnp.nan, sol.theta)
    residuals = jnp.where(used, theta_fit - data.theta_obs, jnp.nan)
    phi_fit = jnp.where(jnp.isfinite(theta_fit), sol.phi, jnp.nan)
    dphi = phi_fit - data.phi_obs
    phi_residuals = jnp.where(
        data.phi_weights > 0, jnp.arctan2(jnp.sin(dphi), jnp.cos(dphi)), jnp.nan
    )
    if not cfg.has_phi:
        phi_fit = jnp.full_like(phi_fit, jnp.nan)
    failed = jnp.any(used & ~jnp.isfinite(theta_fit))
    top, y0 = _assemble(values, data.base)
    vector = jnp.stack([values[n] for n in cfg.free])
    return dict(
        top=top, y0=y0, values=vector, std_errors=std, covariance=cov, correlation=corr,
        theta_fit=theta_fit, residuals=residuals, phi_fit=phi_fit, phi_residuals=phi_residuals,
        rms=jnp.sqrt(jnp.nanmean(jnp.where(used, residuals, jnp.nan) ** 2)),
        result=FIT_RESULTS.where(
            jnp.all(jnp.isfinite(u)),
            FIT_RESULTS.where(failed, FIT_RESULTS.simulation_failed, code),
            FIT_RESULTS.optimiser_failed,  # (Gauss-Newton can accept a step to nan)
        ),
    )


@eqx.filter_jit
def _run_stage(u0, data, cfg, batched):
    if batched:
        return jax.vmap(lambda u, d: _stage(u, d, cfg))(u0, data)
    return _stage(u0, data, cfg)


@eqx.filter_jit
def _run_finish(u, code, data, cfg, batched):
    if batched:
        return jax.vmap(lambda v, c, d: _finish(v, c, d, cfg))(u, code, data)
    return _finish(u, code, data, cfg)


# ---------------------------------------------------------------------------------------------
# Set-up in numpy: checks, masks, smoothing and the level ladder.


def _as_1d_times(ts) -> np.ndarray:
    arr = np.asarray(ts, dtype=float)
    if arr.ndim != 1 or arr.size < 2:
        raise ValueError(f"ts must be a 1-d array of at least 2 times, got shape {arr.shape}.")
    if not np.all(np.isfinite(arr)):
        raise ValueError("ts must hold finite times (NaN or inf found); mark missing data with "
                         "NaN in theta_obs instead.")
    if np.any(np.diff(arr) <= 0):
        raise ValueError("ts must be strictly increasing.")
    return arr


def _observations(name, obs, n) -> np.ndarray:
    arr = np.asarray(obs, dtype=float)
    if arr.ndim not in (1, 2) or arr.shape[-1] != n:
        raise ValueError(
            f"{name} must have shape (N,) or (batch, N) with N = len(ts) = {n}, got {arr.shape}."
        )
    if np.any(np.isinf(arr)):
        raise ValueError(f"{name} holds inf; use NaN to mark missing samples (they are masked).")
    return arr


def _smoother(ts: np.ndarray):
    """A Gaussian kernel from the data times onto a uniform grid, as a band: for each grid point
    the indices of the samples within 4 kernel widths and their weights (memory G x M, with M
    the most samples in one band, not G x N)."""
    span = ts[-1] - ts[0]
    width = max(span / 80.0, 3.0 * float(np.median(np.diff(ts))))
    num = int(min(max(np.ceil(4 * span / width) + 1, 50), 2000))
    grid = np.linspace(ts[0], ts[-1], num)
    lo = np.searchsorted(ts, grid - 4 * width, side="left")
    hi = np.searchsorted(ts, grid + 4 * width, side="right")
    band = int(np.max(hi - lo))
    index = np.minimum(lo[:, None] + np.arange(band)[None, :], ts.size - 1)
    inside = (lo[:, None] + np.arange(band)[None, :]) < hi[:, None]
    weight = np.where(inside, np.exp(-0.5 * ((grid[:, None] - ts[index]) / width) ** 2), 0.0)
    return (index, weight), grid


def _ladder(theta: np.ndarray, mask: np.ndarray, band, grid):
    """Levels between the smoothed start and maximum, and the data's first crossing times.

    Returns the levels, their times and whether the record rises enough (0.3 rad) to use them.
    """
    index, weight = band
    y = mask * np.nan_to_num(theta)
    smooth = np.sum(weight * y[index], -1) / np.maximum(np.sum(weight * mask[index], -1), 1e-300)
    start, top = smooth[0], smooth.max()
    rises = top - start > 0.3
    lo, hi = start + 0.1 * (top - start), top - 0.1 * (top - start)
    levels = np.linspace(lo, hi, NUM_LEVELS) if rises else np.zeros(NUM_LEVELS)
    times = np.asarray(_first_crossings(jnp.asarray(smooth), jnp.asarray(grid), jnp.asarray(levels)))
    return levels, times, rises


def _window_ends(ts: np.ndarray) -> list[float]:
    """Ends of the growing windows: the first holds 1/64 of the record (at least 10 samples),
    each next one twice as much, the last the whole record. A short first window keeps the
    nutation's phase error (it grows with time and with the error in the spin) under a cycle."""
    span = ts[-1] - ts[0]
    width = max(span / 64, ts[min(10, ts.size - 1)] - ts[0])
    ends = []
    while width < span:
        ends.append(float(ts[0] + width))
        width *= 2
    return ends + [float(ts[-1])]


def _moving_rms(ts: np.ndarray, residuals: np.ndarray, width: float) -> np.ndarray:
    """RMS of the finite residuals within width/2 of each sample (nan where fewer than 3)."""
    finite = np.isfinite(residuals)
    sq = np.cumsum(np.concatenate([[0.0], np.where(finite, residuals, 0.0) ** 2]))
    count = np.cumsum(np.concatenate([[0], finite.astype(int)]))
    lo = np.searchsorted(ts, ts - width / 2, side="left")
    hi = np.searchsorted(ts, ts + width / 2, side="right")
    num = count[hi] - count[lo]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(num >= 3, np.sqrt((sq[hi] - sq[lo]) / np.maximum(num, 1)), np.nan)


def _describes_until(ts: np.ndarray, residuals: np.ndarray, noise: float) -> float:
    """End of the initial stretch where the moving RMS (over 5% of the record) of the residuals
    stays below 3 x `noise`."""
    rms = _moving_rms(ts, residuals, 0.05 * (ts[-1] - ts[0]))
    if not np.isfinite(noise) or np.all(np.isnan(rms)):
        return float("nan")
    bad = np.nonzero(rms > 3.0 * noise)[0]
    return float(ts[-1]) if bad.size == 0 else float(ts[max(bad[0] - 1, 0)])


def _noise_level(ts: np.ndarray, residuals: np.ndarray) -> float:
    """The residual level of the best-described stretches: the 10th percentile of the moving RMS
    over 5% of the record. For a model that describes the data, this is the noise (about 0.8
    of its standard deviation at 40 samples a window)."""
    rms = _moving_rms(ts, residuals, 0.05 * (ts[-1] - ts[0]))
    return float(np.nanpercentile(rms, 10)) if np.any(np.isfinite(rms)) else float("nan")


def _check_guess(top_guess, y0_guess, free, batch):
    if not isinstance(top_guess, TippeTop):
        raise TypeError(f"top_guess must be a tippejax.TippeTop, got {type(top_guess).__name__}.")
    if not isinstance(y0_guess, State):
        raise TypeError(
            f"y0_guess must be a tippejax.State (see initial_state), got {type(y0_guess).__name__}."
        )
    fields = {f: np.asarray(getattr(top_guess, f), dtype=float) for f in TOP_FIELDS}
    for f, v in fields.items():
        if not np.all(np.isfinite(v)):
            raise ValueError(f"top_guess.{f} is not finite.")
        if v.ndim > 1 or (v.ndim == 1 and (batch is None or v.shape[0] != batch)):
            raise ValueError(
                f"top_guess.{f} has shape {v.shape}: a guess is one top, or one per recording "
                f"when theta_obs has shape (batch, N)."
            )
    for failed, message in _checks(*(fields[f] for f in ("m", "R", "eps", "A", "C", "g", "mu"))):
        if np.any(failed):
            raise ValueError(f"top_guess is not a valid top: {message}")
    for name in ("m", "R", "g", "mu"):
        if name in free and np.any(fields[name] == 0):
            raise ValueError(f"{name!r} is free but its guess is 0; give a positive guess.")
    launch = {k: np.asarray(v, dtype=float) for k, v in _launch_of(y0_guess).items()}
    theta0 = launch["theta0"]
    if np.any(np.sin(theta0) < 1e-6):
        raise ValueError(
            "y0_guess is at a pole (theta = 0 or pi), where the precession rate is undefined and "
            "a top does not rise; launch the guess at a small tilt instead."
        )
    for k, v in launch.items():
        if not np.all(np.isfinite(v)):
            raise ValueError(f"y0_guess gives a non-finite launch quantity {k}.")
    if "spin" in free and np.any(launch["spin"] == 0):
        raise ValueError("'spin' is free but the guess has zero spin: give a non-zero guess "
                         "(its sign is kept; theta alone cannot tell the spin's direction).")
    if "A" in free and np.any(fields["A"] / fields["C"] <= 0.5):
        raise ValueError("'A' is free but the guess has A/C = 1/2: give A/C > 1/2.")
    if "C" in free and "A" not in free and np.any(fields["C"] >= 2 * fields["A"]):
        raise ValueError("'C' is free but the guess has C >= 2A, which no rigid body has.")
    return fields, launch


def fit(
    top_guess: TippeTop,
    y0_guess: State,
    ts: ArrayLike,
    theta_obs: ArrayLike,
    *,
    free: Sequence[str] = ("mu", "eps", "spin"),
    phi_obs: ArrayLike | None = None,
    model: Literal["full", "so3", "routhian"] = "full",
    method: Literal["levenberg_marquardt", "gauss_newton", "adam"] = "levenberg_marquardt",
    strategy: Literal["levels", "windows", "plain"] = "levels",
    t0: float | None = None,
    weights: ArrayLike | None = None,
    sigma: float | None = None,
    max_steps: int = 200,
    tol: float = 1e-6,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    solver: diffrax.AbstractSolver | None = None,
    sim_max_steps: int = 100_000,
    learning_rate: float = 0.02,
    trim: bool = True,
) -> FitResult:
    r"""Fit free parameters of the top and its launch to a measured tilt $\theta(t_k)$.

    **Arguments:**

    - `top_guess`: a `TippeTop`; its fields give the fixed parameters and the starting guess.
    - `y0_guess`: the `State` at time `t0` (see `initial_state`); gives the launch quantities.
    - `ts`: the observation times (strictly increasing, finite), shape `(N,)`.
    - `theta_obs`: the measured tilt (rad), shape `(N,)`, or `(batch, N)` to fit several
      recordings at once (vmapped: one compilation; all recordings step together, so the
      batch runs as long as its slowest member: this pays on an accelerator, while on a CPU
      a loop of single fits was measured faster, see `benchmarks/RESULTS.md`). **NaN marks a
      missing sample, which is masked** (left out of the loss), e.g. video frames where the top
      was not found.
    - `free`: names of the parameters to fit: top fields `m, R, eps, A, C, g, mu` and launch
      quantities `theta0, spin, theta_dot, phi_dot, vx, vy`. The spin keeps the sign of its
      guess (theta alone cannot tell its direction).
    - `phi_obs`: optional precession angle (rad, unwrapped or not; differences are wrapped),
      weighted by $\sin\theta^{obs}$ (the axis' horizontal displacement), NaN masked.
    - `model`: level of model to fit with, `"full"`, `"so3"` or `"routhian"`.
    - `method`: `"levenberg_marquardt"` (default; `optimistix.LevenbergMarquardt`),
      `"gauss_newton"` (`optimistix.GaussNewton`) or `"adam"` (`optax.adam` at
      `learning_rate` in the unconstrained coordinates). Jacobians by forward mode.
    - `strategy`: `"levels"` (default: level-crossing times of the smoothed tilt first, then the
      record), `"windows"` (continuation: the first 20%, 40%, ... of the record in turn) or
      `"plain"` (the whole record at once).
    - `t0`: time of `y0_guess` (default `ts[0]`; must be `<= ts[0]`).
    - `weights`: optional non-negative weight per sample (e.g. `1/sigma_k^2`).
    - `sigma`: the noise of `theta_obs` (rad), if known: the level `describes_until` judges the
      residuals against (default: estimated from the residuals, see `FitResult.noise`).
    - `max_steps`: optimiser steps per stage. `tol`: the optimiser's relative and absolute
      tolerance on the parameters and the loss.
    - `rtol`, `atol`, `solver`, `sim_max_steps`: passed to `simulate` for every trial.
    - `trim`: for a record the model does not describe to its end (a real top whose stem
      lands, data from another engine), fit again on the part it describes: after each fit,
      `describes_until` on the whole record becomes the end of the next fit's window, until it
      moves by less than 2% of the record (at most 4 fits). `FitResult.fitted_until` says
      where the fit ended; residuals are reported on the whole record. Costs nothing extra for
      a record the first fit describes.

    Every trial's simulation runs with `throw=False`. Save times after a trial stops (contact
    lost, the $R_n$ singularity, max steps) get the finite residual `FAILED_RESIDUAL` ($\pi$),
    so such a trial has a large loss and is rejected, never a NaN.

    **Returns:** a `FitResult`, with standard errors from the Gauss-Newton covariance
    $s^2 (J^\top J)^{-1}$ scaled by the residual variance $s^2 = \mathrm{RSS}/(N - p)$.
    """
    if trim:
        return _trimmed_fit(
            top_guess, y0_guess, ts, theta_obs, free=free, phi_obs=phi_obs, model=model,
            method=method, strategy=strategy, t0=t0, weights=weights, sigma=sigma,
            max_steps=max_steps, tol=tol, rtol=rtol, atol=atol, solver=solver,
            sim_max_steps=sim_max_steps, learning_rate=learning_rate,
        )
    free = tuple(free)
    unknown = [n for n in free if n not in FREE_NAMES]
    if unknown:
        raise ValueError(f"Unknown names in free: {unknown}; choose from {FREE_NAMES}.")
    if not free:
        raise ValueError(f"free is empty; name at least one of {FREE_NAMES}.")
    if len(set(free)) != len(free):
        raise ValueError(f"free names a parameter twice: {free}.")
    if model not in ("full", "so3", "routhian"):
        allowed = tuple(m for m in MODELS if m in ("full", "so3", "routhian"))
        raise ValueError(f"fit supports model in {allowed}, got {model!r}.")
    if method not in METHODS:
        raise ValueError(f"Unknown method {method!r}; choose one of {METHODS}.")
    if strategy not in STRATEGIES:
        raise ValueError(f"Unknown strategy {strategy!r}; choose one of {STRATEGIES}.")
    if not (isinstance(max_steps, (int, np.integer)) and max_steps > 0):
        raise ValueError(f"max_steps must be a positive integer, got {max_steps!r}.")
    if not tol > 0:
        raise ValueError(f"tol must be positive, got {tol}.")
    if sigma is not None and not (np.isfinite(sigma) and sigma > 0):
        raise ValueError(f"sigma must be a positive noise level (rad), got {sigma}.")
    ts_np = _as_1d_times(ts)
    n = ts_np.size
    obs = _observations("theta_obs", theta_obs, n)
    batch = obs.shape[0] if obs.ndim == 2 else None
    obs2 = obs.reshape(-1, n)
    phi2 = None
    if phi_obs is not None:
        phi_arr = _observations("phi_obs", phi_obs, n)
        if phi_arr.shape != obs.shape:
            raise ValueError(f"phi_obs has shape {phi_arr.shape}, theta_obs {obs.shape}.")
        phi2 = phi_arr.reshape(-1, n)
    if weights is None:
        w2 = np.ones_like(obs2)
    else:
        w = np.broadcast_to(np.asarray(weights, dtype=float), obs.shape).reshape(-1, n)
        if np.any(~np.isfinite(w)) or np.any(w < 0):
            raise ValueError("weights must be finite and non-negative.")
        w2 = w.copy()
    mask2 = np.isfinite(obs2) & (w2 > 0)
    for b in range(obs2.shape[0]):
        if mask2[b].sum() <= len(free):
            raise ValueError(
                f"Recording {b} has {mask2[b].sum()} usable samples (not NaN) for "
                f"{len(free)} free parameters; a fit needs more samples than parameters."
            )
    t0 = float(ts_np[0]) if t0 is None else float(t0)
    if not t0 <= ts_np[0]:
        raise ValueError(f"t0 = {t0} must not be later than the first observation ts[0] = {ts_np[0]}.")
    fields, launch = _check_guess(top_guess, y0_guess, free, batch)

    dtype = jnp.result_type(top_guess.m)
    bsize = obs2.shape[0]
    band, grid = _smoother(ts_np)
    ladders = [_ladder(obs2[b], mask2[b].astype(float), band, grid) for b in range(bsize)]
    rises = np.array([lad[2] for lad in ladders])

    def per_rec(x):  # a field of the guess: scalar or (batch,)
        x = np.asarray(x, dtype=float)
        return jnp.asarray(np.broadcast_to(x, (bsize,)), dtype)

    base = _Base(
        top={f: per_rec(v) for f, v in fields.items()},
        launch={k: per_rec(v) for k, v in launch.items()},
    )
    data = _Data(
        base=base,
        ts=jnp.asarray(np.broadcast_to(ts_np, (bsize, n)), dtype),
        t0=per_rec(t0),
        t_end=per_rec(ts_np[-1]),
        theta_obs=jnp.asarray(np.where(mask2, obs2, 0.0), dtype),
        weights=jnp.asarray(np.where(mask2, w2, 0.0), dtype),
        mask=jnp.asarray(mask2, dtype),
        phi_obs=jnp.asarray(np.nan_to_num(phi2) if phi2 is not None else np.zeros_like(obs2), dtype),
        phi_weights=jnp.asarray(
            np.where(np.isfinite(phi2) & mask2, w2, 0.0) if phi2 is not None else np.zeros_like(obs2),
            dtype,
        ),
        smoother_index=jnp.asarray(np.broadcast_to(band[0], (bsize,) + band[0].shape)),
        smoother_weight=jnp.asarray(np.broadcast_to(band[1], (bsize,) + band[1].shape), dtype),
        grid=jnp.asarray(np.broadcast_to(grid, (bsize,) + grid.shape), dtype),
        levels=jnp.asarray(np.stack([lad[0] for lad in ladders]), dtype),
        t_levels=jnp.asarray(np.stack([lad[1] for lad in ladders]), dtype),
        level_weight=jnp.zeros((bsize,), dtype),
        rtol=per_rec(rtol),
        atol=per_rec(atol),
        tol=per_rec(tol),
    )
    cfg = _Config(
        free=free, model=model, method=method, max_steps=int(max_steps),
        sim_max_steps=int(sim_max_steps), has_phi=phi2 is not None, solver=solver,
        learning_rate=float(learning_rate),
    )
    batched = batch is not None
    if not batched:
        data = jax.tree_util.tree_map(lambda x: x[0], data)

    def with_stage(theta_weight_mask, t_end, level_weight, stage_tol=_STAGE_TOL):
        w = jnp.asarray(np.where(mask2 & theta_weight_mask, w2, 0.0), dtype)
        pw = data.phi_weights
        if phi2 is not None:
            pw = jnp.asarray(
                np.where(np.isfinite(phi2) & mask2 & theta_weight_mask, w2, 0.0), dtype
            )
        lw = jnp.asarray(np.broadcast_to(level_weight, (bsize,)), dtype)
        te, to = per_rec(t_end), per_rec(max(stage_tol, tol))
        if not batched:
            w, pw, lw, te, to = w[0], pw[0], lw[0], te[0], to[0]
        return eqx.tree_at(
            lambda d: (d.weights, d.phi_weights, d.level_weight, d.t_end, d.tol),
            data, (w, pw, lw, te, to),
        )

    everything = np.ones((bsize, n), bool)
    stages = []
    if strategy == "levels":
        # Stage 1: level-crossing times only (records that do not rise skip it: weight 0, and
        # their theta residuals are then used from the start). Then the record in growing
        # windows, the level times still in the loss: the nutation's phase error grows with
        # time, so even 1% off in the spin puts a long record in another valley of the loss,
        # while an early window alone leaves directions free that the levels pin down. Last,
        # the whole record alone (the loss the covariance is about).
        stage1_theta = np.broadcast_to(~rises[:, None], (bsize, n))
        stages.append(with_stage(stage1_theta, ts_np[-1], rises.astype(float)))
        if rises.any():  # (a record that does not rise was fitted whole in stage 1)
            for t_end in _window_ends(ts_np)[:-1]:
                inside = np.broadcast_to(ts_np <= t_end + 1e-12, (bsize, n))
                stages.append(with_stage(inside, ts_np[-1], rises.astype(float)))
        stages.append(with_stage(everything, ts_np[-1], 0.0, tol))
    elif strategy == "windows":
        ends = _window_ends(ts_np)
        for t_end in ends:
            inside = np.broadcast_to(ts_np <= t_end + 1e-12, (bsize, n))
            stages.append(with_stage(inside, t_end, 0.0, tol if t_end == ends[-1] else _STAGE_TOL))
    else:
        stages.append(with_stage(everything, ts_np[-1], 0.0, tol))

    p = len(free)
    # The optimiser runs in float64 when JAX has it, whatever the top's precision (optimistix's
    # damping terms are float64 then, and must match the coordinates).
    u = jnp.zeros((bsize, p) if batched else (p,), jnp.result_type(float))
    histories, counts = [], []
    code = None
    for stage_data in stages:
        u, history, k, code = _run_stage(u, stage_data, cfg, batched)
        histories.append(history)
        counts.append(k)
    final = stages[-1]
    out = _run_finish(u, code, final, cfg, batched)
    hist = jnp.concatenate(histories, axis=-1)
    stage_ends = jnp.stack([jnp.asarray(c) for c in counts], axis=-1)
    stage_ends = jnp.cumsum(stage_ends, axis=-1)
    # Compact the histories: each stage's steps one after the other, nan-padded at the end.
    hist_np = np.asarray(hist).reshape(bsize, len(stages), int(max_steps))
    counts_np = np.asarray(jnp.stack([jnp.asarray(c) for c in counts], -1)).reshape(bsize, -1)
    packed = np.full((bsize, len(stages) * int(max_steps)), np.nan)
    for b in range(bsize):
        row = np.concatenate([hist_np[b, s, : counts_np[b, s]] for s in range(len(stages))])
        packed[b, : row.size] = row
    code = out["result"]
    residuals = np.asarray(out["residuals"]).reshape(bsize, n)
    if sigma is None:
        noise = np.array([_noise_level(ts_np, residuals[b]) for b in range(bsize)])
    else:
        noise = np.broadcast_to(np.asarray(sigma, dtype=float), (bsize,)).copy()
    describes = np.array([_describes_until(ts_np, residuals[b], noise[b]) for b in range(bsize)])
    theta_obs_out = np.where(mask2, obs2, np.nan)
    ts_out = np.broadcast_to(ts_np, (bsize, n))
    if not batched:
        packed, describes, theta_obs_out = packed[0], describes[0], theta_obs_out[0]
        noise, ts_out = noise[0], ts_out[0]
    return FitResult(
        top=out["top"], y0=out["y0"], values=out["values"], std_errors=out["std_errors"],
        covariance=out["covariance"], correlation=out["correlation"],
        loss_history=jnp.asarray(packed, dtype), stage_ends=stage_ends,
        ts=jnp.asarray(ts_out, dtype), theta_obs=jnp.asarray(theta_obs_out, dtype),
        theta_fit=out["theta_fit"], residuals=out["residuals"], rms=out["rms"],
        describes_until=jnp.asarray(describes, dtype), noise=jnp.asarray(noise, dtype),
        fitted_until=jnp.asarray(np.broadcast_to(ts_np[-1], describes.shape), dtype),
        phi_fit=out["phi_fit"], phi_residuals=out["phi_residuals"],
        converged=code == FIT_RESULTS.successful, result=code, num_steps=sum(counts), free=free, model=model, method=method, strategy=strategy,
    )


_TRIM_ROUNDS = 4


def _trimmed_fit(top_guess, y0_guess, ts, theta_obs, **kwargs) -> FitResult:
    """`fit` on the part of the record the model describes (see `trim` in `fit`)."""
    res = fit(top_guess, y0_guess, ts, theta_obs, trim=False, **kwargs)
    ts_np = np.asarray(ts, dtype=float)
    obs = np.asarray(theta_obs, dtype=float)
    phi = kwargs.get("phi_obs")
    phi = None if phi is None else np.asarray(phi, dtype=float)
    obs2 = obs.reshape(-1, ts_np.size)
    span = ts_np[-1] - ts_np[0]
    shortest = ts_np[0] + 0.1 * span
    ends = np.full(obs2.shape[0], ts_np[-1])

    def on_whole_record(result):
        theta_fit = np.asarray(result.theta_fit).reshape(obs2.shape)
        residuals = theta_fit - obs2  # nan where the data are missing or the run failed
        noise = np.asarray(result.noise, dtype=float).reshape(-1)
        describes = np.array([
            _describes_until(ts_np, residuals[b], noise[b]) for b in range(obs2.shape[0])
        ])
        return residuals, describes

    residuals, describes = on_whole_record(res)
    for _ in range(_TRIM_ROUNDS - 1):
        new_ends = np.where(np.isfinite(describes), np.maximum(describes, shortest), ends)
        if np.all(np.abs(new_ends - ends) <= 0.02 * span):
            break
        ends = new_ends
        cut = ts_np[None, :] > ends[:, None]
        masked = np.where(cut, np.nan, obs2).reshape(obs.shape)
        if phi is not None:
            kwargs["phi_obs"] = np.where(cut, np.nan, phi.reshape(obs2.shape)).reshape(obs.shape)
        res = fit(top_guess, y0_guess, ts, masked, trim=False, **kwargs)
        residuals, describes = on_whole_record(res)
    dtype = res.rms.dtype
    shape = np.shape(np.asarray(res.rms))
    return eqx.tree_at(
        lambda r: (r.theta_obs, r.residuals, r.describes_until, r.fitted_until),
        res,
        (
            jnp.asarray(obs, dtype),
            jnp.asarray(residuals.reshape(obs.shape), dtype),
            jnp.asarray(describes.reshape(shape), dtype),
            jnp.asarray(ends.reshape(shape), dtype),
        ),
    )
