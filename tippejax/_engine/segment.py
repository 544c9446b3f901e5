"""One segment of a run: one `diffrax.diffeqsolve` of one level, with its events.

A segment integrates one level from `t0` until `t1` or a terminating event, saving at the
times of `ts` that fall inside it (or only its end, in summary mode), and records the first
downward crossing of each observed condition (see `watch.py`).
"""

from __future__ import annotations

import functools

import diffrax
from diffrax._root_finder import use_stepsize_tol  # diffrax exports no public name for it
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, PyTree

from .._models.base import AbstractLevel
from .watch import WatchedSolver, event_root_finder, locate_observed


def as_event_dtype(x):
    # diffrax compares event conditions with a Python 0.0 inside `lax.cond`: both branches
    # need the default float dtype, also for a float32 top in a float64 process.
    return jnp.asarray(x, dtype=jnp.result_type(float))


class Watch(eqx.Module):
    """The watched conditions of a level: terminating ones first, then observed ones."""

    level: AbstractLevel
    names: tuple[str, ...] = eqx.field(static=True)

    def __call__(self, y, top):
        conditions = self.level.conditions(top, y)
        return as_event_dtype(jnp.stack([conditions.get(name) for name in self.names]))


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
    samples: int,
) -> Segment:
    """Integrate `level` from `(t0, y0)` to `t1` or the first terminating event."""
    names = terminating + observed
    watch = Watch(level, names)
    controller = diffrax.PIDController(rtol=rtol, atol=atol, norm=level.error_norm)
    if isinstance(solver, diffrax.AbstractImplicitSolver):
        # diffrax gives an implicit solver's root finder the controller's tolerances; it
        # cannot see through the wrapper below, so do it here.
        attrs = [
            a for a in ("rtol", "atol", "norm")
            if getattr(solver.root_finder, a) is use_stepsize_tol
        ]
        solver = eqx.tree_at(
            lambda s: tuple(getattr(s.root_finder, a) for a in attrs),
            solver,
            tuple(getattr(controller, a) for a in attrs),
        )
    if isinstance(solver, diffrax.AbstractRungeKutta) and solver.scan_kind is None:
        # What diffrax's adjoints do to a bare Runge-Kutta solver (for forward-mode
        # autodiff through its stages); they cannot see through the wrapper.
        kind = "lax" if isinstance(adjoint, diffrax.ForwardMode) else "bounded"
        solver = eqx.tree_at(lambda s: s.scan_kind, solver, kind, is_leaf=lambda x: x is None)
    watched = WatchedSolver(
        solver, watch, tuple(range(len(terminating), len(names))), samples=samples
    )
    dtype = jnp.result_type(t0)
    finder = event_root_finder(dtype)

    def first_terminating(t, y, args, **kwargs):
        return functools.reduce(jnp.minimum, list(watch(y, args)[: len(terminating)]))

    event = diffrax.Event(first_terminating, finder, direction=False)
    subs = [diffrax.SubSaveAt(t1=True)]
    if ts is not None:
        subs.append(diffrax.SubSaveAt(ts=jnp.clip(ts, t0, t1)))
    terms = diffrax.ODETerm(level.vector_field)
    sol = diffrax.diffeqsolve(
        terms,
        watched,
        t0,
        t1,
        None,
        y0,
        top,
        saveat=diffrax.SaveAt(subs=subs, solver_state=True),
        stepsize_controller=controller,
        event=event,
        max_steps=max_steps,
        adjoint=adjoint,
        throw=False,
        progress_meter=progress_meter,
    )
    t_end = sol.ts[0][-1]
    y_end = jax.tree_util.tree_map(lambda x: x[-1], sol.ys[0])
    # Which terminating condition fired: at the located event it is (to the root finder's
    # tolerance) zero and the others are positive, so it is the smallest.
    stopped = sol.result == diffrax.RESULTS.event_occurred
    end_values = watch(y_end, top)[: len(terminating)]
    first = jnp.argmin(end_values)
    fired = {name: stopped & (first == i) for i, name in enumerate(terminating)}
    observed_times = {}
    for i, name in enumerate(observed):
        t_obs = locate_observed(
            watched, terms, top, sol.solver_state, len(terminating) + i, finder
        )
        observed_times[name] = jnp.where(t_obs <= t_end, t_obs, jnp.nan)
    return Segment(
        ys=sol.ys[1] if ts is not None else None,
        y_end=y_end,
        t_end=t_end,
        solver_result=sol.result,
        fired=fired,
        observed=observed_times,
        num_steps=sol.stats["num_steps"],
        num_rejected_steps=sol.stats["num_rejected_steps"],
    )
