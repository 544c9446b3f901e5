"""The event watch of a batch with shared steps: a terminating event freezes its member."""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, PyTree

from .bernstein import fell, hidden_crossing
from .events import EventRecords
from .watch import STOP, AbstractWatchedSolver


class _SharedWatchState(eqx.Module):
    """The watch's state for a batch whose members share their steps: every field has a member
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

    def member_states(self) -> EventRecords:
        """The per-member records with a leading member axis, for `jax.vmap` of
        `locate_observed` and `locate_terminating`."""

        def lead(x, k):
            return jnp.moveaxis(x, tuple(range(x.ndim - k, x.ndim)), tuple(range(k)))

        return EventRecords(
            last_t0=self.last_t0,
            last_t1=self.last_t1,
            last_y0=jax.tree_util.tree_map(lambda x: lead(x, 1), self.last_y0),
            stopped=self.stopped,
            found=self.found,
            step_t0=self.step_t0,
            step_t1=self.step_t1,
            step_y0=jax.tree_util.tree_map(lambda x: lead(x, 2), self.step_y0),
        )


class SharedWatchedSolver(AbstractWatchedSolver):
    """`WatchedSolver` for a batch of members integrated as one state with shared steps.

    The state's leaves have the members as their LAST axis (`shared.MEMBER_AXIS`);
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
        t0, dummy, previous, previous_rate = self._start(terms, t0, t1, y0, args)
        n_members = previous.shape[0]
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
        # end, end_rate: (N, n); positive: (5 * pieces + 1, N, n)
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
        frozen = solver_state.stopped
        running = ~frozen
        watched = self._still_watched(solver_state.found, end.shape[-1])
        hidden = hidden_crossing(positive, watched) & running
        new = fell(positive, self.observed) & ~solver_state.found & running[:, None]
        stops_now = jnp.zeros_like(running)
        if self.terminating:
            stops_now = (
                jnp.any(fell(positive, self.terminating), axis=-1)
                & running
                & (result == diffrax.RESULTS.successful)
            )
        hold = frozen | stops_now

        # Masks over the members, `(N,)` or `(N, m)`, broadcast against the states' trailing
        # member axes: `(w, N)` or `(w, N, m)`.
        y1 = jax.tree_util.tree_map(lambda a, b: jnp.where(hold, a.astype(b.dtype), b), y0, y1)
        if y_error is not None:
            y_error = jax.tree_util.tree_map(
                lambda e: jnp.where(frozen, jnp.zeros((), e.dtype), jnp.where(hidden, jnp.inf, e)),
                y_error,
            )
        stopped = hold
        every = jnp.all(stopped)
        result = diffrax.RESULTS.where(every & (result == diffrax.RESULTS.successful), STOP, result)
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

        book = (
            solver_state.found,
            solver_state.step_t0,
            solver_state.step_t1,
            solver_state.step_y0,
            solver_state.last_t0,
            solver_state.last_t1,
            solver_state.last_y0,
        )
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
