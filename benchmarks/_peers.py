"""The peers a user has for tippejax's scene, each on the same SO(3) equations: a plain diffrax
script, compiled numba DOP853 (CyRK) and scipy's DOP853 on the vector-form model in numpy.

The scene: the standard top `tj.default_top()`, theta0 = 0.1, spin 150 rad/s for one top and
spins linspace(140, 160, N) for a batch, 20 s, the final state."""

from __future__ import annotations

import functools
import math

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec

import tippejax as tj

TOP = tj.default_top()
PARAMS = np.array([float(getattr(TOP, k)) for k in ("m", "R", "eps", "A", "C", "g", "mu")])
THETA0, SPIN, T1 = 0.1, 150.0, 20.0
PI = dict(pcoeff=0.4, icoeff=0.3)  # the PI controller tippejax uses (diffrax's suggestion)
BLOCK = 128  # members per block of the plain script in blocks (simulate_batch's CPU layout)


def spins(n: int) -> np.ndarray:
    return np.linspace(140.0, 160.0, n)


def state_error(final, ref) -> float:
    """max(|a - a_ref|, |omega - omega_ref| / |omega_ref|) of final states (..., 6)."""
    final, ref = np.asarray(final, float), np.asarray(ref, float)
    d_omega = (
        np.abs(final[..., 3:] - ref[..., 3:]) / np.linalg.norm(ref[..., 3:], axis=-1)[..., None]
    )
    return float(max(np.max(np.abs(final[..., :3] - ref[..., :3])), np.max(d_omega)))


# --- the plain diffrax script ------------------------------------------------------------------


def so3_field(t, y, p):
    """The SO(3) equations (translation dropped in the friction law), axis a and omega."""
    m, R, eps, A, C, g, mu = p
    a, w = y[:3], y[3:]
    q = eps * a - jnp.array([0.0, 0.0, R])
    vq = jnp.cross(w, q).at[2].set(0.0)
    tau = jnp.cross(q, jnp.array([0.0, 0.0, 1.0]) - mu * vq)  # torque per unit normal force
    o0 = -(C - A) / A * jnp.dot(w, a) * jnp.cross(w, a)
    o1 = tau / A + (1 / C - 1 / A) * jnp.dot(a, tau) * a
    h0 = -eps * (jnp.cross(o0, a)[2] + jnp.cross(w, jnp.cross(w, a))[2])
    h1 = -eps * jnp.cross(o1, a)[2]
    rn = (g + h0) / (1 / m - h1)
    return jnp.concatenate([jnp.cross(w, a), o0 + rn * o1])


def launch(spin):
    a = jnp.array([0.0, -jnp.sin(THETA0), jnp.cos(THETA0)])
    return jnp.concatenate([a, spin * a])


def plain_solve(spin, rtol, atol, *, controller=None, solver=None):
    """One top: Dopri8, PIDController, no events. Returns (final state, steps)."""
    pid = diffrax.PIDController(rtol=rtol, atol=atol, **(controller or {}))
    kw = dict(saveat=diffrax.SaveAt(t1=True), stepsize_controller=pid, max_steps=100_000)
    term, y0 = diffrax.ODETerm(so3_field), launch(spin)
    sol = diffrax.diffeqsolve(
        term, solver or diffrax.Dopri8(), 0.0, T1, None, y0, tuple(PARAMS), **kw
    )
    return sol.ys[-1], sol.stats["num_steps"]


def plain_shared(spins_, rtol, atol, *, solver=None):
    """The batch as ONE solve whose state is (N, 6): every member takes the same steps, each
    member's error controlled (the norm is the largest member's RMS norm)."""
    term = diffrax.ODETerm(jax.vmap(so3_field, in_axes=(None, 0, None)))
    norm = lambda x: jnp.max(jnp.sqrt(jnp.mean(x**2, axis=1)))  # noqa: E731
    pid = diffrax.PIDController(rtol=rtol, atol=atol, norm=norm)
    kw = dict(saveat=diffrax.SaveAt(t1=True), stepsize_controller=pid, max_steps=100_000)
    y0 = jax.vmap(launch)(spins_)
    sol = diffrax.diffeqsolve(
        term, solver or diffrax.Dopri8(), 0.0, T1, None, y0, tuple(PARAMS), **kw
    )
    return sol.ys[-1], jnp.full(spins_.shape, sol.stats["num_steps"])


def in_blocks(batched):
    """`batched(spins, *rest)` over blocks of at most BLOCK members under `lax.map`."""

    def run(spins_, *rest):
        n = spins_.shape[0]
        block = max(k for k in range(1, min(n, BLOCK) + 1) if n % k == 0)
        out = jax.lax.map(lambda s: batched(s, *rest), spins_.reshape(n // block, block))
        return jax.tree_util.tree_map(lambda x: x.reshape(n, *x.shape[2:]), out)

    return run


def over_devices(fn, n_args: int, devices=None, compiler_options=None):
    """`jax.jit` of `fn(spins, *rest)`; on several devices each runs its own shard's loop
    (`jax.shard_map`, as `tj.simulate_batch` does), the other arguments whole."""
    devices = jax.devices() if devices is None else devices
    if len(devices) > 1:
        mesh = Mesh(np.array(devices), ("batch",))
        specs = (PartitionSpec("batch"),) + (PartitionSpec(),) * (n_args - 1)
        fn = jax.shard_map(fn, mesh=mesh, in_specs=specs, out_specs=specs[0], check_vma=False)
    return jax.jit(fn, compiler_options=compiler_options)


@functools.cache
def plain(kind: str = "vmap", n_devices: int | None = None):
    """The plain script over a batch, `run(spins, rtol, atol) -> (finals, steps)`:
    "vmap" (`jax.vmap`), "blocks" (vmap in blocks, compiled with `tj.compiler_options()`: the
    strongest JAX script we know on a CPU), "shared" (one solve for the batch); on every device
    unless `n_devices`."""
    devices = jax.devices()[: n_devices or None]
    batched = plain_shared if kind == "shared" else jax.vmap(plain_solve, in_axes=(0, None, None))
    if kind == "blocks":
        return over_devices(in_blocks(batched), 3, devices, tj.compiler_options())
    return over_devices(batched, 3, devices)


@functools.cache
def plain_single(kind: str = "vmap"):
    return jax.jit(functools.partial(plain_solve, controller=PI if kind == "pi" else None))


# --- numba: CyRK's compiled DOP853 on the same equations ---------------------------------------


try:  # the compiled peer (`pip install -e ".[bench]"`); defined at module level so that
    # numba caches its compilation on disk
    import numba
    from CyRK import nbsolve_ivp
except ImportError:  # pragma: no cover
    numba = None
else:

    @numba.njit(cache=True)
    def _numba_rhs(t, y, p):
        m, R, eps, A, C, g, mu = p[0], p[1], p[2], p[3], p[4], p[5], p[6]
        ax, ay, az, wx, wy, wz = y[0], y[1], y[2], y[3], y[4], y[5]
        n = wx * ax + wy * ay + wz * az
        dx, dy, dz = wy * az - wz * ay, wz * ax - wx * az, wx * ay - wy * ax
        qx, qy, qz = eps * ax, eps * ay, eps * az - R
        fx, fy = -mu * (wy * qz - wz * qy), -mu * (wz * qx - wx * qz)
        tx, ty, tz = qy - qz * fy, qz * fx - qx, qx * fy - qy * fx
        k0 = -(C - A) / A * n
        at = (1.0 / C - 1.0 / A) * (ax * tx + ay * ty + az * tz)
        o1x, o1y, o1z = tx / A + at * ax, ty / A + at * ay, tz / A + at * az
        h0 = -eps * (k0 * (dx * ay - dy * ax) + (wx * dy - wy * dx))
        rn = (g + h0) / (1.0 / m + eps * (o1x * ay - o1y * ax))
        out = np.empty(6)
        out[0], out[1], out[2] = dx, dy, dz
        out[3], out[4], out[5] = k0 * dx + rn * o1x, k0 * dy + rn * o1y, k0 * dz + rn * o1z
        return out

    @numba.njit(parallel=True, cache=True)
    def _numba_loop(spins_, theta0, t1, rtol, atol, p, ts):
        finals, steps = np.empty((spins_.shape[0], 6)), np.empty(spins_.shape[0], np.int64)
        for i in numba.prange(spins_.shape[0]):
            y0 = np.empty(6)
            y0[0], y0[1], y0[2] = 0.0, -np.sin(theta0), np.cos(theta0)
            y0[3:] = spins_[i] * y0[:3]
            res = nbsolve_ivp(  # (numba: no ** unpacking in a jitted function)
                _numba_rhs, (0.0, t1), y0, (p,), rtol, atol, rk_method=2, t_eval=ts, warnings=False
            )
            finals[i], steps[i] = res.y[:, -1], res.size - 1
        return finals, steps


@functools.cache
def numba_batch():
    """`run(spins, rtol, atol, threads=None, ts=None) -> (finals, steps)`: CyRK's `nbsolve_ivp`
    (DOP853) in a `numba.prange` loop over the tops, on `threads` threads (default all)."""
    if numba is None:
        raise RuntimeError("the numba peer needs numba and CyRK: pip install -e '.[bench]'")

    def run(spins_, rtol, atol, threads=None, ts=None):
        # set before every call: a prange loop that ran between JAX's calls keeps no count
        numba.set_num_threads(threads or numba.config.NUMBA_NUM_THREADS)
        ts_ = np.empty(0) if ts is None else np.asarray(ts, float)
        spins_ = np.asarray(spins_, float)
        finals, steps = _numba_loop(spins_, THETA0, T1, float(rtol), float(atol), PARAMS, ts_)
        return finals, (steps if ts is None else None)  # with ts CyRK reports len(ts)

    return run


# --- scipy: DOP853 on the vector-form model in numpy --------------------------------------------


class VectorModel:
    """The full (x, y, vx, vy, a, omega) or SO(3) (a, omega) model of tippejax in the global
    vector form, on Python floats (for 3-vectors faster than numpy arrays): scipy's strongest
    form of the model, not a strawman. R_n from the vertical Newton equation."""

    def __init__(self, variant: str, params=PARAMS):
        self.full = variant == "full"
        self.p = tuple(float(x) for x in params)

    def dynamics(self, a, w, v):
        """(R_n, omega_dot, horizontal slip velocity)."""
        m, R, eps, A, C, g, mu = self.p
        (ax, ay, az), (wx, wy, wz) = a, w
        n = wx * ax + wy * ay + wz * az
        dx, dy, dz = wy * az - wz * ay, wz * ax - wx * az, wx * ay - wy * ax
        qx, qy, qz = eps * ax, eps * ay, eps * az - R
        vqx, vqy = v[0] + wy * qz - wz * qy, v[1] + wz * qx - wx * qz
        fx, fy = -mu * vqx, -mu * vqy
        tx, ty, tz = qy - qz * fy, qz * fx - qx, qx * fy - qy * fx
        k0 = -(C - A) / A * n
        at = (1.0 / C - 1.0 / A) * (ax * tx + ay * ty + az * tz)
        o1 = (tx / A + at * ax, ty / A + at * ay, tz / A + at * az)
        h0 = -eps * (k0 * (dx * ay - dy * ax) + (wx * dy - wy * dx))
        rn = (g + h0) / (1.0 / m + eps * (o1[0] * ay - o1[1] * ax))
        wdot = (k0 * dx + rn * o1[0], k0 * dy + rn * o1[1], k0 * dz + rn * o1[2])
        return rn, wdot, (vqx, vqy)

    def split(self, y):
        y = y.tolist()
        return (y[4:7], y[7:10], y[2:4]) if self.full else (y[0:3], y[3:6], (0.0, 0.0))

    def rhs(self, t, y):
        a, w, v = self.split(y)
        rn, wdot, vq = self.dynamics(a, w, v)
        adot = (w[1] * a[2] - w[2] * a[1], w[2] * a[0] - w[0] * a[2], w[0] * a[1] - w[1] * a[0])
        if self.full:
            k = -self.p[6] * rn / self.p[0]
            return np.array([v[0], v[1], k * vq[0], k * vq[1], *adot, *wdot])
        return np.array([*adot, *wdot])

    def y0(self, theta0, spin, phi_dot=0.0):
        """The state of `tj.initial_state(top, theta0, spin, phi_dot=...)`."""
        a = np.array([0.0, -math.sin(theta0), math.cos(theta0)])
        w = np.array([0.0, 0.0, phi_dot]) + (spin - phi_dot * math.cos(theta0)) * a
        return np.concatenate([np.zeros(4), a, w]) if self.full else np.concatenate([a, w])

    def solve(self, y0, t1, *, rtol, atol, t_eval=None):
        """solve_ivp(DOP853) with the inversion (a_z through 0). Returns theta at t_eval (or the
        final state), t_invert, steps."""
        from scipy.integrate import solve_ivp

        k = 6 if self.full else 2

        def upright(t, y):
            return y[k]

        upright.direction = -1
        kw = dict(method="DOP853", rtol=rtol, atol=atol, t_eval=t_eval, events=upright)
        sol = solve_ivp(self.rhs, (0.0, t1), y0, **kw)
        if not sol.success:
            raise RuntimeError(sol.message)
        a = sol.y[k - 2 : k + 1]
        t_invert = float(sol.t_events[0][0]) if len(sol.t_events[0]) else math.nan
        out = np.arctan2(np.hypot(a[0], a[1]), a[2]) if t_eval is not None else sol.y[:, -1]
        return out, t_invert, (sol.nfev - 1) // 12
