"""One segment of a run: one `diffrax.diffeqsolve` of one level, with its events watched and
located (`watch.py`, `events.py`), its state packed by `packing.py`."""

from __future__ import annotations

from collections.abc import Callable

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from diffrax._root_finder import use_stepsize_tol  # diffrax exports no public name for it
from jaxtyping import Array, Bool, Float, PyTree

from .._models.base import AbstractLevel
from .events import EventRecords, event_root_finder, locate_observed, locate_terminating
from .packing import PACK_WIDTH, FlatField, ravel_state
from .unrolled import StageLoopERK, UnrolledERK, own_stage_loop, unroll_stages, unrollable
from .watch import WatchedSolver, ended_on_event


def as_event_dtype(x):
    # diffrax compares event conditions with a Python 0.0 inside `lax.cond`: both branches
    # need the default float dtype, also for a float32 top in a float64 process.
    return jnp.asarray(x, dtype=jnp.result_type(float))


class Watch(eqx.Module):
    """The watched conditions of a level: terminating ones first, then observed ones."""

    level: AbstractLevel
    unravel: Callable = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True)

    def __call__(self, y, top):
        conditions = self.level.conditions(top, self.unravel(y))
        return as_event_dtype(jnp.stack([conditions.get(name) for name in self.names]))

    def floors(self, top):
        """Each watched condition's rounding floor (`AbstractLevel.condition_floors`; 0 for
        the conditions it does not name), or None where the level gives none."""
        given = self.level.condition_floors(top)
        if given is None:
            return None
        return as_event_dtype(jnp.stack([jnp.asarray(given.get(n, 0.0)) for n in self.names]))


STEP_CONTROL = dict(pcoeff=0.4, icoeff=0.3)
"""The step-size controller's coefficients (`diffrax.PIDController`): a PI controller, the
first of diffrax's suggestions for problems whose error estimate does not vary smoothly,
instead of diffrax's default I controller (pcoeff 0, icoeff 1)."""


class Segment(eqx.Module):
    """What one segment returns (single run; leading axes only under `vmap`)."""

    ys: PyTree | None  # level states at the save times (None in summary mode)
    y_end: PyTree  # level state where the segment ended
    t_end: Float[Array, ""]
    solver_result: diffrax.RESULTS
    fired: dict[str, Bool[Array, ""]]  # which terminating event stopped the segment
    observed: dict[str, Float[Array, ""]]  # first crossing time of each observed event
    num_steps: Array
    num_rejected_steps: Array
    # lowest value of each condition `run_segment(lowest=...)` names, at the accepted steps'
    # ends (and the start)
    lowest: dict[str, Float[Array, ""]] = eqx.field(default_factory=dict)


def run_segment(
    level: AbstractLevel,
    top,
    y0: PyTree,
    t0,
    t1,
    ts: Float[Array, " n"] | None,
    *,
    solver: diffrax.AbstractSolver,
    rtol,
    atol,
    terminating: tuple[str, ...],
    observed: tuple[str, ...],
    max_steps: int,
    adjoint: diffrax.AbstractAdjoint,
    progress_meter: diffrax.AbstractProgressMeter,
    pieces: int,
    locate: bool = True,
    pack_width: int | None = None,
    lowest: tuple[str, ...] = (),
) -> Segment:
    """Integrate `level` from `(t0, y0)` to `t1` or the first terminating event.

    With `locate=False` no event is located inside its step: an event's time is the start of
    the step in which its condition fell through zero (earlier than the crossing by less than
    a step), and a run that ends on a terminating event ends there, at the state that step
    started from. No step is taken again and no root is found, so the program is smaller to
    compile; for callers that need to know only which save times lie before an event (a
    fit's residuals). `pack_width`: the layout of the state in the solver (`ravel_state`;
    `pack_width_for` picks it; default: a batch's, `PACK_WIDTH`). `lowest`: watched conditions
    (among `terminating` and `observed`) whose lowest value over the segment is returned in
    `Segment.lowest` (`WatchedSolver`'s `lowest`)."""
    if pack_width is None:
        pack_width = PACK_WIDTH
    names = terminating + observed
    unknown = [name for name in lowest if name not in names]
    if unknown:
        raise ValueError(f"run_segment: lowest names {unknown}, not among the watched {names}.")
    y0_flat, unravel = ravel_state(y0, pack_width)
    field = FlatField(level, unravel, pack_width)
    watch = Watch(level, unravel, names)
    controller = diffrax.PIDController(rtol=rtol, atol=atol, norm=field.error_norm, **STEP_CONTROL)
    solver = _prepared_solver(solver, controller, adjoint)
    watched = WatchedSolver(
        solver,
        watch,
        **_event_indices(terminating, observed),
        pieces=pieces,
        lowest=tuple(names.index(n) for n in lowest),
    )
    terms = diffrax.ODETerm(field)
    sol = _solve(
        terms,
        watched,
        controller,
        top,
        y0_flat,
        t0,
        t1,
        ts,
        max_steps=max_steps,
        adjoint=adjoint,
        progress_meter=progress_meter,
    )
    # The watch ends the solve on the step where a terminating condition fell through zero
    # (its result is `event_occurred`); the crossing is then located inside that step.
    stopped = ended_on_event(sol.result, sol.solver_state)
    solver_result = diffrax.RESULTS.where(stopped, diffrax.RESULTS.event_occurred, sol.result)
    t_end, flat_end, fired, observed_times = _run_end(
        watched,
        terms,
        top,
        sol.solver_state.records(),
        stopped,
        sol.ts[0][-1],
        jax.tree_util.tree_map(lambda x: x[-1], sol.ys[0]),
        terminating,
        observed,
        locate=locate,
        finder=event_root_finder(jnp.result_type(t0)),
    )
    return Segment(
        ys=jax.vmap(unravel)(sol.ys[1]) if ts is not None else None,
        y_end=unravel(flat_end),
        t_end=t_end,
        solver_result=solver_result,
        fired=fired,
        observed=observed_times,
        num_steps=sol.stats["num_steps"],
        # Counted by the watch, not read from diffrax's own counter (see `_WatchState.tally`).
        num_rejected_steps=sol.stats["num_steps"] - sol.solver_state.accepted.astype(int),
        lowest={name: sol.solver_state.lowest[i] for i, name in enumerate(lowest)},
    )


def _event_indices(terminating, observed) -> dict[str, tuple[int, ...]]:
    """The indices of the observed and of the terminating events in a segment's watch, which
    lists the terminating ones first (a watched solver's `observed` and `terminating`)."""
    n = len(terminating)
    return dict(observed=tuple(range(n, n + len(observed))), terminating=tuple(range(n)))


def _solve(
    terms, watched, controller, top, y0_flat, t0, t1, ts, *, max_steps, adjoint, progress_meter
):
    """The segment's `diffrax.diffeqsolve`: saving the end (and the save times `ts` inside
    `[t0, t1]`) and the watch's final state."""
    subs = [diffrax.SubSaveAt(t1=True)]
    if ts is not None:
        subs.append(diffrax.SubSaveAt(ts=jnp.clip(ts, t0, t1)))
    return diffrax.diffeqsolve(
        terms,
        watched,
        t0,
        t1,
        None,
        y0_flat,
        top,
        saveat=diffrax.SaveAt(subs=subs, solver_state=True),
        stepsize_controller=controller,
        max_steps=max_steps,
        adjoint=adjoint,
        throw=False,
        progress_meter=progress_meter,
    )


def _run_end(
    watched: WatchedSolver,
    terms,
    top,
    records: EventRecords,
    stopped,
    t_last,
    flat_last,
    terminating,
    observed,
    *,
    locate: bool,
    finder,
):
    """Where one run's segment ended and what fired in it, from the watch's `records`: the
    end time and flat state (at the located terminating crossing where the run `stopped` on
    one, else its last saved time and state `t_last`, `flat_last`), which terminating event
    fired, and the time of each observed event (nan if none before the end)."""
    t_end, flat_end = t_last, flat_last
    if terminating:
        if locate:
            t_event, flat_event = _where_fired(
                stopped,
                lambda: locate_terminating(watched, terms, top, records, finder),
                (records.last_t1, records.last_y0),
            )
        else:
            t_event, flat_event = records.last_t0, records.last_y0
        t_end = jnp.where(stopped, t_event.astype(t_last.dtype), t_last)
        flat_end = jax.tree_util.tree_map(
            lambda a, b: jnp.where(stopped, a.astype(b.dtype), b), flat_event, flat_last
        )
    # Which terminating condition fired: at the located event it is (to the root finder's
    # tolerance) zero and the others are positive, so it is the smallest. Unlocated, it is the
    # smallest at the end of the step it fell in (where it is negative).
    end_values = watched.watch(flat_end if locate else flat_last, top)[: len(terminating)]
    first = jnp.argmin(end_values)
    fired = {name: stopped & (first == i) for i, name in enumerate(terminating)}
    observed_times = {}
    for i, name in enumerate(observed):
        if locate:
            t_obs = _where_fired(
                records.found[i],
                lambda i=i: locate_observed(
                    watched, terms, top, records, len(terminating) + i, finder
                ),
                jnp.asarray(jnp.nan, records.step_t1.dtype),
            )
        else:
            t_obs = jnp.where(records.found[i], records.step_t0[i], jnp.nan)
        observed_times[name] = jnp.where(t_obs <= t_end, t_obs, jnp.nan)
    return t_end, flat_end, fired, observed_times


def _where_fired(fired, locate, unfired):
    """`locate()` where the event `fired`, else `unfired` (of the same structure): the root
    find runs only for an event that fell in the run (`lax.cond`; under `vmap`, where the
    condition is batched, both branches run and the result is selected)."""

    def skip():
        return jax.tree_util.tree_map(
            lambda x, ref: jnp.asarray(x).astype(ref.dtype), unfired, jax.eval_shape(locate)
        )

    return jax.lax.cond(fired, locate, skip)


def _prepared_solver(solver, controller, adjoint):
    """`solver` as a segment runs it: an implicit solver's root finder given the controller's
    tolerances, the stage loop of a Runge-Kutta solver chosen for the adjoint, and an explicit
    one's stages written out where `unroll_stages()` (accelerators, by default), else run
    in tippejax's own stage loop (`StageLoopERK`)."""
    if isinstance(solver, diffrax.AbstractImplicitSolver):
        # diffrax gives an implicit solver's root finder the controller's tolerances; it
        # cannot see through the wrapper below, so do it here.
        attrs = [
            a
            for a in ("rtol", "atol", "norm")
            if getattr(solver.root_finder, a) is use_stepsize_tol
        ]
        solver = eqx.tree_at(
            lambda s: tuple(getattr(s.root_finder, a) for a in attrs),
            solver,
            tuple(getattr(controller, a) for a in attrs),
        )
    if isinstance(solver, diffrax.AbstractRungeKutta) and solver.scan_kind is None:
        # How the stages of a step loop. Reverse mode needs a differentiable loop
        # ("checkpointed", diffrax's own default for a bare solver); forward mode
        # (`adjoint=diffrax.ForwardMode()`) runs fastest as a plain "lax" loop. diffrax's
        # adjoints would pick "bounded" (so that `jax.jvp` can go through the checkpointed
        # solve), which makes every step several times dearer; forward mode has its own
        # adjoint instead.
        kind = "lax" if isinstance(adjoint, diffrax.ForwardMode) else "checkpointed"
        solver = eqx.tree_at(lambda s: s.scan_kind, solver, kind, is_leaf=lambda x: x is None)
    if unrollable(solver):
        # Same tableau, faster program (`tippejax._engine.unrolled`): on accelerators the
        # stages written out, on CPUs a stage loop without diffrax's transposed copy of the
        # stages.
        if unroll_stages():
            solver = UnrolledERK(solver)
        elif own_stage_loop():
            solver = StageLoopERK(solver)
    return solver
