"""One segment of a run: one `diffrax.diffeqsolve` of one level, with its events watched and
located (`watch.py`, `events.py`)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from diffrax._root_finder import use_stepsize_tol  # diffrax exports no public name for it
from jaxtyping import Array, Bool, Float, PyTree

from .._models.base import AbstractLevel
from .events import EventRecords, event_root_finder, locate_observed, locate_terminating
from .unrolled import StageLoopERK, UnrolledERK, own_stage_loop, unroll_stages, unrollable
from .watch import STOP, SharedWatchedSolver, WatchedSolver, ended_on_event


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


PACK_WIDTH = 6
"""Most components in one flat vector of a level state in a batch (see `ravel_state`): a
user's `jax.vmap`, a GPU, and tippejax's own batches compiled with its CPU options
(`tippejax._engine.cpu`) alike: for the full level 4 + 6 + 4, faster in a batch than the
whole state in one vector (see the performance page)."""

ONE_TOP_PACK_WIDTH = 64
"""Most components in one flat vector of a level state in a run of one top: the whole state
in one vector (see `ravel_state`)."""

FORWARD_MODE_PACK_WIDTH = ONE_TOP_PACK_WIDTH
"""Most components in one flat vector of a level state in a run of one top differentiated in
forward mode (`adjoint=diffrax.ForwardMode()`, and the Jacobian of `simulate`'s default
adjoint): the whole state in one vector, as undifferentiated (see `ravel_state`)."""

STEP_CONTROL = dict(pcoeff=0.4, icoeff=0.3)
"""The step-size controller's coefficients (`diffrax.PIDController`): a PI controller, the
first of diffrax's suggestions for problems whose error estimate does not vary smoothly,
instead of diffrax's default I controller (pcoeff 0, icoeff 1)."""


SHARED_PACK_WIDTH = 4
"""Most components in one flat vector of a member's state in a batch with shared steps
(`run_segment_shared`; see `ravel_state`): SO(3) axis, omega (3 + 3), full position and
velocity, axis, omega (4 + 3 + 3). With the members last (`MEMBER_AXIS`) every component is a
row of the batch, and narrower vectors give XLA:CPU smaller loops over the rows."""


def pack_width_for(*trees, adjoint=None) -> int:
    """A batch's width, `PACK_WIDTH`, where any leaf of `trees` is batched by `jax.vmap` (seen
    at trace time); else `FORWARD_MODE_PACK_WIDTH` with `adjoint=diffrax.ForwardMode()`, else
    `ONE_TOP_PACK_WIDTH`. JAX has no public test for "inside vmap"; where its private
    tracer class is not found, the batch layout is used (only speed depends on the choice). A
    function jitted inside `jax.vmap` is traced unbatched and gets the one-top layout."""
    try:
        from jax._src.interpreters.batching import BatchTracer
    except ImportError:  # pragma: no cover
        return PACK_WIDTH
    leaves = jax.tree_util.tree_leaves(trees)
    if any(isinstance(x, BatchTracer) for x in leaves):
        return PACK_WIDTH
    if isinstance(adjoint, diffrax.ForwardMode):
        return FORWARD_MODE_PACK_WIDTH
    return ONE_TOP_PACK_WIDTH


def ravel_state(y: PyTree, width: int = PACK_WIDTH):
    """A level state as a tuple of flat vectors, with the inverse: the leaves, in order, packed
    whole into vectors of at most `width` components (`PACK_WIDTH`, in a batch: SO(3) axis and
    omega, then frame and spin angle, 6 + 4; full: 4 + 6 + 4; `ONE_TOP_PACK_WIDTH`, for one
    top: one vector).

    diffrax's Runge-Kutta stages combine the state leaf by leaf; with two or three leaves
    instead of the level's five or six, each step runs several times fewer (tiny) operations,
    which on a CPU is what a step of a 10-dimensional system costs. In a batch the leaves are
    not all concatenated into one vector because XLA:CPU runs the stage combinations of a
    batch of some widths much slower than of others (`PACK_WIDTH`).

    A run of one top wants the opposite: with two or more vectors the stage combinations of a
    step are independent chains of operations, and XLA:CPU's thunk executor then runs the step
    on two threads (it runs a program sequentially only if it is a chain or all its buffers
    are at most 512 bytes), which for steps this small costs more than it gains. So one top
    keeps its state in one vector (`ONE_TOP_PACK_WIDTH`), also when differentiated in forward
    mode (each vector then carries a batch of tangents; `FORWARD_MODE_PACK_WIDTH`). A
    vmapped batch keeps `PACK_WIDTH`.
    """
    leaves, treedef = jax.tree_util.tree_flatten(y)
    dtype = jnp.result_type(*leaves)
    shapes = [jnp.shape(x) for x in leaves]
    sizes = [math.prod(shape) for shape in shapes]
    groups, filled = [], width
    for i, size in enumerate(sizes):
        if not groups or filled + size > width:
            groups.append([])
            filled = 0
        groups[-1].append(i)
        filled += size
    flat = tuple(
        jnp.concatenate([jnp.ravel(jnp.asarray(leaves[i], dtype)) for i in group])
        for group in groups
    )

    def unravel(flat):
        out = [None] * len(leaves)
        for group, vector in zip(groups, flat):
            start = 0
            for i in group:
                out[i] = vector[start : start + sizes[i]].reshape(shapes[i])
                start += sizes[i]
        return jax.tree_util.tree_unflatten(treedef, out)

    return flat, unravel


class FlatField(eqx.Module):
    """A level's vector field on its state flattened by `ravel_state` (one or two leaves)."""

    level: AbstractLevel
    unravel: Callable = eqx.field(static=True)
    width: int = eqx.field(static=True, default=PACK_WIDTH)

    def __call__(self, t, y, top):
        return ravel_state(self.level.vector_field(t, self.unravel(y), top), self.width)[0]

    def error_norm(self, scaled_error):
        return self.level.error_norm(self.unravel(scaled_error))


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
            t_event, flat_event = locate_terminating(watched, terms, top, records, finder)
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
            t_obs = locate_observed(watched, terms, top, records, len(terminating) + i, finder)
        else:
            t_obs = jnp.where(records.found[i], records.step_t0[i], jnp.nan)
        observed_times[name] = jnp.where(t_obs <= t_end, t_obs, jnp.nan)
    return t_end, flat_end, fired, observed_times


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


def top_axes(top):
    """`jax.vmap`'s `in_axes` for a top whose fields are scalars (shared by every member) or
    1-d (one value per member)."""
    return jax.tree_util.tree_map(lambda x: 0 if jnp.ndim(x) == 1 else None, top)


MEMBER_AXIS = -1
"""Where the members are in the leaves of a shared solve's state: LAST, each leaf `(w, N)`,
so that each component of the batch is one contiguous row and the stages' arithmetic runs
along the members (structure of arrays), on CPUs and GPUs alike; with the field's algebra
written out by components (`rigid_body_dynamics_by_components`) it vectorises along them."""


def members_last(tree):
    """Leaves `(N, ...)` -> `(..., N)`: the layout of a shared solve's state."""
    return jax.tree_util.tree_map(lambda x: jnp.moveaxis(x, 0, -1), tree)


def members_first(tree):
    """Leaves `(..., N)` -> `(N, ...)`: one member per leading index, for `jax.vmap`."""
    return jax.tree_util.tree_map(lambda x: jnp.moveaxis(x, -1, 0), tree)


class SharedField(eqx.Module):
    """The vector field of a batch integrated as one state: `FlatField` vmapped over the
    members (the LAST axis of every leaf, `MEMBER_AXIS`); `args` is the top, one or one per
    member."""

    field: FlatField
    axes: PyTree = eqx.field(static=True)  # `top_axes` of the top

    def __call__(self, t, y, top):
        return jax.vmap(self.field, in_axes=(None, MEMBER_AXIS, self.axes), out_axes=MEMBER_AXIS)(
            t, y, top
        )

    def error_norm(self, scaled_error):
        """The largest of the members' own norms (`FlatField.error_norm`): a step is accepted
        when it is accurate enough for every member, as each member's own run asks."""
        return jnp.max(jax.vmap(self.field.error_norm, in_axes=MEMBER_AXIS)(scaled_error))


class SharedWatch(eqx.Module):
    """`Watch` vmapped over the members (the last axis of the state's leaves): the conditions
    of a batch, shape `(N, n)`."""

    watch: Watch
    axes: PyTree = eqx.field(static=True)

    def __call__(self, y, top):
        return jax.vmap(self.watch, in_axes=(MEMBER_AXIS, self.axes))(y, top)


def run_segment_shared(
    level: AbstractLevel,
    top,
    y0: PyTree,
    t0,
    t1,
    ts: Float[Array, " n"] | None,
    *,
    idle: Bool[Array, " N"],
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
    pack_width: int = PACK_WIDTH,
) -> Segment:
    """`run_segment` for a batch of members with shared steps: one `diffrax.diffeqsolve` whose
    state is every member's state (`y0`'s leaves have a leading member axis N; in the solve
    the members are the last axis, `MEMBER_AXIS`), with the members' field vmapped, the error
    norm the largest member norm, and the events watched per member by `SharedWatchedSolver`
    (a member whose terminating event fell is frozen while the others go on). `top`: one top,
    or one per member (see `top_axes`). `t0`, `t1` are common; `idle` marks members that do
    not run (their segment has zero length, as in `run_segment` with `t1 = t0`).

    Per member, the result is what `run_segment` gives (a `Segment` whose every leaf has the
    leading axis N) to about the tolerances: the steps differ, and each member's events are
    located on its own step, taken again for that member alone (`run_segment`'s own end of a
    run, vmapped). `num_steps` and `num_rejected_steps` are the shared solve's, for every
    member. Under `jax.vmap` of `run_segment` instead, each member has its own step size and
    the while loop runs batched with selects at every step, which costs several times one
    loop over the whole batch.

    A function of its own rather than a flag of `run_segment`: the state's layout (members
    last), the field, the watch and the solver differ, and idle members need their own
    masks."""
    # the field's algebra written out by components: with the members last it vectorises
    # along them (`AbstractLevel.by_components`)
    level = dataclasses.replace(level, by_components=True)
    names = terminating + observed
    member0 = jax.tree_util.tree_map(lambda x: x[0], y0)
    _, unravel = ravel_state(member0, pack_width)
    y0_members = jax.vmap(lambda y: ravel_state(y, pack_width)[0])(y0)  # leaves (N, w)
    field = FlatField(level, unravel, pack_width)
    watch = Watch(level, unravel, names)
    axes = top_axes(top)
    shared_field = SharedField(field, axes)
    controller = diffrax.PIDController(
        rtol=rtol, atol=atol, norm=shared_field.error_norm, **STEP_CONTROL
    )
    solver = _prepared_solver(solver, controller, adjoint)
    indices = _event_indices(terminating, observed)
    watched = SharedWatchedSolver(
        solver, SharedWatch(watch, axes), **indices, pieces=pieces, idle=idle
    )
    sol = _solve(
        diffrax.ODETerm(shared_field),
        watched,
        controller,
        top,
        members_last(y0_members),
        t0,
        t1,
        ts,
        max_steps=max_steps,
        adjoint=adjoint,
        progress_meter=progress_meter,
    )
    state = sol.solver_state
    ended = state.stopped & ~idle  # frozen by a terminating event
    common = diffrax.RESULTS.where(sol.result == STOP, diffrax.RESULTS.successful, sol.result)
    solver_result = jax.vmap(
        lambda ended, idle: diffrax.RESULTS.where(
            idle,
            diffrax.RESULTS.successful,
            diffrax.RESULTS.where(ended, diffrax.RESULTS.event_occurred, common),
        )
    )(ended, idle)
    # Each member's end as a run of its own would find it, on its own step.
    single = WatchedSolver(solver, watch, **indices, pieces=pieces)
    finder = event_root_finder(jnp.result_type(t0))
    t_end, flat_end, fired, observed_times = jax.vmap(
        lambda top, records, ended, flat_last: _run_end(
            single,
            diffrax.ODETerm(field),
            top,
            records,
            ended,
            sol.ts[0][-1],
            flat_last,
            terminating,
            observed,
            locate=locate,
            finder=finder,
        ),
        in_axes=(axes, 0, 0, 0),
    )(
        top,
        state.member_states(),
        ended,
        members_first(jax.tree_util.tree_map(lambda x: x[-1], sol.ys[0])),
    )
    # Idle members end where they started, with no event.
    t_end = jnp.where(idle, jnp.asarray(t0, t_end.dtype), t_end)
    flat_end = jax.tree_util.tree_map(
        lambda a, b: jnp.where(
            idle.reshape(idle.shape + (1,) * (b.ndim - 1)), a.astype(b.dtype), b
        ),
        y0_members,
        flat_end,
    )
    observed_times = {name: jnp.where(idle, jnp.nan, t) for name, t in observed_times.items()}
    ys = None
    if ts is not None:
        ys = jax.vmap(jax.vmap(unravel))(  # (T, w, N) -> (N, T, w)
            jax.tree_util.tree_map(lambda x: jnp.moveaxis(x, -1, 0), sol.ys[1])
        )
    steps = jnp.where(idle, 0, jnp.asarray(sol.stats["num_steps"], int))  # idle: none
    return Segment(
        ys=ys,
        y_end=jax.vmap(unravel)(flat_end),
        t_end=t_end,
        solver_result=solver_result,
        fired=fired,
        observed=observed_times,
        num_steps=steps,
        num_rejected_steps=jnp.where(idle, 0, steps - state.accepted.astype(int)),
    )
