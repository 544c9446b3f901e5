r"""The optimisers that run one stage of a fit, inside `jit` (and `vmap` over recordings).

Levenberg-Marquardt and Gauss-Newton come from optimistix and step inside a `lax.while_loop`
that also records the loss after each step; Adam comes from optax. Each stage starts from the
coordinates the previous one ended at and stops on the optimiser's own tolerance (`Data.tol`)
or after `Config.max_steps` steps (or the smaller budget `Data.steps` of a stage that only
ranks or seeds: a budget is a value, not a new compilation).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
import optimistix as optx

from .problem import Config, Data, residual_fn, value_and_jacobian
from .result import FIT_RESULTS


def optimistix_stage(u0, data: Data, cfg: Config):
    if cfg.method == "levenberg_marquardt":
        solver = optx.LevenbergMarquardt(rtol=data.tol, atol=data.tol)
    else:
        solver = optx.GaussNewton(rtol=data.tol, atol=data.tol)
    residuals = residual_fn(cfg)

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
        return (~done) & (k < cfg.max_steps) & (k < data.steps)

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
    if cfg.method == "adam":
        return optax_stage(u0, data, cfg)
    return optimistix_stage(u0, data, cfg)
