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
values at the start (carried). A step is rejected (its error estimate is set to infinity, so
the step-size controller shrinks it) when the Bernstein coefficients of a condition's quintic
on the step (on `pieces` equal parts of it, `_bernstein_polygon`) change sign more than once:
by the variation-diminishing property of the Bernstein basis they change sign at least as
often as the quintic does, so no step is kept in which the quintic crosses zero and back.

The quintic follows the condition to $O((h\nu)^6)$ of its swing over a step ($\nu$ the
nutation frequency). The watch before checked its sign at `samples - 1` points of the step
(default 8), and before that the conditions themselves at as many points of the dense output.
On the first, brief dip of $R_n$ of the standard top at 200 rad/s (2 ms below zero, 0.8% of
the swing of the contact condition), with exact data, over every placement of a step that
holds the whole dip (`benchmarks/watch.py`): the 8-point quintic saw it in every placement of
steps up to half a nutation period (Dopri8 takes a third of one at rtol 1e-6) and in 87% and
75% of them at 0.7 and 0.9 period; the Bernstein coefficients see it in all. On 2304 random
launches of 24 random tops (full and SO(3) levels, seed 0), the two agree on every result
code and outcome, with 0.01% more steps; in one launch the 8-point check had passed over a
brief first contact loss that the Bernstein check finds (3.5387 s, a solve at rtol 1e-12
agreeing, against 3.5754 s; `tests/test_engine.py`). They cost less as well: six
coefficients, the first and last the end values, against seven points; a batch of 1000 SO(3)
tops in blocks of 125 (one CPU device, the engine's loop alone) ran the watch at 1.15x a plain
solve's time per step, the 8-point quintic at 1.29x. Per step the watch costs one
dense-output evaluation with its derivative and two evaluations of the conditions with
theirs.

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

import functools
import math
from collections.abc import Callable
from fractions import Fraction
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, PyTree

from .unrolled import AbstractTableauSolver

EVENT_PIECES = 1
"""Parts of a step on which the watch checks each condition's quintic by its Bernstein
coefficients, by default (`simulate`, `simulate_tilt`, `inversion_time` and the staged maps;
`benchmarks/watch.py` measures what it finds and what it rejects)."""

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


def _hermite_to_power() -> list[list[Fraction]]:
    r"""The exact matrix that maps the Hermite data of a condition over a step,
    $(c_0, h\dot c_0, c_{1/2}, h\dot c_{1/2}, c_1, h\dot c_1)$, to the power coefficients
    $a_0, \dots, a_5$ of its quintic interpolant $p(s) = \sum_j a_j s^j$, $s\in[0, 1]$: the
    inverse of the Hermite conditions, by Gauss-Jordan elimination in rationals (so that the
    weights that are zero are exactly zero)."""
    half = Fraction(1, 2)
    rows = []
    for s in (Fraction(0), half, Fraction(1)):
        rows.append([s**j for j in range(6)])
        rows.append([j * s ** (j - 1) if j else Fraction(0) for j in range(6)])
    n = 6
    aug = [row + [Fraction(int(i == k)) for k in range(n)] for i, row in enumerate(rows)]
    for col in range(n):
        pivot = next(r for r in range(col, n) if aug[r][col] != 0)
        aug[col], aug[pivot] = aug[pivot], aug[col]
        aug[col] = [x / aug[col][col] for x in aug[col]]
        for r in range(n):
            if r != col and aug[r][col] != 0:
                aug[r] = [x - aug[r][col] * y for x, y in zip(aug[r], aug[col])]
    return [row[n:] for row in aug]


def _matmul(a, b):
    return [[sum(x * b[k][j] for k, x in enumerate(row)) for j in range(len(b[0]))] for row in a]


def _quintic_samples(samples: int) -> np.ndarray:
    r"""The matrix that maps the Hermite data of a condition over a step (`_hermite_to_power`)
    to the values of its quintic interpolant at $s = k/$`samples`, $k = 1, \dots,$
    `samples` $- 1$ (the watch's check before the Bernstein polygon; `benchmarks/watch.py`
    compares the two)."""
    s = [[Fraction(k, samples) ** j for j in range(6)] for k in range(1, samples)]
    return np.array(_matmul(s, _hermite_to_power()), dtype=float)


@functools.cache
def _bernstein_polygon(pieces: int) -> np.ndarray:
    r"""The matrix that maps the Hermite data of a condition over a step (`_hermite_to_power`)
    to the Bernstein coefficients of its quintic on each of `pieces` equal parts of the step,
    in order, each part's last coefficient (its end value, the next part's first) once: shape
    `(5 * pieces + 1, 6)`, exact in rationals before it is rounded to floats.

    On part $k$, $s = (k + u)/P$, the quintic is $q(u) = \sum_i b_i \binom5i u^i(1-u)^{5-i}$
    with $q(u) = \sum_i c_i u^i$, $c_i = \sum_{j\ge i} a_j \binom ji k^{j-i}/P^j$ and
    $b_i = \sum_{l\le i} \binom il c_l / \binom5l$. By the variation-diminishing property of the
    Bernstein basis (Descartes' rule of signs after $u = x/(1+x)$), the number of roots of the
    quintic inside a part is at most the number of sign changes of that part's coefficients, so
    the sign changes of the whole sequence bound the crossings in the step from above."""
    to_bernstein = [[Fraction(math.comb(i, j), math.comb(5, j)) if j <= i else Fraction(0)
                     for j in range(6)] for i in range(6)]
    rows = []
    for k in range(pieces):
        shift = [[Fraction(math.comb(j, i) * k ** (j - i), pieces**j) if j >= i else Fraction(0)
                  for j in range(6)] for i in range(6)]
        part = _matmul(_matmul(to_bernstein, shift), _hermite_to_power())
        rows.extend(part if k == pieces - 1 else part[:-1])
    return np.array(rows, dtype=float)


class EventRecords(eqx.Module):
    """Where the events of a solve fell, as `locate_observed` and `locate_terminating` read
    them: the first accepted step of each observed event (`found`, its times `step_t0`,
    `step_t1` and the state it started from, `step_y0`, leading axis m) and the last accepted
    step (`last_t0`, `last_t1`, `last_y0`: the step a terminating event fell in, when
    `stopped`)."""

    found: Bool[Array, " m"]
    step_t0: Float[Array, " m"]
    step_t1: Float[Array, " m"]
    step_y0: PyTree
    last_t0: Float[Array, ""]
    last_t1: Float[Array, ""]
    last_y0: PyTree
    stopped: Bool[Array, ""]


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
            leaves.append(vector[..., start:start + size].reshape(lead + shape).astype(dtype))
            start += size
        return jax.tree_util.tree_unflatten(self.treedef, leaves)

    def pack(self, found, stopped, step_t0, step_t1, step_y0, last_t0, last_t1, last_y0,
             dtype) -> Array:
        m = self.events
        return jnp.concatenate([
            found.astype(dtype), stopped.astype(dtype)[None],
            step_t0.astype(dtype), step_t1.astype(dtype),
            jnp.reshape(step_y0, (m * self.size,)).astype(dtype),
            last_t0.astype(dtype)[None], last_t1.astype(dtype)[None], last_y0.astype(dtype),
        ])

    def unpack(self, record) -> EventRecords:
        m, n = self.events, self.size
        at = np.cumsum([0, m, 1, m, m, m * n, 1, 1, n])
        part = [record[..., a:b] for a, b in zip(at[:-1], at[1:])]
        lead = record.shape[:-1]
        return EventRecords(
            found=part[0] > 0.5, stopped=part[1][..., 0] > 0.5, step_t0=part[2],
            step_t1=part[3], step_y0=self.unflat(part[4].reshape(lead + (m, n))),
            last_t0=part[5][..., 0], last_t1=part[6][..., 0], last_y0=self.unflat(part[7]),
        )


class _WatchState(eqx.Module):
    inner: PyTree
    previous: Float[Array, " n"]  # watched conditions at the start of the step
    # Their time derivatives there and, last, the number of accepted steps (diffrax keeps a
    # solver state only from those), in one vector: updated by one kernel. As a counter of its
    # own, or as diffrax's rejected-step counter, one more small kernel a step made XLA:CPU run
    # a single top's step on two threads, at twice the cost (47 against 25 ms for the standard
    # top's 20 s; `benchmarks/RESULTS.md`, peers.py).
    tally: Float[Array, " n+1"]
    # `EventRecords` packed in one vector (`_RecordLayout`), written by one select: as eight
    # arrays of the loop's state, in a batch of 1000 SO(3) tops in blocks of 125 (one CPU
    # device, the engine's loop alone) they cost 9% of a plain solve's time per step, packed 4%.
    record: Float[Array, " k"]
    layout: _RecordLayout = eqx.field(static=True)

    @property
    def previous_rate(self) -> Float[Array, " n"]:
        return self.tally[:-1]

    @property
    def accepted(self) -> Float[Array, ""]:
        return self.tally[-1]

    def records(self) -> EventRecords:
        return self.layout.unpack(self.record)

    @property
    def stopped(self) -> Bool[Array, ""]:
        return self.layout.unpack(self.record).stopped


class WatchedSolver(diffrax.AbstractWrappedSolver):
    """Wraps `solver` so that no accepted step holds more than one crossing of a watched
    condition, and records the step of the first downward crossing of each observed one.

    **Arguments:**

    - `solver`: any diffrax solver with an error estimate.
    - `watch`: `watch(y, args) -> Float[Array, "n"]`, the watched conditions of one state.
    - `observed`: indices (into `watch`'s output) of the observed, non-terminating events.
    - `pieces`: number of equal parts of each step on whose Bernstein coefficients the
      quintic of each condition is checked (`_bernstein_polygon`).
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

    def init(self, terms, t0, t1, y0, args) -> _WatchState:
        m = len(self.observed)
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
        leaves, treedef = jax.tree_util.tree_flatten(y0)
        layout = _RecordLayout(m, treedef, tuple(jnp.shape(x) for x in leaves),
                               tuple(jnp.result_type(x) for x in leaves))
        record_dtype = jnp.result_type(dtype, *leaves)
        y_flat = layout.flat(y0, record_dtype)
        record = layout.pack(
            jnp.zeros(m, bool), jnp.array(False), jnp.full(m, t0), jnp.full(m, dummy),
            jnp.broadcast_to(y_flat, (m, y_flat.shape[0])), t0, dummy, y_flat, record_dtype,
        )
        return _WatchState(
            inner=self.solver.init(terms, t0, t1, y0, args),
            previous=previous,
            tally=jnp.concatenate([previous_rate, jnp.zeros(1, previous_rate.dtype)]),
            record=record,
            layout=layout,
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
                          self.pieces)
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
        layout, record = solver_state.layout, solver_state.record
        m, n = layout.events, layout.size
        new = fell & ~(record[:m] > 0.5)
        stopped = jnp.array(False)
        if self.terminating:
            stops = jnp.asarray(self.terminating, int)
            stopped = jnp.any(positive[:-1, stops] & ~positive[1:, stops]) & (
                result == diffrax.RESULTS.successful
            )
            result = diffrax.RESULTS.where(stopped, STOP, result)
        # Where events fell: the first step of each observed event, and the step a terminating
        # one fell in, written with one select over the packed record, in the steps where one
        # fell (a conditional: in a run of one top, bookkeeping updated at every step made
        # XLA:CPU run the step's small kernels on two threads, at twice the cost of a step;
        # under `vmap` the conditional becomes that select).
        dtype = record.dtype
        t0, t1 = jnp.asarray(t0, dtype), jnp.asarray(t1, dtype)

        def write(record):
            y_flat = layout.flat(y0, dtype)
            written = layout.pack(
                jnp.ones(m, bool), stopped, jnp.full(m, t0), jnp.full(m, t1),
                jnp.broadcast_to(y_flat, (m, n)), t0, t1, y_flat, dtype,
            )
            where = layout.pack(
                new, jnp.array(True), new, new, jnp.broadcast_to(new[:, None], (m, n)),
                stopped, stopped, jnp.full(n, stopped), bool,
            )
            return jnp.where(where, written, record)

        record = jax.lax.cond(jnp.any(new) | stopped, write, lambda r: r, record)
        state = _WatchState(
            inner=inner,
            previous=end,
            tally=jnp.concatenate([end_rate, solver_state.tally[-1:] + 1]),
            record=record,
            layout=layout,
        )
        return y1, y_error, dense_info, state, result


def _signs(previous, previous_rate, mid, mid_rate, end, end_rate, h, pieces: int):
    """Whether each Bernstein coefficient of each condition's quintic over the step is
    positive (`_bernstein_polygon`, on `pieces` parts of the step): shape
    `(5 * pieces + 1,) + end.shape` (the conditions on the last axis, any leading axes
    before). The first row is the sign at the start of the step, the last at its end."""
    h = h.astype(end.dtype)
    data = (previous, h * previous_rate, mid, h * mid_rate, end, h * end_rate)
    weights = _bernstein_polygon(pieces).astype(np.dtype(end.dtype))
    # Each coefficient a sum of scaled data, the zero weights left out (the end coefficients
    # are the end values, the next ones two terms): XLA fuses these; as a matrix product
    # they ran as a small batched dot per member of a batch.
    rows = []
    for row in weights:
        terms = [w * x for w, x in zip(row, data) if w != 0.0]
        rows.append(sum(terms[1:], terms[0]))
    return jnp.stack(rows) > 0


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
        lead = lambda x, k: jnp.moveaxis(x, tuple(range(x.ndim - k, x.ndim)),  # noqa: E731
                                         tuple(range(k)))
        return EventRecords(
            last_t0=self.last_t0,
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
        # end, end_rate: (N, n); positive: (5 * pieces + 1, N, n)
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
    solver: WatchedSolver, terms, args, state: EventRecords, index: int, root_finder
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
    solver: WatchedSolver, terms, args, state: EventRecords, root_finder
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
