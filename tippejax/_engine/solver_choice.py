"""The default solver, chosen from measured work-precision (see the performance page).

Non-stiff friction: Dopri8 (8th order, 14 stages) takes several times fewer steps than Tsit5
for the same error and is faster at every rtol from 1e-4 to 1e-10. Its long steps do not hide
events: `WatchedSolver` checks the conditions on each step's dense output. Stiff friction:
explicit steps are limited by stability, and Tsit5's cheaper steps win until the friction is
very stiff; above `IMPLICIT_RATE` only an implicit solver (Kvaerno5) finishes. A level whose
steps follow a slow flow (the gyroscopic level: tens of steps a run) runs Dopri5 where Dopri8
would be the default: with so few steps a step's fixed cost outweighs the steps saved, and
Dopri5's dense output, which the event watch evaluates several times a step, is cheaper than
Tsit5's.
"""

from __future__ import annotations

import weakref

import diffrax
import jax
import numpy as np

from .._top import TippeTop

STIFF_RATE = 1000.0
"""Friction damping rate (1/s) above which Tsit5 is faster than Dopri8 (stability-limited steps)."""

IMPLICIT_RATE = 5.0e5
"""Friction damping rate (1/s) above which the default solver is implicit (Kvaerno5)."""


def friction_rate(top: TippeTop):
    r"""Damping rate of sliding, $k g\, m (R+\epsilon)^2/A$ (1/s): the stiffness of the friction,
    with $k$ the law's viscous coefficient at zero slip (`stiffness_coefficient`; $\mu$ for the
    viscous law)."""
    k = top.friction.stiffness_coefficient()
    return k * top.g * top.m * (top.R + top.eps) ** 2 / top.A


def is_traced(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def default_solver(top: TippeTop, *, slow_flow: bool = False) -> diffrax.AbstractSolver:
    """Dopri8 (Dopri5 for a `slow_flow` level); Tsit5 above a friction rate of `STIFF_RATE`;
    Kvaerno5 above `IMPLICIT_RATE`.

    Needs a concrete top. For a traced top (under `jit` or `vmap`) the stiffness cannot be read:
    `simulate` then uses Dopri8 (Dopri5 for a `slow_flow` level) and reports members whose
    friction is too stiff for an explicit solver (`RESULTS.stiff_under_trace`) at once instead
    of running them into `max_steps`.
    """
    return solver_for_rate(host_friction_rate(top), slow_flow=slow_flow)


def host_friction_rate(top: TippeTop) -> float | None:
    """The largest `friction_rate` of a concrete `top` (over its batch), read on the host;
    None for a traced top."""
    leaves = jax.tree_util.tree_leaves(top)
    if any(is_traced(x) for x in leaves):
        return None
    known = _RATES.get(id(top))
    if known is not None and known[0]() is top:  # (the same top: the same immutable arrays)
        return known[1]
    numpy_top = jax.tree_util.tree_map(  # (one transfer for every leaf)
        lambda x: np.asarray(x, dtype=float), jax.device_get(top)
    )
    rate = float(np.max(friction_rate(numpy_top)))
    try:
        ref = weakref.ref(top)
    except TypeError:  # pragma: no cover
        return rate
    if len(_RATES) > 256:
        _RATES.clear()
    _RATES[id(top)] = (ref, rate)
    return rate


_RATES: dict = {}  # id(top) -> (a weak reference to it, its rate): an eager loop asks again


def solver_for_rate(rate: float | None, *, slow_flow: bool = False) -> diffrax.AbstractSolver:
    """`default_solver` of a top whose `host_friction_rate` is `rate` (None: traced)."""
    explicit = _SOLVERS["Dopri5" if slow_flow else "Dopri8"]
    if rate is None:
        return explicit
    if rate > IMPLICIT_RATE:
        return _SOLVERS["Kvaerno5"]
    return _SOLVERS["Tsit5"] if rate > STIFF_RATE else explicit


_SOLVERS = {name: getattr(diffrax, name)() for name in ("Dopri5", "Dopri8", "Tsit5", "Kvaerno5")}
"""The default solvers, built once (immutable modules: every call may share them)."""
