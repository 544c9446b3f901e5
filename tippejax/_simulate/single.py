"""`simulate`: one top from one state, at the level of model asked for."""

from __future__ import annotations

import dataclasses
from typing import Literal

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from .._auto import choose_model
from .._cache import cacheable, cached_call, calling_context
from .._engine.chain import level_chain
from .._engine.cpu import own_compiler_options
from .._engine.packing import pack_width_for
from .._engine.sensitivity import ForwardSensitivities
from .._engine.solver_choice import (
    IMPLICIT_RATE,
    STIFF_RATE,
    friction_rate,
    host_friction_rate,
    solver_for_rate,
)
from .._engine.watch import EVENT_PIECES
from .._errors import result_error_if
from .._models.levels import LEVELS, check_friction
from .._outcome import classify_program
from .._solution import RESULTS, Solution
from .._state import State
from .._top import TippeTop
from .checks import (
    as_dtype,
    check_run_options,
    check_stem,
    check_top_and_state,
    checked_state,
    concrete,
    save_times,
    tolerances_for,
    warn_of_friction,
)
from .programs import outcome_of, run, run_traced, trim_saves

MODELS = (*LEVELS, "auto")
"""The levels `simulate` runs (`model=`), and `"auto"`."""


def default_solvers(top: TippeTop, level):
    """`default_solver` of every level of `level`'s chain (`level_chain`): one solver where
    they agree, else a tuple of one per level (the gyroscopic level's slow flow runs Dopri5,
    and the full model it hands over to runs its own default, Dopri8 for moderate friction)."""
    rate = host_friction_rate(top)  # (read once: a host read per level costs a sync each)
    solvers = tuple(solver_for_rate(rate, slow_flow=lvl.slow_flow) for lvl in level_chain(level))
    return solvers[0] if all(s == solvers[0] for s in solvers) else solvers


def _differentiated_eagerly(args) -> bool:
    """Whether the inputs `args` are differentiated by an eager `jax.grad`, `jax.jvp` or
    `jax.jacfwd` alone: some leaf is a tracer of forward or reverse mode (one with a `primal`)
    over a concrete value, and no leaf is traced otherwise (`jax.vmap`, `jax.jit`). False
    where JAX's tracers look otherwise: then `run` is used, the same derivatives in one
    program."""
    found = False
    for x in jax.tree_util.tree_leaves(args):
        while isinstance(x, jax.core.Tracer):
            primal = getattr(x, "primal", None)
            if primal is None:
                return False
            x, found = primal, True
    return found


def simulate(
    top: TippeTop,
    y0: State,
    t1: float,
    *,
    model: Literal["full", "so3", "routhian", "gyroscopic", "auto"] = "full",
    saveat: ArrayLike | None = None,
    t0: float = 0.0,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    solver: diffrax.AbstractSolver | None = None,
    max_steps: int = 1_000_000,
    throw: bool = True,
    progress: bool = False,
    on_contact_loss: Literal["stop", "continue"] = "stop",
    tolerance: float | None = None,
    summary: bool = False,
    adjoint: diffrax.AbstractAdjoint | None = None,
    event_pieces: int = EVENT_PIECES,
    body: bool | None = None,
) -> Solution:
    r"""Integrate the motion of `top` from `y0` at `t0` to `t1` with the chosen level of model.

    **Arguments:**

    - `top`: one `TippeTop` (use `jax.vmap` or `simulate_batch` for batches).
    - `y0`: the initial `State` (see `initial_state`).
    - `t1`: final time (s).
    - `model`: `"full"` (translation included), `"so3"` (translation dropped in the friction),
      `"routhian"` (reduced system with $J$ fixed; leaves the chart for the SO(3) level when
      $|\sin\theta| <$ `CHART_SIN_MIN`, reported as `"routhian->so3"`), `"gyroscopic"` (the
      slow flow for $\theta$ alone with the nutation averaged out, see `GyroscopicLevel`:
      `y0` is first projected onto the slow manifold; the
      solution is the state on it, with no nutation and no translation; where gyroscopic
      balance is lost, the slow manifold repels, or the launch carries more nutation than
      the level can project, the run hands over to the full model from the reconstructed
      state, reported as `sol.model == "gyroscopic->full"`), or
      `"auto"` (the cheapest of `"full"`, `"so3"`, `"routhian"`, `"gyroscopic"` whose measured
      error for the top's group and the launch's regime is below `tolerance`; the gyroscopic
      level only for a launch it accepts; the full model where that group and regime were
      not measured; see the levels page). A top with a stem (`tj.Stem`) runs at the full
      level (`"auto"` picks it): just before the stem touches the table it hands over to the
      stem level, two compliant contacts (`sol.model == "full->stem"`, `sol.t_stem`,
      `sol.t_ball_return`; `docs/friction.md`, "The stem").
    - `saveat`: save times within `[t0, t1]`, non-decreasing (default: 1001 points from `t0`
      to `t1`). Grids are padded internally to the next power of two (at least 16), so
      lengths that share that bucket share one compilation. Events (inversion, contact loss,
      the $R_n$ singularity, the chart edge) are located inside the solve, whatever the save
      grid.
    - `summary`: save nothing but the state where the run ended (`sol.ts` is `(t_final,)`);
      memory per run then does not grow with the save grid. Not with `saveat`.
    - `rtol`, `atol`: tolerances of the step-size controller, a PI controller
      (`diffrax.PIDController` with pcoeff 0.4, icoeff 0.3), which at equal error takes fewer
      step attempts than diffrax's default I controller. For float32 tops `rtol` is raised to
      at least `1e-5` and `atol` to `1e-7`.
    - `solver`: any diffrax solver with an error estimate; default `default_solver(top)`:
      Dopri8 (Dopri5 for the gyroscopic level), Tsit5 under strong friction, Kvaerno5 under
      very stiff friction. An explicit Runge-Kutta solver's stages do not run in
      diffrax's stage loop: on a GPU or other accelerator they are written out (a faster
      program that compiles slower), on a CPU they run in tippejax's own loop, which forms
      each stage without copying the others (faster in a batch). The same tableau, results
      equal to rounding (`TIPPEJAX_UNROLL_STAGES`).
    - `max_steps`: maximum number of steps per segment.
    - `adjoint`: how derivatives of the run are computed. Default (None): from the run's
      forward-mode Jacobian in the inputs that are differentiated (top fields, launch state,
      times), for `jax.grad`/`jax.vjp` and `jax.jacfwd`/`jax.jvp` alike
      (`tippejax/_engine/sensitivity.py`): its cost grows with the number of differentiated
      scalars (a run of one top has at most ~25), not with the outputs, and it is cheaper
      than reverse mode through the solve's steps (see the gradients page). Or a diffrax
      adjoint: `diffrax.RecursiveCheckpointAdjoint()` (reverse mode through the steps; no
      forward mode) or `diffrax.ForwardMode()` (forward mode only).
    - `throw`: raise on failure (contact loss with `on_contact_loss="stop"`, the $R_n$
      singularity, max steps, NaN, loss of gyroscopic balance). With `False` the failure is in
      `sol.result`.
    - `progress`: show diffrax's tqdm progress meter.
    - `on_contact_loss`: `"stop"` ends the run at $R_n = 0$ (a failure); `"continue"` goes on,
      flags `result = contact_lost` and does not raise for it. Past the loss friction feeds
      energy into the top, and a run can then take ever shorter steps up to `max_steps`, many
      times the steps of a run to `t1` that keeps contact: in a batch such a member holds up
      the others; keep `max_steps` small.
    - `tolerance`: for `model="auto"`, the largest acceptable error in $\theta(t)$ (rad).
    - `event_pieces`: along each step every event condition is followed by a quintic (its
      values and rates at the start, middle and end of the step). A step is rejected and
      shortened when the Bernstein coefficients of the quintic on this many equal parts of the
      step change sign more than once, which bounds the quintic's crossings from above: no
      step is kept in which the quintic crosses zero and back (the quintic follows the
      condition to about the solver's tolerance; a dip it does not follow is reported by
      `RESULTS.contact_loss_missed` where a save time sees it; `WatchedSolver` and the event
      watch's derivation page). More parts reject fewer steps needlessly and cost more per
      step; the default, 1, is usually enough (the performance page shows what each finds
      and rejects).
    - `body`: whether to integrate the body vector `sol.states.body`, and with it the spin
      angle `sol.psi`. The full and SO(3) levels carry it as 4 more state components (10 for
      the SO(3) level against 6, 14 against 10 for the full level), a noticeable part of a
      batch's time (see the performance page). Default: with a saved trajectory,
      not in summary mode (there `sol.psi` and `sol.states.body` are nan unless `body=True`).
      Everything else, `psi_dot` included, does not depend on it.

    **Returns:** a `Solution`.
    """
    if model not in MODELS:
        raise ValueError(f"Unknown model {model!r}; choose one of {MODELS}.")
    if on_contact_loss not in ("stop", "continue"):
        raise ValueError(f"on_contact_loss must be 'stop' or 'continue', got {on_contact_loss!r}.")
    check_top_and_state(top, y0)
    check_run_options(max_steps, event_pieces, t0, t1, rtol, atol, summary, saveat, body)
    dtype = jnp.result_type(top.m)
    if model == "auto":
        # (a top with a stem runs at the full level, which hands over to the stem level)
        model = "full" if top.stem is not None else choose_model(top, y0, tolerance=tolerance)
    check_friction(model, top)
    check_stem(model, top, y0)
    warn_of_friction(top)
    rtol, atol = tolerances_for(dtype, rtol, atol)
    ts, n_save = save_times(summary, saveat, t0, t1, dtype)
    y0 = jax.tree_util.tree_map(lambda x: as_dtype(x, dtype), y0)
    y0 = checked_state(y0)
    guard_stiff = solver is None and not concrete(top)
    if solver is None:
        solver = default_solvers(top, LEVELS[model])
    if adjoint is None:
        adjoint = ForwardSensitivities()
    level = dataclasses.replace(LEVELS[model], body=not summary if body is None else bool(body))
    options = dict(
        level=level,
        solver=solver,
        guard_stiff=guard_stiff,
        stop_on_contact=on_contact_loss == "stop",
        max_steps=int(max_steps),
        adjoint=adjoint,
        progress=progress,
        pieces=int(event_pieces),
        pack_width=pack_width_for(top, y0, t0, t1, rtol, atol, ts, adjoint=adjoint),
        jacobian_pack_width=pack_width_for(
            top, y0, t0, t1, rtol, atol, ts, adjoint=diffrax.ForwardMode()
        ),
    )
    args = (top, y0, ts, *(as_dtype(x, dtype) for x in (t0, t1, rtol, atol)))
    with cacheable():
        if concrete(*args) or calling_context() == "vmap":
            # (concrete inputs, or an eager `jax.vmap`, whose batched `run` JAX runs as a
            # program of its own: compiled with tippejax's options, as a concrete call is.
            # Inside a caller's `jit` the same call is traced into the caller's program.)
            out = cached_call(
                run, *args, compiler_options=own_compiler_options(), **options, outcome=True
            )
        else:
            # (a traced call. An eager `jax.grad` or `jax.jacfwd` runs the Jacobian as a
            # program of its own, `run_traced`; a caller's `jit` traces `run`, one
            # program. The classification is a program of its own, which an eager
            # `jax.grad` compiles apart from the differentiated solve, and a caller's `jit`
            # inlines.)
            own_jacobian = (
                isinstance(adjoint, ForwardSensitivities)
                and options["pack_width"] == options["jacobian_pack_width"]
                and _differentiated_eagerly(args)
            )
            program = run_traced if own_jacobian else run
            out = program(*args, **options)
            out["outcome"], out["settled"] = outcome_of(top, out, classify_program)
    out = trim_saves(out, n_save)
    name = model
    ran = level.for_top(top)  # (the full level of a top with a stem goes on to the stem level)
    if ran.fallback() is not None:
        switch = out["t_chart_switch"]
        fallback = ran.fallback().name
        if concrete(switch):
            if bool(np.any(np.isfinite(np.asarray(switch)))):
                name = f"{model}->{fallback}"
        else:
            name = f"{model}(->{fallback} where t_chart_switch is finite)"
    del out["theta_end"], out["jellet_launch"]
    sol = Solution(model=name, **out)
    if throw:
        sol = _raise_if_failed(sol, on_contact_loss, top)
    return sol


def simulate_tilt(
    top: TippeTop,
    y0: State,
    ts,
    *,
    t0,
    t1,
    model: str,
    rtol,
    atol,
    solver=None,
    max_steps: int,
    adjoint,
    event_pieces: int = EVENT_PIECES,
) -> dict:
    """The tilt and precession angle at the save times `ts`, and the contact-loss time, of the
    run `simulate(..., saveat=ts, on_contact_loss="continue", throw=False)` would make.

    For a fit's residuals, traced inside its programs: only what they read is computed (not the
    other `Solution` fields, the outcome, nor the inversion event), and events are not located
    inside their step (`run_segment`'s `locate=False`: the contact loss is dated to the start of
    the step it fell in, less than a step early, so at most the samples inside that step are
    counted as after it), which makes the fit's programs smaller to trace and compile. No
    argument checks (the fit makes its own) and no save-grid bucketing (its grids are bucketed
    already), and no body vector (`simulate`'s `body=False`). Returns a dict with `ts`, `theta`,
    `phi`, `t_contact_loss` and `result`."""
    dtype = jnp.result_type(top.m)
    if dtype != jnp.float64:
        rtol, atol = jnp.maximum(rtol, 1e-5), jnp.maximum(atol, 1e-7)
    guard_stiff = solver is None and not concrete(top)
    if solver is None:
        solver = default_solvers(top, LEVELS[model])
    out = run(
        top,
        y0,
        jnp.asarray(ts, dtype),
        jnp.asarray(t0, dtype),
        jnp.asarray(t1, dtype),
        jnp.asarray(rtol, dtype),
        jnp.asarray(atol, dtype),
        level=dataclasses.replace(LEVELS[model], body=False),
        solver=solver,
        guard_stiff=guard_stiff,
        stop_on_contact=False,
        max_steps=int(max_steps),
        adjoint=adjoint,
        progress=False,
        pieces=int(event_pieces),
        names=("theta", "phi"),
        inversion=False,
        locate=False,
    )
    return {k: out[k] for k in ("ts", "theta", "phi", "t_contact_loss", "result")}


def _max_steps_hint(top: TippeTop) -> str:
    """What to do about `max_steps_reached`, for this top's friction (concrete top)."""
    rate = float(np.max(np.asarray(friction_rate(top))))
    if rate <= STIFF_RATE:
        return (
            f" This top's friction is not stiff (tj.friction_rate(top) = {rate:.3g}/s, below "
            f"{STIFF_RATE:g}/s), so an implicit solver would not help: the steps are set by the "
            "nutation (a few per period 2 pi A/(C n)), and their number grows with spin x "
            "(t1 - t0). Raise max_steps, shorten the run, or loosen rtol/atol."
        )
    if rate <= IMPLICIT_RATE:
        return (
            f" This top's friction is stiff (tj.friction_rate(top) = {rate:.3g}/s): explicit "
            "steps are limited by stability. Raise max_steps, or pass an implicit solver "
            "(solver=diffrax.Kvaerno5())."
        )
    return (
        f" This top's friction is very stiff (tj.friction_rate(top) = {rate:.3g}/s): pass an "
        "implicit solver (solver=diffrax.Kvaerno5(), the default for such a top) and raise "
        "max_steps."
    )


def _past_contact_loss_hint(t_loss: float) -> str:
    """The `max_steps_reached` message of a run that went on past a contact loss."""
    return (
        "The maximum number of solver steps was reached before t1, in a run that lost contact "
        f"with the table at t = {t_loss:.6g} s and went on (on_contact_loss='continue'). Past "
        "that time the model is not physical: friction proportional to a negative R_n feeds "
        "energy into the top, whose motion can then need ever shorter steps (docs/notes.md, "
        "'Contact loss'). More max_steps may not get it to t1: stop at the loss "
        "(on_contact_loss='stop') or end the run near t_contact_loss."
    )


def _raise_if_failed(sol: Solution, on_contact_loss: str, top: TippeTop | None = None) -> Solution:
    allowed = [RESULTS.successful]
    if on_contact_loss == "continue":
        allowed.append(RESULTS.contact_lost)
    if concrete(sol.result):  # (read on the host: no device program)
        codes = np.ravel(np.asarray(sol.result._value))
        failed = ~np.isin(codes, [int(r._value) for r in allowed])
        if bool(np.any(failed)):
            first = int(np.argmax(failed))
            item = jax.tree_util.tree_map(lambda x: np.ravel(np.asarray(x))[first], sol.result)
            message = RESULTS.message(item)
            if codes[first] == int(RESULTS.max_steps_reached._value):
                t_loss = float(np.ravel(np.asarray(sol.t_contact_loss))[first])
                if np.isfinite(t_loss):
                    message = _past_contact_loss_hint(t_loss)
                elif top is not None and concrete(top):
                    message = "The maximum number of solver steps was reached before t1." + (
                        _max_steps_hint(top)
                    )
            raise RuntimeError(
                f"tippejax.simulate failed: {message} "
                "(pass throw=False to get the flagged solution instead)."
            )
        return sol
    failed = sol.result != allowed[0]
    for code in allowed[1:]:
        failed = failed & (sol.result != code)
    return result_error_if(sol, sol.result, failed)
