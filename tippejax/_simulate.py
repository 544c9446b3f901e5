r"""`simulate`: one top from one state, at the level of model asked for.

The physics lives in `tippejax._models` (one level per file); the engine in
`tippejax._engine` runs a level's segments with diffrax and locates its events. This module
checks the arguments, picks the level and the solver, and computes the observed fields.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Literal

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from ._cache import cacheable, cached_call, calling_context, to_device
from ._engine.chain import run_chain, run_chain_shared
from ._engine.cpu import own_compiler_options
from ._engine.segment import (
    FORWARD_MODE_PACK_WIDTH,
    PACK_WIDTH,
    SHARED_PACK_WIDTH,
    pack_width_for,
    top_axes,
)
from ._engine.sensitivity import ForwardSensitivities, forward_sensitivities, jacobian_of
from ._engine.solver_choice import (
    IMPLICIT_RATE,
    STIFF_RATE,
    default_solver,
    friction_rate,
    is_traced,
)
from ._engine.watch import EVENT_PIECES
from ._errors import error_if, result_error_if
from ._invariants import energy, jellet, normal_force, slip_velocity
from ._models.levels import LEVELS
from ._solution import RESULTS, Solution
from ._state import State, euler_angles, euler_rates, spin
from ._top import TippeTop

MODELS = (*LEVELS, "auto")


OBSERVED = ("theta", "phi", "psi", "theta_dot", "phi_dot", "psi_dot", "spin", "position",
            "velocity", "jellet", "energy", "normal_force", "slip_speed")
"""The `Solution` fields computed from the states at the save times."""


def _observe(top, states: State, friction_model: str, valid, names=OBSERVED):
    """The `Solution` fields `names` of states at the save times (nan where not `valid`)."""
    theta, phi, psi = euler_angles(states)
    rates = []  # the Euler rates, computed (traced) once if any is asked for

    def rate(i):
        if not rates:
            rates.extend(euler_rates(states))
        return rates[i]

    makers = dict(
        theta=lambda: theta,
        phi=lambda: jnp.unwrap(jnp.where(valid, phi, 0.0)),
        psi=lambda: jnp.unwrap(jnp.where(valid, psi, 0.0)),
        theta_dot=lambda: rate(0),
        phi_dot=lambda: rate(1),
        psi_dot=lambda: rate(2),
        spin=lambda: spin(states),
        position=lambda: states.position,
        velocity=lambda: states.velocity,
        jellet=lambda: jellet(top, states),
        energy=lambda: energy(top, states, model=friction_model),
        normal_force=lambda: normal_force(top, states, model=friction_model),
        slip_speed=lambda: jnp.linalg.norm(
            slip_velocity(top, states, model=friction_model), axis=-1
        ),
    )
    fields = {k: makers[k]() for k in names}

    def mask(x):
        return jnp.where(valid.reshape(valid.shape + (1,) * (x.ndim - valid.ndim)), x, jnp.nan)

    return {k: mask(v) for k, v in fields.items()}


@eqx.filter_jit
def _run(top, y0, ts, t0, t1, rtol, atol, *, level, solver, guard_stiff, stop_on_contact,
         max_steps, adjoint, progress, pieces, names=OBSERVED, inversion=True, locate=True,
         pack_width=PACK_WIDTH, jacobian_pack_width=FORWARD_MODE_PACK_WIDTH, outcome=False):
    """The run of one top (`run_chain`) and its observed fields (`_outputs`); with
    `outcome=True` also `sol.outcome` and `sol.settled` (`_classify`), in the same program.

    The default adjoint differentiates the segment chain alone (`_chain`); the observed
    fields, simple functions of its states, are differentiated by JAX's own rules after it.
    (An eager `jax.grad` of `simulate` does not come here: see `_run_traced`.)"""
    chain, result = _chain(
        top, y0, ts, t0, t1, rtol, atol, level=level, solver=solver, guard_stiff=guard_stiff,
        stop_on_contact=stop_on_contact, max_steps=max_steps, adjoint=adjoint,
        progress=progress, pieces=pieces, inversion=inversion, locate=locate,
        pack_width=pack_width, jacobian_pack_width=jacobian_pack_width)
    out = _outputs(top, y0, ts, chain, result, level=level, names=names)
    if outcome:
        out["outcome"], out["settled"] = _outcome_of(top, out, _classify)
    return out


def _run_traced(top, y0, ts, t0, t1, rtol, atol, *, names=OBSERVED, inversion=True,
                locate=True, **options):
    """`_run` (without the outcome) for an eager `jax.grad`, `jax.jvp` or `jax.jacfwd` of
    `simulate` (`_differentiated_eagerly`): its segment chain and its observed fields as two
    programs, with the chain's derivative rule outside both.

    JAX calls the rule with concrete inputs, and the chain's forward-mode Jacobian is then a
    top-level program of its own (`_run_jacobian`): compiled with tippejax's options
    (`own_compiler_options`) and kept in the store of traced programs (`cached_call`), which
    JAX allows for neither the program it derives from `_run`'s nor a nested `jit`. First
    call of an eager `jax.grad` of t_invert (8 s run) in a new process, paired with the
    single program it replaced (2-core AMD EPYC, 2026-11-29): median 0.80x as long with the
    cache off (6 pairs, 0.60-0.97x: 10.3-14.4 s against 14.1-17.1 s), 0.51x and 0.88x with an
    empty cache, 1.7-2.0 s against 6.9-7.5 s with a warm one (the stored Jacobian is not
    traced again)."""
    core = {k: v for k, v in options.items() if k not in ("adjoint", "jacobian_pack_width")}
    core.update(pack_width=options["jacobian_pack_width"], inversion=inversion, locate=locate)

    def jacobian(args, live):
        return cached_call(_run_jacobian, *args, compiler_options=own_compiler_options(),
                           live=live, **core)

    chain, result = _chain(top, y0, ts, t0, t1, rtol, atol, **options, inversion=inversion,
                           locate=locate, jacobian=jacobian)
    return _outputs_program(top, y0, ts, chain, result, level=options["level"], names=names)


def _chain(top, y0, ts, t0, t1, rtol, atol, *, level, solver, guard_stiff, stop_on_contact,
           max_steps, adjoint, progress, pieces, inversion, locate, pack_width,
           jacobian_pack_width, jacobian=None):
    """`_run_core` with the derivatives `adjoint` asks for: the default
    (`ForwardSensitivities`) from its forward-mode Jacobian (`sensitivity.py`), with
    `jacobian` for concrete inputs (see `forward_sensitivities`)."""
    options = dict(level=level, solver=solver, guard_stiff=guard_stiff,
                   stop_on_contact=stop_on_contact, max_steps=max_steps, progress=progress,
                   pieces=pieces, inversion=inversion, locate=locate)
    run = functools.partial(_run_core, **options)
    if isinstance(adjoint, ForwardSensitivities) and pack_width == jacobian_pack_width:
        # (the default: derivatives from the forward-mode Jacobian, `sensitivity.py`; the
        # widths agree for one top, `simulate_batch` and a user's `jax.vmap` alike with the
        # widths of `segment.py`.) The value and the Jacobian are one staged solve, so that
        # `jax.grad` and `jax.jacfwd` trace it once: JAX traces a `custom_jvp`'s value
        # under `jit` eagerly, and the Jacobian's rule transforms the same cached jaxpr.
        run = functools.partial(_run_core_staged, **options, adjoint=diffrax.ForwardMode(),
                                pack_width=pack_width)
        run = forward_sensitivities(run, run, jacobian=jacobian)
    elif isinstance(adjoint, ForwardSensitivities):
        # (layouts that differ between the value and the Jacobian: two programs)
        run = forward_sensitivities(
            functools.partial(run, adjoint=diffrax.RecursiveCheckpointAdjoint(),
                              pack_width=pack_width),
            functools.partial(run, adjoint=diffrax.ForwardMode(),
                              pack_width=jacobian_pack_width),
            jacobian=jacobian)
    else:
        run = functools.partial(run, adjoint=adjoint, pack_width=pack_width)
    # (JAX keys its cache of traced programs on the context's abstract mesh: unset here at
    # the first trace, the empty mesh where `jax.grad` replays `_run`'s jaxpr and calls the
    # Jacobian's rule. Set it, so that both find the one trace of `_run_core_staged`.)
    with jax.sharding.use_abstract_mesh(jax.sharding.get_abstract_mesh()):
        return run(top, y0, ts, t0, t1, rtol, atol)


@eqx.filter_jit
def _run_jacobian(top, y0, ts, t0, t1, rtol, atol, *, live, **options):
    """`_run_core`'s outputs and their forward-mode Jacobian in the leaves `live` of its
    arguments (`jacobian_of`): the program an eager `jax.grad` of `simulate` runs."""
    run = functools.partial(_run_core, **options, adjoint=diffrax.ForwardMode())
    return jacobian_of(run, (top, y0, ts, t0, t1, rtol, atol), live)


def _run_core(top, y0, ts, t0, t1, rtol, atol, *, level, solver, guard_stiff, stop_on_contact,
              max_steps, adjoint, progress, pieces, inversion, locate, pack_width):
    too_stiff = jnp.array(False)
    if guard_stiff:
        # Traced top with the default (explicit) solver: a very stiff member would run into
        # max_steps and hold up the whole batch. Give it zero length and say why.
        too_stiff = friction_rate(top) > IMPLICIT_RATE
        t1 = jnp.where(too_stiff, t0, t1)
    meter = diffrax.TqdmProgressMeter() if progress else diffrax.NoProgressMeter()
    out = run_chain(
        level, top, y0, t0, t1, ts, stop_on_contact=stop_on_contact, solver=solver,
        rtol=rtol, atol=atol, max_steps=max_steps, adjoint=adjoint, progress_meter=meter,
        pieces=pieces, inversion=inversion, locate=locate, pack_width=pack_width,
    )
    result = RESULTS.where(too_stiff, RESULTS.stiff_under_trace, out.result)
    return out, result


_run_core_staged = eqx.filter_jit(_run_core)
"""`_run_core` as a program of its own inside `_run`'s: its trace is cached per static
options and argument shapes, for the value and the Jacobian of `forward_sensitivities`."""


def _outputs(top, y0, ts, out, result, *, level, names=OBSERVED):
    """`_run`'s outputs for one member from its `ChainOutput` `out` (and its `result`): the
    observed fields at the save times, with the safety net for a missed contact loss."""
    dtype = jnp.result_type(top.m)
    friction_model = level.friction_model
    t_contact_loss = out.t_contact_loss
    if ts is None:
        times = out.t_final[None]
        states = jax.tree_util.tree_map(lambda x: x[None], out.state_end)
        valid = jnp.ones(1, bool)
        fields = _observe(top, states, friction_model, valid, names)
    else:
        times = ts
        states = out.states
        valid = (ts <= out.t_final) & jnp.all(jnp.isfinite(states.axis), axis=-1)
        # (the normal force is needed for the safety net below; it is dropped after)
        fields = _observe(top, states, friction_model, valid,
                          tuple(dict.fromkeys(names + ("normal_force",))))
        # Safety net: R_n < 0 at a save time before any located contact loss means a dip
        # shorter than the event watch's resolution went unseen. Report it; return nothing
        # from that save time on, nor a later loss time as if it were the first.
        missed_at = valid & (fields["normal_force"] < 0) & ~(ts >= t_contact_loss)
        missed = jnp.any(missed_at)
        t_missed = jnp.min(jnp.where(missed_at, ts, jnp.inf))
        result = RESULTS.where(
            missed & ((result == RESULTS.successful) | (result == RESULTS.contact_lost)),
            RESULTS.contact_loss_missed,
            result,
        )
        t_contact_loss = jnp.where(missed, jnp.nan, t_contact_loss)
        valid = valid & (ts < t_missed)
        fields = {
            k: jnp.where(valid.reshape(valid.shape + (1,) * (v.ndim - 1)), v, jnp.nan)
            for k, v in fields.items() if k in names
        }
        states = jax.tree_util.tree_map(
            lambda x: jnp.where(valid.reshape(valid.shape + (1,) * (x.ndim - 1)), x, jnp.nan),
            states,
        )
    nonfinite = jnp.any(
        jnp.stack([jnp.any(valid & ~jnp.isfinite(fields[k])) for k in ("theta", "jellet")
                   if k in fields])
    )
    result = RESULTS.where((result == RESULTS.successful) & nonfinite, RESULTS.nonfinite, result)
    return dict(
        theta_end=euler_angles(out.state_end)[0], jellet_launch=jellet(top, y0),
        ts=times.astype(dtype), states=states, result=result, t_invert=out.t_invert,
        t_contact_loss=t_contact_loss, t_chart_switch=out.t_chart_switch,
        t_final=out.t_final, num_steps=out.num_steps,
        num_rejected_steps=out.num_rejected_steps, **fields,
    )


_outputs_program = eqx.filter_jit(_outputs)
"""`_outputs` as a program of its own, for `_run_traced`."""


_SAVED = ("ts", "states", "theta", "phi", "psi", "theta_dot", "phi_dot", "psi_dot", "spin",
          "position", "velocity", "jellet", "energy", "normal_force", "slip_speed")
"""The outputs with a save-time axis."""


def save_bucket(n: int) -> int:
    """Length a save grid of `n` times is padded to: the next power of two, at least 16."""
    return max(16, 1 << (int(n) - 1).bit_length())


SETTLE_TOL = 0.1
"""Tilt distance (rad) within which a run's end counts as `settled` on its outcome."""


def _classify(top, J, theta_end, result):
    """`sol.outcome`, `sol.settled`: the end state classified as `outcome_map` does."""
    from ._maps import classify_end  # (_maps imports simulate)

    outcome, settled, _ = classify_end(top, J, theta_end, result, settle_tol=SETTLE_TOL)
    return outcome, settled


_classify_program = eqx.filter_jit(_classify)


def _outcome_of(top, out, classify):
    """`sol.outcome`, `sol.settled` of `_run`'s outputs `out` by `classify` (`_classify`, or
    `_classify_program` for a traced call); integer outputs, so their inputs' derivatives are
    not traced."""
    return classify(*jax.lax.stop_gradient((top, out["jellet_launch"], out["theta_end"])),
                    out["result"])


def _concrete(*xs) -> bool:
    return not any(is_traced(x) for x in jax.tree_util.tree_leaves(xs))


def _differentiated_eagerly(args) -> bool:
    """Whether the inputs `args` are differentiated by an eager `jax.grad`, `jax.jvp` or
    `jax.jacfwd` alone: some leaf is a tracer of forward or reverse mode (one with a `primal`)
    over a concrete value, and no leaf is traced otherwise (`jax.vmap`, `jax.jit`). False
    where JAX's tracers look otherwise: then `_run` is used, the same derivatives in one
    program."""
    found = False
    for x in jax.tree_util.tree_leaves(args):
        while isinstance(x, jax.core.Tracer):
            primal = getattr(x, "primal", None)
            if primal is None:
                return False
            x, found = primal, True
    return found


def _as_dtype(x, dtype):
    """`x` as an array of `dtype`: a jax array or tracer of that dtype as it is, a host value
    put on the device without a program (`to_device`), else converted by `jnp.asarray`."""
    if isinstance(x, jax.Array) or is_traced(x):
        return x if jnp.result_type(x) == dtype else jnp.asarray(x, dtype)
    return to_device(x, dtype)


def _check_top_and_state(top: TippeTop, y0: State):
    if not isinstance(top, TippeTop):
        raise TypeError(f"top must be a tippejax.TippeTop, got {type(top).__name__}.")
    if not isinstance(y0, State):
        raise TypeError(
            f"y0 must be a tippejax.State (see tj.initial_state), got {type(y0).__name__}."
        )
    shapes = {jnp.shape(x) for x in jax.tree_util.tree_leaves(top)}
    if shapes != {()}:
        raise ValueError(
            f"simulate takes one top, but this TippeTop has fields of shape {sorted(shapes)}. "
            "For a sweep of tops or launches use tj.simulate_batch(tops, theta0, spin, t1, "
            "grid=...), or jax.vmap(lambda top: tj.simulate(top, ...))(tops)."
        )
    if y0.axis.shape != (3,):
        raise ValueError(
            f"simulate takes one state, but y0.axis has shape {y0.axis.shape}. Use jax.vmap over "
            "states (or tj.simulate_batch) for a batch."
        )


_STATE_TOL = 1e-6
_STATE_MESSAGE = (
    "y0 is not a valid state: its axis and body vectors must be unit vectors, perpendicular to "
    f"each other (within {_STATE_TOL:g}), and every field finite. Build states with "
    "tj.initial_state or tj.state_from_euler."
)


def _state_defect(y0: State, xp=jnp):
    """How far `y0`'s axis and body vectors are from unit vectors perpendicular to each other
    (inf if a field is not finite); `xp=np` for a concrete state (no device programs)."""
    a, b = y0.axis, y0.body
    defect = xp.maximum(xp.abs(xp.sum(a * a) - 1), xp.abs(xp.sum(b * b) - 1))
    defect = xp.maximum(defect, xp.abs(xp.sum(a * b)))
    finite = xp.all(
        xp.stack([xp.all(xp.isfinite(x)) for x in jax.tree_util.tree_leaves(y0)])
    )
    return xp.where(finite, defect, xp.inf)


def _check_tolerances(rtol, atol):
    for name, value, lowest in (("rtol", rtol, "> 0"), ("atol", atol, ">= 0")):
        if _concrete(value):
            v = float(value)
            bad = not np.isfinite(v) or (v <= 0 if name == "rtol" else v < 0)
            if bad:
                raise ValueError(f"{name} must be finite and {lowest}, got {value}.")


def _check_saveat(saveat, t0, t1, dtype):
    """`saveat` checked, as a numpy array where it and the times are concrete (no device
    program), else as a traced array that raises at run time if it is out of order."""
    concrete = _concrete(saveat, t0, t1)
    ts = np.asarray(saveat, dtype=dtype) if concrete else jnp.asarray(saveat, dtype=dtype)
    if ts.ndim != 1 or ts.shape[0] < 1:
        raise ValueError(f"saveat must be a 1-d array of save times, got shape {ts.shape}.")
    if concrete:
        arr = np.asarray(ts, dtype=float)
        if not np.all(np.isfinite(arr)):
            raise ValueError("saveat must hold finite times.")
        if np.any(np.diff(arr) < 0):
            raise ValueError("saveat must be non-decreasing.")
        # The same rounding as the save times themselves (float32 tops round t1 too).
        lo, hi = float(np.asarray(t0, dtype)), float(np.asarray(t1, dtype))
        if arr[0] < lo or arr[-1] > hi:
            raise ValueError(
                f"saveat must lie within [t0, t1] = [{t0}, {t1}], got times from {arr[0]} to "
                f"{arr[-1]}. Pass a larger t1 or drop the later save times."
            )
    else:
        bad = (ts[0] < t0) | (ts[-1] > t1) | jnp.any(jnp.diff(ts) < 0)
        ts = error_if(ts, bad, "saveat must be non-decreasing and lie within [t0, t1].")
    return ts


def _check_run_options(max_steps, event_pieces, t0, t1, rtol, atol, summary, saveat, body):
    """`simulate`'s checks of its options past the model, the top and the state."""
    if not (isinstance(max_steps, (int, np.integer)) and max_steps > 0):
        raise ValueError(f"max_steps must be a positive integer, got {max_steps!r}.")
    if not (isinstance(event_pieces, (int, np.integer)) and event_pieces >= 1):
        raise ValueError(f"event_pieces must be a positive integer, got {event_pieces!r}.")
    if _concrete(t0, t1) and not float(t1) > float(t0):
        raise ValueError(f"t1 must be greater than t0, got t0={t0}, t1={t1}.")
    _check_tolerances(rtol, atol)
    if summary and saveat is not None:
        raise ValueError("Pass either saveat or summary=True, not both.")
    if body is not None and not isinstance(body, (bool, np.bool_)):
        raise ValueError(f"body must be True, False or None (the default), got {body!r}.")


def _tolerances_for(dtype, rtol, atol):
    """`rtol`, `atol` raised to at least 1e-5 and 1e-7 for a float32 top."""
    if dtype != jnp.float64:
        if _concrete(rtol, atol):
            rtol, atol = max(float(rtol), 1e-5), max(float(atol), 1e-7)
        else:
            rtol, atol = jnp.maximum(rtol, 1e-5), jnp.maximum(atol, 1e-7)
    return rtol, atol


def _save_times(summary, saveat, t0, t1, dtype):
    """The save grid a run uses (None in summary mode), padded to its bucket, and the number
    of save times asked for (None in summary mode)."""
    if summary:
        ts = None
    elif saveat is None:
        if _concrete(t0, t1):  # (numpy: no device program for a default grid)
            ts = np.linspace(np.asarray(t0, dtype), np.asarray(t1, dtype), 1001, dtype=dtype)
        else:
            ts = jnp.linspace(t0, t1, 1001, dtype=dtype)
    else:
        ts = _check_saveat(saveat, t0, t1, dtype)
    # Save grids are padded to a bucket length (the next power of two, at least 16) with
    # copies of the last time, and the outputs cut back: a new length of `saveat` reuses the
    # compiled program of its bucket instead of compiling anew.
    n_save = None if ts is None else int(ts.shape[0])
    if ts is not None:
        bucket = save_bucket(n_save)
        xp = np if isinstance(ts, np.ndarray) else jnp
        if bucket > n_save:
            ts = xp.concatenate([ts, xp.broadcast_to(ts[-1:], (bucket - n_save,))])
        if xp is np:
            ts = to_device(ts, dtype)
    return ts, n_save


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
      slow flow for $\theta$ alone with the nutation averaged out, see
      `tippejax/_models/gyroscopic.py`: `y0` is first projected onto the slow manifold; the
      solution is the state on it, with no nutation and no translation; where gyroscopic
      balance is lost, the slow manifold repels, or the launch carries more nutation than
      the level can project, the run hands over to the full model from the reconstructed
      state, reported as `sol.model == "gyroscopic->full"`), or
      `"auto"` (the cheapest of `"full"`, `"so3"`, `"routhian"`, `"gyroscopic"` whose measured
      error for the top's group and the launch's regime, `benchmarks/LEVELS.md`, is below
      `tolerance`; the gyroscopic level only for a launch it accepts; the full model where
      that group and regime were not measured).
    - `saveat`: save times within `[t0, t1]`, non-decreasing (default: 1001 points from `t0`
      to `t1`). Grids are padded internally to the next power of two (at least 16), so
      lengths that share that bucket share one compilation. Events (inversion, contact loss, the $R_n$ singularity, the chart edge) are
      located inside the solve, whatever the save grid.
    - `summary`: save nothing but the state where the run ended (`sol.ts` is `(t_final,)`);
      memory per run then does not grow with the save grid. Not with `saveat`.
    - `rtol`, `atol`: tolerances of the step-size controller, a PI controller
      (`diffrax.PIDController` with pcoeff 0.4, icoeff 0.3: at equal error 0.89-0.93x the
      step attempts of diffrax's default I controller on random tops,
      `benchmarks/step_control.py`). For float32 tops `rtol` is raised to at least `1e-5` and
      `atol` to `1e-7`.
    - `solver`: any diffrax solver with an error estimate; default `default_solver(top)`:
      Dopri8 (Dopri5 for the gyroscopic level), Tsit5 under strong friction, Kvaerno5 under
      very stiff friction. An explicit Runge-Kutta solver's stages do not run in
      diffrax's stage loop: on a GPU or other accelerator they are written out (a faster
      program that compiles slower), on a CPU they run in tippejax's own loop, which forms
      each stage without copying the others (about 2x faster in a batch). The same
      tableau, results equal to rounding (`TIPPEJAX_UNROLL_STAGES`).
    - `max_steps`: maximum number of steps per segment.
    - `adjoint`: how derivatives of the run are computed. Default (None): from the run's
      forward-mode Jacobian in the inputs that are differentiated (top fields, launch state,
      times), for `jax.grad`/`jax.vjp` and `jax.jacfwd`/`jax.jvp` alike
      (`tippejax/_engine/sensitivity.py`): its cost grows with the number of differentiated
      scalars (a run of one top has at most ~25), not with the outputs; for the seven fields
      of the standard top's 20 s run 3.4-5.5x the solve in either mode on a 2-core CPU
      (`benchmarks/RESULTS.md`, gradients.py), against 5.4-8.1x for reverse mode through the
      solve's steps. Or a diffrax adjoint: `diffrax.RecursiveCheckpointAdjoint()` (reverse
      mode through the steps; no forward mode) or `diffrax.ForwardMode()` (forward mode
      only).
    - `throw`: raise on failure (contact loss with `on_contact_loss="stop"`, the $R_n$
      singularity, max steps, NaN, loss of gyroscopic balance). With `False` the failure is in
      `sol.result`.
    - `progress`: show diffrax's tqdm progress meter.
    - `on_contact_loss`: `"stop"` ends the run at $R_n = 0$ (a failure); `"continue"` goes on,
      flags `result = contact_lost` and does not raise for it. Past the loss friction feeds
      energy into the top, and a run can then take ever shorter steps up to `max_steps`
      (of 100 spins 140-160 rad/s of `benchmarks/peers.py`'s scene at the full level, 5 ran
      into 20,000 steps within about a second of the loss, where the others end 20 s in
      about 2,000): in a batch such a member holds up the others; keep `max_steps` small.
    - `tolerance`: for `model="auto"`, the largest acceptable error in $\theta(t)$ (rad).
    - `event_pieces`: along each step every event condition is followed by a quintic (its
      values and rates at the start, middle and end of the step). A step is rejected and
      shortened when the Bernstein coefficients of the quintic on this many equal parts of the
      step change sign more than once, which bounds the quintic's crossings from above: no
      step is kept in which the quintic crosses zero and back (the quintic follows the
      condition to about the solver's tolerance; a dip it does not follow is reported by
      `RESULTS.contact_loss_missed` where a save time sees it; `tippejax/_engine/watch.py`).
      More parts reject fewer steps needlessly and cost more per step; the default, 1, is
      measured in `benchmarks/RESULTS.md` (watch.py).
    - `body`: whether to integrate the body vector `sol.states.body`, and with it the spin
      angle `sol.psi`. The full and SO(3) levels carry it as 4 more state components (10 for
      the SO(3) level against 6, 14 against 10 for the full level), which costs about a fifth
      of a batch's time (`benchmarks/RESULTS.md`, peers.py). Default: with a saved trajectory,
      not in summary mode (there `sol.psi` and `sol.states.body` are nan unless `body=True`).
      Everything else, `psi_dot` included, does not depend on it.

    **Returns:** a `Solution`.
    """
    if model not in MODELS:
        raise ValueError(f"Unknown model {model!r}; choose one of {MODELS}.")
    if on_contact_loss not in ("stop", "continue"):
        raise ValueError(f"on_contact_loss must be 'stop' or 'continue', got {on_contact_loss!r}.")
    _check_top_and_state(top, y0)
    _check_run_options(max_steps, event_pieces, t0, t1, rtol, atol, summary, saveat, body)
    dtype = jnp.result_type(top.m)
    if model == "auto":
        from ._auto import choose_model

        model = choose_model(top, y0, tolerance=tolerance)
    rtol, atol = _tolerances_for(dtype, rtol, atol)
    ts, n_save = _save_times(summary, saveat, t0, t1, dtype)
    y0 = jax.tree_util.tree_map(lambda x: _as_dtype(x, dtype), y0)
    if _concrete(y0):  # (checked in numpy: no device program)
        defect = _state_defect(jax.tree_util.tree_map(np.asarray, y0), xp=np)
        if not float(defect) < _STATE_TOL:
            raise ValueError(_STATE_MESSAGE)
    else:
        defect = _state_defect(y0)
        y0 = error_if(y0, ~(defect < _STATE_TOL), _STATE_MESSAGE)
    guard_stiff = solver is None and not _concrete(top)
    if solver is None:
        solver = default_solver(top, slow_flow=LEVELS[model].slow_flow)
    if adjoint is None:
        adjoint = ForwardSensitivities()
    level = dataclasses.replace(LEVELS[model], body=not summary if body is None else bool(body))
    options = dict(
        level=level, solver=solver, guard_stiff=guard_stiff,
        stop_on_contact=on_contact_loss == "stop", max_steps=int(max_steps),
        adjoint=adjoint, progress=progress, pieces=int(event_pieces),
        # (a slow-flow level's chain, which hands over to the full model, keeps the batch
        # layout: with one vector its single top ran 22 ms against 12 ms, peers.py scene)
        pack_width=PACK_WIDTH if LEVELS[model].slow_flow else pack_width_for(
            top, y0, t0, t1, rtol, atol, ts, adjoint=adjoint),
        jacobian_pack_width=PACK_WIDTH if LEVELS[model].slow_flow else pack_width_for(
            top, y0, t0, t1, rtol, atol, ts, adjoint=diffrax.ForwardMode()),
    )
    args = (top, y0, ts, *(_as_dtype(x, dtype) for x in (t0, t1, rtol, atol)))
    with cacheable():
        if _concrete(*args) or calling_context() == "vmap":
            # (concrete inputs, or an eager `jax.vmap`, whose batched `_run` JAX runs as a
            # program of its own: compiled with tippejax's options, as a concrete call is.
            # Inside a caller's `jit` the same call is traced into the caller's program.)
            out = cached_call(_run, *args, compiler_options=own_compiler_options(), **options,
                              outcome=True)
        else:
            # (a traced call. An eager `jax.grad` or `jax.jacfwd` runs the Jacobian as a
            # program of its own, `_run_traced`; a caller's `jit` traces `_run`, one
            # program. The classification is a program of its own, which an eager
            # `jax.grad` compiles apart from the differentiated solve, and a caller's `jit`
            # inlines.)
            own_jacobian = (isinstance(adjoint, ForwardSensitivities)
                            and options["pack_width"] == options["jacobian_pack_width"]
                            and _differentiated_eagerly(args))
            run = _run_traced if own_jacobian else _run
            out = run(*args, **options)
            out["outcome"], out["settled"] = _outcome_of(top, out, _classify_program)
    if n_save is not None and out["ts"].shape[0] != n_save:
        for key in _SAVED:
            out[key] = jax.tree_util.tree_map(lambda x: x[:n_save], out[key])
    name = model
    if LEVELS[model].fallback() is not None:
        switch = out["t_chart_switch"]
        fallback = LEVELS[model].fallback().name
        if _concrete(switch):
            if bool(np.any(np.isfinite(np.asarray(switch)))):
                name = f"{model}->{fallback}"
        else:
            name = f"{model}(->{fallback} where t_chart_switch is finite)"
    del out["theta_end"], out["jellet_launch"]
    sol = Solution(model=name, **out)
    if throw:
        sol = _raise_if_failed(sol, on_contact_loss, top)
    return sol


SHARED_MODELS = ("full", "so3")
"""The levels a batch with shared steps runs (`simulate_batch(..., steps="shared")`): the
levels that are one segment."""

SHARED_OPTIONS = ("model", "saveat", "t0", "rtol", "atol", "solver", "max_steps",
                  "on_contact_loss", "summary", "event_pieces", "body")
"""The options of `simulate` a batch with shared steps takes."""


def shared_run_options(top: TippeTop, t1, *, model="full", saveat=None, t0=0.0, rtol=1e-8,
                       atol=1e-10, solver=None, max_steps=1_000_000, on_contact_loss="stop",
                       summary=False, event_pieces=EVENT_PIECES, body=None):
    """`simulate`'s checks and defaults for a batch with shared steps (a concrete `top`, one
    or a batch). Returns the arrays of the run (`ts` None in summary mode, `t0`, `t1`,
    `rtol`, `atol`), its static options for `_run_shared`, and the number of save times."""
    if model not in SHARED_MODELS:
        raise ValueError(
            f"steps='shared' runs the models {SHARED_MODELS} (one segment each), got "
            f"model={model!r}; use steps='per_member' for it."
        )
    if on_contact_loss not in ("stop", "continue"):
        raise ValueError(f"on_contact_loss must be 'stop' or 'continue', got {on_contact_loss!r}.")
    _check_run_options(max_steps, event_pieces, t0, t1, rtol, atol, summary, saveat, body)
    dtype = jnp.result_type(top.m)
    rtol, atol = _tolerances_for(dtype, rtol, atol)
    ts, n_save = _save_times(summary, saveat, t0, t1, dtype)
    if solver is None:
        solver = default_solver(top, slow_flow=False)
    if isinstance(solver, diffrax.AbstractImplicitSolver):
        raise ValueError(
            "steps='shared' runs explicit solvers only (an implicit one would solve the whole "
            f"batch as one system), got {type(solver).__name__} (the default for very stiff "
            "friction); use steps='per_member' for it."
        )
    level = dataclasses.replace(LEVELS[model], body=not summary if body is None else bool(body))
    arrays = dict(ts=ts, t0=jnp.asarray(t0, dtype), t1=jnp.asarray(t1, dtype),
                  rtol=jnp.asarray(rtol, dtype), atol=jnp.asarray(atol, dtype))
    static = dict(level=level, solver=solver, stop_on_contact=on_contact_loss == "stop",
                  max_steps=int(max_steps), pieces=int(event_pieces))
    return arrays, static, n_save


@eqx.filter_jit
def _run_shared(tops, y0s, ts, t0, t1, rtol, atol, *, level, solver, stop_on_contact,
                max_steps, pieces, pack_width=SHARED_PACK_WIDTH):
    """`_run` for a batch whose members share their steps (`run_chain_shared`): `y0s` has a
    leading member axis, `tops` is one top or one per member. Returns `_run`'s outputs with
    the member axis leading, and each member's outcome and settled flag."""
    axes = top_axes(tops)
    out = run_chain_shared(
        level, tops, y0s, t0, t1, ts, stop_on_contact=stop_on_contact, solver=solver,
        rtol=rtol, atol=atol, max_steps=max_steps,
        # Not differentiated: the plain while loop of forward mode.
        adjoint=diffrax.ForwardMode(), progress_meter=diffrax.NoProgressMeter(),
        pieces=pieces, pack_width=pack_width,
    )
    fields = jax.vmap(
        lambda top, y0, o: _outputs(top, y0, ts, o, o.result, level=level),
        in_axes=(axes, 0, 0),
    )(tops, y0s, out)
    theta_end, jellet_launch = fields.pop("theta_end"), fields.pop("jellet_launch")
    outcome, settled = jax.vmap(_classify, in_axes=(axes, 0, 0, 0))(
        tops, jellet_launch, theta_end, fields["result"]
    )
    return dict(fields, outcome=outcome, settled=settled)


def simulate_tilt(top: TippeTop, y0: State, ts, *, t0, t1, model: str, rtol, atol,
                  solver=None, max_steps: int, adjoint, event_pieces: int = EVENT_PIECES) -> dict:
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
    guard_stiff = solver is None and not _concrete(top)
    if solver is None:
        solver = default_solver(top, slow_flow=LEVELS[model].slow_flow)
    out = _run(
        top, y0, jnp.asarray(ts, dtype), jnp.asarray(t0, dtype), jnp.asarray(t1, dtype),
        jnp.asarray(rtol, dtype), jnp.asarray(atol, dtype),
        level=dataclasses.replace(LEVELS[model], body=False), solver=solver,
        guard_stiff=guard_stiff, stop_on_contact=False, max_steps=int(max_steps),
        adjoint=adjoint, progress=False, pieces=int(event_pieces), names=("theta", "phi"),
        inversion=False, locate=False,
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
    if _concrete(sol.result):  # (read on the host: no device program)
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
                elif top is not None and _concrete(top):
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


__all__ = ["simulate", "MODELS"]
