"""tippejax against its peers on one scene: scipy, compiled numba, a plain diffrax script.

Scene (issue 18): the standard top `tj.default_top()`, theta0 = 0.1, spin 150 rad/s for a single
top and spins linspace(140, 160, B) for a batch, 20 s, SO(3) equations (translation dropped in
the friction law), in summary mode (final state only) and with 6 save times
[0.5, 1, 2, 5, 10, 20] s.

Peers, each with the same SO(3) equations written once in its own language:

- scipy `solve_ivp(method="DOP853")` on the numpy vector field of `_common.VectorModel`;
- CyRK's `nbsolve_ivp` (DOP853 compiled by numba) on a numba vector field (`so3_rhs` below);
  a batch runs it in a `numba.prange` loop over the tops, on every core;
- a plain diffrax script (`plain_solve`, ~25 lines): Dopri8, PIDController, `jax.vmap`, no events;
  in batches also the same script in `simulate_batch`'s CPU layout (blocks of at most 128
  members under `lax.map`, compiled with tippejax's CPU options: `_plain_blocks`), the
  strongest JAX script we know for this batch;
- tippejax at each level (so3, full, routhian, gyroscopic), `tj.simulate` in `jax.vmap`, events
  on (inversion observed, contact loss and the R_n singularity terminating), default solver;
  and `tj.simulate_batch` (so3, full), the public batch function.

Error: of the final state at t1 = 20 s, max(|a - a_ref|, |omega - omega_ref| / |omega_ref|),
against a tight reference of the same equations (CyRK DOP853 at rtol 1e-13 for the SO(3)
equations, checked against the plain diffrax script at 1e-13; each tippejax level against
itself at rtol 1e-12, since the full and gyroscopic levels have other equations). Every peer
runs a ladder of rtols (atol = rtol * 1e-2) on the single top; times and steps are interpolated
(log-log) at a common error, the plain script's error at rtol 1e-8, and each peer's batch runs
at the rtol that gives it that error (interpolated on its ladder). "Per step" is wall time over
the sum of the members' own steps (a vmapped batch runs in lock-step, so its lanes also idle).

Batches run in this process on one JAX device, then in a subprocess with two host devices
(`--xla_force_host_platform_device_count=2`), each device running the loop of its half of the
batch (`jax.shard_map`, as `tj.simulate_batch` does; jit on sharded inputs would run one loop
whose condition is reduced across the devices at every step). The row `tippejax so3,
simulate_batch` is the batch as a user runs it, through the public function.
numba's prange batch uses all cores (`numba.get_num_threads()`), and again with one thread.

    python benchmarks/peers.py            # ~10 min on 2 cores
    python benchmarks/peers.py --quick    # smaller ladder and batches
    python benchmarks/peers.py --big      # also batches of 1e4

Writes its section of benchmarks/RESULTS.md and benchmarks/peers.png.
"""

from __future__ import annotations

import functools
import json
import os
import pathlib
import subprocess
import sys
import time

_WORKER = "--worker" in sys.argv
if not _WORKER:
    # This process measures one device; the 2-device numbers come from a subprocess.
    os.environ.setdefault("TIPPEJAX_HOST_DEVICES", "1")

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

from jax.sharding import Mesh, NamedSharding, PartitionSpec  # noqa: E402

import tippejax as tj  # noqa: E402
from tippejax._devices import shard_over  # noqa: E402
from tippejax._engine.cpu import CPU_COMPILER_OPTIONS  # noqa: E402

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _common import (  # noqa: E402
    VectorModel,
    interleaved,
    interp_loglog,
    machine_line,
    peak_flops,
    standard_params,
    table,
    verdict,
    write_section,
)

QUICK = "--quick" in sys.argv
BIG = "--big" in sys.argv
T1 = 20.0
THETA0 = 0.1
SPIN = 150.0
TS = np.array([0.5, 1.0, 2.0, 5.0, 10.0, 20.0])
RTOLS = (1e-6, 1e-8, 1e-10) if QUICK else (1e-6, 1e-7, 1e-8, 1e-9, 1e-10)
SCIPY_RTOLS = (1e-6, 1e-8) if QUICK else (1e-6, 1e-8, 1e-10)
TARGET_RTOL = 1e-8  # the common error is the plain script's error at this rtol
BATCH = 200 if QUICK else 1000
REPEATS = 1 if QUICK else 2
LEVEL_NAMES = ("so3", "full", "routhian", "gyroscopic")
# The gyroscopic level has other equations (no nutation): its error against the SO(3)
# reference is a model error, so it runs at the default rtol, outside the equal-error rule.
GYRO = "tippejax gyroscopic"
P = standard_params()
PARAMS = np.array([P["m"], P["R"], P["eps"], P["A"], P["C"], P["g"], P["mu"]])
TOP = tj.default_top()


# ----------------------------------------------------------------------------------------------
# The plain diffrax script: the SO(3) equations, Dopri8, PIDController, vmap, no events
# ----------------------------------------------------------------------------------------------


def so3_field(t, y, p):
    m, R, eps, A, C, g, mu = p
    a, w = y[:3], y[3:]
    q = eps * a - jnp.array([0.0, 0.0, R])
    vq = jnp.cross(w, q).at[2].set(0.0)  # slip velocity, no translation
    tau = jnp.cross(q, jnp.array([0.0, 0.0, 1.0]) - mu * vq)  # torque per unit R_n
    o0 = -(C - A) / A * jnp.dot(w, a) * jnp.cross(w, a)
    o1 = tau / A + (1 / C - 1 / A) * jnp.dot(a, tau) * a
    h0 = -eps * (jnp.cross(o0, a)[2] + jnp.cross(w, jnp.cross(w, a))[2])
    h1 = -eps * jnp.cross(o1, a)[2]
    rn = (g + h0) / (1 / m - h1)
    return jnp.concatenate([jnp.cross(w, a), o0 + rn * o1])


PI_CONTROLLER = dict(pcoeff=0.4, icoeff=0.3)
"""The plain script's stronger form: the PI step-size controller tippejax uses (the first of
diffrax's suggested coefficients for a PIDController), instead of diffrax's default I
controller; `benchmarks/step_control.py` measures the difference on random tops."""


def plain_solve(spin, rtol, atol, ts=None, controller=None, solver=None):
    a = jnp.array([0.0, -jnp.sin(THETA0), jnp.cos(THETA0)])
    saveat = diffrax.SaveAt(t1=True) if ts is None else diffrax.SaveAt(ts=ts)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(so3_field), diffrax.Dopri8() if solver is None else solver, 0.0, T1, None,
        jnp.concatenate([a, spin * a]), tuple(PARAMS), saveat=saveat, max_steps=100_000,
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol, **(controller or {})),
    )
    return sol.ys[-1], sol.stats["num_steps"]


def member_norm(x):
    """The largest member's RMS norm of a batched (N, 6) error."""
    return jnp.max(jnp.sqrt(jnp.mean(x**2, axis=1)))


def plain_shared_solve(spins, rtol, atol, solver=None):
    """The plain script with shared steps: ONE `diffeqsolve` whose state is the whole batch
    (N, 6), the vector field vmapped over the members and the controller's norm the largest
    member's RMS norm (every member's error controlled, all take the same steps). Returns the
    final states and the number of steps. `solver`: Dopri8 unless given."""
    axis = jnp.array([0.0, -jnp.sin(THETA0), jnp.cos(THETA0)])
    y0 = jnp.concatenate([jnp.broadcast_to(axis, (spins.shape[0], 3)),
                          spins[:, None] * axis], axis=1)
    field = jax.vmap(so3_field, in_axes=(None, 0, None))
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field), diffrax.Dopri8() if solver is None else solver, 0.0, T1, None, y0, tuple(PARAMS),
        saveat=diffrax.SaveAt(t1=True), max_steps=100_000,
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol, norm=member_norm))
    return sol.ys[-1], sol.stats["num_steps"]


_plain_vmap = jax.jit(jax.vmap(plain_solve, in_axes=(0, None, None, None)))

_plain_vmap_pi = jax.jit(jax.vmap(functools.partial(plain_solve, controller=PI_CONTROLLER),
                                  in_axes=(0, None, None, None)))


def plain_reference(spins, rtol=1e-12):
    """The final states (N, 6) of the plain script at `rtol` (atol rtol/100), member by member:
    the reference of a batch's errors (`state_error`)."""
    finals, _ = _plain_vmap(jnp.asarray(spins), jnp.asarray(rtol), jnp.asarray(rtol * 1e-2), None)
    return np.asarray(finals)


def batch_mesh(size):
    """A one-axis mesh over every device where a batch of `size` splits evenly over more than
    one, else None."""
    devices = jax.devices()
    if len(devices) > 1 and size % len(devices) == 0:
        return Mesh(np.array(devices), ("batch",))
    return None


@functools.cache
def _plain_sharded(n_devices, with_saves, pi=False):
    """The plain vmap script with each device running its own shard's loop (`jax.shard_map`,
    as `simulate_batch` does): the stronger script on several devices (jit on sharded inputs
    reduces the loop condition across the devices at every step: 1.40 against 1.20 ms per top
    on 2 devices, `shared_steps.py`)."""
    mesh = Mesh(np.array(jax.devices()[:n_devices]), ("batch",))
    whole = PartitionSpec()
    solve = functools.partial(plain_solve, controller=PI_CONTROLLER if pi else None)
    if with_saves:
        fn = jax.vmap(solve, in_axes=(0, None, None, None))
        specs = (PartitionSpec("batch"), whole, whole, whole)
    else:
        fn = jax.vmap(lambda s, r, a: solve(s, r, a), in_axes=(0, None, None))
        specs = (PartitionSpec("batch"), whole, whole)
    return jax.jit(jax.shard_map(fn, mesh=mesh, in_specs=specs,
                                 out_specs=PartitionSpec("batch"), check_vma=False))


def plain_batch(spins, rtol, atol, ts=None, pi=False):
    """The plain script over a batch of spins: `jax.vmap`; on several devices, each its shard.
    `pi`: with `PI_CONTROLLER`."""
    n = len(jax.devices())
    if n > 1 and spins.shape[0] % n == 0:
        rtol, atol = jnp.asarray(rtol), jnp.asarray(atol)
        if ts is None:
            return _plain_sharded(n, False, pi)(spins, rtol, atol)
        return _plain_sharded(n, True, pi)(spins, rtol, atol, jnp.asarray(ts))
    return (_plain_vmap_pi if pi else _plain_vmap)(spins, rtol, atol, ts)
plain_single = jax.jit(plain_solve)
plain_single_pi = jax.jit(functools.partial(plain_solve, controller=PI_CONTROLLER))
PLAIN_PI = "plain diffrax, PI controller"
PLAIN_BLOCKS = "plain diffrax, blocks of 125, tippejax's CPU options"
BLOCK_OPTIONS = CPU_COMPILER_OPTIONS  # LLVM level 1, XLA:CPU's element-wise loop emitter


def _largest_divisor(n, most):
    return max(k for k in range(1, min(n, most) + 1) if n % k == 0)


@functools.cache
def _plain_blocks(n_devices):
    """The plain script given `simulate_batch`'s CPU layout (`tippejax._batch.PER_MEMBER_BLOCK`):
    each device's members in blocks of at most 128 (`lax.map` over `vmap`), compiled with
    tippejax's CPU options (`tippejax._engine.cpu.CPU_COMPILER_OPTIONS`: LLVM level 1, XLA:CPU's
    element-wise loop emitter): the strongest form of the script a user could write."""
    def local(spins, rtol, atol):
        n = spins.shape[0]
        block = _largest_divisor(n, 128)
        out = jax.lax.map(lambda s: jax.vmap(plain_solve, in_axes=(0, None, None))(s, rtol, atol),
                          spins.reshape(n // block, block))
        return jax.tree_util.tree_map(lambda x: x.reshape(n, *x.shape[2:]), out)

    if n_devices == 1:
        return jax.jit(local, compiler_options=BLOCK_OPTIONS)
    mesh = Mesh(np.array(jax.devices()[:n_devices]), ("batch",))
    whole = PartitionSpec()
    return jax.jit(jax.shard_map(local, mesh=mesh, in_specs=(PartitionSpec("batch"), whole, whole),
                                 out_specs=PartitionSpec("batch"), check_vma=False),
                   compiler_options=BLOCK_OPTIONS)


def plain_blocks(spins, rtol, atol):
    n = len(jax.devices())
    n = n if n > 1 and spins.shape[0] % n == 0 else 1
    return _plain_blocks(n)(spins, jnp.asarray(rtol), jnp.asarray(atol))


# ----------------------------------------------------------------------------------------------
# tippejax
# ----------------------------------------------------------------------------------------------


@eqx.filter_jit
def _tj_batch(spins, rtol, atol, ts, level, body, mesh):
    def local(spins, rtol, atol, ts):
        def one(spin):
            y0 = tj.initial_state(TOP, THETA0, spin)
            kw = dict(summary=True) if ts is None else dict(saveat=ts)
            sol = tj.simulate(TOP, y0, T1, model=level, rtol=rtol, atol=atol, throw=False,
                              body=body, **kw)
            final = jnp.concatenate([sol.states.axis[-1], sol.states.omega[-1]])
            return final, sol.num_steps
        return jax.vmap(one)(spins)

    if mesh is None:
        return local(spins, rtol, atol, ts)
    return shard_over(local, mesh, "batch", (spins, rtol, atol, ts), (True, False, False, False))


def tj_batch(spins, rtol, atol, ts, level, body=None):
    """`tj.simulate` in `jax.vmap` over the spins; on several devices each runs its own shard's
    loop (`jax.shard_map`), as `tj.simulate_batch` does and as the plain script does."""
    return _tj_batch(spins, rtol, atol, ts, level, body, batch_mesh(spins.shape[0]))


@eqx.filter_jit
def tj_single(spin, rtol, atol, level):
    """One top, not vmapped (as a user runs one): the final state and the steps."""
    y0 = tj.initial_state(TOP, THETA0, spin)
    sol = tj.simulate(TOP, y0, T1, model=level, rtol=rtol, atol=atol, throw=False, summary=True)
    return jnp.concatenate([sol.states.axis[-1], sol.states.omega[-1]]), sol.num_steps


SIMULATE_BATCH = "tippejax so3, simulate_batch"
SIMULATE_BATCH_FULL = "tippejax full, simulate_batch"


def tj_simulate_batch(spins, rtol, ts=None, level="so3"):
    """The batch as a user runs it: `tj.simulate_batch` (checks in Python, padding, sharding
    with `jax.shard_map` over every device, on CPU devices blocks of at most 128 members
    compiled with tippejax's CPU options, the whole `Solution` back)."""
    kw = dict(summary=True) if ts is None else dict(saveat=np.asarray(ts))
    sol = tj.simulate_batch(TOP, THETA0, np.asarray(spins), T1, grid=(), model=level,
                            rtol=float(rtol), atol=float(rtol) * 1e-2, **kw)
    final = jnp.concatenate([sol.states.axis[:, -1], sol.states.omega[:, -1]], axis=-1)
    return final, sol.num_steps


def single_runner(name, runner):
    """The single-top form of a batch runner: the JAX peers called on one top without `vmap`
    (a batch of one runs the same program vmapped, which XLA:CPU executes differently), with
    the outputs given a leading axis of one."""
    if name in ("plain diffrax", PLAIN_PI):
        single = plain_single if name == "plain diffrax" else plain_single_pi

        def run(spin, rtol):
            final, steps = single(jnp.asarray(spin[0]), rtol, rtol * 1e-2)
            return final[None], steps[None]
        return run
    if name.startswith("tippejax"):
        level = name.split()[-1]

        def run(spin, rtol):
            final, steps = tj_single(jnp.asarray(spin[0]), jnp.asarray(rtol),
                                     jnp.asarray(rtol * 1e-2), level)
            return final[None], steps[None]
        return run
    return runner


# ----------------------------------------------------------------------------------------------
# numba: the same vector field, compiled, DOP853 from CyRK
# ----------------------------------------------------------------------------------------------


NUMBA_THREADS = None
"""Threads of numba's prange loop (None: every core, `numba.config.NUMBA_NUM_THREADS`)."""


def numba_parts():
    import numba
    from CyRK import nbsolve_ivp

    @numba.njit
    def so3_rhs(t, y, p):
        m, R, eps, A, C, g, mu = p[0], p[1], p[2], p[3], p[4], p[5], p[6]
        ax, ay, az, wx, wy, wz = y[0], y[1], y[2], y[3], y[4], y[5]
        n = wx * ax + wy * ay + wz * az
        dx, dy, dz = wy * az - wz * ay, wz * ax - wx * az, wx * ay - wy * ax
        qx, qy, qz = eps * ax, eps * ay, eps * az - R
        vqx, vqy = wy * qz - wz * qy, wz * qx - wx * qz
        fx, fy = -mu * vqx, -mu * vqy
        tx, ty, tz = qy - qz * fy, qz * fx - qx, qx * fy - qy * fx
        k0 = -(C - A) / A * n
        o0x, o0y, o0z = k0 * dx, k0 * dy, k0 * dz
        at = (1.0 / C - 1.0 / A) * (ax * tx + ay * ty + az * tz)
        o1x, o1y, o1z = tx / A + at * ax, ty / A + at * ay, tz / A + at * az
        h0 = -eps * ((o0x * ay - o0y * ax) + (wx * dy - wy * dx))
        h1 = -eps * (o1x * ay - o1y * ax)
        rn = (g + h0) / (1.0 / m - h1)
        out = np.empty(6)
        out[0], out[1], out[2] = dx, dy, dz
        out[3], out[4], out[5] = o0x + rn * o1x, o0y + rn * o1y, o0z + rn * o1z
        return out

    @numba.njit(parallel=True)
    def batch(spins, theta0, t1, rtol, atol, p, ts):
        n_tops = spins.shape[0]
        finals = np.empty((n_tops, 6))
        steps = np.empty(n_tops, np.int64)
        for i in numba.prange(n_tops):
            y0 = np.empty(6)
            y0[0], y0[1], y0[2] = 0.0, -np.sin(theta0), np.cos(theta0)
            y0[3:] = spins[i] * y0[:3]
            res = nbsolve_ivp(so3_rhs, (0.0, t1), y0, args=(p,), rtol=rtol, atol=atol,
                              rk_method=2, t_eval=ts, warnings=False)
            finals[i] = res.y[:, -1]
            steps[i] = res.size - 1
        return finals, steps

    empty = np.empty(0)

    def run(spins, rtol, atol, ts=None):
        """(finals, steps); with `ts`, steps are unknown (nbsolve_ivp then reports ts)."""
        # The thread count is set before every call: a prange loop that had run between JAX's
        # calls without it ran 1.3-1.5 ms per top instead of 0.89 (numba_goal.py, 2026-11-28).
        numba.set_num_threads(NUMBA_THREADS or numba.config.NUMBA_NUM_THREADS)
        finals, steps = batch(np.asarray(spins, float), THETA0, T1, rtol, atol, PARAMS,
                              empty if ts is None else np.asarray(ts, float))
        return finals, (steps if ts is None else None)

    return run, numba


# ----------------------------------------------------------------------------------------------
# Measurements
# ----------------------------------------------------------------------------------------------


def state_error(final, ref):
    final, ref = np.asarray(final, float), np.asarray(ref, float)
    return max(np.max(np.abs(final[..., :3] - ref[:3])),
               np.max(np.abs(final[..., 3:] - ref[3:])) / np.linalg.norm(ref[3:]))


def peer_runners():
    """{name: fn(spins, rtol, ts) -> (finals, steps)} for the batchable peers."""
    nb_run, _ = numba_parts()
    runners = {
        "numba DOP853 (CyRK)": lambda s, r, ts=None: nb_run(s, r, r * 1e-2, ts),
        "plain diffrax": lambda s, r, ts=None: plain_batch(
            s, r, r * 1e-2, None if ts is None else jnp.asarray(ts)),
        PLAIN_BLOCKS: lambda s, r, ts=None: plain_blocks(s, r, r * 1e-2),
        PLAIN_PI: lambda s, r, ts=None: plain_batch(
            s, r, r * 1e-2, None if ts is None else jnp.asarray(ts), pi=True),
    }
    for level in LEVEL_NAMES:
        runners[f"tippejax {level}"] = (
            lambda s, r, ts=None, level=level: tj_batch(
                s, jnp.asarray(r), jnp.asarray(r * 1e-2),
                None if ts is None else jnp.asarray(ts), level)[:2]
        )
    runners[SIMULATE_BATCH] = tj_simulate_batch
    runners[SIMULATE_BATCH_FULL] = functools.partial(tj_simulate_batch, level="full")
    # The body vector (psi): summary runs leave it out by default, saved runs carry it.
    for body in (True, False):
        runners[f"tippejax so3, body={body}"] = (
            lambda s, r, ts=None, body=body: tj_batch(
                s, jnp.asarray(r), jnp.asarray(r * 1e-2),
                None if ts is None else jnp.asarray(ts), "so3", body)[:2]
        )
    return runners


def engine_parts(rtol: float):
    """Runners for the profile: the SO(3) level's own field (axis and omega, no body vector) in
    a plain diffrax loop, without and with the event watch of the engine, as `tj.simulate`
    wires them (same conditions, same `pieces`)."""
    import dataclasses

    from tippejax._engine.segment import FlatField, Watch, ravel_state
    from tippejax._engine.watch import WatchedSolver
    from tippejax._models.levels import LEVELS

    level = dataclasses.replace(LEVELS["so3"], body=False)

    def make(watched):
        @jax.jit
        def run(spins):
            def one(spin):
                y = level.from_state(TOP, tj.initial_state(TOP, THETA0, spin))
                flat, unravel = ravel_state(y)
                field = FlatField(level, unravel)
                solver = diffrax.Dopri8()
                if watched:
                    watch = Watch(level, unravel, ("singular", "contact", "upright"))
                    solver = WatchedSolver(solver, watch, (2,), pieces=1, terminating=(0, 1))
                sol = diffrax.diffeqsolve(
                    diffrax.ODETerm(field), solver, 0.0, T1, None, flat, TOP,
                    saveat=diffrax.SaveAt(t1=True), max_steps=100_000,
                    stepsize_controller=diffrax.PIDController(
                        rtol=rtol, atol=rtol * 1e-2, norm=field.error_norm),
                )
                return sol.ys[0][-1], sol.stats["num_steps"]
            return jax.vmap(one)(spins)
        return run

    return {"tippejax SO(3) field, plain loop, no watch": make(False),
            "tippejax SO(3) field, plain loop, with the watch": make(True)}


def profile(rtols, spins):
    """Per top against the plain script, one run, interleaved: the field alone, the field with
    the watch, the whole engine; batch of `len(spins)` and one top."""
    parts = engine_parts(rtols["tippejax so3"])
    out = {}
    for label, sp in (("batch", spins_device(spins)), ("one top (vmap of 1)", jnp.asarray(spins[:1]))):
        fns = {"plain diffrax": lambda sp=sp: plain_batch(sp, TARGET_RTOL, TARGET_RTOL * 1e-2,
                                                          None)}
        for name, run in parts.items():
            fns[name] = lambda run=run, sp=sp: run(sp)
        r = rtols["tippejax so3"]
        fns["tj.simulate(model='so3', summary=True)"] = lambda sp=sp: tj_batch(
            sp, jnp.asarray(r), jnp.asarray(r * 1e-2), None, "so3")
        timed = interleaved(fns, repeats=5 if label == "batch" else 9)
        base = timed["plain diffrax"][0]
        out[label] = {k: dict(wall=t.wall / base.wall, cpu=t.cpu / base.cpu,
                              cpu_per_wall=t.cpu / t.wall) for k, (t, _) in timed.items()}
    r = rtols["tippejax so3"]
    one = jnp.asarray(spins[0])
    timed = interleaved({
        "plain diffrax": lambda: plain_single(one, TARGET_RTOL, TARGET_RTOL * 1e-2),
        "tj.simulate(model='so3', summary=True)": lambda: tj_single(
            one, jnp.asarray(r), jnp.asarray(r * 1e-2), "so3"),
    }, repeats=9)
    base = timed["plain diffrax"][0]
    out["one top (not vmapped)"] = {
        k: dict(wall=t.wall / base.wall, cpu=t.cpu / base.cpu, cpu_per_wall=t.cpu / t.wall)
        for k, (t, _) in timed.items()}
    return out


def flops_per_member_step() -> dict:
    """Flops of one step of the plain script per member, from XLA's cost analysis of its
    vmapped vector field (13 evaluations a Dopri8 step, first same as last) plus the
    Runge-Kutta combinations (2 flops per stage, earlier stage and component); the controller
    and the error norm are left out, so a lower bound. (XLA counts a while loop's body once,
    so the cost analysis of the whole solve is not the work done.)"""
    import math

    n = 1000
    y = jnp.stack([jnp.concatenate([jnp.array([0.0, -jnp.sin(THETA0), jnp.cos(THETA0)]),
                                    s * jnp.array([0.0, -jnp.sin(THETA0), jnp.cos(THETA0)])])
                   for s in np.linspace(140.0, 160.0, 4)])
    y = jnp.tile(y, (n // 4, 1))
    field = jax.vmap(lambda yy: so3_field(0.0, yy, tuple(PARAMS)))
    cost = jax.jit(field).lower(y).compile().cost_analysis()
    f_field = float(cost.get("flops", math.nan)) / n
    f_rk = 2 * sum(range(14)) * 6
    return dict(field=f_field, rk=f_rk, step=13 * f_field + f_rk)


def ladder(runners):
    """Single top, every peer, every rtol: time (median), steps, error; and compile times."""
    spin = np.array([SPIN])
    refs = {}
    nb_ref, _ = runners["numba DOP853 (CyRK)"](spin, 1e-13)
    refs["so3 equations"] = np.asarray(nb_ref[0])
    plain_ref, _ = plain_batch(jnp.asarray(spin), 1e-13, 1e-15, None)
    ref_check = state_error(plain_ref[0], refs["so3 equations"])
    compile_s = {}
    for level in LEVEL_NAMES:
        args = (jnp.asarray(SPIN), jnp.asarray(1e-12), jnp.asarray(1e-14), level)
        first = time.perf_counter()
        out = jax.block_until_ready(tj_single(*args))
        first = time.perf_counter() - first
        again = time.perf_counter()
        jax.block_until_ready(tj_single(*args))
        compile_s[f"tippejax {level}"] = first - (time.perf_counter() - again)
        refs[level] = np.asarray(out[0])
    refs["gyroscopic"] = refs["so3 equations"]
    rows = {}
    for name, batch_run in runners.items():
        if "body=" in name or name in (SIMULATE_BATCH, SIMULATE_BATCH_FULL, PLAIN_BLOCKS):
            continue  # batch rows only
        run = single_runner(name, batch_run)
        ref = refs[name.split()[-1]] if name.startswith("tippejax") else refs["so3 equations"]
        rows[name] = []
        for i, rtol in enumerate(RTOLS):
            jspin = spin if name.startswith("numba") else jnp.asarray(spin)
            timing, out = interleaved({"x": lambda: run(jspin, rtol)}, repeats=3)["x"]
            finals, steps = out
            rows[name].append(dict(rtol=rtol, wall=timing.wall, cpu=timing.cpu, steps=int(np.asarray(steps)[0]),
                                   error=state_error(np.asarray(finals)[0], ref)))
    model = VectorModel(P, "so3")
    rows["scipy DOP853"] = []
    for rtol in SCIPY_RTOLS:
        walls, cpus, out = [], [], None
        for _ in range(2 if rtol < 1e-9 else 3):
            t, c = time.perf_counter(), time.process_time()
            out = solve_scipy(model, rtol)
            walls.append(time.perf_counter() - t)
            cpus.append(time.process_time() - c)
        final, steps = out
        rows["scipy DOP853"].append(dict(rtol=rtol, wall=float(np.median(walls)), cpu=float(np.median(cpus)), steps=steps,
                                         error=state_error(final, refs["so3 equations"])))
    return rows, compile_s, ref_check


def solve_scipy(model, rtol):
    from scipy.integrate import solve_ivp

    sol = solve_ivp(model.rhs, (0.0, T1), model.y0(THETA0, SPIN), method="DOP853", rtol=rtol,
                    atol=rtol * 1e-2)
    return sol.y[:, -1], (sol.nfev - 1) // 12


def at_error(rows, target):
    errors = [r["error"] for r in rows]
    out = {}
    for key in ("wall", "cpu", "steps", "rtol"):
        value, extrapolated = interp_loglog(target, errors, [r[key] for r in rows])
        out[key] = value
        out["extrapolated"] = extrapolated
    return out


def batch_times(runners, rtols, spins, names, saves=(False,), repeats=REPEATS):
    """{(name, saves): dict(wall, steps_sum, steps_median, steps_max, error_median)}."""
    fns = {}
    for name in names:
        for with_saves in saves:
            ts = TS if with_saves else None
            sp = spins if name.startswith("numba") else spins_device(spins)
            fns[(name, with_saves)] = (lambda run=runners[name], r=rtols[name], sp=sp, ts=ts:
                                       run(sp, r, ts))
    timed = interleaved(fns, repeats=repeats)
    out = {}
    for key, (timing, (finals, steps)) in timed.items():
        row = dict(wall=timing.wall, cpu=timing.cpu, first=timing.first_wall)
        if steps is not None:
            steps = np.asarray(steps)
            row.update(steps_sum=int(steps.sum()), steps_median=float(np.median(steps)),
                       steps_max=int(steps.max()))
        out[key] = row
    return out


def single_top(runners, rtols):
    """tippejax so3, one top at its equal-error rtol (to compare 1 and 2 host devices)."""
    run, r = single_runner("tippejax so3", runners["tippejax so3"]), rtols["tippejax so3"]
    timing, _ = interleaved({"x": lambda: run(np.asarray([SPIN]), r)}, repeats=7)["x"]
    return dict(wall=timing.wall, cpu=timing.cpu)


def spins_device(spins):
    devices = jax.devices()
    x = jnp.asarray(spins)
    if len(devices) > 1 and len(spins) % len(devices) == 0:
        sharding = NamedSharding(Mesh(np.array(devices), ("batch",)), PartitionSpec("batch"))
        x = jax.device_put(x, sharding)
    return x


def worker():
    """Batch timings on this process's devices; prints one JSON line."""
    args = json.loads(sys.argv[sys.argv.index("--worker") + 1])
    runners = peer_runners()
    spins = np.linspace(140.0, 160.0, args["batch"])
    res = batch_times(runners, args["rtols"], spins, args["names"], saves=(False,),
                      repeats=args["repeats"])
    res[("tippejax so3 single top", False)] = single_top(runners, args["rtols"])
    print("JSON" + json.dumps({f"{k[0]}|{int(k[1])}": v for k, v in res.items()},
                              default=float))
    print("DEVICES", len(jax.devices()))


def in_subprocess(devices, payload):
    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}",
               TIPPEJAX_HOST_DEVICES=str(devices))
    out = subprocess.run([sys.executable, __file__, "--worker", json.dumps(payload)], env=env,
                         capture_output=True, text=True, check=False)
    line = [x for x in out.stdout.splitlines() if x.startswith("JSON")]
    if not line:
        raise RuntimeError(out.stderr[-3000:])
    ndev = [x for x in out.stdout.splitlines() if x.startswith("DEVICES")][0].split()[1]
    return {tuple(k.split("|")): v for k, v in json.loads(line[0][4:]).items()}, int(ndev)


def main():
    start = time.perf_counter()
    load0 = os.getloadavg()[0]
    runners = peer_runners()
    _, numba = numba_parts()
    cores = numba.get_num_threads()
    print(machine_line(), "| jax devices in this process:", len(jax.devices()))
    rows, compile_s, ref_check = ladder(runners)
    target = [r for r in rows["plain diffrax"] if r["rtol"] == TARGET_RTOL][0]["error"]
    eq = {name: at_error(r, target) for name, r in rows.items() if name != GYRO}
    gyro = [r for r in rows[GYRO] if r["rtol"] == TARGET_RTOL][0]
    eq[GYRO] = dict(gyro, extrapolated=False)
    rtols = {name: float(v["rtol"]) for name, v in eq.items()}
    rtols[SIMULATE_BATCH] = rtols["tippejax so3"]
    rtols[SIMULATE_BATCH_FULL] = rtols["tippejax full"]
    rtols[PLAIN_BLOCKS] = rtols["plain diffrax"]  # the same solve, run in blocks
    for body in (True, False):
        rtols[f"tippejax so3, body={body}"] = rtols["tippejax so3"]
    for name, v in eq.items():
        print(f"{name:24s} at error {target:.2e}: rtol {v['rtol']:.2e}, steps {v['steps']:.0f}, "
              f"wall {v['wall'] * 1e3:.2f} ms")
    print(f"ladder done {time.perf_counter() - start:.0f} s")

    spins = np.linspace(140.0, 160.0, BATCH)
    batch_names = [n for n in runners if n != "tippejax so3, body=False"]
    b1 = batch_times(runners, rtols, spins, batch_names, saves=(False,))
    b1.update(batch_times(runners, rtols, spins, ["plain diffrax", "tippejax so3",
                                                  "tippejax so3, body=False",
                                                  "numba DOP853 (CyRK)"], saves=(True,)))
    global NUMBA_THREADS
    NUMBA_THREADS = 1
    nb1 = batch_times(runners, rtols, spins, ["numba DOP853 (CyRK)"])
    NUMBA_THREADS = None
    single1 = single_top(runners, rtols)
    prof = profile(rtols, spins)
    flops = flops_per_member_step()
    print(f"batch 1 device done {time.perf_counter() - start:.0f} s")
    b2, ndev2 = in_subprocess(2, dict(batch=BATCH, rtols=rtols, repeats=REPEATS,
                                      names=["plain diffrax", PLAIN_PI, PLAIN_BLOCKS,
                                             "tippejax so3", SIMULATE_BATCH, "tippejax full",
                                             SIMULATE_BATCH_FULL]))
    print(f"batch 2 devices done {time.perf_counter() - start:.0f} s")
    big = {}
    if BIG:
        big_spins = np.linspace(140.0, 160.0, 10_000)
        big = batch_times(runners, rtols, big_spins,
                          ["numba DOP853 (CyRK)", "plain diffrax", PLAIN_BLOCKS, "tippejax so3",
                           SIMULATE_BATCH], repeats=1)
        big2, _ = in_subprocess(2, dict(batch=10_000, rtols=rtols, repeats=1,
                                        names=["plain diffrax", PLAIN_BLOCKS, "tippejax so3",
                                               SIMULATE_BATCH]))
        big.update({(k[0] + " (2 devices)", False): v for k, v in big2.items()
                    if "single top" not in k[0]})
    elapsed = time.perf_counter() - start
    single2 = b2.pop(("tippejax so3 single top", "0"))
    report(rows, eq, target, compile_s, ref_check, b1, nb1, b2, ndev2, big, cores, elapsed,
           load0, (single1, single2), prof, flops)
    chart(rows, target)


def report(rows, eq, target, compile_s, ref_check, b1, nb1, b2, ndev2, big, cores, elapsed,
           load0, singles, prof, flops):
    def ms(x):
        return f"{x * 1e3:.3g}"

    def us(x):
        return f"{x * 1e6:.3g}"

    plain = eq["plain diffrax"]
    lines = [
        "## peers.py: tippejax against scipy, compiled numba and a plain diffrax script",
        "",
        f"`python benchmarks/peers.py{' --quick' if QUICK else ''}{' --big' if BIG else ''}` "
        f"({elapsed:.0f} s; 1-minute load average {load0:.1f} at the start, "
        f"{os.getloadavg()[0]:.1f} at the end). {machine_line()}. Chart: `peers.png`.",
        "",
        "Scene: standard top, SO(3) equations, theta0 0.1, 20 s; single top spin 150 rad/s, "
        f"batches spins linspace(140, 160, {BATCH}). Error: final state, "
        "max(|a - a_ref|, |omega - omega_ref| / |omega_ref|), against a tight reference of "
        f"the same equations (CyRK at rtol 1e-13; the plain diffrax script at 1e-13 agrees to "
        f"{ref_check:.1e}; each tippejax level against itself at rtol 1e-12). "
        f"**Equal error** = {target:.2e}, the plain script's error at rtol {TARGET_RTOL:g} "
        "(atol = rtol/100 everywhere); each peer's times and steps are interpolated (log-log) "
        "on its rtol ladder at that error, and its batches run at the rtol that gives it (the "
        "'rtol' column). Wall times: medians after a compiling call, peers timed in interleaved "
        "rounds; process CPU time beside wall time, since the machine is shared and a loaded "
        "machine inflates wall time (CPU time of a peer that runs on 2 threads counts both). "
        "'per step' = time / sum of the members' own steps.",
        "",
        "### Single top at equal error",
        "",
    ]
    hdr = ["peer", "rtol at equal error", "steps", "vs plain steps", "ms per top",
           "vs plain", "CPU ms", "vs plain (CPU)", "us per step", "compile s"]
    body = []
    for name, v in eq.items():
        body.append([
            name, f"{v['rtol']:.2e}" + ("*" if v["extrapolated"] else ""), f"{v['steps']:.0f}",
            f"{v['steps'] / plain['steps']:.2f}", ms(v["wall"]),
            f"{v['wall'] / plain['wall']:.2f}", ms(v["cpu"]), f"{v['cpu'] / plain['cpu']:.2f}",
            us(v["wall"] / v["steps"]),
            f"{compile_s[name]:.1f}" if name in compile_s else "",
        ])
    lines += [table(hdr, body), "", "(* extrapolated beyond the ladder.) 'compile s': first "
              "call less a later one. The gyroscopic level "
              f"runs at rtol {TARGET_RTOL:g}: its error ({eq[GYRO]['error']:.1e}) is the model "
              "error of the slow flow against the SO(3) equations, not a solver error.", ""]

    def batch_table(res, n, title, devices):
        hdr = ["peer", "mode", "devices / threads", "steps median", "steps max",
               "ms per top", "vs plain", "CPU ms per top", "vs plain (CPU)",
               "us per member-step", "CPU us per member-step"]
        body = []
        base = {s: res.get(("plain diffrax", s)) for s in (False, True)}
        for (name, saves), v in res.items():
            per_top = v["wall"] / n
            ref = base.get(saves)
            body.append([
                name, "6 saves" if saves else "summary",
                (f"{cores} threads (prange)" if name.startswith("numba") else str(devices)),
                f"{v['steps_median']:.0f}" if "steps_median" in v else "",
                str(v.get("steps_max", "")), ms(per_top),
                f"{v['wall'] / ref['wall']:.2f}" if ref else "",
                ms(v["cpu"] / n), f"{v['cpu'] / ref['cpu']:.2f}" if ref else "",
                us(v["wall"] / v["steps_sum"]) if "steps_sum" in v else "",
                us(v["cpu"] / v["steps_sum"]) if "steps_sum" in v else "",
            ])
        return [f"### {title}", "", table(hdr, body), ""]

    lines += batch_table(b1, BATCH, f"Batch of {BATCH}, one JAX device", 1)
    nb = nb1[("numba DOP853 (CyRK)", False)]
    lines += [f"numba with 1 thread: {ms(nb['wall'] / BATCH)} ms per top, "
              f"{us(nb['wall'] / nb['steps_sum'])} us per step. numba's t_eval is linear "
              "interpolation between steps (CyRK's `nbsolve_ivp` has no dense output): its "
              "'6 saves' row is timing only.", ""]
    b2k = {(k[0], k[1] == "1"): v for k, v in b2.items()}
    lines += batch_table(b2k, BATCH, f"Batch of {BATCH}, {ndev2} host devices (sharded)", ndev2)
    one, two = singles
    lines += [f"One top (tippejax so3, 7 calls) with 1 host device: {ms(one['wall'])} ms "
              f"(CPU {ms(one['cpu'])}); with {ndev2} host devices: {ms(two['wall'])} ms (CPU "
              f"{ms(two['cpu'])}): ratio {two['wall'] / one['wall']:.2f} (CPU "
              f"{two['cpu'] / one['cpu']:.2f}). A single solve runs on the first device.", ""]
    if big:
        lines += batch_table(big, 10_000, "Batch of 1e4", "1 (or 2 where named)")

    # Targets
    so3, full = eq["tippejax so3"], eq["tippejax full"]

    def ratio(res, name, base="plain diffrax"):
        return res[(name, False)]["wall"] / res[(base, False)]["wall"]

    def cpu_ratio(res, name, base="plain diffrax"):
        return res[(name, False)]["cpu"] / res[(base, False)]["cpu"]

    s1, c1 = ratio(b1, SIMULATE_BATCH), cpu_ratio(b1, SIMULATE_BATCH)
    s2, c2 = ratio(b2k, SIMULATE_BATCH), cpu_ratio(b2k, SIMULATE_BATCH)
    v1, v2 = ratio(b1, "tippejax so3"), ratio(b2k, "tippejax so3")
    nb_all = b1[("numba DOP853 (CyRK)", False)]["wall"]
    best_tj = min(b1[(SIMULATE_BATCH, False)]["wall"], b2k[(SIMULATE_BATCH, False)]["wall"])
    full_b = ratio(b1, SIMULATE_BATCH_FULL, SIMULATE_BATCH)
    full_b2 = ratio(b2k, SIMULATE_BATCH_FULL, SIMULATE_BATCH)
    full_v = ratio(b1, "tippejax full", "tippejax so3")
    full_v2 = ratio(b2k, "tippejax full", "tippejax so3")
    trows = [
        ["steps at equal error <= 1.05x plain", f"{so3['steps'] / plain['steps']:.2f}x",
         verdict(so3["steps"] / plain["steps"] <= 1.05)],
        [f"batch {BATCH} summary <= 1.2x plain, 1 device (`tj.simulate_batch`)",
         f"{s1:.2f}x (CPU {c1:.2f}x)", verdict(s1 <= 1.2)],
        [f"batch {BATCH} summary <= 1.2x plain, {ndev2} devices (`tj.simulate_batch`)",
         f"{s2:.2f}x (CPU {c2:.2f}x)", verdict(s2 <= 1.2)],
        [f"(the same, `tj.simulate` in the user's own `jax.vmap`, 1 and {ndev2} devices)",
         f"{v1:.2f}x, {v2:.2f}x", ""],
        [f"(`tj.simulate_batch` against the plain script in blocks with the same CPU options, 1 and "
         f"{ndev2} devices)",
         f"{ratio(b1, SIMULATE_BATCH, PLAIN_BLOCKS):.2f}x, "
         f"{ratio(b2k, SIMULATE_BATCH, PLAIN_BLOCKS):.2f}x", ""],
        [f"goal: batch {BATCH} at or below numba prange ({cores} threads), per member",
         f"{best_tj / nb_all:.2f}x", verdict(best_tj <= nb_all)],
        [f"(batch {BATCH} summary against the plain script with tippejax's PI controller, "
         f"1 and {ndev2} devices)",
         f"{ratio(b1, SIMULATE_BATCH, PLAIN_PI):.2f}x, "
         f"{ratio(b2k, SIMULATE_BATCH, PLAIN_PI):.2f}x", ""],
        ["(steps at equal error against the plain script with the PI controller)",
         f"{so3['steps'] / eq[PLAIN_PI]['steps']:.2f}x", ""],
        ["single top <= 1.2x plain",
         f"{so3['wall'] / plain['wall']:.2f}x (CPU {so3['cpu'] / plain['cpu']:.2f}x)",
         verdict(so3["wall"] / plain["wall"] <= 1.2)],
        ["full <= 1.3x so3 (single top, equal error)", f"{full['wall'] / so3['wall']:.2f}x",
         verdict(full["wall"] / so3["wall"] <= 1.3)],
        [f"full <= 1.3x so3 (batch {BATCH}, 1 device, `tj.simulate_batch`)", f"{full_b:.2f}x",
         verdict(full_b <= 1.3)],
        [f"full <= 1.3x so3 (batch {BATCH}, {ndev2} devices, `tj.simulate_batch`)",
         f"{full_b2:.2f}x", verdict(full_b2 <= 1.3)],
        [f"(full / so3 with `tj.simulate` in the user's `jax.vmap`, 1 and {ndev2} devices)",
         f"{full_v:.2f}x, {full_v2:.2f}x", ""],
        ["compile <= 2 s per level", ", ".join(
            f"{k.split()[-1]} {v:.1f} s" for k, v in compile_s.items()
            if k.startswith("tippejax")),
         verdict(all(v <= 2 for k, v in compile_s.items() if k.startswith("tippejax")))],
    ]
    lines += ["### Targets (issue 18)", "", table(["target", "measured", "verdict"], trows), "",
              "The numba goal's row compares with the prange loop as it ran in this process, "
              "beside JAX's one CPU device, where 2 threads gained little over one; "
              "`benchmarks/numba_goal.py` measures the goal in interleaved rounds with numba's "
              "threads at their best (its section below), and is the verdict to quote.", ""]

    # Profile: what is left, and the arithmetic peak
    lines += ["### Profile: what is left", "",
              "Per top against the plain script, one run, interleaved rounds (wall and process CPU "
              "time; 'CPU/wall' > 1: XLA ran the solve on more than one thread):", ""]
    body = []
    for label, res in prof.items():
        for name, v in res.items():
            body.append([label, name, f"{v['wall']:.2f}", f"{v['cpu']:.2f}",
                         f"{v['cpu_per_wall']:.2f}"])
    lines += [table(["case", "run", "wall vs plain", "CPU vs plain", "CPU/wall"], body), ""]
    peak, peak_text = peak_flops()
    plain_b = b1[("plain diffrax", False)]
    rate = flops["step"] * plain_b["steps_sum"] / plain_b["wall"]
    lines += [
        f"Flops per member-step of the plain script (a lower bound: XLA's cost analysis of its "
        f"vmapped vector field, {flops['field']:.0f} flops, x 13 evaluations a Dopri8 step, plus "
        f"the Runge-Kutta combinations, {flops['rk']:.0f}): {flops['step']:.0f}. The plain "
        f"batch of {BATCH} on one device runs {rate / 1e9:.2f} GFLOP/s, "
        f"{100 * rate / peak:.1f}% of the peak of {peak_text}; tippejax's SO(3) batch does the "
        "same work plus its watch. A batch of tiny systems on XLA:CPU is bound by the number of "
        "small kernels each step launches and the memory they stream, not by arithmetic; "
        "compiled numba (one top per thread, everything in registers) runs the same steps "
        f"{plain_b['wall'] / b1[('numba DOP853 (CyRK)', False)]['wall']:.1f}x faster than the "
        "plain diffrax script on the same cores.", ""]

    lines += ["### Ladders (single top)", ""]
    body = []
    for name, rs in rows.items():
        for r in rs:
            body.append([name, f"{r['rtol']:.0e}", str(r["steps"]), f"{r['error']:.2e}",
                         ms(r["wall"]), ms(r["cpu"])])
    lines += [table(["peer", "rtol", "steps", "error", "ms", "CPU ms"], body), ""]
    text = "\n".join(lines)
    print(text)
    write_section("peers.py", text)


def chart(rows, target):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for name, rs in rows.items():
        if name == GYRO:
            continue
        err = [r["error"] for r in rs]
        axes[0].loglog(err, [r["cpu"] * 1e3 for r in rs], "o-", label=name, ms=3)
        axes[1].loglog(err, [r["steps"] for r in rs], "o-", label=name, ms=3)
    # process CPU time: on a shared machine wall time also counts the waits for a core
    for ax, ylabel in zip(axes, ("CPU ms per solve (single top)", "steps")):
        ax.axvline(target, color="grey", lw=0.8, ls=":")
        ax.set_xlabel("error of the final state")
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle("Standard top, SO(3) equations, 20 s: work against error")
    fig.tight_layout()
    fig.savefig(HERE / "peers.png", dpi=110)


if __name__ == "__main__":
    if _WORKER:
        worker()
    else:
        main()
