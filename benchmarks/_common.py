"""Shared pieces of the benchmark scripts: machine facts, timing, the RESULTS.md sections, and
the scipy baseline (`VectorModel`: the same vector-form model as tippejax, in numpy).

Not a benchmark itself; `engine.py`, `batch.py` and `gradients.py` import it.
"""

from __future__ import annotations

import math
import os
import pathlib
import platform
import re
import statistics
import time

import numpy as np
from scipy.integrate import solve_ivp

HERE = pathlib.Path(__file__).resolve().parent
RESULTS = HERE / "RESULTS.md"
SCRIPTS = ("engine.py", "batch.py", "gradients.py", "float32.py", "fitting.py", "maps.py")
HEADER_MARK = "<!-- header -->"


# ----------------------------------------------------------------------------------------------
# Machine
# ----------------------------------------------------------------------------------------------


def cpu_facts() -> dict:
    """Processor name, cores, clock (GHz) and SIMD flags from /proc/cpuinfo."""
    name, mhz, flags = platform.processor() or "unknown", None, set()
    try:
        text = pathlib.Path("/proc/cpuinfo").read_text()
        for line in text.splitlines():
            key, _, value = line.partition(":")
            key, value = key.strip(), value.strip()
            if key == "model name":
                name = value
            elif key == "cpu MHz" and mhz is None:
                mhz = float(value)
            elif key == "flags" and not flags:
                flags = set(value.split())
    except OSError:
        pass
    cores = os.cpu_count() or 1
    return dict(name=name, cores=cores, ghz=(mhz or 0.0) / 1e3, flags=flags)


def peak_flops() -> tuple[float, str]:
    """Float64 peak of the cores (flop/s) and the assumption behind it."""
    cpu = cpu_facts()
    if {"avx2", "fma"} <= cpu["flags"]:
        per_cycle, why = 16, "AVX2 + FMA: 2 FMA units x 4 doubles x 2 flops"
    elif "avx" in cpu["flags"]:
        per_cycle, why = 8, "AVX without FMA: 1 add + 1 mul unit x 4 doubles"
    else:
        per_cycle, why = 4, "SSE2: 2 units x 2 doubles"
    peak = cpu["cores"] * cpu["ghz"] * 1e9 * per_cycle
    text = (
        f"{cpu['cores']} cores x {cpu['ghz']:.3f} GHz (/proc/cpuinfo 'cpu MHz') x {per_cycle} "
        f"flop/cycle ({why}) = {peak / 1e9:.1f} GFLOP/s"
    )
    return peak, text


def machine_line() -> str:
    import diffrax
    import jax

    cpu = cpu_facts()
    return (
        f"{cpu['name']}, {cpu['cores']} cores @ {cpu['ghz']:.2f} GHz, "
        f"jax {jax.__version__}, diffrax {diffrax.__version__}, {jax.devices()[0].platform}"
    )


def machine_block() -> str:
    import diffrax
    import equinox
    import jax
    import scipy

    cpu = cpu_facts()
    return "\n".join(
        [
            f"- processor: {cpu['name']}, {cpu['cores']} cores (`os.cpu_count()`), "
            f"{cpu['ghz']:.2f} GHz, SIMD: "
            + ", ".join(f for f in ("sse2", "avx", "avx2", "fma", "avx512f") if f in cpu["flags"]),
            f"- {platform.platform()}, python {platform.python_version()}",
            f"- jax {jax.__version__}, diffrax {diffrax.__version__}, equinox "
            f"{equinox.__version__}, scipy {scipy.__version__}, numpy {np.__version__}, "
            f"devices {jax.devices()}",
        ]
    )


# ----------------------------------------------------------------------------------------------
# Timing
# ----------------------------------------------------------------------------------------------


class Timing:
    """Wall-clock and process CPU time of a first (compiling) call and of later calls."""

    def __init__(self):
        self.first_wall = self.first_cpu = math.nan
        self.walls: list[float] = []
        self.cpus: list[float] = []

    @property
    def wall(self) -> float:
        return statistics.median(self.walls)

    @property
    def cpu(self) -> float:
        return statistics.median(self.cpus)

    @property
    def compile(self) -> float:
        """First call less the median of the later calls (wall clock)."""
        return self.first_wall - self.wall


def _call(fn, args, kwargs):
    import jax

    wall, cpu = time.perf_counter(), time.process_time()
    out = jax.block_until_ready(fn(*args, **kwargs))
    return time.perf_counter() - wall, time.process_time() - cpu, out


def timed(fn, *args, repeats: int = 5, **kwargs):
    """(Timing, output): a first call, then `repeats` calls, each followed by
    `jax.block_until_ready` on its output."""
    timing = Timing()
    timing.first_wall, timing.first_cpu, out = _call(fn, args, kwargs)
    for _ in range(repeats):
        wall, cpu, out = _call(fn, args, kwargs)
        timing.walls.append(wall)
        timing.cpus.append(cpu)
    return timing, out


def interleaved(fns: dict, repeats: int = 5):
    """{name: (Timing, output)} for zero-argument callables, timed side by side: one first call
    each, then `repeats` rounds calling each once, so that the load of a shared machine falls
    on all of them alike."""
    timings = {name: Timing() for name in fns}
    outs = {}
    for name, fn in fns.items():
        t = timings[name]
        t.first_wall, t.first_cpu, outs[name] = _call(fn, (), {})
    for _ in range(repeats):
        for name, fn in fns.items():
            wall, cpu, outs[name] = _call(fn, (), {})
            timings[name].walls.append(wall)
            timings[name].cpus.append(cpu)
    return {name: (timings[name], outs[name]) for name in fns}


# ----------------------------------------------------------------------------------------------
# RESULTS.md
# ----------------------------------------------------------------------------------------------


def paired_ratios(walls, base_walls) -> list[float]:
    """Round-by-round ratios of two runs' times from `interleaved` (each round's pair shares
    the machine's load of that moment)."""
    return [a / b for a, b in zip(walls, base_walls)]


def _fresh_results() -> str:
    parts = [
        "# Benchmark results: engine, batches, gradients",
        "",
        HEADER_MARK,
        "<!-- /header -->",
        "",
    ]
    for script in SCRIPTS:
        parts += [f"<!-- {script} -->", f"(`benchmarks/{script}` has not been run yet.)",
                  f"<!-- /{script} -->", ""]
    return "\n".join(parts)


def write_section(script: str, body: str) -> None:
    """Replace the section of `script` (and the machine header) in benchmarks/RESULTS.md.

    A RESULTS.md without the header marker (the old, obsolete layout) is replaced by a fresh
    file; a script without a section yet gets one at the end. Other sections are kept.
    """
    text = RESULTS.read_text() if RESULTS.exists() else ""
    if HEADER_MARK not in text:
        text = _fresh_results()
    header = (
        f"{HEADER_MARK}\nEach section below is written by the script it names "
        "(`python benchmarks/<script>` from the repository root). Machine of the latest run:\n\n"
        f"{machine_block()}\n\n"
        "The machine is shared and noisy (2 cores): quote ratios and medians measured side by "
        "side in one run, not single absolute times.\n<!-- /header -->"
    )
    text = re.sub(r"<!-- header -->.*?<!-- /header -->", lambda _: header, text, flags=re.S)
    block = f"<!-- {script} -->\n{body.strip()}\n<!-- /{script} -->"
    pattern = rf"<!-- {re.escape(script)} -->.*?<!-- /{re.escape(script)} -->"
    if re.search(pattern, text, flags=re.S):
        text = re.sub(pattern, lambda _: block, text, flags=re.S)
    else:
        text = text.rstrip("\n") + "\n\n" + block + "\n"
    RESULTS.write_text(text)


def table(headers, rows) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(str(x) for x in row) + " |" for row in rows]
    return "\n".join(lines)


def verdict(met: bool) -> str:
    return "**met**" if met else "**missed**"


def random_top(rng):
    """A seeded random top from the ranges users have, none of them tuned on: A/C in
    [0.6, 1.7], eps/R in [0.03, 0.4], mu log-uniform in [0.05, 1] s/m (m 20 g, R 25 mm).
    Returns `(top, A/C, eps/R, mu, n_ref)` with `n_ref` its n1 (n2 in group I, where n1 is
    not finite), the scale of its launch spins."""
    import tippejax as tj

    a_c, e_r = rng.uniform(0.6, 1.7), rng.uniform(0.03, 0.4)
    mu = float(np.exp(rng.uniform(np.log(0.05), np.log(1.0))))
    top = tj.TippeTop.from_ratios(a_c, e_r, m=0.02, R=0.025, mu=mu)
    th = tj.thresholds(top)
    n_ref = float(th.n1) if np.isfinite(float(th.n1)) else float(th.n2)
    return top, a_c, e_r, mu, n_ref


# ----------------------------------------------------------------------------------------------
# scipy baseline: the vector-form model of tippejax/_models/_rigid_body.py, in numpy
# ----------------------------------------------------------------------------------------------


def standard_params() -> dict:
    """`tj.default_top()` as floats: A/C = 0.9, eps/R = 0.3, m = 20 g, R = 25 mm, mu = 0.3 s/m."""
    m, R = 0.02, 0.025
    C = 0.4 * m * R**2
    return dict(m=m, R=R, eps=0.3 * R, A=0.9 * C, C=C, g=9.81, mu=0.3)


class VectorModel:
    r"""The full or SO(3) model in the global vector form, as a numpy right-hand side.

    State: full `(x, y, vx, vy, a_x, a_y, a_z, w_x, w_y, w_z)`; so3 `(a, omega)`. Mirrors
    `rigid_body_dynamics`: $q = \epsilon a - R e_Z$, $v_Q = v_O + \omega\times q$ (vertical
    component zeroed), $\dot\omega = \dot\omega_0 + R_n I^{-1}(q\times(e_Z - \mu v_Q))$,
    $R_n = (g + \ddot h_0)/(1/m - \ddot h_1)$. Written on Python floats (3-vectors as tuples),
    which for 3-vectors is ~5x faster per call than `np.cross`/`np.dot` on arrays: the
    strongest plain-numpy baseline, not a strawman.
    """

    def __init__(self, params: dict, variant: str):
        if variant not in ("full", "so3"):
            raise ValueError(variant)
        self.p = dict(params)
        self.variant = variant
        self.size = 10 if variant == "full" else 6

    def dynamics(self, a, w, v):
        """(R_n, omega_dot, v_Q, denominator) for axis a, omega w, horizontal velocity v."""
        p = self.p
        m, R, eps, A, C, g, mu = p["m"], p["R"], p["eps"], p["A"], p["C"], p["g"], p["mu"]
        ax, ay, az = a
        wx, wy, wz = w
        n = wx * ax + wy * ay + wz * az
        # a_dot = w x a
        dx, dy, dz = wy * az - wz * ay, wz * ax - wx * az, wx * ay - wy * ax
        qx, qy, qz = eps * ax, eps * ay, eps * az - R
        # v_Q = v_O + w x q, v_O = (vx, vy, -eps a_dot_z); vertical component set to 0
        vqx = v[0] + (wy * qz - wz * qy)
        vqy = v[1] + (wz * qx - wx * qz)
        fx, fy, fz = -mu * vqx, -mu * vqy, 1.0
        tx, ty, tz = qy * fz - qz * fy, qz * fx - qx * fz, qx * fy - qy * fx
        k0 = -(C - A) / A * n
        o0x, o0y, o0z = k0 * dx, k0 * dy, k0 * dz
        at = (1.0 / C - 1.0 / A) * (ax * tx + ay * ty + az * tz)
        o1x, o1y, o1z = tx / A + at * ax, ty / A + at * ay, tz / A + at * az
        # z components of (omega_dot_0 x a), (w x a_dot), (omega_dot_1 x a)
        h0 = -eps * ((o0x * ay - o0y * ax) + (wx * dy - wy * dx))
        h1 = -eps * (o1x * ay - o1y * ax)
        den = 1.0 / m - h1
        rn = (g + h0) / den
        return rn, (o0x + rn * o1x, o0y + rn * o1y, o0z + rn * o1z), (vqx, vqy), den

    def rhs(self, t, y):
        yl = y.tolist()
        if self.variant == "full":
            _, _, vx, vy, ax, ay, az, wx, wy, wz = yl
            v = (vx, vy)
        else:
            ax, ay, az, wx, wy, wz = yl
            v = (0.0, 0.0)
        rn, (ox, oy, oz), (vqx, vqy), _ = self.dynamics((ax, ay, az), (wx, wy, wz), v)
        adot = (wy * az - wz * ay, wz * ax - wx * az, wx * ay - wy * ax)
        if self.variant == "full":
            k = -self.p["mu"] * rn / self.p["m"]
            return np.array([vx, vy, k * vqx, k * vqy, *adot, ox, oy, oz])
        return np.array([*adot, ox, oy, oz])

    def y0(self, theta0, spin, *, phi_dot=0.0):
        """The state of `tj.initial_state(top, theta0, spin, phi_dot=...)` (phi = psi = 0)."""
        st, ct = math.sin(theta0), math.cos(theta0)
        a = np.array([0.0, -st, ct])
        # omega = phi_dot e_Z + theta_dot N + psi_dot a, N = (1, 0, 0), psi_dot = n - phi_dot cos
        psi_dot = spin - phi_dot * ct
        w = np.array([0.0, 0.0, phi_dot]) + psi_dot * a
        if self.variant == "full":
            return np.concatenate([np.zeros(4), a, w])
        return np.concatenate([a, w])

    def axis_slice(self):
        return slice(4, 7) if self.variant == "full" else slice(0, 3)

    def solve(self, y0, t1, t_eval, *, rtol, atol, method="DOP853"):
        """solve_ivp on [0, t1]; returns (theta at t_eval, t_invert, nfev, number of steps)."""
        sl = self.axis_slice()

        def upright(t, y):
            return y[sl][2]

        upright.direction = -1
        sol = solve_ivp(self.rhs, (0.0, t1), y0, method=method, t_eval=t_eval, rtol=rtol,
                        atol=atol, events=upright)
        if not sol.success:
            raise RuntimeError(sol.message)
        a = sol.y[sl]
        theta = np.arctan2(np.hypot(a[0], a[1]), a[2])
        t_inv = sol.t_events[0][0] if len(sol.t_events[0]) else np.nan
        steps = (sol.nfev - 1) // 12 if method == "DOP853" else None
        return theta, t_inv, sol.nfev, steps


    def solve_summary(self, y0, t1, *, rtol, atol, method="DOP853"):
        """What `tj.simulate(..., summary=True)` computes: the run to t1 or to contact loss
        (R_n D = 0, a terminal event, as on_contact_loss="stop"), the first inversion, the
        final theta. Returns a dict."""
        sl = self.axis_slice()

        def upright(t, y):
            return y[sl][2]

        def contact(t, y):
            yl = y.tolist()
            a, w = (yl[4:7], yl[7:10]) if self.variant == "full" else (yl[0:3], yl[3:6])
            v = yl[2:4] if self.variant == "full" else (0.0, 0.0)
            rn, _, _, den = self.dynamics(a, w, v)
            return rn * den

        upright.direction = -1
        contact.direction = -1
        contact.terminal = True
        sol = solve_ivp(self.rhs, (0.0, t1), y0, method=method, rtol=rtol, atol=atol,
                        events=(upright, contact))
        if not sol.success:
            raise RuntimeError(sol.message)
        a = sol.y[sl, -1]
        return dict(
            theta=float(np.arctan2(np.hypot(a[0], a[1]), a[2])), t_final=float(sol.t[-1]),
            t_invert=float(sol.t_events[0][0]) if len(sol.t_events[0]) else math.nan,
            t_contact_loss=float(sol.t_events[1][0]) if len(sol.t_events[1]) else math.nan,
            nfev=int(sol.nfev),
        )


def interp_loglog(x_query, xs, ys):
    """log-log linear interpolation of y(x) through the points (xs, ys), extrapolating linearly
    (in log-log) from the two nearest points outside their range; also says whether it had to.
    """
    xs, ys = np.asarray(xs, float), np.asarray(ys, float)
    keep = np.isfinite(xs) & np.isfinite(ys) & (xs > 0) & (ys > 0)
    lx, ly = np.log(xs[keep]), np.log(ys[keep])
    order = np.argsort(lx)
    lx, ly = lx[order], ly[order]
    q = math.log(x_query)
    if q < lx[0]:
        i, extrapolated = 0, True
    elif q > lx[-1]:
        i, extrapolated = len(lx) - 2, True
    else:
        i, extrapolated = max(0, min(int(np.searchsorted(lx, q)) - 1, len(lx) - 2)), False
    slope = (ly[i + 1] - ly[i]) / (lx[i + 1] - lx[i])
    return math.exp(ly[i] + slope * (q - lx[i])), extrapolated
