"""A segment of a batch with shared steps: one solve whose state is every member's state."""

from __future__ import annotations

import dataclasses

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, PyTree

from .._models.base import AbstractLevel
from .events import event_root_finder
from .packing import PACK_WIDTH, FlatField, ravel_state
from .segment import (
    STEP_CONTROL,
    Segment,
    Watch,
    _event_indices,
    _prepared_solver,
    _run_end,
    _solve,
)
from .shared_watch import SharedWatchedSolver
from .watch import STOP, WatchedSolver


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
