"""`outcome_map(model="auto")`: each launch at the cheapest adequate level."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._analysis.potential import effective_potential_d2_closed_form
from .._auto import choose_model
from .._engine.solver_choice import default_solver
from .._invariants import jellet
from .._models.levels import LEVELS
from .._outcome import classify_end
from .._solution import RESULTS
from .._state import euler_angles, initial_state
from .._top import TippeTop
from .stages import staged_outcomes


def auto_models(top: TippeTop, flat_theta, flat_spin, tolerance) -> tuple[list[str], np.ndarray]:
    """The level `model="auto"` picks for each launch: `choose_model`'s rule, evaluated once
    per class of launches that it cannot tell apart (regime x whether the gyroscopic level
    accepts the launch), since the rule depends on nothing else."""
    if tolerance is None:
        return ["full"], np.zeros(flat_theta.size, int)
    y0s = initial_state(top, jnp.asarray(flat_theta), jnp.asarray(flat_spin))
    J = np.asarray(jax.vmap(lambda y: jellet(top, y))(y0s))
    up = np.asarray(effective_potential_d2_closed_form(top, 0.0, J)) > 0
    down = np.asarray(effective_potential_d2_closed_form(top, np.pi, J)) > 0
    accepts = np.asarray(jax.vmap(lambda y: LEVELS["gyroscopic"].in_chart(top, y))(y0s))
    key = up.astype(int) * 4 + down.astype(int) * 2 + accepts.astype(int)
    models: list[str] = []
    index = np.zeros(flat_theta.size, int)
    for k in np.unique(key):
        members = np.flatnonzero(key == k)
        y_rep = jax.tree_util.tree_map(lambda x: x[members[0]], y0s)
        name = choose_model(top, y_rep, tolerance=tolerance)
        if name not in models:
            models.append(name)
        index[members] = models.index(name)
    return models, index


@eqx.filter_jit
def _classify_all(top, J, theta_final, result, settle_tol):
    """`classify_end` of every launch; `result` holds `RESULTS` codes as integers."""
    item = type(RESULTS.successful)

    def one(j, theta, code):
        code = item(code.astype(RESULTS.successful._value.dtype), RESULTS)
        return classify_end(top, j, theta, code, settle_tol=settle_tol)

    return jax.vmap(one)(J, theta_final, result)


def staged_map(
    top: TippeTop, flat_theta, flat_spin, t1, *, rtol, atol, solver, max_steps, settle_tol, devices
):
    """`outcome_map(model="auto")` with `tolerance=None`: the stages of `stages.py`.

    **Returns:** `(fields, routes, index)`: the per-launch fields of an `OutcomeMap`, the
    distinct routes (levels in the order they ran) and each launch's index into them."""
    dtype = jnp.result_type(top.m)
    y0 = initial_state(top, jnp.asarray(flat_theta, dtype), jnp.asarray(flat_spin, dtype))
    if solver is None:
        solver, slow_solver = default_solver(top), default_solver(top, slow_flow=True)
    else:
        slow_solver = solver
    run = staged_outcomes(
        top,
        y0,
        t1,
        rtol=rtol,
        atol=atol,
        solver=solver,
        slow_solver=slow_solver,
        max_steps=max_steps,
        devices=devices,
    )
    J = np.asarray(jax.vmap(lambda y: jellet(top, y))(y0))
    theta_final = np.asarray(
        jax.vmap(lambda y: euler_angles(y)[0])(jax.tree_util.tree_map(jnp.asarray, run["state"]))
    )
    outcome, settled, expected = _classify_all(
        top, jnp.asarray(J), jnp.asarray(theta_final), jnp.asarray(run["result"]), float(settle_tol)
    )
    fields = dict(
        outcome=np.asarray(outcome),
        settled=np.asarray(settled),
        theta_final=theta_final,
        theta_expected=np.asarray(expected),
        t_invert=run["t_invert"],
        t_contact_loss=run["t_contact_loss"],
        t_final=run["t_final"],
        jellet=J,
        result=run["result"].astype(np.int8),
        num_steps=run["num_steps"].astype(np.int32),
    )
    routes, index = np.unique(run["route"], return_inverse=True)
    return fields, [str(r) for r in routes], index
