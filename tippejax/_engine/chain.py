"""A run as a chain of segments: a level until its chart ends, then its fallback level.

The Routhian level hands over to the SO(3) level near a pole; the full and SO(3) levels are
one segment. A level whose chart ends with no fallback (the gyroscopic level) stops there and
reports its `chart_end_result`; started outside its chart, it is not integrated at all.
Contact loss either ends the run (a terminating event) or is observed and the run goes on past
it (`stop_on_contact=False`); the inversion is observed (unless `inversion=False`). The chain
is static (it depends on the level only), so under `jit`/`vmap` every segment is compiled once
and a member that does not need a segment runs it with zero length.
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._invariants import normal_force, normal_force_denominator
from .._models.base import AbstractLevel
from .._solution import RESULTS
from .._state import State, state_from_euler
from .segment import run_segment


def level_chain(level: AbstractLevel) -> tuple[AbstractLevel, ...]:
    chain = [level]
    while chain[-1].fallback() is not None:
        chain.append(chain[-1].fallback())
    return tuple(chain)


def _where_tree(pred, a, b):
    return jax.tree_util.tree_map(lambda x, y: jnp.where(pred, x, y), a, b)


def _chart_end_code(level: AbstractLevel):
    """The `RESULTS` member a chart end reports when `level` has no fallback (else None)."""
    if level.has_chart and level.fallback() is None and level.chart_end_result is not None:
        return getattr(RESULTS, level.chart_end_result)
    return None


def _segment_result(segment, stop_on_contact, chart_end=None):
    ok = (segment.solver_result == diffrax.RESULTS.successful) | (
        segment.solver_result == diffrax.RESULTS.event_occurred
    )
    result = RESULTS.where(ok, RESULTS.successful, RESULTS.solver_failed)
    result = RESULTS.where(
        segment.solver_result == diffrax.RESULTS.max_steps_reached,
        RESULTS.max_steps_reached,
        result,
    )
    result = RESULTS.where(segment.fired["singular"], RESULTS.normal_force_singular, result)
    if stop_on_contact:
        result = RESULTS.where(segment.fired["contact"], RESULTS.contact_lost, result)
    if chart_end is not None:
        result = RESULTS.where(segment.fired["chart"], chart_end, result)
    return result


class ChainOutput(eqx.Module):
    states: State | None  # common states at the save times (nan outside the run)
    state_end: State
    t_final: Float[Array, ""]
    result: RESULTS
    t_invert: Float[Array, ""]
    t_contact_loss: Float[Array, ""]
    t_chart_switch: Float[Array, ""]
    num_steps: Array
    num_rejected_steps: Array


def run_chain(
    level: AbstractLevel,
    top,
    state0: State,
    t0,
    t1,
    ts,
    *,
    stop_on_contact: bool,
    inversion: bool = True,
    y0=None,
    **segment_options,
) -> ChainOutput:
    """Run `level`, then its fallbacks, from `state0` at `t0` to `t1` (see the module
    docstring). With `inversion=False` the inversion is not watched (`t_invert` is nan): a
    caller that needs only the motion (a fit's residuals) compiles a smaller program. `y0`:
    the first level's own state at `t0`, for a caller that has it (default
    `level.from_state(top, state0)`); `state0` must be its common state."""
    chain = level_chain(level)
    dtype = jnp.result_type(top.m)
    nan = jnp.array(jnp.nan, dtype)
    friction_model = chain[0].friction_model
    # R_n <= 0, or its denominator <= 0, already at t0: no sign change for an event to see.
    singular0 = normal_force_denominator(top, state0, model=friction_model) <= 0
    lost0 = (normal_force(top, state0, model=friction_model) <= 0) & ~singular0
    dead0 = singular0 | (lost0 & stop_on_contact)
    result = RESULTS.where(singular0, RESULTS.normal_force_singular, RESULTS.successful)
    result = RESULTS.where(lost0 & ~singular0, RESULTS.contact_lost, result)
    # A regular stand-in for members whose segment is skipped (zero length), so that no
    # conversion from a singular chart makes nans that would poison gradients.
    stand_in = state_from_euler(1.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    stand_in = jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), stand_in)

    state, t_start = state0, jnp.asarray(t0, dtype)
    active = ~dead0
    states = None
    if ts is not None:
        states = jax.tree_util.tree_map(
            lambda x: jnp.full(ts.shape + x.shape, jnp.nan, dtype), state0
        )
    t_invert, t_contact_loss, t_chart_switch = nan, jnp.where(lost0, t_start, nan), nan
    steps = rejected = jnp.array(0)
    state_end, t_final = state0, t_start
    for i, lvl in enumerate(chain):
        last = i == len(chain) - 1
        runs = active & lvl.in_chart(top, state)
        chart_end = _chart_end_code(lvl)
        if not last:
            # Outside this level's chart from the start: hand over at once.
            hand_over_now = active & ~runs
        elif chart_end is not None:
            # Outside the chart of a level with no fallback: nothing to integrate; say why.
            result = RESULTS.where(
                active & ~runs & (result == RESULTS.successful), chart_end, result
            )
        if i == 0 and y0 is not None:
            y_start = y0
        else:
            y_start = lvl.from_state(top, _where_tree(runs, state, stand_in))
        t_stop = jnp.where(runs, t1, t_start)
        terminating = ("singular",) + (("chart",) if lvl.has_chart else ()) + (
            ("contact",) if stop_on_contact else ()
        )
        observed = (("upright",) if inversion else ()) + (
            () if stop_on_contact else ("contact",)
        )
        seg = run_segment(
            lvl, top, y_start, t_start, t_stop, ts, terminating=terminating, observed=observed,
            **segment_options,
        )
        steps = steps + seg.num_steps
        rejected = rejected + seg.num_rejected_steps
        seg_result = _segment_result(seg, stop_on_contact, chart_end)
        result = RESULTS.where(
            runs & (result == RESULTS.successful), seg_result, result
        )
        if ts is not None:
            inside = runs & (ts >= t_start) & (ts <= seg.t_end)
            seg_states = jax.vmap(lambda y: lvl.to_state(top, y))(seg.ys)
            states = jax.tree_util.tree_map(
                lambda new, old: jnp.where(
                    inside.reshape(inside.shape + (1,) * (new.ndim - 1)), new, old
                ),
                seg_states,
                states,
            )
        end = lvl.to_state(top, seg.y_end)
        state_end = _where_tree(runs, end, state_end)
        t_final = jnp.where(runs, seg.t_end, t_final)
        if inversion:
            upright = seg.observed["upright"]
            t_invert = jnp.where(runs & jnp.isnan(t_invert), upright, t_invert)
        if stop_on_contact:
            contact = jnp.where(seg.fired["contact"], seg.t_end, nan)
        else:
            contact = seg.observed["contact"]
        t_contact_loss = jnp.where(runs & jnp.isnan(t_contact_loss), contact, t_contact_loss)
        if not last:
            switch = runs & seg.fired["chart"] & (seg_result == RESULTS.successful)
            switch = switch | hand_over_now
            t_chart_switch = jnp.where(switch, jnp.where(runs, seg.t_end, t_start), t_chart_switch)
            state = _where_tree(runs, end, state)
            t_start = jnp.where(runs, seg.t_end, t_start)
            active = switch
    if not stop_on_contact:
        result = RESULTS.where(
            (result == RESULTS.successful) & jnp.isfinite(t_contact_loss),
            RESULTS.contact_lost,
            result,
        )
    return ChainOutput(
        states=states,
        state_end=state_end,
        t_final=t_final,
        result=result,
        t_invert=t_invert,
        t_contact_loss=t_contact_loss,
        t_chart_switch=t_chart_switch,
        num_steps=steps,
        num_rejected_steps=rejected,
    )
