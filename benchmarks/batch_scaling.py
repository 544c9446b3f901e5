"""Batch throughput of `tj.simulate_batch`: time per launch for 1, 8 and 32 launches, and sharding.

Two measurements per batch size:

- `simulate_batch`: the public function, called as a user would (median of `REPEATS` calls after
  a first call). It builds its `filter_jit(vmap(...))` afresh on each call, so every call
  re-traces and re-compiles; its time is mostly compilation (see RESULTS.md).
- `kernel`: the same `vmap` of `tj.simulate` under one `eqx.filter_jit`, built once, compiled once
  (compile time apart), then median of `REPEATS` runs: the throughput of the batch itself.

With `--sharded` (run in a subprocess with
`XLA_FLAGS=--xla_force_host_platform_device_count=2`) it compares the batch of 32 split over two
host devices with the unsplit batch, and prints one JSON line. Called by `work_precision.py`;
on its own:

    PYTHONPATH=. python benchmarks/batch_scaling.py
"""

from __future__ import annotations

import json
import os
import pathlib
import statistics
import subprocess
import sys
import time

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

import tippejax as tj

REPEATS = 3
SIZES = (1, 8, 32)
T1 = 2.0
N_SAVE = 201
SPIN = 100.0


def launch_angles(n):
    return np.linspace(0.1, 0.3, n)


def median_time(call):
    """(first-call time, median of REPEATS later calls), each with block_until_ready."""
    start = time.perf_counter()
    jax.block_until_ready(call())
    first = time.perf_counter() - start
    times = []
    for _ in range(REPEATS):
        start = time.perf_counter()
        jax.block_until_ready(call())
        times.append(time.perf_counter() - start)
    return first, statistics.median(times)


def make_kernel(ts):
    """One jit of the vmapped simulation (what simulate_batch does inside), traced once."""

    def batch(top, thetas, spins):
        def one(theta, spin):
            y0 = tj.initial_state(top, theta, spin)
            return tj.simulate(top, y0, T1, saveat=ts, solver=diffrax.Tsit5(), throw=False)

        return jax.vmap(one)(thetas, spins).theta

    return eqx.filter_jit(eqx.debug.assert_max_traces(batch, max_traces=1))


def public_call(top, n, ts, **kwargs):
    return lambda: tj.simulate_batch(
        top, launch_angles(n), [SPIN], T1, saveat=ts, solver=diffrax.Tsit5(), **kwargs
    ).theta


def unsharded():
    """Time per launch for each batch size, public function and kernel."""
    top = tj.default_top()
    ts = jnp.linspace(0.0, T1, N_SAVE)
    rows = []
    for n in SIZES:
        thetas = jnp.asarray(launch_angles(n))
        spins = jnp.full((n,), SPIN)
        kernel = make_kernel(ts)
        k_first, k_median = median_time(lambda: kernel(top, thetas, spins))
        p_first, p_median = median_time(public_call(top, n, ts))
        rows.append(
            dict(
                n=n,
                kernel_compile_s=k_first - k_median,
                kernel_median_s=k_median,
                public_first_s=p_first,
                public_median_s=p_median,
            )
        )
        print(f"batch n={n}: kernel {k_median:.3f}s, simulate_batch {p_median:.3f}s", flush=True)
    return rows


def sharded():
    """Batch of 32 over all host devices vs on one (meant for 2 forced host devices)."""
    top = tj.default_top()
    ts = jnp.linspace(0.0, T1, N_SAVE)
    n = SIZES[-1]
    devices = jax.devices()
    thetas = jnp.asarray(launch_angles(n))
    spins = jnp.full((n,), SPIN)
    sharding = NamedSharding(Mesh(np.array(devices), ("batch",)), PartitionSpec("batch"))
    thetas_s, spins_s = jax.device_put(thetas, sharding), jax.device_put(spins, sharding)
    out = dict(devices=[str(d) for d in devices])
    kernel = make_kernel(ts)
    _, out["kernel_unsharded_s"] = median_time(lambda: kernel(top, thetas, spins))
    kernel_s = make_kernel(ts)
    _, out["kernel_sharded_s"] = median_time(lambda: kernel_s(top, thetas_s, spins_s))
    _, out["public_unsharded_s"] = median_time(public_call(top, n, ts, shard=False))
    _, out["public_sharded_s"] = median_time(public_call(top, n, ts, shard=True))
    return out


def sharded_in_subprocess():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    root = pathlib.Path(__file__).resolve().parent.parent
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(root), env.get("PYTHONPATH")]))
    done = subprocess.run(
        [sys.executable, __file__, "--sharded"], env=env, capture_output=True, text=True
    )
    if done.returncode != 0:
        return dict(error=done.stderr[-2000:])
    return json.loads(done.stdout.strip().splitlines()[-1])


if __name__ == "__main__":
    if "--sharded" in sys.argv:
        print(json.dumps(sharded()))
    else:
        print(json.dumps(dict(unsharded=unsharded(), sharded=sharded_in_subprocess()), indent=1))
