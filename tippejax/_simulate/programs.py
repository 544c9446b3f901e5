"""The compiled programs of a run: the segment chain, its derivatives and the observed fields."""

from __future__ import annotations

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from .._cache import cached_call
from .._engine.chain import run_chain
from .._engine.cpu import own_compiler_options
from .._engine.packing import FORWARD_MODE_PACK_WIDTH, PACK_WIDTH
from .._engine.sensitivity import ForwardSensitivities, forward_sensitivities, jacobian_of
from .._engine.solver_choice import IMPLICIT_RATE, friction_rate
from .._invariants import energy, jellet, normal_force, slip_velocity
from .._models.stem import stem_observables
from .._outcome import classify
from .._solution import RESULTS, SAVED_FIELDS
from .._state import State, euler_angles, euler_rates, spin

OBSERVED = SAVED_FIELDS[1:]
"""The `Solution` fields computed from the states at the save times."""


def _observe(top, states: State, friction_model: str, valid, names=OBSERVED):
    """The `Solution` fields `names` of states at the save times (nan where not `valid`)."""
    theta, phi, psi = euler_angles(states)
    rates = []  # the Euler rates, computed (traced) once if any is asked for

    def rate(i):
        if not rates:
            rates.extend(euler_rates(states))
        return rates[i]

    makers = dict(
        theta=lambda: theta,
        phi=lambda: jnp.unwrap(jnp.where(valid, phi, 0.0)),
        psi=lambda: jnp.unwrap(jnp.where(valid, psi, 0.0)),
        theta_dot=lambda: rate(0),
        phi_dot=lambda: rate(1),
        psi_dot=lambda: rate(2),
        spin=lambda: spin(states),
        position=lambda: states.position,
        velocity=lambda: states.velocity,
        jellet=lambda: jellet(top, states),
        energy=lambda: energy(top, states, model=friction_model),
        normal_force=lambda: normal_force(top, states, model=friction_model),
        slip_speed=lambda: jnp.linalg.norm(
            slip_velocity(top, states, model=friction_model), axis=-1
        ),
    )
    fields = {k: makers[k]() for k in names}

    def mask(x):
        return jnp.where(valid.reshape(valid.shape + (1,) * (x.ndim - valid.ndim)), x, jnp.nan)

    return {k: mask(v) for k, v in fields.items()}


@eqx.filter_jit
def _run(
    top,
    y0,
    ts,
    t0,
    t1,
    rtol,
    atol,
    *,
    level,
    solver,
    guard_stiff,
    stop_on_contact,
    max_steps,
    adjoint,
    progress,
    pieces,
    names=OBSERVED,
    inversion=True,
    locate=True,
    pack_width=PACK_WIDTH,
    jacobian_pack_width=FORWARD_MODE_PACK_WIDTH,
    outcome=False,
):
    """The run of one top (`run_chain`) and its observed fields (`outputs`); with
    `outcome=True` also `sol.outcome` and `sol.settled` (`classify`), in the same program.

    The default adjoint differentiates the segment chain alone (`_chain`); the observed
    fields, simple functions of its states, are differentiated by JAX's own rules after it.
    (An eager `jax.grad` of `simulate` does not come here: see `run_traced`.)"""
    chain, result = _chain(
        top,
        y0,
        ts,
        t0,
        t1,
        rtol,
        atol,
        level=level,
        solver=solver,
        guard_stiff=guard_stiff,
        stop_on_contact=stop_on_contact,
        max_steps=max_steps,
        adjoint=adjoint,
        progress=progress,
        pieces=pieces,
        inversion=inversion,
        locate=locate,
        pack_width=pack_width,
        jacobian_pack_width=jacobian_pack_width,
    )
    out = outputs(top, y0, ts, chain, result, level=level, names=names)
    if outcome:
        out["outcome"], out["settled"] = outcome_of(top, out, classify)
    return out


run = _run
"""The program of a run (`_run`, the name JAX's compile log and the store of traced programs
show)."""


def run_traced(
    top, y0, ts, t0, t1, rtol, atol, *, names=OBSERVED, inversion=True, locate=True, **options
):
    """`run` (without the outcome) for an eager `jax.grad`, `jax.jvp` or `jax.jacfwd` of
    `simulate` (`_differentiated_eagerly`): its segment chain and its observed fields as two
    programs, with the chain's derivative rule outside both.

    JAX calls the rule with concrete inputs, and the chain's forward-mode Jacobian is then a
    top-level program of its own (`_run_jacobian`): compiled with tippejax's options
    (`own_compiler_options`) and kept in the store of traced programs (`cached_call`), which
    JAX allows for neither the program it derives from `run`'s nor a nested `jit`: a warm
    cache spares a new process the tracing of the Jacobian, and a cold one compiles two
    smaller programs instead of one large one."""
    core = {k: v for k, v in options.items() if k not in ("adjoint", "jacobian_pack_width")}
    core.update(pack_width=options["jacobian_pack_width"], inversion=inversion, locate=locate)

    def jacobian(args, live):
        return cached_call(
            _run_jacobian, *args, compiler_options=own_compiler_options(), live=live, **core
        )

    chain, result = _chain(
        top,
        y0,
        ts,
        t0,
        t1,
        rtol,
        atol,
        **options,
        inversion=inversion,
        locate=locate,
        jacobian=jacobian,
    )
    return _outputs_program(top, y0, ts, chain, result, level=options["level"], names=names)


def _chain(
    top,
    y0,
    ts,
    t0,
    t1,
    rtol,
    atol,
    *,
    level,
    solver,
    guard_stiff,
    stop_on_contact,
    max_steps,
    adjoint,
    progress,
    pieces,
    inversion,
    locate,
    pack_width,
    jacobian_pack_width,
    jacobian=None,
):
    """`_run_core` with the derivatives `adjoint` asks for: the default
    (`ForwardSensitivities`) from its forward-mode Jacobian (`sensitivity.py`), with
    `jacobian` for concrete inputs (see `forward_sensitivities`)."""
    options = dict(
        level=level,
        solver=solver,
        guard_stiff=guard_stiff,
        stop_on_contact=stop_on_contact,
        max_steps=max_steps,
        progress=progress,
        pieces=pieces,
        inversion=inversion,
        locate=locate,
    )
    run = functools.partial(_run_core, **options)
    if isinstance(adjoint, ForwardSensitivities) and pack_width == jacobian_pack_width:
        # (the default: derivatives from the forward-mode Jacobian, `sensitivity.py`; the
        # widths agree for one top, `simulate_batch` and a user's `jax.vmap` alike with the
        # widths of `segment.py`.) The value and the Jacobian are one staged solve, so that
        # `jax.grad` and `jax.jacfwd` trace it once: JAX traces a `custom_jvp`'s value
        # under `jit` eagerly, and the Jacobian's rule transforms the same cached jaxpr.
        run = functools.partial(
            _run_core_staged, **options, adjoint=diffrax.ForwardMode(), pack_width=pack_width
        )
        run = forward_sensitivities(run, run, jacobian=jacobian)
    elif isinstance(adjoint, ForwardSensitivities):
        # (layouts that differ between the value and the Jacobian: two programs)
        run = forward_sensitivities(
            functools.partial(
                run, adjoint=diffrax.RecursiveCheckpointAdjoint(), pack_width=pack_width
            ),
            functools.partial(run, adjoint=diffrax.ForwardMode(), pack_width=jacobian_pack_width),
            jacobian=jacobian,
        )
    else:
        run = functools.partial(run, adjoint=adjoint, pack_width=pack_width)
    # (JAX keys its cache of traced programs on the context's abstract mesh: unset here at
    # the first trace, the empty mesh where `jax.grad` replays `run`'s jaxpr and calls the
    # Jacobian's rule. Set it, so that both find the one trace of `_run_core_staged`.)
    with jax.sharding.use_abstract_mesh(jax.sharding.get_abstract_mesh()):
        return run(top, y0, ts, t0, t1, rtol, atol)


@eqx.filter_jit
def _run_jacobian(top, y0, ts, t0, t1, rtol, atol, *, live, **options):
    """`_run_core`'s outputs and their forward-mode Jacobian in the leaves `live` of its
    arguments (`jacobian_of`): the program an eager `jax.grad` of `simulate` runs."""
    run = functools.partial(_run_core, **options, adjoint=diffrax.ForwardMode())
    return jacobian_of(run, (top, y0, ts, t0, t1, rtol, atol), live)


def _run_core(
    top,
    y0,
    ts,
    t0,
    t1,
    rtol,
    atol,
    *,
    level,
    solver,
    guard_stiff,
    stop_on_contact,
    max_steps,
    adjoint,
    progress,
    pieces,
    inversion,
    locate,
    pack_width,
):
    too_stiff = jnp.array(False)
    if guard_stiff:
        # Traced top with the default (explicit) solver: a very stiff member would run into
        # max_steps and hold up the whole batch. Give it zero length and say why.
        too_stiff = friction_rate(top) > IMPLICIT_RATE
        t1 = jnp.where(too_stiff, t0, t1)
    meter = diffrax.TqdmProgressMeter() if progress else diffrax.NoProgressMeter()
    out = run_chain(
        level,
        top,
        y0,
        t0,
        t1,
        ts,
        stop_on_contact=stop_on_contact,
        solver=solver,
        rtol=rtol,
        atol=atol,
        max_steps=max_steps,
        adjoint=adjoint,
        progress_meter=meter,
        pieces=pieces,
        inversion=inversion,
        locate=locate,
        pack_width=pack_width,
    )
    result = RESULTS.where(too_stiff, RESULTS.stiff_under_trace, out.result)
    return out, result


_run_core_staged = eqx.filter_jit(_run_core)
"""`_run_core` as a program of its own inside `run`'s: its trace is cached per static
options and argument shapes, for the value and the Jacobian of `forward_sensitivities`."""


def outputs(top, y0, ts, out, result, *, level, names=OBSERVED):
    """`run`'s outputs for one member from its `ChainOutput` `out` (and its `result`): the
    observed fields at the save times, with the safety net for a missed contact loss."""
    dtype = jnp.result_type(top.m)
    friction_model = level.friction_model
    t_contact_loss = out.t_contact_loss
    if ts is None:
        times = out.t_final[None]
        states = jax.tree_util.tree_map(lambda x: x[None], out.state_end)
        valid = jnp.ones(1, bool)
        fields = _observe(top, states, friction_model, valid, names)
        fields = _stem_phase(top, times, states, out, fields)
    else:
        times = ts
        states = out.states
        valid = (ts <= out.t_final) & jnp.all(jnp.isfinite(states.axis), axis=-1)
        # (the normal force is needed for the safety net below; it is dropped after)
        fields = _observe(
            top, states, friction_model, valid, tuple(dict.fromkeys(names + ("normal_force",)))
        )
        fields = _stem_phase(top, times, states, out, fields)
        # Safety net: R_n < 0 at a save time before any located contact loss means a dip
        # shorter than the event watch's resolution went unseen. Report it; return nothing
        # from that save time on, nor a later loss time as if it were the first.
        missed_at = valid & (fields["normal_force"] < 0) & ~(ts >= t_contact_loss)
        missed = jnp.any(missed_at)
        t_missed = jnp.min(jnp.where(missed_at, ts, jnp.inf))
        result = RESULTS.where(
            missed & ((result == RESULTS.successful) | (result == RESULTS.contact_lost)),
            RESULTS.contact_loss_missed,
            result,
        )
        t_contact_loss = jnp.where(missed, jnp.nan, t_contact_loss)
        valid = valid & (ts < t_missed)
        fields = {
            k: jnp.where(valid.reshape(valid.shape + (1,) * (v.ndim - 1)), v, jnp.nan)
            for k, v in fields.items()
            if k in names
        }
        states = jax.tree_util.tree_map(
            lambda x: jnp.where(valid.reshape(valid.shape + (1,) * (x.ndim - 1)), x, jnp.nan),
            states,
        )
    fields = _mask_unmodelled(fields, level, times, out.t_chart_switch)
    nonfinite = jnp.any(
        jnp.stack(
            [jnp.any(valid & ~jnp.isfinite(fields[k])) for k in ("theta", "jellet") if k in fields]
        )
    )
    result = RESULTS.where((result == RESULTS.successful) & nonfinite, RESULTS.nonfinite, result)
    return dict(
        theta_end=euler_angles(out.state_end)[0],
        jellet_launch=jellet(top, y0),
        ts=times.astype(dtype),
        states=states,
        result=result,
        t_invert=out.t_invert,
        t_contact_loss=t_contact_loss,
        t_chart_switch=out.t_chart_switch,
        t_final=out.t_final,
        num_steps=out.num_steps,
        num_rejected_steps=out.num_rejected_steps,
        **_stem_events(top, out),
        **fields,
    )


def _mask_unmodelled(fields: dict, level, times, t_switch) -> dict:
    """nan for the fields a level does not model (`AbstractLevel.unmodelled`), at the save
    times it produced: before `t_switch` (where a chain left the level for its fallback), and
    after it those its fallback does not model."""
    fallback = level.fallback()
    after = () if fallback is None else fallback.unmodelled
    if not level.unmodelled and not after:
        return fields
    first = jnp.isnan(t_switch) | (times < t_switch)
    out = dict(fields)
    for name, value in fields.items():
        drop = jnp.where(first, name in level.unmodelled, name in after)
        drop = drop.reshape(drop.shape + (1,) * (value.ndim - drop.ndim))
        out[name] = jnp.where(drop, jnp.nan, value)
    return out


def _stem_phase(top, times, states, out, fields):
    """`fields` with the stem level's normal force and slip speed (`stem_observables`) at the
    save times from the hand-over to it on (a top with a stem; else `fields` as they are)."""
    if top.stem is None or not {"normal_force", "slip_speed"} & set(fields):
        return fields
    on_stem_level = times >= out.t_chart_switch  # (False where it is nan)
    stem_fields = stem_observables(top, states)
    return {
        k: jnp.where(on_stem_level, stem_fields[k], v) if k in stem_fields else v
        for k, v in fields.items()
    }


def _stem_events(top, out) -> dict:
    """`sol.t_stem` and `sol.t_ball_return`: the stem level's own events (nan without a stem,
    or where the run did not reach them)."""
    nan = jnp.full_like(out.t_final, jnp.nan)
    events = out.level_events
    return dict(t_stem=events.get("stem_touch", nan), t_ball_return=events.get("ball_return", nan))


_outputs_program = eqx.filter_jit(outputs)
"""`outputs` as a program of its own, for `run_traced`."""


SAVED = (
    "ts",
    "states",
    "theta",
    "phi",
    "psi",
    "theta_dot",
    "phi_dot",
    "psi_dot",
    "spin",
    "position",
    "velocity",
    "jellet",
    "energy",
    "normal_force",
    "slip_speed",
)
"""The outputs with a save-time axis."""


def outcome_of(top, out, classify):
    """`sol.outcome`, `sol.settled` of `run`'s outputs `out` by `classify` (or
    `classify_program` for a traced call); integer outputs, so their inputs' derivatives are
    not traced."""
    return classify(
        *jax.lax.stop_gradient((top, out["jellet_launch"], out["theta_end"])), out["result"]
    )


def trim_saves(out: dict, n_save: int | None, axis: int = 0) -> dict:
    """`out` with its save-time outputs (`SAVED`) cut back from the bucket's length to the
    `n_save` times asked for, along `axis` (1 for a batch whose members lead): in one program
    (`_trimmed`) for concrete outputs, not one dispatched slice per field."""
    if n_save is None or out["ts"].shape[axis] == n_save:
        return out
    out = dict(out)
    out.update(_trimmed({key: out[key] for key in SAVED}, n_save, axis))
    return out


@functools.partial(jax.jit, static_argnums=(1, 2))
def _trimmed(saved: dict, n_save: int, axis: int) -> dict:
    """The leaves of `saved` cut to their first `n_save` entries along `axis`."""
    index = (slice(None),) * axis + (slice(None, n_save),)
    return jax.tree_util.tree_map(lambda x: x[index], saved)
