r"""The optimisers that run one stage of a fit.

Levenberg-Marquardt and Gauss-Newton (`least_squares`) step on the host, in numpy, around one
compiled program: the residuals and their Jacobian at a point (`Setup.evaluate`, the same
program `finish` takes the covariance from). The p x p algebra of a step is nothing beside a
simulation, and the fit then compiles one program with a forward-mode solve in it instead of
two (an optimiser loop around the solve was a second program as large as the first, 8-11 s of
XLA compilation in a new process). The steps are optimistix's: `optx.LevenbergMarquardt`
(a damped Newton descent, `(J^T J + I/s) d = -J^T r` solved as a least-squares problem by
QR, in the classical trust region: ratio cut-offs 0.01 and 0.99, step size x3.5 or x0.25,
the first step always accepted) and `optx.GaussNewton` (every step accepted, undamped),
both stopping on optimistix's Cauchy test at `rtol = atol = Data.tol` in the max norm
(`tests/test_fit.py` checks the iterates against optimistix's own solver). Recordings of a
batch step side by side, each with its own damping and stopping test.

Adam comes from optax and steps inside a `lax.while_loop` (`optax_stage`). Each stage starts
from the coordinates the previous one ended at and stops on the optimiser's tolerance
(`Data.tol`) or after `Config.max_steps` steps (or the smaller budget `Data.steps` of a stage
that only ranks or seeds: a budget is a value, not a new compilation).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax

from .problem import Config, Data, value_and_jacobian
from .result import FIT_RESULTS

# optimistix's ClassicalTrustRegion
_LOW_CUTOFF, _HIGH_CUTOFF, _LOW_CONSTANT, _HIGH_CONSTANT = 0.01, 0.99, 0.25, 3.5


def _cauchy(tol, y, y_diff, f, f_diff) -> bool:
    """optimistix's `cauchy_termination` in the max norm, with rtol = atol = tol."""
    y_ok = np.max(np.abs(y_diff) / (tol + tol * np.abs(y))) < 1
    f_ok = np.max(np.abs(f_diff) / (tol + tol * np.abs(f))) < 1
    return bool(y_ok and f_ok)


def _damped_step(jac, r, step_size, dtype) -> np.ndarray:
    """The damped Newton step `d` of least squares `[J; sqrt(lam) I] d = [r; 0]`, lam = 1/s
    (optimistix's `damped_newton_step`, solved by QR); the step is `-d`."""
    p = jac.shape[-1]
    eps = np.finfo(dtype).eps
    lam = 1.0 / step_size if step_size > eps else np.finfo(dtype).max
    a = np.concatenate([jac, np.sqrt(lam) * np.eye(p)])
    b = np.concatenate([r, np.zeros(p)])
    q, rr = np.linalg.qr(a)
    return np.linalg.solve(rr, q.T @ b)


def least_squares(evaluate: Callable, u0, *, tol, steps, max_steps: int, damped: bool = True):
    """Levenberg-Marquardt (`damped`) or Gauss-Newton from `u0` (shape `(B, p)`), each of
    the B recordings on its own, with `evaluate(u) -> (residuals (B, M), Jacobian (B, M, p))`
    called once per step for the whole batch (a recording that has stopped keeps its point).

    Returns the end points (the last accepted ones), the loss at the accepted point after each
    step (nan after the last), the step counts and the codes (`FIT_RESULTS` values)."""
    u0 = np.asarray(u0)
    dtype = u0.dtype
    bsize, p = u0.shape
    tol = np.broadcast_to(np.asarray(tol, float), (bsize,))
    budget = np.minimum(np.broadcast_to(np.asarray(steps, float), (bsize,)), max_steps)
    y, y_eval = u0.copy(), u0.copy()
    r = jac = None
    step_size = np.ones(bsize)
    first = np.ones(bsize, bool)
    done = np.zeros(bsize, bool)
    failed = np.zeros(bsize, bool)
    count = np.zeros(bsize, int)
    history = np.full((bsize, max_steps), np.nan, dtype)
    while True:
        active = ~done & (count < budget)
        if not active.any():
            break
        r_eval, jac_eval = (np.asarray(x, float) for x in evaluate(y_eval))
        if r is None:
            r, jac = np.zeros_like(r_eval), np.zeros_like(jac_eval)
        for b in np.flatnonzero(active):
            re, je = r_eval[b], jac_eval[b]
            if damped:
                diff = y_eval[b] - y[b]
                predicted = 0.5 * (np.sum((jac[b] @ diff + r[b]) ** 2) - np.sum(r[b] ** 2))
                change = 0.5 * np.sum(re**2) - 0.5 * np.sum(r[b] ** 2)
                accept = bool(change <= _LOW_CUTOFF * predicted) or first[b]
                good = (change < _HIGH_CUTOFF * predicted) and predicted < 0 and not first[b]
                step_size[b] *= (_HIGH_CONSTANT if good else 1.0) if accept else _LOW_CONSTANT
            else:
                accept = True
            if accept:
                done[b] = _cauchy(tol[b], y_eval[b], y_eval[b] - y[b], re, re - r[b])
                y[b], r[b], jac[b] = y_eval[b], re, je
            first[b] = False
            with np.errstate(all="ignore"):
                try:
                    if damped:
                        d = _damped_step(jac[b], r[b], step_size[b], dtype)
                    else:
                        d = np.linalg.lstsq(jac[b], r[b], rcond=None)[0]
                except np.linalg.LinAlgError:
                    d = np.full(p, np.nan)
            if not np.all(np.isfinite(d)) or not np.all(np.isfinite(r[b])):
                done[b] = failed[b] = True  # a singular system or a non-finite loss
            y_eval[b] = y[b] - d
            history[b, count[b]] = 0.5 * np.sum(r[b] ** 2)
            count[b] += 1
    codes = np.where(
        done & ~failed,
        FIT_RESULTS.successful._value,
        np.where(done, FIT_RESULTS.optimiser_failed._value, FIT_RESULTS.max_steps_reached._value),
    ).astype(np.asarray(FIT_RESULTS.successful._value).dtype)
    return y, history, count, codes


def optax_stage(u0, data: Data, cfg: Config):
    optimiser = optax.adam(cfg.learning_rate)
    history0 = jnp.full(cfg.max_steps, jnp.nan, u0.dtype)

    def loss_and_grad(u):
        r, jac = value_and_jacobian(u, data, cfg)
        return 0.5 * jnp.sum(r**2), jac.T @ r

    def cond(carry):
        *_, k, done = carry
        return (~done) & (k < cfg.max_steps) & (k < data.steps)

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


def optimise(u0, data, cfg):
    """The in-program optimisers (Adam); Levenberg-Marquardt and Gauss-Newton run on the
    host (`least_squares`)."""
    if cfg.method != "adam":
        raise ValueError(f"{cfg.method!r} runs on the host (least_squares), not in a program.")
    return optax_stage(u0, data, cfg)
