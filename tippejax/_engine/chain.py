"""A run as a chain of segments: a level until its chart ends, then its fallback level."""

from __future__ import annotations

import dataclasses
import functools

import diffrax
import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from .._invariants import normal_force, normal_force_denominator
from .._models.base import AbstractLevel
from .._solution import RESULTS
from .._state import State, state_from_euler
from .segment import run_segment
from .shared import run_segment_shared, top_axes


def level_chain(level: AbstractLevel) -> tuple[AbstractLevel, ...]:
    """`level`, then its fallbacks in turn (a level's options are static: the chain is a
    function of the level alone, kept once built)."""
    try:
        return _level_chain(level)
    except TypeError:  # (an unhashable level)
        return _build_chain(level)


@functools.lru_cache(maxsize=64)
def _level_chain(level: AbstractLevel) -> tuple[AbstractLevel, ...]:
    return _build_chain(level)


def _build_chain(level: AbstractLevel) -> tuple[AbstractLevel, ...]:
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
    lowest: dict[str, Float[Array, ""]]  # see `run_chain(lowest=...)`
    # first downward crossing of each level's own observed events (`observed_events`), by
    # name (nan if none): the stem level's stem touch and ball return
    level_events: dict[str, Float[Array, ""]]


class _Carry(eqx.Module):
    """What a chain carries from one segment to the next (one member; leading axes only under
    `vmap`): the fields of `ChainOutput` so far, and where the next segment starts."""

    states: State | None
    state_end: State
    t_final: Float[Array, ""]
    result: RESULTS
    t_invert: Float[Array, ""]
    t_contact_loss: Float[Array, ""]
    t_chart_switch: Float[Array, ""]
    num_steps: Array
    num_rejected_steps: Array
    lowest: dict[str, Float[Array, ""]]
    level_events: dict[str, Float[Array, ""]]
    state: State  # the common state the next segment starts from
    t_start: Float[Array, ""]
    active: Array  # whether the member runs the next segment


class _Start(eqx.Module):
    """How one member enters a segment (see `_segment_start`)."""

    runs: Array  # it integrates the segment (else the segment has zero length for it)
    hand_over_now: Array  # outside this level's chart from the start: on to the fallback
    y_start: PyTree  # the level's state at the segment's start
    t_stop: Float[Array, ""]
    result: RESULTS


def _chain_start(
    level: AbstractLevel,
    top,
    state0: State,
    t0,
    ts,
    stop_on_contact: bool,
    lowest=(),
    event_names: tuple[str, ...] = (),
):
    """The carry of one member before its first segment: the checks at `t0`; `event_names`:
    the chain's levels' own observed events."""
    dtype = jnp.result_type(top.m)
    nan = jnp.array(jnp.nan, dtype)
    friction_model = level.friction_model
    # R_n <= 0, or its denominator <= 0, already at t0: no sign change for an event to see.
    singular0 = normal_force_denominator(top, state0, model=friction_model) <= 0
    lost0 = (normal_force(top, state0, model=friction_model) <= 0) & ~singular0
    dead0 = singular0 | (lost0 & stop_on_contact)
    result = RESULTS.where(singular0, RESULTS.normal_force_singular, RESULTS.successful)
    result = RESULTS.where(lost0 & ~singular0, RESULTS.contact_lost, result)
    t_start = jnp.asarray(t0, dtype)
    states = None
    if ts is not None:
        states = jax.tree_util.tree_map(
            lambda x: jnp.full(ts.shape + x.shape, jnp.nan, dtype), state0
        )
    return _Carry(
        states=states,
        state_end=state0,
        t_final=t_start,
        result=result,
        t_invert=nan,
        t_contact_loss=jnp.where(lost0, t_start, nan),
        t_chart_switch=nan,
        num_steps=jnp.array(0),
        num_rejected_steps=jnp.array(0),
        lowest={name: jnp.array(jnp.inf, dtype) for name in lowest},
        level_events={name: nan for name in event_names},
        state=state0,
        t_start=t_start,
        active=~dead0,
    )


def _segment_start(chain, i: int, top, carry: _Carry, t1, y0=None) -> _Start:
    """How one member enters segment `i` of `chain`."""
    lvl, last = chain[i], i == len(chain) - 1
    dtype = jnp.result_type(top.m)
    # A regular stand-in for members whose segment is skipped (zero length), so that no
    # conversion from a singular chart makes nans that would poison gradients.
    stand_in = state_from_euler(1.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    stand_in = jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), stand_in)
    # (states of a chain through the stem level carry the height: the stand-in keeps the
    # state's, which no level reads on entry)
    stand_in = dataclasses.replace(
        stand_in, height=carry.state.height, height_rate=carry.state.height_rate
    )
    active, state, result = carry.active, carry.state, carry.result
    runs = active & lvl.in_chart(top, state)
    chart_end = _chart_end_code(lvl)
    hand_over_now = jnp.array(False)
    if not last:
        # Outside this level's chart from the start: hand over at once.
        hand_over_now = active & ~runs
    elif chart_end is not None:
        # Outside the chart of a level with no fallback: nothing to integrate; say why.
        result = RESULTS.where(active & ~runs & (result == RESULTS.successful), chart_end, result)
    if i == 0 and y0 is not None:
        y_start = y0
    else:
        y_start = lvl.from_state(top, _where_tree(runs, state, stand_in))
    t_stop = jnp.where(runs, t1, carry.t_start)
    return _Start(
        runs=runs, hand_over_now=hand_over_now, y_start=y_start, t_stop=t_stop, result=result
    )


def _segment_events(lvl: AbstractLevel, stop_on_contact: bool, inversion: bool):
    """The terminating and the observed event names of a segment of `lvl`."""
    terminating = (
        ("singular",)
        + (("chart",) if lvl.has_chart else ())
        + (("contact",) if stop_on_contact else ())
    )
    observed = (("upright",) if inversion else ()) + (() if stop_on_contact else ("contact",))
    return terminating, observed + lvl.observed_events


def _segment_end(
    chain,
    i: int,
    top,
    carry: _Carry,
    start: _Start,
    seg,
    ts,
    *,
    stop_on_contact: bool,
    inversion: bool,
) -> _Carry:
    """The carry of one member after segment `i` of `chain` (its `Segment` `seg`)."""
    lvl, last = chain[i], i == len(chain) - 1
    dtype = jnp.result_type(top.m)
    nan = jnp.array(jnp.nan, dtype)
    runs, t_start = start.runs, carry.t_start
    seg_result = _segment_result(seg, stop_on_contact, _chart_end_code(lvl))
    result = RESULTS.where(runs & (start.result == RESULTS.successful), seg_result, start.result)
    states = carry.states
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
    t_invert = carry.t_invert
    if inversion:
        upright = seg.observed["upright"]
        t_invert = jnp.where(runs & jnp.isnan(t_invert), upright, t_invert)
    if stop_on_contact:
        contact = jnp.where(seg.fired["contact"], seg.t_end, nan)
    else:
        contact = seg.observed["contact"]
    t_contact_loss = carry.t_contact_loss
    t_contact_loss = jnp.where(runs & jnp.isnan(t_contact_loss), contact, t_contact_loss)
    level_events = dict(carry.level_events)  # the level's own events: their first crossing
    for name in lvl.observed_events:
        level_events[name] = jnp.where(
            runs & jnp.isnan(level_events[name]), seg.observed[name], level_events[name]
        )
    state, active, t_chart_switch = carry.state, carry.active, carry.t_chart_switch
    if not last:
        switch = runs & seg.fired["chart"] & (seg_result == RESULTS.successful)
        switch = switch | start.hand_over_now
        t_chart_switch = jnp.where(switch, jnp.where(runs, seg.t_end, t_start), t_chart_switch)
        state = _where_tree(runs, end, state)
        t_start = jnp.where(runs, seg.t_end, t_start)
        active = switch
    return _Carry(
        states=states,
        state_end=_where_tree(runs, end, carry.state_end),
        t_final=jnp.where(runs, seg.t_end, carry.t_final),
        result=result,
        t_invert=t_invert,
        t_contact_loss=t_contact_loss,
        t_chart_switch=t_chart_switch,
        num_steps=carry.num_steps + seg.num_steps,
        num_rejected_steps=carry.num_rejected_steps + seg.num_rejected_steps,
        lowest={
            name: jnp.where(runs, jnp.minimum(low, seg.lowest[name].astype(low.dtype)), low)
            for name, low in carry.lowest.items()
        },
        level_events=level_events,
        state=state,
        t_start=t_start,
        active=active,
    )


def _chain_output(carry: _Carry, stop_on_contact: bool) -> ChainOutput:
    result = carry.result
    if not stop_on_contact:
        result = RESULTS.where(
            (result == RESULTS.successful) & jnp.isfinite(carry.t_contact_loss),
            RESULTS.contact_lost,
            result,
        )
    return ChainOutput(
        states=carry.states,
        state_end=carry.state_end,
        t_final=carry.t_final,
        result=result,
        t_invert=carry.t_invert,
        t_contact_loss=carry.t_contact_loss,
        t_chart_switch=carry.t_chart_switch,
        num_steps=carry.num_steps,
        num_rejected_steps=carry.num_rejected_steps,
        lowest=carry.lowest,
        level_events=carry.level_events,
    )


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
    shared_steps: bool = False,
    lowest: tuple[str, ...] = (),
    **segment_options,
) -> ChainOutput:
    """Run `level`, then its fallbacks, from `state0` at `t0` to `t1`.

    The Routhian level hands over to the SO(3) level near a pole; the full and SO(3) levels
    are one segment. A level whose chart ends with no fallback (the gyroscopic level) stops
    there and reports its `chart_end_result`; started outside its chart, it is not integrated
    at all. Contact loss either ends the run (a terminating event) or is observed and the run
    goes on past it (`stop_on_contact=False`); the inversion is observed (unless
    `inversion=False`: `t_invert` is nan, and a caller that needs only the motion, a fit's
    residuals, compiles a smaller program). The chain is static (it depends on the level
    only), so under `jit`/`vmap` every segment is compiled once and a member that does not
    need a segment runs it with zero length; the last (fallback) segment is skipped where no
    member enters it (`_last_fallback`). `solver`: one solver for every segment, or a tuple of
    one per level of the chain (`level_chain`'s order). `y0`: the first level's own state at `t0`, for a
    caller that has it (default `level.from_state(top, state0)`); `state0` must be its common
    state.

    What a member does before, between and after its segments is written per member
    (`_chain_start`, `_segment_start`, `_segment_end`, `_chain_output`). With
    `shared_steps=True` the run is a batch of members (the leading axis of `state0`; `top` one
    top or one per member, see `top_axes`) whose steps are shared: those per-member parts are
    vmapped around one `run_segment_shared` for the whole batch. Only for a level that is one
    segment (no chart, no fallback: the full and SO(3) levels). Every member's output is then
    what a run of its own gives it, to about the tolerances (its steps differ).

    `lowest`: names of watched conditions (`"contact"`; `"upright"` with `inversion`) whose
    lowest value over the run, at the start and at the end of every accepted step, is
    returned in `ChainOutput.lowest` (inf where no segment ran): how near the run came to an
    event, for an outcome map's indicators. Not with shared steps."""
    # The level as it runs this top, and the launch in the form its chain carries: the full
    # level of a top with a stem goes on to the stem level, whose states carry the height.
    level = level.for_top(top)
    state0 = level.common_state(top, state0)
    chain = level_chain(level)
    if shared_steps and (len(chain) != 1 or level.has_chart):
        raise ValueError(
            f"shared steps run one segment; the {level.name!r} level chains segments for this "
            f"top ({' -> '.join(lvl.name for lvl in chain)})."
        )
    if shared_steps and lowest:
        raise ValueError("run_chain: lowest= is not kept with shared steps.")
    event_names = tuple(dict.fromkeys(e for lvl in chain for e in lvl.observed_events))
    each = _each_member(top) if shared_steps else _as_one
    carry = each(
        lambda top, s: _chain_start(chain[0], top, s, t0, ts, stop_on_contact, lowest, event_names)
    )(top, state0)
    for i, lvl in enumerate(chain):
        start = each(lambda top, c: _segment_start(chain, i, top, c, t1, y0))(top, carry)
        terminating, observed = _segment_events(lvl, stop_on_contact, inversion)
        events = dict(terminating=terminating, observed=observed, **segment_options)
        events["solver"] = _solver_of(events["solver"], i)
        if not shared_steps:
            events["lowest"] = lowest
        end = functools.partial(
            _segment_end, chain, i, ts=ts, stop_on_contact=stop_on_contact, inversion=inversion
        )
        if shared_steps:
            seg = run_segment_shared(
                lvl, top, start.y_start, t0, t1, ts, idle=~start.runs, **events
            )
            carry = each(end)(top, carry, start, seg)
        elif i == 0:
            seg = run_segment(lvl, top, start.y_start, carry.t_start, start.t_stop, ts, **events)
            carry = end(top, carry, start, seg)
        elif i == len(chain) - 1:
            carry = _last_fallback(lvl, top, carry, start, ts, events, end)
        else:  # (no chain has a fallback that falls back again: a segment for every member)
            seg = run_segment(lvl, top, start.y_start, carry.t_start, start.t_stop, ts, **events)
            carry = end(top, carry, start, seg)
    return each(lambda top, c: _chain_output(c, stop_on_contact))(top, carry)


def _solver_of(solver, i: int):
    """The solver of segment `i`: `solver` itself, or its `i`-th entry where it is a tuple of
    one solver per level of the chain (`level_chain`'s order; `simulate`'s default solvers,
    which for the gyroscopic level's chain are the slow flow's and the full model's own)."""
    return solver[i] if isinstance(solver, tuple) else solver


def _last_fallback(
    lvl: AbstractLevel, top, carry: _Carry, start: _Start, ts, events, end
) -> _Carry:
    """The carry after the chain's last segment, a fallback level's (`end(top, carry, start,
    segment)`, `_segment_end`): integrated, and its states at the save times converted and
    merged, only where some member enters it (`lax.cond`). A run that never leaves its first
    level's chart (a gyroscopic run that does not hand over, a Routhian run that stays away
    from the poles) pays nothing for the fallback. Under `vmap` the segment runs for the whole
    batch as soon as one member needs it (the members that do not run it with zero length).
    Where none enters it, the carry is what `_segment_end` makes of a segment a member does
    not run: unchanged but for the result `_segment_start` gave it."""

    def integrate():
        seg = run_segment(lvl, top, start.y_start, carry.t_start, start.t_stop, ts, **events)
        out = end(top, carry, start, seg)
        # (the same dtypes in both branches of `lax.cond`)
        return jax.tree_util.tree_map(lambda x, ref: jnp.asarray(x).astype(ref.dtype), out, skipped)

    skipped = eqx.tree_at(lambda c: c.result, carry, start.result)
    return jax.lax.cond(eqxi.unvmap_any(start.runs), integrate, lambda: skipped)


def _as_one(fn):
    """`fn` for one run, as it is."""
    return fn


def _each_member(top):
    """`fn(top, *members)` vmapped over the members: `top` along `top_axes`, every other
    argument along its leading axis."""

    def each(fn):
        return lambda top, *rest: jax.vmap(fn, in_axes=(axes,) + (0,) * len(rest))(top, *rest)

    axes = top_axes(top)
    return each
