"""Batches of simulations: a grid of launch angles and spins for one top, sharded over devices."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import ArrayLike

from ._engine.solver_choice import default_solver
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
    **kwargs,
) -> Solution:
    r"""Simulate one top launched from every pair of `theta0` x `spin` (a grid), in one batch.

    Each launch is `initial_state(top, theta, spin)`. The grid is flattened, run under one
    `jax.vmap` (one compilation) with `throw=False`, so a failed member is flagged in
    `sol.result` without stopping the others, and reshaped to `(len(theta0), len(spin))`.
    With `shard=True` and more than one device, the batch is split over all devices with
    `jax.sharding` (padded to a multiple of the device count).

    Other keyword arguments go to `simulate` (`model`, `saveat`, `rtol`, `atol`, `solver`, ...).

    **Returns:** a `Solution` with leading batch axes `(len(theta0), len(spin))`.
    """
    if "throw" in kwargs and kwargs["throw"]:
        raise ValueError("simulate_batch always runs with throw=False; inspect sol.result.")
    kwargs.pop("throw", None)
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
        kwargs["solver"] = default_solver(top)
    dtype = jnp.result_type(top.m)
    devices = jax.devices()
    n_dev = len(devices) if shard else 1
    padded = -(-size // n_dev) * n_dev
    flat_theta = np.concatenate([flat_theta, np.repeat(flat_theta[-1:], padded - size)])
    flat_spin = np.concatenate([flat_spin, np.repeat(flat_spin[-1:], padded - size)])
    thetas = jnp.asarray(flat_theta, dtype)
    spins = jnp.asarray(flat_spin, dtype)
    if n_dev > 1:
        sharding = NamedSharding(Mesh(np.array(devices), ("batch",)), PartitionSpec("batch"))
        thetas = jax.device_put(thetas, sharding)
        spins = jax.device_put(spins, sharding)

    sol = _batch_run(top, thetas, spins, jnp.asarray(t1, dtype), kwargs)
    shape = grid_theta.shape

    def unflatten(x):
        if not isinstance(x, jax.Array):
            return x
        return x[:size].reshape(shape + x.shape[1:])

    return jax.tree_util.tree_map(unflatten, sol)
