"""JAX devices: every CPU core a device (set at import), and batches split over devices and
into blocks."""

from __future__ import annotations

import importlib.metadata
import os
from collections.abc import MutableMapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

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
    """Make every CPU core a JAX device, so that batches spread over the whole machine.

    XLA runs a batch (`jax.vmap` of a solve) on one CPU device, and its while loop on one
    core. With `N` host devices, `simulate_batch` and `outcome_map` shard their launches over
    `jax.devices()` (padding the batch to a multiple of the device count), one core each, and
    a batched `fit` shards its records over the most devices that divide their number
    (`batch_sharding`). A single solve runs on the first device whatever their number.

    JAX makes `N` host devices only when it is told before its CPU backend starts: importing
    tippejax sets JAX's own option `jax_num_cpu_devices` to `N = os.cpu_count()` (with a JAX
    that lacks it, the flag `--xla_force_host_platform_device_count=N` in `XLA_FLAGS`), unless

    - the user chose already: `XLA_FLAGS` holds that flag, or `JAX_NUM_CPU_DEVICES` is set, or
      `jax_num_cpu_devices` was set before the import (the user's choice is kept);
    - the environment variable `TIPPEJAX_HOST_DEVICES` is set: `TIPPEJAX_HOST_DEVICES=1` keeps
      JAX's default single CPU device, another positive integer asks for that many devices;
    - JAX's backends are already running (jax was used before tippejax was imported): then the
      flag could no longer take effect, and nothing is changed.

    **Returns:** the device count set, or None where nothing was changed.
    """
    flags = environ.get("XLA_FLAGS", "")
    if FLAG in flags or environ.get("JAX_NUM_CPU_DEVICES", "").strip():
        return None
    count = requested_devices(environ)
    if count <= 1 or _backends_running():
        return None
    if hasattr(jax.config, "jax_num_cpu_devices"):
        if jax.config.jax_num_cpu_devices not in (-1, None):
            return None
        jax.config.update("jax_num_cpu_devices", count)
        return count
    environ["XLA_FLAGS"] = f"{flags} {FLAG}={count}".strip()  # pragma: no cover - older jax
    return count


use_every_core()


SCHEDULER_ENV = "TIPPEJAX_CPU_SCHEDULER"
SCHEDULER_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler"
SCHEDULER_JAXLIB = ((0, 10),)
"""jaxlib versions (major, minor) whose XLA is known to take `SCHEDULER_FLAG`: XLA aborts the
process on a flag it does not know, so it is set only for these."""


def _jaxlib_version() -> tuple[int, int] | None:
    try:
        major, minor = importlib.metadata.version("jaxlib").split(".")[:2]
        return int(major), int(minor)
    except (importlib.metadata.PackageNotFoundError, ValueError):  # pragma: no cover
        return None


def use_sequential_scheduler(environ: MutableMapping[str, str] = os.environ) -> bool:
    """Add `--xla_cpu_enable_concurrency_optimized_scheduler=false` to `XLA_FLAGS`: XLA:CPU then
    runs a program's operations in their order instead of spreading independent ones over the
    cores.

    A solve of one top is thousands of tiny operations per step; spread over two threads they
    cost more than on one, and the run time of the same compiled program varies between
    processes. A batch sharded over the cores (one device per core, `use_every_core`) runs as
    fast either way. XLA:CPU's executor may still hand kernels to a second thread when many
    are ready at once. Not set where `XLA_FLAGS` holds the flag already (the user's choice),
    where `TIPPEJAX_CPU_SCHEDULER=concurrent` (XLA's default scheduler), where JAX's backends
    already run, or for a jaxlib not in `SCHEDULER_JAXLIB`. Importing tippejax calls it; see
    the performance page for what it changes.

    **Returns:** whether the flag was added."""
    flags = environ.get("XLA_FLAGS", "")
    choice = environ.get(SCHEDULER_ENV, "").strip().lower()
    if choice not in ("", "sequential", "concurrent"):
        raise ValueError(
            f"{SCHEDULER_ENV} must be 'sequential' (tippejax's default) or 'concurrent' "
            f"(XLA's), got {choice!r}."
        )
    if (
        SCHEDULER_FLAG in flags
        or choice == "concurrent"
        or _backends_running()
        or _jaxlib_version() not in SCHEDULER_JAXLIB
    ):
        return False
    environ["XLA_FLAGS"] = f"{flags} {SCHEDULER_FLAG}=false".strip()
    return True


use_sequential_scheduler()


PER_MEMBER_BLOCK = 128
"""Most members in one vmapped solve of a per-member batch on a CPU device: a device's shard
of a larger batch runs as consecutive blocks of at most this many members (`run_in_blocks`:
`jax.lax.map` over `jax.vmap`), compiled with `tippejax._engine.cpu.CPU_COMPILER_OPTIONS`.
Blocks of about a hundred members keep a block's state in the cores' caches, and a block's
loop ends with its own slowest member rather than the shard's (`cpu_block`)."""

SHARED_BLOCK = 512
"""Most members per CPU device in one solve with shared steps: a larger batch is split into
buckets by spin (`simulate_batch`'s `buckets`), each its own shared solve, since the state of a
shared solve and its stages outgrow the cores' caches with the batch."""

SHARED_BLOCK_ACCELERATOR = 2**20
"""Most members per GPU (or other accelerator) device in one shared solve. A GPU runs each
step's arithmetic across the members in parallel and pays a fixed cost per kernel launch, so
the widest state is the cheapest per member; the bound only keeps one solve's stages (13
copies of the batched state for Dopri8) to a few GB in float64."""


def cpu_block(shard_size: int) -> int | None:
    """The block size of a CPU device's shard of `shard_size` members: equal blocks of at most
    `PER_MEMBER_BLOCK` (the shard is padded to a multiple of it), or None for one block."""
    if shard_size <= PER_MEMBER_BLOCK:
        return None
    blocks = -(-shard_size // PER_MEMBER_BLOCK)
    return -(-shard_size // blocks)


def shared_block(platform: str) -> int:
    """`SHARED_BLOCK` on CPU devices, `SHARED_BLOCK_ACCELERATOR` on the others."""
    return SHARED_BLOCK if platform == "cpu" else SHARED_BLOCK_ACCELERATOR


def batch_sharding(size: int):
    """A `NamedSharding` that splits an axis of length `size` over the most of `jax.devices()`
    that divide it, or None where that is one device (a batched fit's records: padding them
    would cost a fit of a copy per pad)."""
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
    members are done."""

    def spec(x, split):
        return PartitionSpec(axis) if split and getattr(x, "ndim", 0) >= 1 else PartitionSpec()

    specs = tuple(
        jax.tree_util.tree_map(lambda x, split=split: spec(x, split), arg)
        for arg, split in zip(args, members, strict=True)
    )
    # check_vma off: diffrax's loop carries arrays made inside it next to the shard's own;
    # with the check on their "varying" types differ and the while loop is refused.
    return jax.shard_map(
        fn, mesh=mesh, in_specs=specs, out_specs=PartitionSpec(axis), check_vma=False
    )(*args)


def run_in_blocks(fn, block, args):
    """`fn(*args)` for a batch whose members are independent, run as consecutive blocks of
    `block` members (`jax.lax.map` over the blocks): as in `shard_over`, the array leaves of
    `args` with at least one axis hold the members along their first (a multiple of `block`
    long) and are split into the blocks; the others go whole to every block. The outputs are
    the blocks' put back together along their first axis. `block` None, or no larger than the
    batch, calls `fn(*args)` once. On a CPU device a vmapped solve runs faster in blocks of
    about a hundred members (`PER_MEMBER_BLOCK`)."""
    split, whole = eqx.partition(args, lambda x: jnp.ndim(x) >= 1)
    leaves = jax.tree_util.tree_leaves(split)
    n = leaves[0].shape[0] if leaves else 0
    if block is None or n <= block:
        return fn(*args)
    blocks = n // block
    parts = jax.tree_util.tree_map(lambda x: x.reshape(blocks, block, *x.shape[1:]), split)
    out = jax.lax.map(lambda part: fn(*eqx.combine(part, whole)), parts)
    return jax.tree_util.tree_map(lambda x: x.reshape(n, *x.shape[2:]), out)


def gather(x) -> np.ndarray:
    """A (possibly multi-process) sharded array as a numpy array on every process."""
    if jax.process_count() > 1 and not x.is_fully_addressable:
        return np.asarray(multihost_utils.process_allgather(x, tiled=True))
    return np.asarray(x)
