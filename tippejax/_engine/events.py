"""Event location: the crossing of a condition found on the dense output of the step the watch
recorded for it."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Bool, Float, PyTree


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


def locate_observed(
    solver, terms, args, state: EventRecords, index: int, root_finder
) -> Float[Array, ""]:
    """Time of the first downward crossing of observed condition `index` (nan if none), for a
    solve by `solver` (a `WatchedSolver`).

    Root-finds the condition on the recorded step's dense output. Differentiable (implicit
    function theorem through `optx.root_find`).
    """
    k = solver.observed.index(index)
    t0, t1 = state.step_t0[k], state.step_t1[k]
    y0 = jax.tree_util.tree_map(lambda x: x[k], state.step_y0)
    interpolation = _retake(solver, terms, t0, t1, y0, args)

    def fn(t, _):
        return solver.watch(interpolation.evaluate(t), args)[index].astype(t1.dtype)

    root = optx.root_find(fn, root_finder, y0=t1, options=dict(lower=t0, upper=t1), throw=False)
    return jnp.where(state.found[k], root.value, jnp.nan)


def locate_terminating(
    solver, terms, args, state: EventRecords, root_finder
) -> tuple[Float[Array, ""], PyTree]:
    """Time and state of the first terminating crossing in the last step of a solve by
    `solver` (a `WatchedSolver`) that ended on one: the root of the smallest terminating
    condition on that step's dense output (differentiable through the implicit function
    theorem, as `locate_observed`)."""
    t0, t1 = state.last_t0, state.last_t1
    interpolation = _retake(solver, terms, t0, t1, state.last_y0, args)
    stops = jnp.asarray(solver.terminating, int)

    def fn(t, _):
        return jnp.min(solver.watch(interpolation.evaluate(t), args)[stops]).astype(t1.dtype)

    root = optx.root_find(fn, root_finder, y0=t1, options=dict(lower=t0, upper=t1), throw=False)
    return root.value, interpolation.evaluate(root.value)


def _retake(solver, terms, t0, t1, y0, args):
    """The dense output of the step from `y0` over `[t0, t1]`, taken again after the solve.

    The watch keeps only where an event's step started (its times and state), not the step's
    dense output: carrying the dense output (for Dopri8, its 14 stages) through every step
    of the loop would cost more than the one step taken again here. From the same state over
    the same interval the step's stages are the same (a first-same-as-last stage is
    recomputed from the same state), so the interpolant is the one the solve saw."""
    inner = solver.solver.init(terms, t0, t1, y0, args)
    _, _, dense_info, _, _ = solver.solver.step(terms, t0, t1, y0, args, inner, False)
    return solver.solver.interpolation_cls(t0=t0, t1=t1, **dense_info)
