"""Every CPU core a JAX device, by default, so that batches spread over the whole machine.

XLA runs a batch (`jax.vmap` of a solve) on one CPU device, and its while loop on one core: a
batch of 1000 tops on an 8-core machine would use one core. With `N` host devices,
`simulate_batch` and `outcome_map` shard their launches over `jax.devices()`
(`jax.sharding`, padding the batch to a multiple of the device count), one core each, and a
batched `fit` shards its records over the most devices that divide their number
(`batch_sharding`). JAX makes `N` host devices only when the
flag `--xla_force_host_platform_device_count=N` is in `XLA_FLAGS` before its CPU backend
starts; importing tippejax puts it there, with `N = os.cpu_count()`, unless

- `XLA_FLAGS` already holds that flag (the user's choice is kept);
- the environment variable `TIPPEJAX_HOST_DEVICES` is set: `TIPPEJAX_HOST_DEVICES=1` keeps
  JAX's default single CPU device, another positive integer asks for that many devices;
- JAX's backends are already running (jax was used before tippejax was imported): then the
  flag could no longer take effect, and nothing is changed.

A single solve runs on the first device whatever their number (`benchmarks/peers.py` measures
one top with one and with two host devices).

Importing tippejax also turns off XLA:CPU's concurrency-optimised scheduler
(`use_sequential_scheduler`; `TIPPEJAX_CPU_SCHEDULER=concurrent` keeps it): one top's solve and
its derivatives ran up to 3x slower, and by how much changed from process to process, with
their tiny operations spread over the cores.
"""

from __future__ import annotations

import os
from collections.abc import MutableMapping

ENV = "TIPPEJAX_HOST_DEVICES"
FLAG = "--xla_force_host_platform_device_count"


def _backends_running() -> bool:
    try:
        from jax._src import xla_bridge  # no public name for this

        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):  # pragma: no cover - other jax versions
        return False


def requested_devices(environ: MutableMapping[str, str] = os.environ) -> int:
    """The number of host devices asked for: `TIPPEJAX_HOST_DEVICES`, else `os.cpu_count()`."""
    value = environ.get(ENV, "").strip()
    if not value:
        return os.cpu_count() or 1
    try:
        count = int(value)
    except ValueError:
        count = 0
    if count < 1:
        raise ValueError(
            f"{ENV} must be a positive integer (the number of CPU devices JAX should make; 1 "
            f"keeps JAX's single device), got {value!r}."
        )
    return count


def use_every_core(environ: MutableMapping[str, str] = os.environ) -> int | None:
    """Add `--xla_force_host_platform_device_count` to `XLA_FLAGS` (see the module docstring).

    **Returns:** the device count set, or None where nothing was changed.
    """
    flags = environ.get("XLA_FLAGS", "")
    if FLAG in flags:
        return None
    count = requested_devices(environ)
    if count <= 1 or _backends_running():
        return None
    environ["XLA_FLAGS"] = f"{flags} {FLAG}={count}".strip()
    return count


use_every_core()


SCHEDULER_ENV = "TIPPEJAX_CPU_SCHEDULER"
SCHEDULER_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler"
SCHEDULER_JAXLIB = ((0, 10),)
"""jaxlib versions (major, minor) whose XLA is known to take `SCHEDULER_FLAG`: XLA aborts the
process on a flag it does not know, so it is set only for these."""


def _jaxlib_version() -> tuple[int, int] | None:
    import importlib.metadata

    try:
        major, minor = importlib.metadata.version("jaxlib").split(".")[:2]
        return int(major), int(minor)
    except (importlib.metadata.PackageNotFoundError, ValueError):  # pragma: no cover
        return None


def use_sequential_scheduler(environ: MutableMapping[str, str] = os.environ) -> bool:
    """Add `--xla_cpu_enable_concurrency_optimized_scheduler=false` to `XLA_FLAGS`: XLA:CPU then
    runs a program's operations in their order instead of spreading independent ones over the
    cores. A solve of one top is thousands of tiny operations per step; spread over two
    threads they cost more than on one, and the run time of the same compiled program moved
    between processes (the standard top's 20 s run with 201 saves, `jax.jacfwd` in the seven
    fields: 130 ms in 15 processes, 340 ms in 4; with the flag 113-115 ms in 10 of 10, and the
    solve 30-32 ms against 33-43; `benchmarks/gradients.py`: its Jacobian 8.4x -> 3.7x the
    solve). A batch sharded over the cores (one device per core, `use_every_core`) runs as
    fast either way; one unsharded batch of 1000 full-model tops on one device ran 18%
    slower with it (`TIPPEJAX_HOST_DEVICES=1`). It does not keep every program on one thread:
    XLA:CPU's executor still hands kernels to a second thread when more than 8 are ready at
    once, and since tippejax's own stage loop (`StageLoopERK`) that Jacobian runs on two
    threads again at 4.3-5.7x the solve by the clock and 9-11x in CPU time (2026-11-28,
    `benchmarks/gradients.py`'s tangent scan: with 1, 2 or 5 tangents it stays on one thread at
    1.7-2.1x). Not set where `XLA_FLAGS` holds the flag
    already (the user's choice), where `TIPPEJAX_CPU_SCHEDULER=concurrent` (XLA's default
    scheduler), where JAX's backends already run, or for a jaxlib not in `SCHEDULER_JAXLIB`.

    **Returns:** whether the flag was added."""
    flags = environ.get("XLA_FLAGS", "")
    choice = environ.get(SCHEDULER_ENV, "").strip().lower()
    if choice not in ("", "sequential", "concurrent"):
        raise ValueError(
            f"{SCHEDULER_ENV} must be 'sequential' (tippejax's default) or 'concurrent' "
            f"(XLA's), got {choice!r}.")
    if (SCHEDULER_FLAG in flags or choice == "concurrent" or _backends_running()
            or _jaxlib_version() not in SCHEDULER_JAXLIB):
        return False
    environ["XLA_FLAGS"] = f"{flags} {SCHEDULER_FLAG}=false".strip()
    return True


use_sequential_scheduler()


def batch_sharding(size: int):
    """A `NamedSharding` that splits an axis of length `size` over the most of `jax.devices()`
    that divide it, or None where that is one device (a batched fit's records: padding them
    would cost a fit of a copy per pad)."""
    import jax
    import numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    devices = jax.devices()
    count = max(k for k in range(1, min(len(devices), size) + 1) if size % k == 0)
    if count == 1:
        return None
    return NamedSharding(Mesh(np.array(devices[:count]), ("batch",)), PartitionSpec("batch"))



def shard_over(fn, mesh, axis: str, args, members):
    """`fn(*args)` for a batch whose members are independent, each device running its own
    shard of the members by itself (`jax.shard_map` over `mesh`'s axis `axis`). `members[i]`
    says whether `args[i]` holds members: its array leaves with at least one axis are split
    along their first, its scalars are given whole to every device; the other arguments go
    whole to every device. The outputs are the shards' put together along their first axis.

    A batch of solves jitted on sharded inputs instead (`jax.jit`'s automatic partitioning)
    runs ONE while loop over all devices, whose condition (is any member still running?) is
    reduced across them at every step: every device takes as many steps as the slowest member
    of the whole batch and waits for the others at each. Here each device loops until its own
    members are done (`benchmarks/shared_steps.py`, 1000 SO(3) tops, one solve per member,
    2 host devices: 1.68 -> 1.38 s)."""
    import jax
    from jax.sharding import PartitionSpec

    def spec(x, split):
        return PartitionSpec(axis) if split and getattr(x, "ndim", 0) >= 1 else PartitionSpec()

    specs = tuple(jax.tree_util.tree_map(lambda x, split=split: spec(x, split), arg)
                  for arg, split in zip(args, members, strict=True))
    # check_vma off: diffrax's loop carries arrays made inside it next to the shard's own;
    # with the check on their "varying" types differ and the while loop is refused.
    return jax.shard_map(fn, mesh=mesh, in_specs=specs, out_specs=PartitionSpec(axis),
                         check_vma=False)(*args)


def run_in_blocks(fn, block, args):
    """`fn(*args)` for a batch whose members are independent, run as consecutive blocks of
    `block` members (`jax.lax.map` over the blocks): as in `shard_over`, the array leaves of
    `args` with at least one axis hold the members along their first (a multiple of `block`
    long) and are split into the blocks; the others go whole to every block. The outputs are
    the blocks' put back together along their first axis. `block` None, or no larger than the
    batch, calls `fn(*args)` once. On a CPU device a vmapped solve runs faster in blocks of
    about a hundred members (`tippejax._batch.PER_MEMBER_BLOCK`)."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    split, whole = eqx.partition(args, lambda x: jnp.ndim(x) >= 1)
    leaves = jax.tree_util.tree_leaves(split)
    n = leaves[0].shape[0] if leaves else 0
    if block is None or n <= block:
        return fn(*args)
    blocks = n // block
    parts = jax.tree_util.tree_map(lambda x: x.reshape(blocks, block, *x.shape[1:]), split)
    out = jax.lax.map(lambda part: fn(*eqx.combine(part, whole)), parts)
    return jax.tree_util.tree_map(lambda x: x.reshape(n, *x.shape[2:]), out)
