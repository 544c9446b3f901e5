"""The launches of a map: each one run and classified, in chunks sharded over every device."""

from __future__ import annotations

import dataclasses
import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .._devices import cpu_block, gather, run_in_blocks, shard_over
from .._engine.chain import run_chain
from .._engine.cpu import CpuProgram
from .._engine.packing import PACK_WIDTH
from .._engine.watch import EVENT_PIECES
from .._invariants import jellet
from .._models.levels import LEVELS
from .._outcome import classify_end, stable_states
from .._solution import RESULTS
from .._state import euler_angles, initial_state

INDICATORS = ("contact_margin", "theta_max", "decision_margin")
r"""The continuous indicators each launch of a map returns besides its outcome:

- `contact_margin`: $\min_t (g + \ddot h_0)/g = \min_t R_n D/g$ over the run ($D$ the
  denominator of eq. reactie; 1 for a top at rest, 0 where contact is lost), from the
  watched contact condition (`run_chain(lowest=...)`);
- `theta_max`: the largest tilt the run reached ($\arccos \min_t a_Z$);
- `decision_margin`: how far (rad) the final tilt is from flipping its classification, half
  the gap between its distances to the nearest and the second-nearest stable state of its
  $J$ ($\pi$ where only one is stable)."""


def _indicators(top, J, theta_final, lowest):
    theta, stable, _ = stable_states(top, J)
    distance = jnp.sort(jnp.where(stable, jnp.abs(theta_final - theta), jnp.inf))
    gap = jnp.where(jnp.isfinite(distance[1]), 0.5 * (distance[1] - distance[0]), jnp.pi)
    return dict(
        contact_margin=lowest["contact"] / top.g,
        theta_max=jnp.arccos(jnp.clip(lowest["upright"], -1.0, 1.0)),
        decision_margin=gap,
    )


def _classified_runs(top_static, options, top_fields, launches, t1):
    """Every launch of `launches` (rows: `theta0, spin, theta_dot, phi_dot, phi, psi, vx,
    vy`) run to its `t1` (0 for padding: no step) and classified; `top_fields` per launch
    (leaves with one axis) or shared (scalars)."""
    level, rtol, atol, solver, max_steps, settle_tol = options

    def one(fields, launch, t1):
        top = eqx.combine(fields, top_static)
        theta0, spin, theta_dot, phi_dot, phi, psi, vx, vy = launch
        y0 = initial_state(
            top, theta0, spin, theta_dot=theta_dot, phi_dot=phi_dot, phi=phi, psi=psi, vx=vx, vy=vy
        )
        # What `simulate(..., summary=True, throw=False)` runs in a batch, with the lowest
        # contact condition and tilt cosine kept.
        out = run_chain(
            level,
            top,
            y0,
            jnp.zeros((), t1.dtype),
            t1,
            None,
            stop_on_contact=True,
            solver=solver,
            rtol=rtol,
            atol=atol,
            max_steps=max_steps,
            adjoint=diffrax.ForwardMode(),
            progress_meter=diffrax.NoProgressMeter(),
            pieces=EVENT_PIECES,
            pack_width=PACK_WIDTH,
            lowest=("contact", "upright"),
        )
        J = jellet(top, y0)
        theta_f = euler_angles(out.state_end)[0]
        result = out.result
        # (as `simulate`: a non-finite end is a failure)
        nonfinite = ~jnp.isfinite(theta_f) | ~jnp.isfinite(jellet(top, out.state_end))
        result = RESULTS.where(
            (result == RESULTS.successful) & nonfinite, RESULTS.nonfinite, result
        )
        outcome, settled, expected = classify_end(top, J, theta_f, result, settle_tol=settle_tol)
        return dict(
            outcome=outcome,
            settled=settled,
            theta_final=theta_f,
            theta_expected=expected,
            t_invert=out.t_invert,
            t_contact_loss=out.t_contact_loss,
            t_final=out.t_final,
            jellet=J,
            result=result._value.astype(jnp.int8),
            num_steps=out.num_steps.astype(jnp.int32),
            **_indicators(top, J, theta_f, out.lowest),
        )

    field_axes = jax.tree_util.tree_map(lambda x: 0 if x.ndim == 1 else None, top_fields)
    return jax.vmap(one, in_axes=(field_axes, 0, 0))(top_fields, launches, t1)


def _run_chunk_impl(top_fields, top_static, launches, t1, options, mesh, block=None):
    """One sharded chunk of launches, each device its own shard (`shard_over`), on CPU devices
    in blocks of `block` members (`run_in_blocks`, see `simulate_batch`)."""

    def local(top_fields, launches, t1):
        return run_in_blocks(
            functools.partial(_classified_runs, top_static, options),
            block,
            (top_fields, launches, t1),
        )

    return shard_over(local, mesh, "launch", (top_fields, launches, t1), (True, True, True))


_run_chunk = eqx.filter_jit(_run_chunk_impl)
_run_chunk_cpu = CpuProgram(_run_chunk_impl)


def map_level(model: str):
    """The level a map runs: `simulate`'s in summary mode (no body vector)."""
    return dataclasses.replace(LEVELS[model], body=False)


def chunk_layout(size: int, chunk_size: int, devices) -> tuple[int, int | None]:
    """`(chunk, block)`: launches per compiled chunk (at most `chunk_size`, no more than
    `size` needs, a multiple of the device count and, on CPU devices, of the block) and the
    block of each device's shard (`cpu_block`)."""
    n_dev = len(devices)
    chunk = max(1, min(int(chunk_size), size))
    chunk = -(-chunk // n_dev) * n_dev
    block = cpu_block(chunk // n_dev) if devices[0].platform == "cpu" else None
    if block is not None:
        chunk = -(-chunk // (block * n_dev)) * block * n_dev
    return chunk, block


def run_launches(
    tops,
    launches: np.ndarray,
    t1,
    *,
    batched_top: bool,
    model: str,
    rtol,
    atol,
    solver,
    max_steps,
    settle_tol,
    chunk: int,
    block,
    devices,
    order: np.ndarray | None = None,
    progress=None,
) -> dict[str, np.ndarray]:
    """Run and classify the launches (rows of `launches`, shape `(N, 8)`) in chunks of
    `chunk` sharded over `devices` (see `chunk_layout`); `tops` one top, or one per launch
    (`batched_top`).

    With an `order` (an estimate of each launch's cost) the launches run sorted by it, and
    each chunk deals them out to the devices in turn: a device's blocks then hold launches of
    similar cost (a block's loop ends with its slowest), and the devices equal shares. A
    chunk is filled up with runs of no length (copies of a launch to `t = 0`). `progress(n)`
    is called after each chunk with its number of launches.

    **Returns:** numpy arrays per launch in the launches' order, on every process."""
    size = launches.shape[0]
    n_dev = len(devices)
    perm = np.arange(size) if order is None else np.argsort(order, kind="stable")
    cpu = devices[0].platform == "cpu"
    run_chunk = _run_chunk_cpu if cpu else _run_chunk
    mesh = Mesh(np.array(devices), ("launch",))
    sharded = NamedSharding(mesh, PartitionSpec("launch"))
    dtype = jnp.result_type(tops.m)
    fields, static = eqx.partition(tops, eqx.is_array)
    options = (map_level(model), rtol, atol, solver, max_steps, settle_tol)

    def put(values):
        # Each process builds only the shards on its own devices.
        return jax.make_array_from_callback(
            values.shape, sharded, lambda index: np.asarray(values[index], dtype=dtype)
        )

    fields = jax.tree_util.tree_map(lambda x: np.asarray(x, dtype=dtype), fields)
    out = None
    for start in range(0, size, chunk):
        index = perm[start : start + chunk]
        real = np.ones(chunk, bool)
        real[index.size :] = False
        index = np.concatenate([index, np.repeat(index[-1:], chunk - index.size)])
        if order is not None:  # device d takes every n_dev-th launch
            deal = np.arange(chunk).reshape(chunk // n_dev, n_dev).T.ravel()
            index, real = index[deal], real[deal]
        if batched_top:
            chunk_fields = jax.tree_util.tree_map(lambda x: put(x[index]), fields)
        else:  # replicated scalars
            chunk_fields = fields
        ends = np.where(real, float(t1), 0.0)
        part = run_chunk(
            chunk_fields, static, put(launches[index]), put(ends), options, mesh, block
        )
        part = {k: gather(v)[real] for k, v in part.items()}
        if out is None:
            out = {k: np.empty((size,) + v.shape[1:], v.dtype) for k, v in part.items()}
        for k, v in part.items():
            out[k][index[real]] = v
        if progress is not None:
            progress(int(real.sum()))
    return out
