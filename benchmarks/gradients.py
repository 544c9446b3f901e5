"""Gradients through the solve: reverse and forward mode, cost, compile time, correctness.

Standard top, launch theta0 = 0.1, spin 150 rad/s, t1 = 20 s, full model, default solver
(Dopri8). Two quantities, differentiated with respect to all seven fields of the top
(m, R, eps, A, C, g, mu):

- `t_invert` of a summary-mode solve (`summary=True`);
- `sum(theta)` over 201 save points.

Modes, with `simulate`'s default adjoint (forward sensitivities, `tippejax/_engine/
sensitivity.py`): reverse (`jax.grad`) and forward (`jax.jacfwd`); and reverse mode through the
solve's steps (`adjoint=diffrax.RecursiveCheckpointAdjoint()`, the default before); and the
reverse gradient called eagerly, without `jax.jit`. Cost =
median time of the compiled derivative / median time of the compiled forward solve of the same
quantity (rtol 1e-8); compile = first call less the median. Correctness at rtol 1e-12: the
default's reverse mode against reverse mode through the solve (independent routes), and both
modes against central differences (relative step 1e-6). A profile scan times the Jacobian of
sum(theta) in the first k fields, k = 1..7, with process CPU time beside wall time: XLA:CPU
runs some of these programs on one thread and others on two (see `why`). Writes its section of
benchmarks/RESULTS.md.

    python benchmarks/gradients.py
"""

from __future__ import annotations

import os
import pathlib
import sys
import time

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

import tippejax as tj

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _common import interleaved, machine_line, table, verdict, write_section  # noqa: E402

FIELDS = ("m", "R", "eps", "A", "C", "g", "mu")
T1 = 20.0
TS = jnp.linspace(0.0, T1, 201)
LAUNCH = (0.1, 150.0)
TIMING_TOL = (1e-8, 1e-10)
CHECK_TOL = (1e-12, 1e-14)
REL_STEP = 1e-6
REPEATS = 5
LOG: list[str] = []
LOAD = os.getloadavg()


def say(text=""):
    print(text, flush=True)
    LOG.append(text)


def t_invert(top, rtol, atol, adjoint=None):
    y0 = tj.initial_state(top, *LAUNCH)
    sol = tj.simulate(top, y0, T1, summary=True, rtol=rtol, atol=atol, throw=False,
                      adjoint=adjoint)
    return sol.t_invert


def sum_theta(top, rtol, atol, adjoint=None):
    y0 = tj.initial_state(top, *LAUNCH)
    sol = tj.simulate(top, y0, T1, saveat=TS, rtol=rtol, atol=atol, throw=False,
                      adjoint=adjoint)
    return jnp.sum(sol.theta)


QUANTITIES = {"t_invert (summary)": t_invert, "sum(theta), 201 saves": sum_theta}
EAGER = "eager reverse (jax.grad, no jax.jit)"


def as_dict(grad_top) -> dict:
    return {f: float(getattr(grad_top, f)) for f in FIELDS}


def central_differences(value, top, rtol, atol) -> dict:
    out = {}
    for f in FIELDS:
        x = float(getattr(top, f))
        h = REL_STEP * abs(x)
        plus = eqx.tree_at(lambda t: getattr(t, f), top, jnp.asarray(x + h))
        minus = eqx.tree_at(lambda t: getattr(t, f), top, jnp.asarray(x - h))
        out[f] = (float(value(plus, rtol, atol)) - float(value(minus, rtol, atol))) / (2 * h)
    return out


def rel(a: dict, b: dict) -> dict:
    return {f: abs(a[f] - b[f]) / max(abs(b[f]), 1e-300) for f in FIELDS}


def measure(name, fn):
    top = tj.default_top()
    value = eqx.filter_jit(fn)
    reverse = eqx.filter_jit(jax.grad(fn))
    forward = eqx.filter_jit(jax.jacfwd(fn))
    # Profile: one tangent instead of seven; reverse mode through the solve's steps.
    one_tangent = eqx.filter_jit(lambda top, r, a: jax.jvp(
        lambda mu: fn(eqx.tree_at(lambda t: t.mu, top, mu), r, a),
        (top.mu,), (jnp.ones_like(top.mu),))[1])
    two_tangents = eqx.filter_jit(lambda top, r, a: jax.jacfwd(
        lambda mr: fn(eqx.tree_at(lambda t: (t.m, t.R), top, mr), r, a))((top.m, top.R)))
    through = eqx.filter_jit(jax.grad(lambda top, r, a: fn(
        top, r, a, diffrax.RecursiveCheckpointAdjoint())))
    # The reverse gradient once more, compiled with the options tippejax compiles its own
    # programs with (its run time against the default's; its compile time here is less the
    # trace, which the process has cached: compile_cache.py times it in a fresh process).
    with_options = eqx.filter_jit(jax.grad(fn), compiler_options=tj.compiler_options())
    # The reverse gradient called eagerly (no jit of the caller): the Jacobian of the solve is
    # then a program of its own, compiled with tippejax's options (`_simulate._run_traced`),
    # and the caller's Python runs on every call.
    eager = jax.grad(fn)
    r8, a8 = (jnp.asarray(x) for x in TIMING_TOL)
    say(f"{name}: compiling and timing (rtol {TIMING_TOL[0]:g})")
    results = interleaved({
        "forward solve": lambda: value(top, r8, a8),
        "reverse (jax.grad)": lambda: reverse(top, r8, a8),
        "forward mode (jax.jacfwd)": lambda: forward(top, r8, a8),
        "profile: forward mode, 1 tangent (jax.jvp, d/dmu)": lambda: one_tangent(top, r8, a8),
        "profile: forward mode, 2 tangents (jax.jacfwd, d/dm and d/dR)":
            lambda: two_tangents(top, r8, a8),
        "reverse through the solve (jax.grad, RecursiveCheckpointAdjoint)":
            lambda: through(top, r8, a8),
        EAGER: lambda: eager(top, r8, a8),
        "with tj.compiler_options(): reverse (jax.grad)":
            lambda: with_options(top, r8, a8),
    }, repeats=REPEATS)
    base = results["forward solve"][0]
    rows = []
    for label, (timing, out) in results.items():
        rows.append(dict(mode=label, wall=timing.wall, cpu=timing.cpu, compile=timing.compile,
                         compile_cpu=timing.first_cpu - timing.cpu,
                         first=timing.first_wall, ratio=timing.wall / base.wall,
                         ratio_cpu=timing.cpu / base.cpu))
        say(f"  {label}: first {timing.first_wall:.1f} s, median {timing.wall:.3f} s wall "
            f"({timing.wall / base.wall:.2f}x), {timing.cpu:.3f} s CPU "
            f"({timing.cpu / base.cpu:.2f}x), compile {timing.compile:.1f} s")
    # Correctness at tight tolerance (the same compiled functions: rtol/atol are traced).
    r12, a12 = (jnp.asarray(x) for x in CHECK_TOL)
    g_rev = as_dict(reverse(top, r12, a12))
    g_fwd = as_dict(forward(top, r12, a12))
    g_thr = as_dict(through(top, r12, a12))
    fd = central_differences(value, top, r12, a12)
    value12 = float(value(top, r12, a12))
    rev_thr, rev_fd, fwd_fd = rel(g_rev, g_thr), rel(g_rev, fd), rel(g_fwd, fd)
    for f in FIELDS:
        say(f"  d/d{f:3s}: reverse {g_rev[f]:+.10e}, through the solve {g_thr[f]:+.10e}, "
            f"FD {fd[f]:+.10e} | rel rev-through {rev_thr[f]:.1e}, rev-FD {rev_fd[f]:.1e}, "
            f"fwd-FD {fwd_fd[f]:.1e}")
    return dict(name=name, rows=rows, rev=g_rev, fwd=g_fwd, through=g_thr, fd=fd,
                rev_thr=rev_thr, rev_fd=rev_fd, fwd_fd=fwd_fd, value=value12)


def tangent_scan():
    """`jax.jacfwd` of sum(theta) over 201 saves in the first k fields, k = 1..7, against the
    forward solve, interleaved: wall, CPU and CPU/wall per k. Where CPU/wall is ~2 the
    program ran on two threads."""
    top = tj.default_top()
    value = eqx.filter_jit(sum_theta)
    r8, a8 = (jnp.asarray(x) for x in TIMING_TOL)
    fns = {"forward solve": lambda: value(top, r8, a8)}
    for k in range(1, len(FIELDS) + 1):
        fields = FIELDS[:k]

        def of_fields(values, r, a, fields=fields):
            return sum_theta(eqx.tree_at(
                lambda t: tuple(getattr(t, f) for f in fields), top, tuple(values)), r, a)

        jac = eqx.filter_jit(jax.jacfwd(of_fields))
        values = tuple(getattr(top, f) for f in fields)
        fns[f"k = {k}"] = (lambda jac, values: lambda: jac(values, r8, a8))(jac, values)
    say("tangent scan: jax.jacfwd of sum(theta), 201 saves, in the first k fields")
    results = interleaved(fns, repeats=REPEATS)
    base = results["forward solve"][0]
    rows = []
    for label, (timing, _) in results.items():
        rows.append(dict(k=label, ratio=timing.wall / base.wall, ratio_cpu=timing.cpu / base.cpu,
                         threads=timing.cpu / timing.wall))
        say(f"  {label}: {timing.wall / base.wall:.2f}x wall, {timing.cpu / base.cpu:.2f}x CPU, "
            f"CPU/wall {timing.cpu / timing.wall:.2f}")
    return rows


def plain_script():
    """The same derivatives of a plain diffrax script (`peers.py`'s: SO(3) equations, Dopri8,
    PIDController, no events): d(sum of the final axis)/d(seven parameters) by reverse and
    forward mode, against its own solve. The baseline a user has."""
    from peers import PARAMS, THETA0, so3_field

    def solve(p, r, a, adjoint=diffrax.RecursiveCheckpointAdjoint()):
        axis = jnp.array([0.0, -jnp.sin(THETA0), jnp.cos(THETA0)])
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(so3_field), diffrax.Dopri8(), 0.0, T1, None,
            jnp.concatenate([axis, LAUNCH[1] * axis]), tuple(p), max_steps=100_000,
            saveat=diffrax.SaveAt(t1=True), adjoint=adjoint,
            stepsize_controller=diffrax.PIDController(rtol=r, atol=a))
        return jnp.sum(sol.ys[-1][:3])

    p = jnp.asarray(PARAMS)
    r8, a8 = (jnp.asarray(x) for x in TIMING_TOL)
    value = jax.jit(solve)
    reverse = jax.jit(jax.grad(solve))
    forward = jax.jit(jax.jacfwd(lambda p, r, a: solve(p, r, a, diffrax.ForwardMode())))
    results = interleaved({
        "forward solve": lambda: value(p, r8, a8),
        "reverse (jax.grad)": lambda: reverse(p, r8, a8),
        "forward mode (jax.jacfwd, ForwardMode)": lambda: forward(p, r8, a8),
    }, repeats=REPEATS)
    base = results["forward solve"][0]
    rows = []
    for label, (timing, _) in results.items():
        rows.append(dict(mode=label, ratio=timing.wall / base.wall,
                         ratio_cpu=timing.cpu / base.cpu, compile=timing.compile))
        say(f"  plain diffrax script, {label}: {timing.wall / base.wall:.2f}x wall, "
            f"{timing.cpu / base.cpu:.2f}x CPU, compile {timing.compile:.1f} s")
    return rows


def why(results, scan) -> str:
    """The profile behind the cost ratios, from the profile rows."""
    threads = "; ".join(
        f"{q['name']}: " + ", ".join(f"{r['mode'].split(' (')[0]} {r['cpu'] / r['wall']:.1f}"
                                     for r in q["rows"][:3]) for q in results)
    parts = ["**Profile (ratios of CPU time, which does not "
             "depend on whether the second core is free).** CPU time / wall time in this run: "
             f"{threads}. XLA:CPU may run a solve on two threads (ratio ~2 when the second "
             "core is free, ~1 when other work holds it), and does so for some programs and "
             "not others, so wall-clock ratios move with the machine's load; CPU-time ratios "
             "measure the work."]
    for q in results:
        r = {row["mode"].split(" (")[0].split(",")[0]: row for row in q["rows"]}
        fwd7 = r["forward mode"]["ratio_cpu"]
        fwd1, fwd2 = (next(row for row in q["rows"] if tag in row["mode"])["ratio_cpu"]
                      for tag in ("1 tangent", "2 tangents"))
        rev = r["reverse"]["ratio_cpu"]
        through = r["reverse through the solve"]["ratio_cpu"]
        parts.append(
            f"{q['name']}: with the default adjoint both modes build the forward-mode "
            f"Jacobian in the seven fields, so jax.grad ({rev:.1f}x CPU) costs what jax.jacfwd "
            f"does ({fwd7:.1f}x): {fwd1:.1f}x for the dual-number solve with one tangent, "
            f"{fwd2:.1f}x with two"
            + (" (the seven-tangent program on two threads, CPU/wall "
               f"{r['forward mode']['cpu'] / r['forward mode']['wall']:.1f}: see the tangent "
               "scan)" if r["forward mode"]["cpu"] > 1.3 * r["forward mode"]["wall"] else "")
            + ". Reverse mode through the "
            f"solve's steps costs {through:.1f}x: its backward sweep through each step (the "
            "transposed Runge-Kutta stages, the watch, the controller) costs several times "
            "the step, and its checkpoints are not the cost (an earlier run with every step "
            "stored, 8192 checkpoints, cost as much as the default 1413).")
    parts.append(scan_text(scan))
    parts.append(
        "Both are the per-step bookkeeping of the solve (see the engine section's profile) "
        "carried through autodiff, with the same small-kernel overhead. The ratios are "
        "relative to the solve of the same quantity.")
    return " ".join(parts)


def scan_text(scan) -> str:
    """What the tangent scan shows: the cost of the one-thread and the two-thread programs."""
    rows = scan[1:]
    one = [r for r in rows if r["threads"] < 1.3]
    two = [r for r in rows if r["threads"] >= 1.3]
    text = ("**The tangent scan** (the table below: `jax.jacfwd` of sum(theta) in the first k "
            "fields, one program per k). ")
    if one:
        text += ("On one thread (CPU/wall < 1.3: " + ", ".join(r["k"] for r in one)
                 + f") the Jacobian costs {min(r['ratio_cpu'] for r in one):.2f}-"
                 f"{max(r['ratio_cpu'] for r in one):.2f}x the forward solve in CPU time. ")
    if two:
        text += ("On two threads (" + ", ".join(r["k"] for r in two)
                 + f") it costs {min(r['ratio_cpu'] for r in two):.2f}-"
                 f"{max(r['ratio_cpu'] for r in two):.2f}x in CPU time and "
                 f"{min(r['ratio'] for r in two):.2f}-{max(r['ratio'] for r in two):.2f}x in "
                 "wall time: slower by the clock too, not only in CPU. ")
    text += ("Which k lands on two threads is not monotone in k and moves with the program "
             "(on 2026-11-28, 201 saves: k = 3, 4, 6, 7 on two threads, k = 5 on one; 2001 "
             "saves: k = 5 on two, k = 7 on one). `perf record` of the seven-tangent program "
             "(2026-11-28) put 13-23% of the samples in the compiled kernels and the rest in "
             "XLA:CPU's thunk executor and its thread pool (ProcessCompletedOutEdges, the "
             "Eigen pool's PopBack and GlobalSteal, malloc): each loop body of these programs "
             "is a graph of ~20-70 small kernels that is not a chain, so XLA:CPU runs it with "
             "its concurrent executor, which hands half of its ready queue to a pool thread "
             "whenever more than 8 kernels are ready at once (`ThunkExecutor`, "
             "`ExecuteSession::kSplitThreshold = 8`); a loop that then runs on a pool thread "
             "goes on asynchronously, step after step. No XLA flag or compile option changes "
             "this in jaxlib 0.10 (tried: `xla_cpu_multi_thread_eigen`, "
             "`xla_cpu_enable_concurrency_optimized_scheduler`, tippejax's own CPU options, "
             "`PJRT_NPROC=1`). The saved-theta gradient's miss is this executor, not "
             "arithmetic: "
             + (f"the one-thread programs stay at or under {max(r['ratio_cpu'] for r in one):.1f}x"
                f" in CPU time, the two-thread ones from {min(r['ratio_cpu'] for r in two):.1f}x"
                if one and two else "see the table")
             + ". With diffrax's own stage loop "
        "(`TIPPEJAX_UNROLL_STAGES=diffrax`, same day, same scene) every k ran on one thread "
        "but the cost grew with k, to 5.8x at k = 7 (its transposed copy of the stages per "
        "tangent); with the stages written out (`=1`) 6-10x.")
    return text


def report(results, elapsed, plain, scan):
    # Both modes of the default adjoint, each ratio the better of wall and CPU (the second
    # core's load moves the wall clock); then the worst mode and quantity.
    worst_ratio = max(min(r["ratio"], r["ratio_cpu"]) for q in results for r in q["rows"][1:3])
    worst_compile = max(min(r["compile"], r["compile_cpu"]) for q in results
                        for r in q["rows"][1:3])
    worst_cpu = max(r["ratio_cpu"] for q in results for r in q["rows"][1:3])
    worst_reverse = max(min(q["rows"][1]["ratio"], q["rows"][1]["ratio_cpu"]) for q in results)
    worst_modes = max(max(q["rev_thr"].values()) for q in results)
    worst_through = max(min(r["ratio"], r["ratio_cpu"]) for q in results for r in q["rows"]
                        if r["mode"].startswith("reverse through"))
    worst_fd = max(max(max(q["rev_fd"].values()), max(q["fwd_fd"].values())) for q in results)
    lines = [
        "## gradients.py: derivatives through the solve",
        "",
        f"`python benchmarks/gradients.py` ({elapsed:.0f} s). Standard top, theta0 = 0.1, spin "
        f"150 rad/s, t1 = 20 s, full model, default solver (Dopri8); 1-minute load average "
        f"{LOAD[0]:.1f} at the start, {os.getloadavg()[0]:.1f} at the end (2 cores); "
        "derivatives with respect "
        "to all seven fields of the top. Timing at rtol 1e-8, atol 1e-10 (5 interleaved "
        "rounds after the compiling call); correctness at rtol 1e-12, atol 1e-14 (same "
        "compiled functions), central differences of relative step 1e-6.",
        "",
        "### Targets",
        "",
        "| target | measured | verdict |",
        "|---|---|---|",
        "| gradient cost <= 5x the forward solve | "
        + "; ".join(f"{q['name']}: " + ", ".join(
            f"{r['mode'].split(' ')[0]} {r['ratio']:.1f}x wall / {r['ratio_cpu']:.1f}x CPU"
            for r in q["rows"][1:3]) for q in results)
        + f" | {verdict(worst_ratio <= 5)} in both modes ({worst_ratio:.1f}x at worst, "
        f"the better of wall and CPU; reverse mode {worst_reverse:.1f}x)"
        + (f"; by the wall clock only: {worst_cpu:.1f}x in CPU time, where a program ran on "
           "two threads (see the tangent scan); the run on f6529b2 (2026-11-28): 5.7x"
           if worst_cpu > 1.3 * worst_ratio else "") + " |",
        "| (baseline) the same derivatives of a plain diffrax script | "
        + ", ".join(f"{r['mode'].split(' ')[0]} {r['ratio']:.1f}x wall / {r['ratio_cpu']:.1f}x "
                    f"CPU, compile {r['compile']:.1f} s" for r in plain[1:])
        + " | |",
        "| compile time of a gradient <= 10 s | "
        + "; ".join(f"{q['name']}: " + ", ".join(
            f"{r['mode'].split(' ')[0]} {r['compile']:.1f} s wall / {r['compile_cpu']:.1f} s CPU"
            for r in q["rows"][1:3]) for q in results)
        + f" | {verdict(worst_compile <= 10)} in both modes ({worst_compile:.1f} s at "
        "worst) |",
        "| (option) the reverse gradient compiled with `tj.compiler_options()`, against "
        "the default's run | " + "; ".join(
            f"{q['name']}: {q['rows'][-1]['wall'] / q['rows'][1]['wall']:.2f}x wall, "
            f"{q['rows'][-1]['cpu'] / q['rows'][1]['cpu']:.2f}x CPU" for q in results)
        + " (its first call in a fresh process: `compile_cache.py`) | |",
        "| (eager) the reverse gradient called without `jax.jit` (the solve's Jacobian a "
        "program of its own, with tippejax's options), against the solve | " + "; ".join(
            f"{q['name']}: " + ", ".join(
                f"{r['ratio']:.2f}x wall / {r['ratio_cpu']:.2f}x CPU, compile "
                f"{r['compile']:.1f} s" for r in q["rows"] if r["mode"] == EAGER)
            for q in results)
        + " (its first call in a fresh process: `compile_cache.py`) | |",
        f"| (before) reverse mode through the solve (RecursiveCheckpointAdjoint) | "
        f"{worst_through:.1f}x at worst | |",
        f"| default reverse mode == reverse mode through the solve | largest relative "
        f"difference {worst_modes:.1e} | {verdict(worst_modes < 1e-6)} |",
        f"| both match central differences | largest relative difference {worst_fd:.1e} | "
        f"{verdict(worst_fd < 1e-4)} |",
        "",
        why(results, scan),
        "",
    ]
    lines += ["### Profile: the Jacobian of sum(theta), 201 saves, in the first k fields", ""]
    lines.append(table(["tangents", "x forward solve (wall)", "x forward solve (CPU)",
                        "CPU / wall"],
                       [[r["k"], f"{r['ratio']:.2f}", f"{r['ratio_cpu']:.2f}",
                         f"{r['threads']:.2f}"] for r in scan]))
    lines += [""]
    for q in results:
        lines += [f"### {q['name']} (value at rtol 1e-12: {q['value']:.10g})", ""]
        lines.append(table(
            ["run", "median wall s", "x forward solve", "median CPU s", "x (CPU)",
             "first call s", "compile s (wall)", "compile s (CPU)"],
            [[r["mode"], f"{r['wall']:.3f}", f"{r['ratio']:.2f}", f"{r['cpu']:.3f}",
              f"{r['ratio_cpu']:.2f}", f"{r['first']:.1f}", f"{r['compile']:.1f}",
              f"{r['compile_cpu']:.1f}"] for r in q["rows"]]))
        lines += [""]
        lines.append(table(
            ["field", "reverse", "forward", "reverse through the solve", "central difference",
             "rel rev-through", "rel rev-FD", "rel fwd-FD"],
            [[f, f"{q['rev'][f]:+.8e}", f"{q['fwd'][f]:+.8e}", f"{q['through'][f]:+.8e}",
              f"{q['fd'][f]:+.8e}", f"{q['rev_thr'][f]:.1e}", f"{q['rev_fd'][f]:.1e}",
              f"{q['fwd_fd'][f]:.1e}"]
             for f in FIELDS]))
        lines += [""]
    return "\n".join(lines)


def main():
    start = time.perf_counter()
    say(machine_line())
    results = [measure(name, fn) for name, fn in QUANTITIES.items()]
    say("plain diffrax script (the baseline):")
    plain = plain_script()
    scan = tangent_scan()
    body = report(results, time.perf_counter() - start, plain, scan)
    write_section("gradients.py", body)
    say(f"done in {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
