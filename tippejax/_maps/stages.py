"""Outcome maps at the cheapest adequate level (`outcome_map(model="auto")`): the gyroscopic
level where it holds, the full model where it does not, each in batches of its own."""

from __future__ import annotations

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .._devices import gather, shard_over
from .._engine.chain import run_chain
from .._engine.cpu import CpuProgram
from .._engine.watch import EVENT_PIECES
from .._invariants import jellet
from .._models.full import FullLevel
from .._models.gyroscopic import NUTATION_FLOOR, GyroscopicLevel
from .._solution import RESULTS
from .._state import State
from .._top import TippeTop
from .slow_entry import _accepted, _bucketed, _entry, _launch_states, split_state

STAGE_CHUNK = 64
"""Launches per compiled batch of a stage (rounded up to a multiple of the device count)."""

FIRST_WINDOW = 0.5
"""The first window (s) of the full model before the gyroscopic level is asked to take over;
each further window of the same run is twice as long."""

MAX_STAGES = 12
"""Stages of (full window, slow) at most; a run not finished by then goes to the full model."""

MAX_HAND_OVERS = 2
"""Hand-overs of one run at most; after that it stays in the full model to `t1`."""


HAND_OVER_CONTACT = 0.3
r"""The slow stage hands over where the nutation it carries would take this fraction of $g$
off the normal force (`GyroscopicLevel(contact_margin=...)`). A larger fraction misses contact
losses of launches whose nutation lifts the top soon after the slow flow took over."""


def _stage_batch_impl(level, top, states, level_states, t0, t_stop, options, mesh):
    """One compiled chunk of a stage: `level` from `(t0, state)` to `t_stop`, per member
    (starting from `level_states`, the level's own states, where given), each device its own
    shard (`shard_over`)."""
    return shard_over(
        functools.partial(_stage_runs, level, options),
        mesh,
        "launch",
        (top, states, level_states, t0, t_stop),
        (False, True, True, True, True),
    )


_stage_batch_default = eqx.filter_jit(_stage_batch_impl)
_stage_batch_cpu = CpuProgram(_stage_batch_impl)


def _stage_batch(level, top, states, level_states, t0, t_stop, options, mesh):
    """`_stage_batch_impl` compiled for the devices of `mesh`: with tippejax's CPU options on
    CPU devices (`tippejax._engine.cpu`, as `simulate_batch`)."""
    cpu = mesh.devices.flat[0].platform == "cpu"
    run = _stage_batch_cpu if cpu else _stage_batch_default
    return run(level, top, states, level_states, t0, t_stop, options, mesh)


def _stage_runs(level, options, top, states, level_states, t0, t_stop):
    rtol, atol, solver, max_steps = options

    def one(state, y0, start, stop):
        out = run_chain(
            level,
            top,
            state,
            start,
            stop,
            None,
            stop_on_contact=True,
            solver=solver,
            rtol=rtol,
            atol=atol,
            max_steps=max_steps,
            adjoint=diffrax.RecursiveCheckpointAdjoint(),
            progress_meter=diffrax.NoProgressMeter(),
            pieces=EVENT_PIECES,
            y0=y0,
        )
        return dict(
            state=out.state_end,
            t_final=out.t_final,
            result=out.result._value.astype(jnp.int8),
            t_invert=out.t_invert,
            t_contact_loss=out.t_contact_loss,
            num_steps=out.num_steps.astype(jnp.int32),
        )

    return jax.vmap(one)(states, level_states, t0, t_stop)


def _take(tree, index):
    return jax.tree_util.tree_map(lambda x: x[index], tree)


def _put_back(tree, index, values):
    def put(x, v):
        x = np.array(x)
        x[index] = v
        return x

    return jax.tree_util.tree_map(put, tree, values)


class _Runner:
    """Runs the stages' chunks, sharded over `devices` (as `_maps._run_flat`)."""

    def __init__(self, top, devices, options):
        self.top = top
        self.dtype = jnp.result_type(top.m)
        self.n_dev = len(devices)
        self.chunk = -(-STAGE_CHUNK // self.n_dev) * self.n_dev
        self.mesh = Mesh(np.array(devices), ("launch",))
        self.sharding = NamedSharding(self.mesh, PartitionSpec("launch"))
        self.options = options
        fields, static = eqx.partition(top, eqx.is_array)
        fields = jax.tree_util.tree_map(lambda x: np.asarray(x, dtype=self.dtype), fields)
        self.top_host = eqx.combine(fields, static)

    def _put(self, x):
        x = np.asarray(x)
        return jax.make_array_from_callback(x.shape, self.sharding, lambda index: x[index])

    def run(self, level, states, t0, t_stop, order, level_states=None):
        """`level` for the members `states` (host pytree) from `t0` to `t_stop` (from
        `level_states` where given); members are sorted by `order` and run in chunks. Returns
        host arrays in the members' order."""
        size = t0.shape[0]
        perm = np.argsort(order, kind="stable")
        parts = []
        for start in range(0, size, self.chunk):
            index = perm[start : start + self.chunk]
            pad = self.chunk - index.size
            sel = np.concatenate([index, np.repeat(index[-1:], pad)]) if pad else index
            stop = np.asarray(t_stop, float)[sel].copy()
            begin = np.asarray(t0, float)[sel]
            if pad:
                stop[index.size :] = begin[index.size :]  # zero-length padding
            chunk_states, chunk_level = jax.tree_util.tree_map(
                lambda x: self._put(np.asarray(x, self.dtype)[sel]), (states, level_states)
            )
            out = _stage_batch(
                level,
                self.top_host,
                chunk_states,
                chunk_level,
                self._put(begin.astype(self.dtype)),
                self._put(stop.astype(self.dtype)),
                self.options,
                self.mesh,
            )
            parts.append(jax.tree_util.tree_map(lambda x: gather(x)[: index.size], out))
        joined = jax.tree_util.tree_map(lambda *xs: np.concatenate(xs), *parts)
        inverse = np.empty_like(perm)
        inverse[perm] = np.arange(size)
        return jax.tree_util.tree_map(lambda x: x[inverse], joined)


def _spin(states) -> np.ndarray:
    return np.abs(np.sum(np.asarray(states.axis) * np.asarray(states.omega), axis=-1))


def staged_outcomes(
    top: TippeTop, y0: State, t1: float, *, rtol, atol, solver, slow_solver, max_steps, devices
) -> dict[str, np.ndarray]:
    r"""Run the launches `y0` (a batched `State`) to `t1` in stages, each at the cheapest
    adequate level.

    A batch of launches runs in lock-step (`jax.vmap` of a solve takes as many steps as its
    longest member), so a batch that mixed slow-flow runs (tens of steps) with full-model runs
    (thousands) would cost as much as the full-model map. Here every launch is a sequence of
    **stages**, and each stage runs the members that need it as a batch of their own,
    compacted on the host between two compiled calls:

    1. **Full window**: a launch the gyroscopic level does not accept (`in_chart`: gyroscopic
       balance fails, or the launch carries more nutation than it can project) runs in the
       full model for a window (`FIRST_WINDOW`, doubling on each further window of the same
       run), ending early where contact is lost. At the end of the window the state is split
       into the full model's modes at the nearer pole (`split_state`: the slow manifold's
       component and the nutation), and the gyroscopic level takes the run over where
       `entry_margin` is positive: gyroscopic balance with a margin, the nutation about the
       slow manifold decaying ($-\sigma/\nu >$ `ENTRY_DECAY`), the nutation below
       `ENTRY_NUTATION` and taking less than `ENTRY_CONTACT` of $g$ off the normal force.
    2. **Slow**: the slow flow (G3) (`GyroscopicLevel(stop_at_hand_over=True,
       contact_margin=HAND_OVER_CONTACT)`) from the slow component (a launch: the averaged
       projection) to `t1`, or to where the run must go back to the full model: the slow
       manifold repels ($\sigma > 0$, at fast spins during the rise: the route to contact
       loss), gyroscopic balance is lost, or the nutation the run carries would take
       `HAND_OVER_CONTACT` of $g$ off the normal force.
    3. **Replay**: a run handed back goes to the full model again from the state where it
       last left it (the launch, or the end of its last window), through the hand-over time
       and on in windows as in 1. The full model thus decides every contact loss from its own
       state; the slow stage only decides when the full model is needed, and what it computed
       after that state is discarded.

    A run is handed back at most `MAX_HAND_OVERS` times and goes through at most `MAX_STAGES`
    stages; then it finishes in the full model. Members of a full-model stage are sorted by
    spin x length of the window (the full model's steps follow the nutation, whose frequency
    grows with the spin) and run in chunks of `STAGE_CHUNK`, padded with zero-length members
    (one compilation per stage and chunk size), so a chunk holds members of similar cost.

    **The nutation the slow stage carries.** The gyroscopic level is the slow flow of the
    SO(3) model, where the nutation a launch carries (the other root's mode) decays
    (`nutation_damping`). In the full model it does not all decay: at the vertical state that
    mode splits into one that decays faster still and one in which the centre of mass rolls
    round with the contact point, which barely decays (`pole_linearisation`). A launch keeps
    some of it through the rise, the more the larger its tilt, and with it the full model can
    lose contact where the slow flow ($R_n = mg$, $\sigma < 0$) sees nothing. The vertical
    acceleration of the centre of mass that a nutation of amplitude $a$ and frequency $\nu$
    brings is about $\epsilon\sin\theta\,a\nu^2$, and contact is lost where it reaches about
    $g$. So each run carries into the slow stage the amplitude $a$ of its nutation (the modes
    of `pole_linearisation` other than the slow manifold's) and the growth rate of the one
    that outlives the other (the rolling mode's real part), and the slow stage hands over
    where $\epsilon\sin\theta\,a\nu^2$ reaches `HAND_OVER_CONTACT` $g$. A state away from the
    poles ($\sin\theta >$ `POLE_SPLIT_SIN`) is split with the linear projection (SO(3) modes)
    instead.

    **A replay, not a restart** from the slow state with the carried nutation added: where the
    contact loss comes from the carried nutation before the slow manifold repels, and near
    the boundary of the contact-loss region, the outcome turns on the amplitude and phase of
    the nutation the full model carries, which the slow stage knows only roughly. The replay
    gives the full model's outcome wherever the slow stage hands over, at the cost of the
    full model from the last window to the hand-over.

    **Returns:** host arrays per launch: `state` (where each run ended), `t_final`, `result`
    (`RESULTS` code), `t_invert`, `t_contact_loss`, `num_steps` (all stages), `route` (str:
    the levels that ran, e.g. `"gyroscopic->full"`), `hand_overs` (how many times the slow
    stage handed the run back), and `stages` (a list of `(level, members, steps of each
    member, RESULTS code of each member)` in the order the stages ran).
    """
    size = np.asarray(y0.axis).shape[0]
    dtype = jnp.result_type(top.m)
    runner = _Runner(top, devices, (rtol, atol, solver, max_steps))
    slow_runner = _Runner(top, devices, (rtol, atol, slow_solver, max_steps))
    slow = GyroscopicLevel(stop_at_hand_over=True, contact_margin=HAND_OVER_CONTACT, body=False)
    full = FullLevel(body=False)

    state = jax.tree_util.tree_map(lambda x: np.asarray(x, dtype), y0)
    t = np.zeros(size)
    J = _bucketed(_jellets, top, state)
    done = np.zeros(size, bool)
    result = np.zeros(size, np.int8)
    t_invert = np.full(size, np.nan)
    t_loss = np.full(size, np.nan)
    steps = np.zeros(size, np.int64)
    routes: list[list[str]] = [[] for _ in range(size)]
    stages = []
    in_full = ~_bucketed(_accepted, top, state)
    window = np.full(size, FIRST_WINDOW)
    replay_until = np.zeros(size)  # a replayed run is not handed to the slow stage before this
    hand_overs = np.zeros(size, int)
    # where each run last left the full model (for a replay), and the slow stage's states
    left, t_left = state, np.zeros(size)
    _, _, nutation, growth = split_state(top, state, J)
    slow_states = _bucketed(
        _launch_states,
        top,
        state,
        np.log(np.maximum(nutation, NUTATION_FLOOR)).astype(dtype),
        growth.astype(dtype),
    )

    def record(index, out, stage):
        nonlocal state
        state = _put_back(state, index, out["state"])
        t[index] = out["t_final"]
        steps[index] += out["num_steps"]
        first = np.isnan(t_invert[index])
        t_invert[index] = np.where(first, out["t_invert"], t_invert[index])
        t_loss[index] = np.where(np.isnan(t_loss[index]), out["t_contact_loss"], t_loss[index])
        for i in index:
            if not routes[i] or routes[i][-1] != stage:
                routes[i].append(stage)
        stages.append((stage, index, out["num_steps"], out["result"]))

    for stage in range(MAX_STAGES):
        last = stage == MAX_STAGES - 1
        members = np.flatnonzero(in_full & ~done)
        if members.size:
            stop = np.full(members.size, float(t1))
            if not last:
                ahead = np.maximum(t[members] + window[members], replay_until[members])
                stop = np.minimum(ahead, t1)
            out = runner.run(
                full,
                _take(state, members),
                t[members],
                stop,
                -_spin(_take(state, members)) * (stop - t[members]),
            )
            record(members, out, "full")
            code = out["result"]
            ended = (code != RESULTS.successful._value) | (out["t_final"] >= t1)
            result[members[ended]] = code[ended]
            done[members[ended]] = True
            going = members[~ended]
            if going.size:
                # does the slow stage take over where the window ended?
                theta_s, phi_s, nutation, growth = split_state(top, _take(state, going), J[going])
                log_nutation = np.log(np.maximum(nutation, NUTATION_FLOOR)).astype(dtype)
                margin, entering, on_manifold = _bucketed(
                    _entry,
                    top,
                    theta_s.astype(dtype),
                    phi_s.astype(dtype),
                    J[going],
                    log_nutation,
                    growth.astype(dtype),
                )
                enter = (margin > 0) & (hand_overs[going] <= MAX_HAND_OVERS)
                index, rows = going[enter], np.flatnonzero(enter)
                left = _put_back(left, index, _take(state, index))
                t_left[index] = t[index]
                state = _put_back(state, index, _take(on_manifold, rows))
                slow_states = _put_back(slow_states, index, _take(entering, rows))
                in_full[index] = False
                window[going[~enter]] *= 2
        members = np.flatnonzero(~in_full & ~done)
        if not members.size:
            if not np.any(~done):
                break
            continue
        t_invert_before = t_invert[members].copy()
        out = slow_runner.run(
            slow,
            _take(state, members),
            t[members],
            np.full(members.size, float(t1)),
            np.zeros(members.size),
            level_states=_take(slow_states, members),
        )
        record(members, out, "gyroscopic")
        code = out["result"]
        handed = code == RESULTS.no_gyroscopic_balance._value
        result[members[~handed]] = code[~handed]
        done[members[~handed]] = True
        if np.any(handed):
            # the nutation the full model carries may matter from here on (the slow manifold
            # repels, or it may lift the top): run the full model again from where the run
            # left it, at least to the hand-over
            index = members[handed]
            replay_until[index] = t[index]
            t_invert[index] = t_invert_before[handed]
            state = _put_back(state, index, _take(left, index))
            t[index] = t_left[index]
            in_full[index] = True
            window[index] = FIRST_WINDOW
            hand_overs[index] += 1
    members = np.flatnonzero(~done)
    if members.size:
        out = runner.run(
            full,
            _take(state, members),
            t[members],
            np.full(members.size, float(t1)),
            -_spin(_take(state, members)),
        )
        record(members, out, "full")
        result[members] = out["result"]
    return dict(
        state=state,
        t_final=t,
        result=result,
        t_invert=t_invert,
        t_contact_loss=t_loss,
        num_steps=steps,
        route=np.array(["->".join(r) for r in routes]),
        hand_overs=hand_overs,
        stages=stages,
    )


@eqx.filter_jit
def _jellets(top, states):
    return jax.vmap(lambda y: jellet(top, y))(states)
