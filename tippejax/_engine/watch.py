r"""The event watch: a solver wrapper that follows every watched condition along each step, so
that no accepted step hides a crossing (derivation: `docs/derivations/event-watch.md`)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, PyTree

from .bernstein import bernstein_coefficients, fell, hidden_crossing, settled_signs
from .events import EventRecords
from .unrolled import AbstractTableauSolver

EVENT_PIECES = 1
"""Parts of a step on which the watch checks each condition's quintic by its Bernstein
coefficients, by default (`simulate`, `simulate_tilt`, `inversion_time` and the staged maps)."""

STOP = diffrax.RESULTS.internal_error
"""The result a step returns when a terminating condition fell in it (see `WatchedSolver`):
a code diffrax keeps to the end of the solve, and that no diffrax solver returns."""


def ended_on_event(result, state) -> Bool[Array, ""]:
    """Whether a solve with a `WatchedSolver` ended on one of its terminating events."""
    return (result == STOP) & state.stopped


class _RecordLayout(eqx.Module):
    """Where each part of `EventRecords` lies in `_WatchState.record` (static)."""

    events: int  # m
    treedef: Any
    shapes: tuple[tuple[int, ...], ...]
    dtypes: tuple[Any, ...]

    @property
    def size(self) -> int:  # components of one state
        return sum(math.prod(shape) for shape in self.shapes)

    def flat(self, y, dtype) -> Array:
        return jnp.concatenate([jnp.ravel(x).astype(dtype) for x in jax.tree_util.tree_leaves(y)])

    def unflat(self, vector) -> PyTree:
        """`vector`'s last axis as a state; leading axes are kept."""
        leaves, start = [], 0
        lead = vector.shape[:-1]
        for shape, dtype in zip(self.shapes, self.dtypes):
            size = math.prod(shape)
            leaves.append(vector[..., start : start + size].reshape(lead + shape).astype(dtype))
            start += size
        return jax.tree_util.tree_unflatten(self.treedef, leaves)

    def pack(
        self, found, stopped, step_t0, step_t1, step_y0, last_t0, last_t1, last_y0, dtype
    ) -> Array:
        m = self.events
        return jnp.concatenate(
            [
                found.astype(dtype),
                stopped.astype(dtype)[None],
                step_t0.astype(dtype),
                step_t1.astype(dtype),
                jnp.reshape(step_y0, (m * self.size,)).astype(dtype),
                last_t0.astype(dtype)[None],
                last_t1.astype(dtype)[None],
                last_y0.astype(dtype),
            ]
        )

    def unpack(self, record) -> EventRecords:
        m, n = self.events, self.size
        at = np.cumsum([0, m, 1, m, m, m * n, 1, 1, n])
        part = [record[..., a:b] for a, b in zip(at[:-1], at[1:])]
        lead = record.shape[:-1]
        return EventRecords(
            found=part[0] > 0.5,
            stopped=part[1][..., 0] > 0.5,
            step_t0=part[2],
            step_t1=part[3],
            step_y0=self.unflat(part[4].reshape(lead + (m, n))),
            last_t0=part[5][..., 0],
            last_t1=part[6][..., 0],
            last_y0=self.unflat(part[7]),
        )


class _WatchState(eqx.Module):
    inner: PyTree
    previous: Float[Array, " n"]  # watched conditions at the start of the step
    # Their time derivatives there, the lowest values so far of the conditions
    # `WatchedSolver.lowest` names and, last, the number of accepted steps (diffrax keeps a
    # solver state only from those), in one vector: updated by one kernel. One more small
    # kernel a step (a counter of its own, or diffrax's rejected-step counter) made XLA:CPU run
    # a single top's step on two threads, at a higher cost.
    tally: Float[Array, " n+k+1"]
    # `EventRecords` packed in one vector (`_RecordLayout`), written by one select: cheaper
    # per step than eight arrays in the loop's state.
    record: Float[Array, " k"]
    layout: _RecordLayout = eqx.field(static=True)

    @property
    def previous_rate(self) -> Float[Array, " n"]:
        return self.tally[: self.previous.shape[-1]]

    @property
    def lowest(self) -> Float[Array, " k"]:
        """The lowest value of each condition of `WatchedSolver.lowest` at the accepted steps'
        ends (and at the start)."""
        return self.tally[self.previous.shape[-1] : -1]

    @property
    def accepted(self) -> Float[Array, ""]:
        return self.tally[-1]

    def records(self) -> EventRecords:
        return self.layout.unpack(self.record)

    @property
    def stopped(self) -> Bool[Array, ""]:
        return self.layout.unpack(self.record).stopped


class AbstractWatchedSolver(diffrax.AbstractWrappedSolver):
    """What `WatchedSolver` and `SharedWatchedSolver` share: the wrapped solver's interface,
    and the watched step (the inner solver's step, and the signs of the Bernstein
    coefficients of every watched condition's quintic along it). The two differ in what they
    keep between steps and in what a terminating event does (it ends a run; it freezes one
    member of a batch)."""

    solver: diffrax.AbstractSolver
    watch: Callable[[PyTree, Any], Array]
    observed: tuple[int, ...] = eqx.field(static=True)
    pieces: int = eqx.field(static=True, default=1)
    terminating: tuple[int, ...] = eqx.field(static=True, default=())

    @property
    def term_structure(self):
        return self.solver.term_structure

    @property
    def interpolation_cls(self):  # pyright: ignore
        return self.solver.interpolation_cls

    @property
    def term_compatible_contr_kwargs(self):
        return self.solver.term_compatible_contr_kwargs

    def order(self, terms):
        return self.solver.order(terms)

    def strong_order(self, terms):
        return self.solver.strong_order(terms)

    def error_order(self, terms):
        return self.solver.error_order(terms)

    def func(self, terms, t0, y0, args):
        return self.solver.func(terms, t0, y0, args)

    # Implicit solvers (Kvaerno5) are asked for these by diffrax.
    @property
    def root_finder(self):
        return self.solver.root_finder

    @property
    def root_find_max_steps(self):
        return self.solver.root_find_max_steps

    @property
    def scan_kind(self):
        return self.solver.scan_kind

    def _still_watched(self, found, conditions: int):
        """Which conditions the hidden-crossing test counts, given `found` (`(..., m)`, the
        observed events recorded so far): every one but an observed event already recorded
        (only its first crossing is kept, so its later ones, such as a compliant contact's
        chatter after the ball's return, need not be split into steps of their own; the
        terminating events are not among the observed ones). Shape
        `found.shape[:-1] + (conditions,)`; None when nothing is observed (every condition
        counts)."""
        if not self.observed:
            return None
        watched = jnp.ones(found.shape[:-1] + (conditions,), bool)
        return watched.at[..., jnp.array(self.observed)].set(~found)

    def _start(self, terms, t0, t1, y0, args):
        """`t0` in the times' dtype, the end of a dummy step for the events not yet found,
        and the watched conditions and their rates at `y0`."""
        dtype = jnp.result_type(t0, t1)
        t0 = jnp.asarray(t0, dtype)
        # Until an event is found its "step" is a dummy from y0, short enough that taking it
        # again after the solve is harmless (finite values and derivatives, which the masked
        # event time multiplies by zero), and long enough to be a step in this precision.
        tiny = jnp.finfo(dtype).eps * 64 * jnp.maximum(1.0, jnp.abs(t0))
        dummy = t0 + jnp.maximum(1e-6 * jnp.abs(jnp.asarray(t1, dtype) - t0), tiny)
        previous, previous_rate = self._watch_with_rate(
            y0, self.solver.func(terms, t0, y0, args), args
        )
        return t0, dummy, previous, previous_rate

    def _watch_with_rate(self, y, y_dot, args):
        """The watched conditions at `y` and their time derivatives along `y_dot`. The watch
        only decides which steps to reject and where events fell, so no derivative of the
        solution is taken through it."""
        y, y_dot = jax.lax.stop_gradient((y, y_dot))
        values, rates = jax.jvp(lambda z: self.watch(z, args), (y,), (y_dot,))
        return values, rates.astype(values.dtype)

    def _end_rate(self, terms, t1, y1, args, inner):
        """The vector field at the end of the step: the first-same-as-last stage an FSAL
        solver (Dopri5, Dopri8, Tsit5, Kvaerno5) keeps in its state for the next step, else
        evaluated. tippejax's own Runge-Kutta steps (`UnrolledERK`, `StageLoopERK`) keep that
        stage as their whole state."""
        if isinstance(self.solver, AbstractTableauSolver):
            return inner
        if (
            isinstance(inner, tuple)
            and len(inner) == 2
            and jax.tree_util.tree_structure(inner[1]) == jax.tree_util.tree_structure(y1)
        ):
            return inner[1]
        return self.solver.func(terms, t1, y1, args)

    def _watched_step(self, terms, t0, t1, y0, args, inner, previous, previous_rate, made_jump):
        """The inner solver's step, the watched conditions and their rates at its end, and
        the signs of every condition along it (`bernstein_signs`, from `previous` and
        `previous_rate` at its start; within a condition's rounding floor, `Watch.floors`,
        the nearest sign outside it, `settled_signs`):
        `(y1, y_error, dense_info, inner, result, end, end_rate, positive)`."""
        y1, y_error, dense_info, inner, result = self.solver.step(
            terms, t0, t1, y0, args, inner, made_jump
        )
        h = t1 - t0
        y_mid, y_mid_dot = _midpoint(self.solver, dense_info, h)
        # Both points through the conditions (and their jvp) at once: as two separate calls XLA
        # fused them with the dense output into one loop that recomputed much of it.
        points = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), y_mid, y1)
        tangents = jax.tree_util.tree_map(
            lambda a, b: jnp.stack([a, b.astype(a.dtype)]),
            y_mid_dot,
            self._end_rate(terms, t1, y1, args, inner),
        )
        values, rates = jax.vmap(lambda y, y_dot: self._watch_with_rate(y, y_dot, args))(
            points, tangents
        )
        end, end_rate = values[1], rates[1]
        coefficients = bernstein_coefficients(
            previous, previous_rate, values[0], rates[0], end, end_rate, h, self.pieces
        )
        floors = self.watch.floors(args) if hasattr(self.watch, "floors") else None
        positive = coefficients > 0
        if floors is not None:  # (signs within a condition's rounding do not count)
            positive = settled_signs(positive, jnp.abs(coefficients) > floors[None])
        return y1, y_error, dense_info, inner, result, end, end_rate, positive


class WatchedSolver(AbstractWatchedSolver):
    r"""Wraps `solver` so that no accepted step holds more than one crossing of a watched
    condition, and records the step of the first downward crossing of each observed one.

    Along each step the watch follows every watched condition $c(t)$ by its quintic Hermite
    interpolant in $s = (t - t_0)/h$, from $c$ and $\dot c$ at the start, the middle and the
    end of the step. A step is rejected (its error estimate set to infinity, so that the
    step-size controller shrinks it) when the Bernstein coefficients of a condition's quintic,
    on `pieces` equal parts of the step, change sign more than once: they change sign at
    least as often as the quintic does, so no step is kept in which the quintic crosses zero
    and back. The crossing itself is found after the solve on the step's dense output
    (`locate_observed`, `locate_terminating`). The derivation is in
    `docs/derivations/event-watch.md`.

    **Arguments:**

    - `solver`: any diffrax solver with an error estimate.
    - `watch`: `watch(y, args) -> Float[Array, "n"]`, the watched conditions of one state.
    - `observed`: indices (into `watch`'s output) of the observed, non-terminating events.
    - `pieces`: number of equal parts of each step on whose Bernstein coefficients the
      quintic of each condition is checked.
    - `terminating`: indices of the terminating events. A step in which one of them falls
      through zero ends the solve: the step returns `STOP`, a failure code that diffrax
      keeps as the solve's result (the step itself is kept, and it is the last), and sets
      `stopped` in its state; `ended_on_event` reads the two together. (A solver's
      `event_occurred` would not do: diffrax replaces it by the step-size controller's
      `successful`.) The step is kept in the state (`last_t0`, `last_t1`, `last_y0`) for
      `locate_terminating`. Watching here, on the values the step computes anyway, replaces
      a `diffrax.Event`, which would evaluate the conditions a second time at every step and
      carry its own bookkeeping through the loop.
    - `lowest`: indices of conditions whose lowest value over the run (at the start and at
      the end of every accepted step) is kept, `_WatchState.lowest`: a cheap measure of how
      near a run came to an event it did not reach (an outcome map's indicators). Default
      none.
    """

    lowest: tuple[int, ...] = eqx.field(static=True, default=())

    def _lowest_of(self, values, like) -> list:
        """`[values[lowest]]` in `like`'s dtype, or `[]` when nothing is kept (the program is
        then what it was without `lowest`)."""
        if not self.lowest:
            return []
        return [values[jnp.array(self.lowest)].astype(like.dtype)]

    def init(self, terms, t0, t1, y0, args) -> _WatchState:
        m = len(self.observed)
        t0, dummy, previous, previous_rate = self._start(terms, t0, t1, y0, args)
        dtype = t0.dtype
        leaves, treedef = jax.tree_util.tree_flatten(y0)
        layout = _RecordLayout(
            m,
            treedef,
            tuple(jnp.shape(x) for x in leaves),
            tuple(jnp.result_type(x) for x in leaves),
        )
        record_dtype = jnp.result_type(dtype, *leaves)
        y_flat = layout.flat(y0, record_dtype)
        record = layout.pack(
            jnp.zeros(m, bool),
            jnp.array(False),
            jnp.full(m, t0),
            jnp.full(m, dummy),
            jnp.broadcast_to(y_flat, (m, y_flat.shape[0])),
            t0,
            dummy,
            y_flat,
            record_dtype,
        )
        return _WatchState(
            inner=self.solver.init(terms, t0, t1, y0, args),
            previous=previous,
            tally=jnp.concatenate(
                [
                    previous_rate,
                    *self._lowest_of(previous, previous_rate),
                    jnp.zeros(1, previous_rate.dtype),
                ]
            ),
            record=record,
            layout=layout,
        )

    def step(self, terms, t0, t1, y0, args, solver_state: _WatchState, made_jump):
        y1, y_error, dense_info, inner, result, end, end_rate, positive = self._watched_step(
            terms,
            t0,
            t1,
            y0,
            args,
            solver_state.inner,
            solver_state.previous,
            solver_state.previous_rate,
            made_jump,
        )
        layout, record = solver_state.layout, solver_state.record
        m, n = layout.events, layout.size
        found = record[:m] > 0.5
        hidden = hidden_crossing(positive, self._still_watched(found, end.shape[-1]))
        if y_error is not None:
            y_error = jax.tree_util.tree_map(lambda e: jnp.where(hidden, jnp.inf, e), y_error)
        new = fell(positive, self.observed) & ~found
        stopped = jnp.array(False)
        if self.terminating:
            stopped = jnp.any(fell(positive, self.terminating)) & (
                result == diffrax.RESULTS.successful
            )
            result = diffrax.RESULTS.where(stopped, STOP, result)
        # Where events fell: the first step of each observed event, and the step a terminating
        # one fell in, written with one select over the packed record, in the steps where one
        # fell (a conditional: in a run of one top, bookkeeping updated at every step made
        # XLA:CPU run the step's small kernels on two threads; under `vmap` the conditional
        # becomes that select).
        dtype = record.dtype
        t0, t1 = jnp.asarray(t0, dtype), jnp.asarray(t1, dtype)

        def write(record):
            y_flat = layout.flat(y0, dtype)
            written = layout.pack(
                jnp.ones(m, bool),
                stopped,
                jnp.full(m, t0),
                jnp.full(m, t1),
                jnp.broadcast_to(y_flat, (m, n)),
                t0,
                t1,
                y_flat,
                dtype,
            )
            where = layout.pack(
                new,
                jnp.array(True),
                new,
                new,
                jnp.broadcast_to(new[:, None], (m, n)),
                stopped,
                stopped,
                jnp.full(n, stopped),
                bool,
            )
            return jnp.where(where, written, record)

        record = jax.lax.cond(jnp.any(new) | stopped, write, lambda r: r, record)
        lowest = [
            jnp.minimum(solver_state.lowest, low)
            for low in self._lowest_of(end, solver_state.tally)
        ]
        state = _WatchState(
            inner=inner,
            previous=end,
            tally=jnp.concatenate([end_rate, *lowest, solver_state.tally[-1:] + 1]),
            record=record,
            layout=layout,
        )
        return y1, y_error, dense_info, state, result


def _midpoint(solver, dense_info, h):
    """The dense output and its time derivative at the middle of a step of length `h`.

    diffrax's local interpolations are polynomials in the normalised time $s = (t - t_0)/h$
    whose coefficients are the stages $k_i = h f_i$: evaluated on $[0, 1]$ at the constant
    $s = 1/2$ their weights are constants that XLA folds, and $dy/dt = (dy/ds)/h$ (checked
    against the interpolation on the step's own times for Dopri8, Dopri5, Tsit5 and Kvaerno5
    in `tests/test_engine.py`)."""
    unit = solver.interpolation_cls(t0=0.0, t1=1.0, **dense_info)
    half = jnp.asarray(0.5, jnp.result_type(h))
    y_mid, y_s = jax.jvp(unit.evaluate, (half,), (jnp.ones_like(half),))
    return y_mid, jax.tree_util.tree_map(lambda d: d / h.astype(d.dtype), y_s)
