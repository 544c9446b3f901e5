"""Batches of simulations: sweeps of any launch quantity and any field of the top, sharded over
devices."""

from __future__ import annotations

import dataclasses
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import ArrayLike

from ._cache import cacheable
from ._devices import cpu_block, run_in_blocks, shard_over, shared_block
from ._engine.cpu import CpuProgram
from ._engine.shared import top_axes
from ._engine.solver_choice import default_solver, is_traced
from ._models.levels import LEVELS
from ._plausibility import warn_if_implausible_spin
from ._simulate import simulate
from ._simulate.programs import trim_saves
from ._simulate.shared import SHARED_OPTIONS, run_shared, shared_run_options
from ._solution import Solution, drop_save_axis
from ._state import check_theta0, initial_state
from ._top import TippeTop

LAUNCH = ("theta0", "spin", "theta_dot", "phi_dot", "phi", "psi", "vx", "vy")
"""The launch quantities `simulate_batch` sweeps (the arguments of `initial_state`)."""

LAUNCH_INPUTS = {"theta0": "theta0", **{k: f"{k}0" for k in LAUNCH[1:]}}
"""The names of the launch quantities in `sol.inputs` and the exports: the value at $t_0$
(`spin0`, `theta_dot0`, ...), apart from the run's own series (`sol.spin`, ...)."""


def top_leaf_names(top: TippeTop):
    """`(names, leaves, treedef)` of a top's arrays: its own fields by name (`m`, ..., `g`), its
    friction law's fields by theirs (`mu`, `patch_radius`, ...), others by their path."""
    paths, treedef = jax.tree_util.tree_flatten_with_path(top)
    names = []
    for path, _ in paths:
        keys = [getattr(k, "name", str(k)) for k in path]
        names.append(keys[-1] if keys[0] == "friction" or len(keys) == 1 else ".".join(keys))
    return names, [leaf for _, leaf in paths], treedef


def batch_inputs(launch: dict, top_fields: dict, shape) -> dict:
    """Every member's inputs, each with the batch's `shape` (numpy views, no copies): the
    launch quantities (`LAUNCH_INPUTS` names), the top's fields and its ratios `A_over_C`,
    `eps_over_R`."""
    out = {LAUNCH_INPUTS[k]: np.broadcast_to(v, shape) for k, v in launch.items()}
    out.update({k: np.broadcast_to(v, shape) for k, v in top_fields.items()})
    out["A_over_C"] = np.broadcast_to(top_fields["A"] / top_fields["C"], shape)
    out["eps_over_R"] = np.broadcast_to(top_fields["eps"] / top_fields["R"], shape)
    return out


def _batch_run_impl(top, launches, t1, kwargs, mesh=None, block=None):
    # Module-level and jitted once per (shapes, static options): repeated calls reuse it.
    # `top` has either scalar fields (one top) or fields of the launches' length (a sweep).
    def members(top, launches, t1):
        def one(top, launch):
            theta0, spin, theta_dot, phi_dot, phi, psi, vx, vy = launch
            y0 = initial_state(
                top,
                theta0,
                spin,
                theta_dot=theta_dot,
                phi_dot=phi_dot,
                phi=phi,
                psi=psi,
                vx=vx,
                vy=vy,
            )
            return simulate(top, y0, t1, throw=False, **kwargs)

        return jax.vmap(one, in_axes=(top_axes(top), 0))(top, launches)

    def local(top, launches, t1):
        # simulate_batch pads each shard to a multiple of `block`.
        return run_in_blocks(members, block, (top, launches, t1))

    if mesh is None:
        return local(top, launches, t1)
    return shard_over(local, mesh, "batch", (top, launches, t1), (True, True, False))


_batch_run = eqx.filter_jit(_batch_run_impl)
_batch_run_cpu = CpuProgram(_batch_run_impl)


def _launch_state(top, launch):
    theta0, spin, theta_dot, phi_dot, phi, psi, vx, vy = launch
    y0 = initial_state(
        top, theta0, spin, theta_dot=theta_dot, phi_dot=phi_dot, phi=phi, psi=psi, vx=vx, vy=vy
    )
    dtype = jnp.result_type(top.m)
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), y0)


@eqx.filter_jit
def _shared_batch_run(top, launches, arrays, static, mesh):
    # The batch with shared steps (`run_shared`). With a `mesh` every device runs its own
    # shared-step solve on its shard (`jax.shard_map`): steps are shared within a shard only,
    # and the devices never wait for each other inside the loop.
    def local(top, launches, arrays):
        y0s = jax.vmap(_launch_state, in_axes=(top_axes(top), 0))(top, launches)
        return run_shared(top, y0s, **arrays, **static)

    if mesh is None:
        return local(top, launches, arrays)
    return shard_over(local, mesh, "batch", (top, launches, arrays), (True, True, False))


def _concrete_array(name, value):
    if any(is_traced(x) for x in jax.tree_util.tree_leaves(value)):
        raise ValueError(
            f"simulate_batch: {name} is traced (simulate_batch is called outside jax.jit/vmap "
            "with concrete values); inside a transformation use "
            "jax.vmap(lambda ...: tj.simulate(top, tj.initial_state(...), t1))."
        )
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(
            f"simulate_batch: {name} must be a number or an array of numbers, got "
            f"{type(value).__name__}."
        ) from None
    if array.size == 0:
        raise ValueError(f"simulate_batch: {name} is empty.")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"simulate_batch: {name} must be finite (got NaN or inf).")
    return array


def simulate_batch(
    top: TippeTop,
    theta0: ArrayLike,
    spin: ArrayLike,
    t1: float,
    *,
    theta_dot: ArrayLike = 0.0,
    phi_dot: ArrayLike = 0.0,
    phi: ArrayLike = 0.0,
    psi: ArrayLike = 0.0,
    vx: ArrayLike = 0.0,
    vy: ArrayLike = 0.0,
    grid: tuple[str, ...] = ("theta0", "spin"),
    shard: bool = True,
    buckets: int = 1,
    steps: Literal["per_member", "shared"] = "per_member",
    **kwargs,
) -> Solution:
    r"""Simulate a sweep of launches and tops in one compiled batch.

    Each member is `simulate(top_k, initial_state(top_k, theta0_k, spin_k, theta_dot=...,
    phi_dot=..., phi=..., psi=..., vx=..., vy=...), t1)`, where `top_k` is the top itself or
    one member of a batch of tops (`top.replace(mu=np.linspace(0.1, 1, 10))`, a `TippeTop` built
    from arrays). How the quantities combine:

    - The quantities named in `grid` (launch quantities, or `"top"` for a 1-d batch of tops)
      are the axes of a grid, in that order: each is 1-d (a scalar counts as length 1) and the
      result has one axis per name. The default `grid=("theta0", "spin")` is the grid of tilts
      x spins: `simulate_batch(top, theta0=[...], spin=[...], t1=...)` returns shape
      `(len(theta0), len(spin))`.
    - Every other quantity, and the top's fields unless `"top"` is in `grid`, broadcast
      against the grid's shape (numpy rules). With `grid=()` everything broadcasts:
      `simulate_batch(top.replace(mu=mus), 0.1, 100.0, t1=10.0, grid=())` has shape
      `mus.shape`.

    All members run in one compiled program (`jax.vmap`; one compilation per shape and
    options) with `throw=False`, so a failed member is flagged in `sol.result` (`sol.message()` reads it)
    without stopping the others. With `shard=True` and more than one device the batch is split
    over all devices with `jax.sharding` (padded to a multiple of the device count), each
    device running its own members' loops (`jax.shard_map`). On CPU devices each device's
    members run in blocks of at most `PER_MEMBER_BLOCK` (128), one after the other, and the
    batch's program is compiled with tippejax's CPU options (LLVM level 1, XLA's element-wise
    loop emitter; `tippejax._engine.cpu`, for this program only), faster than `simulate` in
    one `vmap` with XLA's defaults (see the performance page). Results agree with a single
    run of each member to about `rtol` (the program's rounding differs).

    Under `vmap` every member takes as many solver steps as the slowest one. With
    `buckets > 1` the members are sorted by $|n|$ (their cost grows with spin x t1), split
    into `buckets` equal-size groups (padded with the last member), each run as its own batch
    through the same compiled function, and put back in order. This pays when the members run
    to `t1` with step counts spread by spin (2-4 buckets for a batch of spins spread over a
    decade); not when many stop early (contact loss). Results agree with `buckets=1` to about
    `rtol`.

    The default solver is `default_solver` of the stiffest top in the batch.

    With `steps="shared"` the members share their steps instead: the batch is ONE
    `diffrax.diffeqsolve` whose state is every member's state, with the members' vector field
    vmapped and the step-size controller's error norm the largest of the members' norms
    (`run_segment_shared`). Under `jax.vmap` each member has its own step size and the while
    loop runs batched with selects at every step, which costs several times one loop over
    the batch. Events are watched and located per member, a member whose run stops (contact
    loss with `on_contact_loss="stop"`, the $R_n$ singularity) is frozen there while the
    others go on, and every member's `Solution` fields agree with `steps="per_member"` to
    about `rtol` (at `rtol=1e-8`: inversion times to about 1e-6 relative; contact-loss
    times, where $R_n$ grazes zero before it crosses, to about 1e-5); `num_steps` and
    `num_rejected_steps` are the shared solve's. Only for the models `"full"` and `"so3"`
    (one segment each) and explicit solvers, with the options `SHARED_OPTIONS` of
    `simulate`; not differentiable. With `shard=True` and several devices every device runs
    its own shared solve on its shard, and a batch is split into buckets (by spin) of at
    most `SHARED_BLOCK` (512) members per CPU device, whatever `buckets` says (each solve
    then fits the cores' caches); on a GPU, up to `SHARED_BLOCK_ACCELERATOR` (2^20) members
    run in one solve. A batch whose members need very different steps (a wide range of
    spins) is best bucketed (`buckets`), since every member takes the steps of
    the one that needs the shortest. For the same reason a member the solver cannot get past
    (one that would run into `max_steps` on its own, such as some runs continued past a
    contact loss) holds up its shared solve: every member still running there ends with
    `max_steps_reached` at that time; run such batches with `steps="per_member"`.

    **Arguments:**

    - `top`: a `TippeTop`, one or a batch.
    - `theta0` (rad, in $[0, \pi]$), `spin` (rad/s), `theta_dot`, `phi_dot` (rad/s), `phi`,
      `psi` (rad), `vx`, `vy` (m/s): the launch, as in `initial_state`; numbers or arrays.
    - `t1`: final time (s), common to all members.
    - `grid`: names forming the axes of a grid (see above).
    - `shard`, `buckets`: see above.
    - `steps`: `"per_member"` (default: `jax.vmap` of `simulate`) or `"shared"` (see above).
    - other keyword arguments go to `simulate` (`model`, `saveat`, `summary`, `rtol`, `atol`,
      `solver`, ...).

    **Returns:** a `Solution` whose fields have the batch's shape as leading axes.
    """
    if "throw" in kwargs and kwargs["throw"]:
        raise ValueError("simulate_batch always runs with throw=False; inspect sol.result.")
    kwargs.pop("throw", None)
    if steps not in ("per_member", "shared"):
        raise ValueError(f"simulate_batch: steps must be 'per_member' or 'shared', got {steps!r}.")
    if steps == "shared":
        bad = sorted(set(kwargs) - set(SHARED_OPTIONS))
        if bad:
            raise ValueError(
                f"simulate_batch(steps='shared') takes the options {SHARED_OPTIONS} of "
                f"simulate, not {', '.join(bad)}; use steps='per_member' for them."
            )
    for bad in ("y0", "theta"):
        if bad in kwargs:
            raise ValueError(
                f"simulate_batch takes the launch as quantities ({', '.join(LAUNCH)}), not {bad}=."
            )
    if isinstance(buckets, bool) or not isinstance(buckets, (int, np.integer)) or buckets < 1:
        raise ValueError(f"simulate_batch: buckets must be an integer >= 1, got {buckets!r}.")
    if not isinstance(top, TippeTop):
        raise TypeError(
            f"simulate_batch: top must be a tippejax.TippeTop, got {type(top).__name__}."
        )
    values = dict(
        theta0=theta0,
        spin=spin,
        theta_dot=theta_dot,
        phi_dot=phi_dot,
        phi=phi,
        psi=psi,
        vx=vx,
        vy=vy,
    )
    launch = {name: _concrete_array(name, v) for name, v in values.items()}
    check_theta0("simulate_batch: theta0", launch["theta0"])
    top_names, top_leaves, top_tree = top_leaf_names(top)
    top_fields = {k: _concrete_array(f"top.{k}", v) for k, v in zip(top_names, top_leaves)}
    top_shape = top.batch_shape

    if isinstance(grid, str):
        grid = (grid,)
    grid = tuple(grid)
    allowed = (*LAUNCH, "top")
    for name in grid:
        if name not in allowed:
            raise ValueError(f"simulate_batch: grid names must be among {allowed}, got {name!r}.")
    if len(set(grid)) != len(grid):
        raise ValueError(f"simulate_batch: grid names a quantity twice: {grid}.")
    axes = len(grid)
    grid_shape = []
    for i, name in enumerate(grid):
        if name == "top":
            if len(top_shape) > 1:
                raise ValueError(
                    "simulate_batch: a top on a grid axis must be a 1-d batch of tops, got "
                    f"batch shape {top_shape}."
                )
            size = top_shape[0] if top_shape else 1
            for k in top_fields:
                top_fields[k] = np.broadcast_to(top_fields[k], (size,))
        else:
            x = launch[name]
            if x.ndim > 1:
                raise ValueError(
                    f"simulate_batch: {name} is a grid axis and must be 1-d, got shape {x.shape}."
                )
            x = np.atleast_1d(x)
            size = x.size
        place = [1] * axes
        place[i] = size
        if name == "top":
            top_fields = {k: v.reshape(place) for k, v in top_fields.items()}
            top_shape = tuple(place)
        else:
            launch[name] = x.reshape(place)
        grid_shape.append(size)
    try:
        shape = np.broadcast_shapes(
            tuple(grid_shape), top_shape, *(v.shape for v in launch.values())
        )
    except ValueError:
        got = ", ".join(f"{k}: {v.shape}" for k, v in launch.items() if v.shape)
        raise ValueError(
            f"simulate_batch: the shapes do not broadcast (grid {tuple(grid_shape)} from "
            f"{grid}, top {top_shape}{', ' + got if got else ''})."
        ) from None
    size = int(np.prod(shape))
    flat = {k: np.broadcast_to(v, shape).ravel() for k, v in launch.items()}
    batched_top = top_shape != ()
    if batched_top:
        flat_top = {k: np.broadcast_to(v, shape).ravel() for k, v in top_fields.items()}
    warn_if_implausible_spin(
        *(np.broadcast_to(top_fields[k], shape) for k in ("m", "R", "C", "g")),
        np.broadcast_to(launch["spin"], shape),
    )
    inputs = batch_inputs(launch, top_fields, shape)

    if steps == "shared":
        arrays, static, n_save = shared_run_options(top, t1, **kwargs)
    elif kwargs.get("solver") is None:
        level = LEVELS.get(kwargs.get("model", "full"))
        kwargs["solver"] = default_solver(top, slow_flow=level is not None and level.slow_flow)
    dtype = jnp.result_type(top.m)
    devices = jax.devices()
    n_dev = len(devices) if shard else 1
    if steps == "shared":
        # At most shared_block(...) members per device in one shared solve (see SHARED_BLOCK).
        block = shared_block(devices[0].platform)
        buckets = max(int(buckets), -(-size // (block * n_dev)))
    buckets = min(int(buckets), size)
    # Member order: by |spin| when bucketing, else the batch's. Each bucket holds `per`
    # members, a multiple of the device count; the tail is padded with the last member.
    order = np.argsort(np.abs(flat["spin"]), kind="stable") if buckets > 1 else np.arange(size)
    per = -(-size // buckets)
    per = -(-per // n_dev) * n_dev
    block = None
    cpu = devices[0].platform == "cpu"
    if steps == "per_member" and cpu:
        # Each device's shard in blocks of at most PER_MEMBER_BLOCK members, equal in size.
        block = cpu_block(per // n_dev)
        if block is not None:
            per = -(-per // (block * n_dev)) * block * n_dev
    order = np.concatenate([order, np.repeat(order[-1:], per * buckets - size)])
    sharding = mesh = None
    if n_dev > 1:
        mesh = Mesh(np.array(devices), ("batch",))
        sharding = NamedSharding(mesh, PartitionSpec("batch"))

    def put(x):
        x = jnp.asarray(x, dtype)
        return x if sharding is None else jax.device_put(x, sharding)

    t1 = jnp.asarray(t1, dtype)
    parts = []
    for b in range(buckets):
        idx = order[b * per : (b + 1) * per]
        launches = tuple(put(flat[k][idx]) for k in LAUNCH)
        if batched_top:
            member_tops = jax.tree_util.tree_unflatten(
                top_tree, [put(flat_top[k][idx]) for k in top_names]
            )
        else:
            member_tops = top
        with cacheable():  # every input was checked above, in Python
            if steps == "shared":
                parts.append(_shared_batch_run(member_tops, launches, arrays, static, mesh))
            else:
                run = _batch_run_cpu if cpu else _batch_run
                parts.append(run(member_tops, launches, t1, kwargs, mesh, block))
    if mesh is not None:
        # Outputs sharded over several CPU devices come to the host before they are joined,
        # cut and reordered: `jnp` on them compiles programs with cross-device collectives
        # (all-gather), and XLA:CPU aborted the process in one of them ("Termination timeout
        # for `all gather RendezvousKey...`: only 1 of them arrived") after 1-3 minutes of
        # repeated 2-device batches with buckets, whatever the batch program's options.
        parts = [
            jax.tree_util.tree_map(lambda x: np.asarray(x) if isinstance(x, jax.Array) else x, p)
            for p in parts
        ]
    arrays_types = (jax.Array, np.ndarray)
    if buckets == 1:
        sol = parts[0]
        back = None
    else:
        sol = jax.tree_util.tree_map(
            lambda *xs: (
                np.concatenate(xs)
                if isinstance(xs[0], np.ndarray)
                else jnp.concatenate(xs)
                if isinstance(xs[0], jax.Array)
                else xs[0]
            ),
            *parts,
        )
        back = np.empty(size, dtype=int)
        back[order[:size]] = np.arange(size)

    def unflatten(x):
        if not isinstance(x, arrays_types):
            return x
        x = x[:size] if back is None else x[back]
        x = x.reshape(shape + x.shape[1:])
        return jax.device_put(x) if isinstance(x, np.ndarray) else x

    if steps == "shared":
        sol = Solution(model=static["level"].name, **trim_saves(dict(sol), n_save, axis=1))
    sol = jax.tree_util.tree_map(unflatten, sol)
    if kwargs.get("summary", False):
        sol = drop_save_axis(sol, len(shape))
    return dataclasses.replace(sol, inputs=inputs, grid=grid)
