"""A batch whose members share their steps (`simulate_batch(..., steps="shared")`)."""

from __future__ import annotations

import dataclasses

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from .._engine.chain import run_chain
from .._engine.packing import SHARED_PACK_WIDTH
from .._engine.shared import top_axes
from .._engine.solver_choice import default_solver
from .._engine.watch import EVENT_PIECES
from .._models.levels import LEVELS
from .._outcome import classify
from .._top import TippeTop
from .checks import check_run_options, save_times, tolerances_for
from .programs import outputs

SHARED_MODELS = ("full", "so3")
"""The levels a batch with shared steps runs (`simulate_batch(..., steps="shared")`): the
levels that are one segment."""

SHARED_OPTIONS = (
    "model",
    "saveat",
    "t0",
    "rtol",
    "atol",
    "solver",
    "max_steps",
    "on_contact_loss",
    "summary",
    "event_pieces",
    "body",
)
"""The options of `simulate` a batch with shared steps takes."""


def shared_run_options(
    top: TippeTop,
    t1,
    *,
    model="full",
    saveat=None,
    t0=0.0,
    rtol=1e-8,
    atol=1e-10,
    solver=None,
    max_steps=1_000_000,
    on_contact_loss="stop",
    summary=False,
    event_pieces=EVENT_PIECES,
    body=None,
):
    """`simulate`'s checks and defaults for a batch with shared steps (a concrete `top`, one
    or a batch). Returns the arrays of the run (`ts` None in summary mode, `t0`, `t1`,
    `rtol`, `atol`), its static options for `run_shared`, and the number of save times."""
    if model not in SHARED_MODELS:
        raise ValueError(
            f"steps='shared' runs the models {SHARED_MODELS} (one segment each), got "
            f"model={model!r}; use steps='per_member' for it."
        )
    if on_contact_loss not in ("stop", "continue"):
        raise ValueError(f"on_contact_loss must be 'stop' or 'continue', got {on_contact_loss!r}.")
    check_run_options(max_steps, event_pieces, t0, t1, rtol, atol, summary, saveat, body)
    dtype = jnp.result_type(top.m)
    rtol, atol = tolerances_for(dtype, rtol, atol)
    ts, n_save = save_times(summary, saveat, t0, t1, dtype)
    if solver is None:
        solver = default_solver(top, slow_flow=False)
    if isinstance(solver, diffrax.AbstractImplicitSolver):
        raise ValueError(
            "steps='shared' runs explicit solvers only (an implicit one would solve the whole "
            f"batch as one system), got {type(solver).__name__} (the default for very stiff "
            "friction); use steps='per_member' for it."
        )
    level = dataclasses.replace(LEVELS[model], body=not summary if body is None else bool(body))
    arrays = dict(
        ts=ts,
        t0=jnp.asarray(t0, dtype),
        t1=jnp.asarray(t1, dtype),
        rtol=jnp.asarray(rtol, dtype),
        atol=jnp.asarray(atol, dtype),
    )
    static = dict(
        level=level,
        solver=solver,
        stop_on_contact=on_contact_loss == "stop",
        max_steps=int(max_steps),
        pieces=int(event_pieces),
    )
    return arrays, static, n_save


@eqx.filter_jit
def run_shared(
    tops,
    y0s,
    ts,
    t0,
    t1,
    rtol,
    atol,
    *,
    level,
    solver,
    stop_on_contact,
    max_steps,
    pieces,
    pack_width=SHARED_PACK_WIDTH,
):
    """`run` for a batch whose members share their steps (`run_chain(..., shared_steps=True)`):
    `y0s` has a leading member axis, `tops` is one top or one per member. Returns `run`'s
    outputs with the member axis leading, and each member's outcome and settled flag."""
    axes = top_axes(tops)
    out = run_chain(
        level,
        tops,
        y0s,
        t0,
        t1,
        ts,
        stop_on_contact=stop_on_contact,
        shared_steps=True,
        solver=solver,
        rtol=rtol,
        atol=atol,
        max_steps=max_steps,
        # Not differentiated: the plain while loop of forward mode.
        adjoint=diffrax.ForwardMode(),
        progress_meter=diffrax.NoProgressMeter(),
        pieces=pieces,
        pack_width=pack_width,
    )
    fields = jax.vmap(
        lambda top, y0, o: outputs(top, y0, ts, o, o.result, level=level),
        in_axes=(axes, 0, 0),
    )(tops, y0s, out)
    theta_end, jellet_launch = fields.pop("theta_end"), fields.pop("jellet_launch")
    outcome, settled = jax.vmap(classify, in_axes=(axes, 0, 0, 0))(
        tops, jellet_launch, theta_end, fields["result"]
    )
    return dict(fields, outcome=outcome, settled=settled)
