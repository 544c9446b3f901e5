"""Batches of simulations: a grid of launch angles and spins for one top, sharded over devices."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import ArrayLike

from ._engine.solver_choice import default_solver
from ._models.levels import LEVELS
from ._simulate import simulate
from ._solution import Solution
from ._state import initial_state
from ._top import TippeTop


@eqx.filter_jit
def _batch_run(top, thetas, spins, t1, kwargs):
    # Module-level and jitted once per (shapes, static options): repeated calls reuse it.
    def one(theta, s):
        return simulate(top, initial_state(top, theta, s), t1, throw=False, **kwargs)

    return jax.vmap(one)(thetas, spins)


def simulate_batch(
    top: TippeTop,
    theta0: ArrayLike,
    spin: ArrayLike,
    t1: float,
    *,
    shard: bool = True,
    buckets: int = 1,
    **kwargs,
) -> Solution:
    r"""Simulate one top launched from every pair of `theta0` x `spin` (a grid), in one batch.

    Each launch is `initial_state(top, theta, spin)`. The grid is flattened, run under one
    `jax.vmap` (one compilation) with `throw=False`, so a failed member is flagged in
    `sol.result` without stopping the others, and reshaped to `(len(theta0), len(spin))`.
    With `shard=True` and more than one device, the batch is split over all devices with
    `jax.sharding` (padded to a multiple of the device count).

    Under `vmap` every member takes as many solver steps as the slowest one. With
    `buckets > 1` the launches are sorted by $|n|$ (their cost grows with spin x t1, and t1 is
    common), split into `buckets` equal-size groups (padded with the last launch), and each
    group is run as its own batch through the same compiled function; the results are put back
    in grid order. This pays when the members run to `t1` with step counts spread by spin
    (`benchmarks/batch.py`: 2-4 buckets ran a batch of spins 20..400 ~1.4x faster); it does not
    when many members stop early (contact loss), and small buckets use the cores less well.
    Results agree with `buckets=1` to about `rtol` (a member's rounding depends on the batch
    size).

    Other keyword arguments go to `simulate` (`model`, `saveat`, `rtol`, `atol`, `solver`, ...).

    **Returns:** a `Solution` with leading batch axes `(len(theta0), len(spin))`.
    """
    if "throw" in kwargs and kwargs["throw"]:
        raise ValueError("simulate_batch always runs with throw=False; inspect sol.result.")
    kwargs.pop("throw", None)
    if isinstance(buckets, bool) or not isinstance(buckets, (int, np.integer)) or buckets < 1:
        raise ValueError(f"simulate_batch: buckets must be an integer >= 1, got {buckets!r}.")
    theta0 = np.atleast_1d(np.asarray(theta0, dtype=float))
    spin = np.atleast_1d(np.asarray(spin, dtype=float))
    for name, values in (("theta0", theta0), ("spin", spin)):
        if values.ndim != 1 or values.size == 0:
            raise ValueError(
                f"simulate_batch: {name} must be a non-empty 1-d list of values, got shape "
                f"{values.shape}."
            )
        if not np.all(np.isfinite(values)):
            raise ValueError(f"simulate_batch: {name} must be finite (got NaN or inf).")
    grid_theta, grid_spin = np.meshgrid(theta0, spin, indexing="ij")
    flat_theta, flat_spin = grid_theta.ravel(), grid_spin.ravel()
    size = flat_theta.size
    if kwargs.get("solver") is None:
        level = LEVELS.get(kwargs.get("model", "full"))
        kwargs["solver"] = default_solver(top, slow_flow=level is not None and level.slow_flow)
    dtype = jnp.result_type(top.m)
    devices = jax.devices()
    n_dev = len(devices) if shard else 1
    buckets = min(int(buckets), size)
    # Launch order: by |spin| when bucketing, else the grid's. Each bucket holds `per`
    # launches, a multiple of the device count; the tail is padded with the last launch.
    order = np.argsort(np.abs(flat_spin), kind="stable") if buckets > 1 else np.arange(size)
    per = -(-size // buckets)
    per = -(-per // n_dev) * n_dev
    order = np.concatenate([order, np.repeat(order[-1:], per * buckets - size)])
    sharding = None
    if n_dev > 1:
        sharding = NamedSharding(Mesh(np.array(devices), ("batch",)), PartitionSpec("batch"))
    t1 = jnp.asarray(t1, dtype)
    parts = []
    for b in range(buckets):
        idx = order[b * per:(b + 1) * per]
        thetas = jnp.asarray(flat_theta[idx], dtype)
        spins = jnp.asarray(flat_spin[idx], dtype)
        if sharding is not None:
            thetas = jax.device_put(thetas, sharding)
            spins = jax.device_put(spins, sharding)
        parts.append(_batch_run(top, thetas, spins, t1, kwargs))
    if buckets == 1:
        sol = parts[0]
        back = None
    else:
        sol = jax.tree_util.tree_map(
            lambda *xs: jnp.concatenate(xs) if isinstance(xs[0], jax.Array) else xs[0], *parts
        )
        back = np.empty(size, dtype=int)
        back[order[:size]] = np.arange(size)
    shape = grid_theta.shape

    def unflatten(x):
        if not isinstance(x, jax.Array):
            return x
        x = x[:size] if back is None else x[back]
        return x.reshape(shape + x.shape[1:])

    return jax.tree_util.tree_map(unflatten, sol)
