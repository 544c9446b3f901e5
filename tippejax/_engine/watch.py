r"""Events that no step can hide: a solver wrapper that watches conditions along each step.

diffrax sees an event from the signs of its condition at the ends of each step. A condition that
falls through zero and rises again inside one step (the brief first dip of $R_n$ below zero
before a top leaves the table, `docs/notes.md`, Contact loss; a nutation that carries $\theta$ across $\pi/2$ and
back) is then missed, and high-order solvers at loose tolerances take steps long enough for that.

`WatchedSolver` wraps any diffrax solver. Along each step it follows every watched condition
$c(t)$ by its quintic Hermite interpolant in $s = (t - t_0)/h$: the values and time derivatives
of $c$ at the start, the middle and the end of the step,

$$c,\ \dot c = \nabla c\cdot\dot y \quad\text{at } s = 0, \tfrac12, 1,$$

with $\dot y$ the vector field at the end (the first-same-as-last stage of an FSAL solver, so no
extra evaluation), the dense output's derivative at the middle, and the previous step's end
values at the start (carried). The quintic is checked at `samples - 1` interior points. If one
condition changes sign more than once along them, the step is rejected (its error estimate is
set to infinity, so the step-size controller shrinks it) until no step holds more than one
crossing.

The quintic follows the condition to $O((h\nu)^6)$ of its swing over a step ($\nu$ the
nutation frequency). It replaced a check of the conditions themselves at `samples - 1` points
of the dense output (a dense-output evaluation and a condition evaluation each). On the first,
brief dip of $R_n$ of the standard top at 200 rad/s (2 ms below zero, 0.8% of the swing of the
contact condition), with exact data, over every placement of a step that holds the whole dip
(`benchmarks/watch.py`): both checks at the default 8 points see it in every placement of
steps up to half a nutation period (Dopri8 takes a third of one at rtol 1e-6); at 0.7 and 0.9
period the quintic sees it in 87% and 75% of them, the old check in 80% and 60% (the quintic
at 16 points: all). Per step the quintic costs one dense-output evaluation with its
derivative and two evaluations of the conditions with theirs; in a batch of 1000 SO(3) tops the
watch adds about a fifth of a plain solve's time at 8 points (16 points: about a quarter),
where the old check added a third (`benchmarks/RESULTS.md`, peers.py).

Then

- a *terminating* event (contact loss, the $R_n$ singularity, the end of a chart) ends the
  solve at the step in which its condition fell through zero (the watch sees it on the values
  it computes anyway, so no `diffrax.Event` evaluates the conditions again at every step), and
  `locate_terminating` finds the crossing on that step's dense output with `EventBisection`;
- an *observed* event, which does not stop the run (the inversion, contact loss when the run
  goes on past it), is recorded in the solver state: the first accepted step in which its
  condition fell through zero (its times and the state it started from). After the solve the
  step is taken again for its dense output, and `locate_observed` finds the crossing on it
  by a root find, which is differentiable through the
  implicit function theorem (as diffrax's events are).

Event times therefore do not depend on the save grid, and they are exact to the root finder's
tolerance whatever the solver's step length (the quintic only decides which step holds a
crossing; the crossing itself is found on the dense output).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, PyTree

EVENT_SAMPLES = 8
"""Points a step at which the watch checks each condition's quintic by default (`simulate`,
`simulate_tilt`, `inversion_time` and the staged maps; `benchmarks/watch.py` measures what it
finds)."""

STOP = diffrax.RESULTS.internal_error
"""The result a step returns when a terminating condition fell in it (see `WatchedSolver`):
a code diffrax keeps to the end of the solve, and that no diffrax solver returns."""


def ended_on_event(result, state) -> Bool[Array, ""]:
    """Whether a solve with a `WatchedSolver` ended on one of its terminating events."""
    return (result == STOP) & state.stopped


class EventBisection(optx.Bisection):
    """Bisection for event times, which stops on the width of the bracket alone.

    `optx.Bisection` also asks for |condition| < atol, which a condition of size O(10) with a
    steep slope cannot meet in floating point. The bracket is the step in which the sign
    changed, which holds exactly one crossing (see `WatchedSolver`); `flip=True` because every
    condition decreases through zero.
    """

    def terminate(self, fn, y, args, options, state, tags):
        del fn, args, options, tags
        width = jnp.abs(state.lower - state.upper)
        return width < self.atol + self.rtol * jnp.abs(y), optx.RESULTS.successful


def event_root_finder(dtype) -> EventBisection:
    tol = 1e-13 if dtype == jnp.float64 else 1e-6
    return EventBisection(rtol=tol, atol=tol, flip=True)


def _quintic_samples(samples: int) -> np.ndarray:
    r"""The matrix that maps the Hermite data of a condition over a step,
    $(c_0, h\dot c_0, c_{1/2}, h\dot c_{1/2}, c_1, h\dot c_1)$, to the values of its quintic
    interpolant at $s = k/$`samples`, $k = 1, \dots,$ `samples` $- 1$."""
    powers = np.arange(6)

    def value(s):
        return s**powers

    def slope(s):
        return powers * s ** np.maximum(powers - 1, 0)

    hermite = np.stack([value(0.0), slope(0.0), value(0.5), slope(0.5), value(1.0), slope(1.0)])
    s = np.arange(1, samples)[:, None] / samples
    return (s**powers) @ np.linalg.inv(hermite)


class _WatchState(eqx.Module):
    inner: PyTree
    previous: Float[Array, " n"]  # watched conditions at the start of the step
    # Their time derivatives there and, last, the number of accepted steps (diffrax keeps a
    # solver state only from those), in one vector: updated by one kernel. As a counter of its
    # own, or as diffrax's rejected-step counter, one more small kernel a step made XLA:CPU run
    # a single top's step on two threads, at twice the cost (47 against 25 ms for the standard
    # top's 20 s; `benchmarks/RESULTS.md`, peers.py).
    tally: Float[Array, " n+1"]
    last_t0: Float[Array, ""]  # the last accepted step (where a terminating event is located)
    last_t1: Float[Array, ""]
    last_y0: PyTree  # the state at its start (the step is taken again to locate the event)
    stopped: Bool[Array, ""]  # a terminating condition fell in the last step
    found: Bool[Array, " m"]  # observed event m already recorded
    step_t0: Float[Array, " m"]
    step_t1: Float[Array, " m"]
    step_y0: PyTree  # the state at the start of that step, leading axis m

    @property
    def previous_rate(self) -> Float[Array, " n"]:
        return self.tally[:-1]

    @property
    def accepted(self) -> Float[Array, ""]:
        return self.tally[-1]


class WatchedSolver(diffrax.AbstractWrappedSolver):
    """Wraps `solver` so that no accepted step holds more than one crossing of a watched
    condition, and records the step of the first downward crossing of each observed one.

    **Arguments:**

    - `solver`: any diffrax solver with an error estimate.
    - `watch`: `watch(y, args) -> Float[Array, "n"]`, the watched conditions of one state.
    - `observed`: indices (into `watch`'s output) of the observed, non-terminating events.
    - `samples`: number of sub-intervals of each step on which signs are checked.
    - `terminating`: indices of the terminating events. A step in which one of them falls
      through zero ends the solve: the step returns `STOP`, a failure code that diffrax
      keeps as the solve's result (the step itself is kept, and it is the last), and sets
      `stopped` in its state; `ended_on_event` reads the two together. (A solver's
      `event_occurred` would not do: diffrax replaces it by the step-size controller's
      `successful`.) The step is kept in the state (`last_t0`, `last_t1`, `last_y0`) for
      `locate_terminating`.
      Watching here, on the values the step computes anyway, replaces a `diffrax.Event`,
      which would evaluate the conditions a second time at every step and carry its own
      bookkeeping through the loop.
    """

    solver: diffrax.AbstractSolver
    watch: Callable[[PyTree, Any], Array]
    observed: tuple[int, ...] = eqx.field(static=True)
    samples: int = eqx.field(static=True, default=8)
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

    def init(self, terms, t0, t1, y0, args) -> _WatchState:
        m = len(self.observed)
        dtype = jnp.result_type(t0, t1)
        t0 = jnp.asarray(t0, dtype)
        stack = lambda x: jnp.broadcast_to(x, (m,) + jnp.shape(x))  # noqa: E731
        # Until an event is found its "step" is a dummy from y0, short enough that taking it
        # again after the solve is harmless (finite values and derivatives, which the masked
        # event time multiplies by zero), and long enough to be a step in this precision.
        tiny = jnp.finfo(dtype).eps * 64 * jnp.maximum(1.0, jnp.abs(t0))
        dummy = t0 + jnp.maximum(1e-6 * jnp.abs(jnp.asarray(t1, dtype) - t0), tiny)
        previous, previous_rate = self._watch_with_rate(
            y0, self.solver.func(terms, t0, y0, args), args
        )
        return _WatchState(
            inner=self.solver.init(terms, t0, t1, y0, args),
            previous=previous,
            tally=jnp.concatenate([previous_rate, jnp.zeros(1, previous_rate.dtype)]),
            last_t0=t0,
            last_t1=dummy,
            last_y0=y0,
            stopped=jnp.array(False),
            found=jnp.zeros(m, bool),
            step_t0=stack(t0),
            step_t1=stack(dummy),
            step_y0=jax.tree_util.tree_map(stack, y0),
        )

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
        evaluated."""
        if (
            isinstance(inner, tuple)
            and len(inner) == 2
            and jax.tree_util.tree_structure(inner[1]) == jax.tree_util.tree_structure(y1)
        ):
            return inner[1]
        return self.solver.func(terms, t1, y1, args)

    def _watched_step(self, terms, t0, t1, y0, args, inner, previous, previous_rate,
                      made_jump):
        """The inner solver's step, the watched conditions and their rates at its end, and
        the signs of every condition along it (`_signs`, from `previous` and `previous_rate`
        at its start): `(y1, y_error, dense_info, inner, result, end, end_rate, positive)`."""
        y1, y_error, dense_info, inner, result = self.solver.step(
            terms, t0, t1, y0, args, inner, made_jump
        )
        h = t1 - t0
        y_mid, y_mid_dot = _midpoint(self.solver, dense_info, h)
        # Both points through the conditions (and their jvp) at once: as two separate calls XLA
        # fused them with the dense output into one loop that recomputed much of it (2.3x a
        # plain solve for one top, against 1.1x).
        points = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), y_mid, y1)
        tangents = jax.tree_util.tree_map(
            lambda a, b: jnp.stack([a, b.astype(a.dtype)]),
            y_mid_dot, self._end_rate(terms, t1, y1, args, inner),
        )
        values, rates = jax.vmap(lambda y, y_dot: self._watch_with_rate(y, y_dot, args))(
            points, tangents
        )
        end, end_rate = values[1], rates[1]
        positive = _signs(previous, previous_rate, values[0], rates[0], end, end_rate, h,
                          self.samples)
        return y1, y_error, dense_info, inner, result, end, end_rate, positive

    def step(self, terms, t0, t1, y0, args, solver_state: _WatchState, made_jump):
        y1, y_error, dense_info, inner, result, end, end_rate, positive = self._watched_step(
            terms, t0, t1, y0, args, solver_state.inner, solver_state.previous,
            solver_state.previous_rate, made_jump,
        )
        changes = jnp.sum(positive[1:] != positive[:-1], axis=0)
        hidden = jnp.any(changes > 1)
        if y_error is not None:
            y_error = jax.tree_util.tree_map(lambda e: jnp.where(hidden, jnp.inf, e), y_error)
        observed = jnp.asarray(self.observed, int)
        fell = jnp.any(positive[:-1, observed] & ~positive[1:, observed], axis=0)
        new = fell & ~solver_state.found
        time_dtype = solver_state.step_t0.dtype
        t0, t1 = jnp.asarray(t0, time_dtype), jnp.asarray(t1, time_dtype)
        take = lambda a, b: jnp.where(  # noqa: E731
            new.reshape(new.shape + (1,) * (jnp.ndim(a) - 1)), a, b
        )
        stack = lambda x: jnp.broadcast_to(x, new.shape + jnp.shape(x))  # noqa: E731
        stopped = jnp.array(False)
        if self.terminating:
            stops = jnp.asarray(self.terminating, int)
            stopped = jnp.any(positive[:-1, stops] & ~positive[1:, stops]) & (
                result == diffrax.RESULTS.successful
            )
            result = diffrax.RESULTS.where(stopped, STOP, result)
        # Where events fell is written only in the steps where one did (a conditional: in a
        # run of one top, bookkeeping updated at every step made XLA:CPU run the step's small
        # kernels on two threads, at twice the cost of a step).
        def write(book):
            found, step_t0, step_t1, step_y0, last_t0, last_t1, last_y0 = book
            return (
                found | new,
                take(stack(t0), step_t0),
                take(stack(t1), step_t1),
                jax.tree_util.tree_map(lambda a, b: take(stack(a), b).astype(b.dtype), y0,
                                       step_y0),
                jnp.where(stopped, t0, last_t0),
                jnp.where(stopped, t1, last_t1),
                jax.tree_util.tree_map(lambda a, b: jnp.where(stopped, a.astype(b.dtype), b),
                                       y0, last_y0),
            )

        book = (solver_state.found, solver_state.step_t0, solver_state.step_t1,
                solver_state.step_y0, solver_state.last_t0, solver_state.last_t1,
                solver_state.last_y0)
        book = jax.lax.cond(jnp.any(new) | stopped, write, lambda b: b, book)
        found, step_t0, step_t1, step_y0, last_t0, last_t1, last_y0 = book
        state = _WatchState(
            inner=inner,
            previous=end,
            tally=jnp.concatenate([end_rate, solver_state.tally[-1:] + 1]),
            last_t0=last_t0,
            last_t1=last_t1,
            last_y0=last_y0,
            stopped=stopped,
            found=found,
            step_t0=step_t0,
            step_t1=step_t1,
            step_y0=step_y0,
        )
        return y1, y_error, dense_info, state, result


def _signs(previous, previous_rate, mid, mid_rate, end, end_rate, h, samples: int):
    """Whether each condition is positive at the start of a step, at its `samples - 1` check
    points (its quintic, see the module docstring) and at its end: shape
    `(samples + 1,) + end.shape` (the conditions on the last axis, any leading axes before)."""
    h = h.astype(end.dtype)
    data = (previous, h * previous_rate, mid, h * mid_rate, end, h * end_rate)
    # The quintic at the check points: a sum of scaled rows, which XLA fuses (as a matrix
    # product it ran as a small batched dot per member of a batch).
    weights = _quintic_samples(samples).astype(np.dtype(end.dtype))
    lead = (1,) * end.ndim
    interior = sum(weights[:, j].reshape((-1,) + lead) * data[j][None] for j in range(6))
    values = jnp.concatenate([previous[None], interior, end[None]])
    return values > 0


class _SharedWatchState(eqx.Module):
    """`_WatchState` for a batch whose members share their steps: every field has a member
    axis but the inner solver's state and the count of accepted steps (the steps are
    common); the member axis leads in the times and flags, and is LAST in the states
    (`last_y0` leaves `(w, N)`, `step_y0` leaves `(w, N, m)`), as in the solve's state.
    `stopped` marks the members frozen since a terminating event (or from the start,
    `SharedWatchedSolver.idle`)."""

    inner: PyTree
    previous: Float[Array, "N n"]
    previous_rate: Float[Array, "N n"]
    accepted: Float[Array, ""]
    last_t0: Float[Array, " N"]
    last_t1: Float[Array, " N"]
    last_y0: PyTree
    stopped: Bool[Array, " N"]
    found: Bool[Array, "N m"]
    step_t0: Float[Array, "N m"]
    step_t1: Float[Array, "N m"]
    step_y0: PyTree  # trailing axes (N, m): each member's own state only

    def member_states(self) -> _WatchState:
        """The per-member records as a `_WatchState` with a leading member axis, for
        `jax.vmap` of `locate_observed` and `locate_terminating` (which read only these)."""
        lead = lambda x, k: jnp.moveaxis(x, tuple(range(x.ndim - k, x.ndim)),  # noqa: E731
                                         tuple(range(k)))
        return _WatchState(
            inner=None, previous=None, tally=None, last_t0=self.last_t0,
            last_t1=self.last_t1,
            last_y0=jax.tree_util.tree_map(lambda x: lead(x, 1), self.last_y0),
            stopped=self.stopped, found=self.found, step_t0=self.step_t0,
            step_t1=self.step_t1,
            step_y0=jax.tree_util.tree_map(lambda x: lead(x, 2), self.step_y0),
        )


class SharedWatchedSolver(WatchedSolver):
    """`WatchedSolver` for a batch of members integrated as one state with shared steps.

    The state's leaves have the members as their LAST axis (`segment.MEMBER_AXIS`);
    `watch(y, args)` returns the conditions of every member, shape `(N, n)`. Each member is
    watched as `WatchedSolver` watches one run, and:

    - a step is rejected if a condition of ANY running member changes sign more than once
      inside it (its error is set to infinity, so the batch norm is infinite);
    - observed events are recorded per member (`found`, `step_t0`, `step_t1` of shape
      `(N, m)`, `step_y0` that member's own state), so that after the solve each member's
      event is located on its own step, taken again for that member alone;
    - a terminating event does not end the solve: it FREEZES its member. From the step it
      fell in, the member's new state is the state it started that step from (kept with the
      step in `last_t0`, `last_t1`, `last_y0` for `locate_terminating`), and from the next
      step on its error is zero, so that it no longer sets the step size. The step it fell in
      keeps its error (the crossing is located on that step's dense output, which must be as
      accurate as in a run of its own). Whatever a frozen member's lane computes after (its
      stages from a state past its event may be nan or inf) is discarded with `jnp.where`,
      never multiplied, so it cannot reach the norm or the other members;
    - the solve ends (the step returns `STOP`) when every member is frozen, else at `t1`.

    `idle`: members that do not run at all (frozen from the start, no event recorded).
    """

    idle: Bool[Array, " N"] | None = None

    def init(self, terms, t0, t1, y0, args) -> _SharedWatchState:
        m = len(self.observed)
        dtype = jnp.result_type(t0, t1)
        t0 = jnp.asarray(t0, dtype)
        previous, previous_rate = self._watch_with_rate(
            y0, self.solver.func(terms, t0, y0, args), args
        )
        n_members = previous.shape[0]
        # The dummy step of `WatchedSolver.init`, for members with no event recorded.
        tiny = jnp.finfo(dtype).eps * 64 * jnp.maximum(1.0, jnp.abs(t0))
        dummy = t0 + jnp.maximum(1e-6 * jnp.abs(jnp.asarray(t1, dtype) - t0), tiny)
        per_event = lambda x: jnp.broadcast_to(x[..., None], x.shape + (m,))  # noqa: E731
        idle = jnp.zeros(n_members, bool) if self.idle is None else self.idle
        return _SharedWatchState(
            inner=self.solver.init(terms, t0, t1, y0, args),
            previous=previous,
            previous_rate=previous_rate,
            accepted=jnp.zeros((), previous_rate.dtype),
            last_t0=jnp.full(n_members, t0),
            last_t1=jnp.full(n_members, dummy),
            last_y0=y0,
            stopped=idle,
            found=jnp.zeros((n_members, m), bool),
            step_t0=jnp.full((n_members, m), t0),
            step_t1=jnp.full((n_members, m), dummy),
            step_y0=jax.tree_util.tree_map(per_event, y0),
        )

    def step(self, terms, t0, t1, y0, args, solver_state: _SharedWatchState, made_jump):
        # end, end_rate: (N, n); positive: (samples + 1, N, n)
        y1, y_error, dense_info, inner, result, end, end_rate, positive = self._watched_step(
            terms, t0, t1, y0, args, solver_state.inner, solver_state.previous,
            solver_state.previous_rate, made_jump,
        )
        frozen = solver_state.stopped
        running = ~frozen
        changes = jnp.sum(positive[1:] != positive[:-1], axis=0)
        hidden = jnp.any(changes > 1, axis=-1) & running
        fell = jnp.any(positive[:-1] & ~positive[1:], axis=0)  # (N, n)
        observed = jnp.asarray(self.observed, int)
        new = fell[:, observed] & ~solver_state.found & running[:, None]
        stops_now = jnp.zeros_like(running)
        if self.terminating:
            stops = jnp.asarray(self.terminating, int)
            stops_now = jnp.any(fell[:, stops], axis=-1) & running & (
                result == diffrax.RESULTS.successful
            )
        hold = frozen | stops_now

        # Masks over the members, `(N,)` or `(N, m)`, broadcast against the states' trailing
        # member axes: `(w, N)` or `(w, N, m)`.
        y1 = jax.tree_util.tree_map(
            lambda a, b: jnp.where(hold, a.astype(b.dtype), b), y0, y1
        )
        if y_error is not None:
            y_error = jax.tree_util.tree_map(
                lambda e: jnp.where(frozen, jnp.zeros((), e.dtype),
                                    jnp.where(hidden, jnp.inf, e)),
                y_error,
            )
        stopped = hold
        every = jnp.all(stopped)
        result = diffrax.RESULTS.where(every & (result == diffrax.RESULTS.successful), STOP,
                                       result)
        time_dtype = solver_state.step_t0.dtype
        t0, t1 = jnp.asarray(t0, time_dtype), jnp.asarray(t1, time_dtype)

        def write(book):
            found, step_t0, step_t1, step_y0, last_t0, last_t1, last_y0 = book
            at_event = lambda x: x[..., None]  # (w, N) -> (w, N, 1), against (w, N, m)  # noqa: E731
            return (
                found | new,
                jnp.where(new, t0, step_t0),
                jnp.where(new, t1, step_t1),
                jax.tree_util.tree_map(
                    lambda a, b: jnp.where(new, at_event(a).astype(b.dtype), b), y0, step_y0
                ),
                jnp.where(stops_now, t0, last_t0),
                jnp.where(stops_now, t1, last_t1),
                jax.tree_util.tree_map(
                    lambda a, b: jnp.where(stops_now, a.astype(b.dtype), b), y0, last_y0
                ),
            )

        book = (solver_state.found, solver_state.step_t0, solver_state.step_t1,
                solver_state.step_y0, solver_state.last_t0, solver_state.last_t1,
                solver_state.last_y0)
        book = jax.lax.cond(jnp.any(new) | jnp.any(stops_now), write, lambda b: b, book)
        found, step_t0, step_t1, step_y0, last_t0, last_t1, last_y0 = book
        state = _SharedWatchState(
            inner=inner,
            previous=end,
            previous_rate=end_rate,
            accepted=solver_state.accepted + 1,
            last_t0=last_t0,
            last_t1=last_t1,
            last_y0=last_y0,
            stopped=stopped,
            found=found,
            step_t0=step_t0,
            step_t1=step_t1,
            step_y0=step_y0,
        )
        return y1, y_error, dense_info, state, result


def locate_observed(
    solver: WatchedSolver, terms, args, state: _WatchState, index: int, root_finder
) -> Float[Array, ""]:
    """Time of the first downward crossing of observed condition `index` (nan if none).

    Root-finds the condition on the recorded step's dense output. Differentiable (implicit function theorem through `optx.root_find`).
    """
    k = solver.observed.index(index)
    t0, t1 = state.step_t0[k], state.step_t1[k]
    y0 = jax.tree_util.tree_map(lambda x: x[k], state.step_y0)
    interpolation = _retake(solver, terms, t0, t1, y0, args)

    def fn(t, _):
        return solver.watch(interpolation.evaluate(t), args)[index].astype(t1.dtype)

    root = optx.root_find(
        fn, root_finder, y0=t1, options=dict(lower=t0, upper=t1), throw=False
    )
    return jnp.where(state.found[k], root.value, jnp.nan)


def locate_terminating(
    solver: WatchedSolver, terms, args, state: _WatchState, root_finder
) -> tuple[Float[Array, ""], PyTree]:
    """Time and state of the first terminating crossing in the last step of a solve that
    ended on one: the root of the smallest terminating condition on that step's dense
    output (differentiable through the implicit function theorem, as `locate_observed`)."""
    t0, t1 = state.last_t0, state.last_t1
    interpolation = _retake(solver, terms, t0, t1, state.last_y0, args)
    stops = jnp.asarray(solver.terminating, int)

    def fn(t, _):
        return jnp.min(solver.watch(interpolation.evaluate(t), args)[stops]).astype(t1.dtype)

    root = optx.root_find(
        fn, root_finder, y0=t1, options=dict(lower=t0, upper=t1), throw=False
    )
    return root.value, interpolation.evaluate(root.value)


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


def _retake(solver: WatchedSolver, terms, t0, t1, y0, args):
    """The dense output of the step from `y0` over `[t0, t1]`, taken again after the solve.

    The watch keeps only where an event's step started (its times and state), not the step's
    dense output: carrying the dense output (for Dopri8, its 14 stages) through every step
    of the loop cost more than the one step taken again here. From the same state over the
    same interval the step's stages are the same (a first-same-as-last stage is recomputed
    from the same state), so the interpolant is the one the solve saw."""
    inner = solver.solver.init(terms, t0, t1, y0, args)
    _, _, dense_info, _, _ = solver.solver.step(terms, t0, t1, y0, args, inner, False)
    return solver.solver.interpolation_cls(t0=t0, t1=t1, **dense_info)
