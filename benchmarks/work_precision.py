"""Work-precision of the solvers: error against a tight reference vs median wall time.

Scenes (each error is measured against a tight reference of the same model level):

1. full model, standard top, theta0 = 0.1, spin 100 rad/s (inverts at ~5.70 s), t1 = 8 s,
   801 save points: Tsit5, Dopri8, Kvaerno5 at rtol 1e-4 ... 1e-10 (atol = rtol * 1e-2) against
   Dopri8 at rtol 1e-13, atol 1e-15. Errors: max |theta - theta_ref| over the save times, and
   |t_invert - t_invert_ref|. The same scene in float32 (Tsit5, rtol 1e-4 and 1e-5).
2. Routhian level vs SO(3) level (same physics), theta0 = 0.6, spin 60, t1 = 3 s, Tsit5, against
   SO(3) Dopri8 at rtol 1e-13.
3. stiff friction, mu = 300 s/m: Tsit5 vs Kvaerno5, t1 = 1 s, against Kvaerno5 at rtol 1e-11.
4. batch throughput and sharding (`batch_scaling.py`).

Every measured function is one `eqx.filter_jit` (with `eqx.debug.assert_max_traces`), taking the
tolerances as arrays so that one compilation serves all of them (float32 excepted: `simulate`
raises its rtol with a Python `max`, so there they are static). Wall time is the median of
`REPEATS` runs after a first call, with `block_until_ready`; compile time is the first call less
that median. Writes benchmarks/RESULTS.md and benchmarks/work_precision.png.

    PYTHONPATH=. python benchmarks/work_precision.py
"""

from __future__ import annotations

import os
import pathlib
import platform
import statistics
import sys
import time

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import tippejax as tj

sys.path.insert(0, str(pathlib.Path(__file__).parent))
import batch_scaling  # noqa: E402

HERE = pathlib.Path(__file__).parent
REPEATS = 3
RTOLS = (1e-4, 1e-6, 1e-8, 1e-10)
RTOLS_F32 = (1e-4, 1e-5)
RTOLS_STIFF = (1e-4, 1e-6, 1e-8)
MAX_STEPS = 1_000_000
SOLVERS = {"Tsit5": diffrax.Tsit5, "Dopri8": diffrax.Dopri8, "Kvaerno5": diffrax.Kvaerno5}
COMPILE = {}


def make_run(model, solver, n_save, *, rtol=None):
    """One jit of `tj.simulate` for a model and solver; t1, save times, tolerances are inputs."""

    def run(top, y0, t1, ts, rtol_, atol_):
        return tj.simulate(
            top, y0, t1, model=model, saveat=ts, rtol=rtol_, atol=atol_, solver=solver,
            max_steps=MAX_STEPS, throw=False,
        )

    if rtol is not None:  # float32: static tolerances

        def run_static(top, y0, t1, ts):
            return run(top, y0, t1, ts, rtol, rtol * 1e-2)

        return eqx.filter_jit(eqx.debug.assert_max_traces(run_static, max_traces=1))
    return eqx.filter_jit(eqx.debug.assert_max_traces(run, max_traces=1))


def timed(name, fn, *args):
    """Median wall time of `fn(*args)`; the first call of `name` is charged to compilation."""
    start = time.perf_counter()
    sol = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    times = []
    for _ in range(REPEATS):
        start = time.perf_counter()
        sol = jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    median = statistics.median(times)
    COMPILE.setdefault(name, first - median)
    return sol, median


def errors(sol, ref):
    theta, theta_ref = np.asarray(sol.theta, float), np.asarray(ref.theta, float)
    both = np.isfinite(theta) & np.isfinite(theta_ref)
    theta_err = float(np.max(np.abs(theta[both] - theta_ref[both]))) if both.any() else np.nan
    return theta_err, abs(float(sol.t_invert) - float(ref.t_invert))


def sweep(label, fn, top, y0, t1, ts, ref, rtols):
    rows = []
    for rtol in rtols:
        sol, median = timed(label, fn, top, y0, t1, ts, jnp.asarray(rtol), jnp.asarray(rtol * 1e-2))
        theta_err, t_inv_err = errors(sol, ref)
        rows.append(row(label, rtol, sol, median, theta_err, t_inv_err))
    return rows


def row(label, rtol, sol, median, theta_err, t_inv_err):
    print(
        f"{label:22s} rtol={rtol:.0e} time={median:.4f}s steps={int(sol.num_steps)} "
        f"theta_err={theta_err:.2e} t_inv_err={t_inv_err:.2e} result={int(sol.result._value)}",
        flush=True,
    )
    return dict(
        label=label, rtol=rtol, time=median, steps=int(sol.num_steps), theta_err=theta_err,
        t_inv_err=t_inv_err, result=tj.RESULTS._index_to_message[int(sol.result._value)] or "ok",
    )


def full_model():
    top = tj.default_top()
    y0 = tj.initial_state(top, 0.1, 100.0)
    t1, ts = jnp.asarray(8.0), jnp.linspace(0.0, 8.0, 801)
    # float32 first: compiled after the float64 Dopri8/Kvaerno5 runs, the float32 trace failed
    # once inside diffrax's event code (cond branches float32 vs float64; see RESULTS.md).
    top32 = top.astype(jnp.float32)
    y32 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), y0)
    ts32, t1_32 = ts.astype(jnp.float32), jnp.asarray(8.0, jnp.float32)
    runs32 = []
    for rtol in RTOLS_F32:
        fn = make_run("full", diffrax.Tsit5(), 801, rtol=rtol)
        runs32.append((rtol, *timed(f"Tsit5 float32 {rtol:.0e}", fn, top32, y32, t1_32, ts32)))
    runs = {name: make_run("full", cls(), 801) for name, cls in SOLVERS.items()}
    ref, _ = timed("Dopri8", runs["Dopri8"], top, y0, t1, ts, jnp.asarray(1e-13), jnp.asarray(1e-15))
    print(f"reference t_invert = {float(ref.t_invert):.9f} s, steps {int(ref.num_steps)}")
    rows = []
    for name, fn in runs.items():
        rows += sweep(name, fn, top, y0, t1, ts, ref, RTOLS)
    for rtol, sol, median in runs32:
        rows.append(row("Tsit5 float32", rtol, sol, median, *errors(sol, ref)))
    return ref, rows


def routhian_vs_so3():
    top = tj.default_top()
    y0 = tj.initial_state(top, 0.6, 60.0)
    t1, ts = jnp.asarray(3.0), jnp.linspace(0.0, 3.0, 301)
    ref_fn = make_run("so3", diffrax.Dopri8(), 301)
    ref, _ = timed("SO(3) Dopri8", ref_fn, top, y0, t1, ts, jnp.asarray(1e-13), jnp.asarray(1e-15))
    rows = []
    for label, model in (("Routhian Tsit5", "routhian"), ("SO(3) Tsit5", "so3")):
        fn = make_run(model, diffrax.Tsit5(), 301)
        rows += sweep(label, fn, top, y0, t1, ts, ref, RTOLS)
    return ref, rows


def stiff():
    top = tj.TippeTop.from_ratios(0.9, 0.3, mu=300.0)
    y0 = tj.initial_state(top, 0.1, 100.0)
    t1, ts = jnp.asarray(1.0), jnp.linspace(0.0, 1.0, 801)
    print(f"stiff: friction rate {float(tj.friction_rate(top)):.0f}/s, default "
          f"{type(tj.default_solver(top)).__name__}")
    # Same shapes as the full-model scene, so these reuse its compilations.
    runs = {name: make_run("full", SOLVERS[name](), 801) for name in ("Tsit5", "Kvaerno5")}
    ref, _ = timed("stiff Kvaerno5", runs["Kvaerno5"], top, y0, t1, ts, jnp.asarray(1e-11),
                   jnp.asarray(1e-13))
    rows = []
    for name, fn in runs.items():
        rows += sweep(f"stiff {name}", fn, top, y0, t1, ts, ref, RTOLS_STIFF)
    return ref, rows


STYLE = {
    "Tsit5": dict(color="C0", marker="o"),
    "Dopri8": dict(color="C1", marker="s"),
    "Kvaerno5": dict(color="C2", marker="^"),
    "Tsit5 float32": dict(color="C3", marker="*", markersize=14, linestyle="none"),
    "Routhian Tsit5": dict(color="C4", marker="D"),
    "SO(3) Tsit5": dict(color="C0", marker="o"),
    "stiff Tsit5": dict(color="C0", marker="o"),
    "stiff Kvaerno5": dict(color="C2", marker="^"),
}


def plot_panel(ax, rows, labels, key, title, ylabel):
    for label in labels:
        sel = [r for r in rows if r["label"] == label]
        x = np.array([r["time"] for r in sel])
        y = np.maximum(np.array([r[key] for r in sel]), 1e-16)
        ax.loglog(x, y, label=label, **{"markersize": 7, **STYLE[label]})
        for r, xi, yi in zip(sel, x, y):
            ax.annotate(f"{r['rtol']:.0e}", (xi, yi), fontsize=7, xytext=(4, 3),
                        textcoords="offset points", color=STYLE[label]["color"])
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("median wall time per run (s, CPU, indicative)")
    ax.set_ylabel(ylabel)
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(fontsize=8)


def plot(rows_full, rows_level, rows_stiff):
    fig, axes = plt.subplots(2, 2, figsize=(13, 10), constrained_layout=True)
    full = ("Tsit5", "Dopri8", "Kvaerno5", "Tsit5 float32")
    plot_panel(axes[0, 0], rows_full, full, "theta_err",
               "Full model, theta0=0.1, n=100, t1=8 s: error in theta(t)",
               "max |theta - theta_ref| (rad)")
    plot_panel(axes[0, 1], rows_full, full, "t_inv_err",
               "Full model: error in the inversion time (ref 5.7005 s)",
               "|t_invert - t_invert_ref| (s)")
    plot_panel(axes[1, 0], rows_level, ("Routhian Tsit5", "SO(3) Tsit5"), "theta_err",
               "Routhian vs SO(3) level, theta0=0.6, n=60, t1=3 s (ref SO(3) Dopri8)",
               "max |theta - theta_ref| (rad)")
    plot_panel(axes[1, 1], rows_stiff, ("stiff Tsit5", "stiff Kvaerno5"), "theta_err",
               "Stiff friction mu=300 s/m, t1=1 s (ref Kvaerno5 rtol 1e-11)",
               "max |theta - theta_ref| (rad)")
    fig.suptitle("tippejax work-precision (labels: rtol; atol = rtol*1e-2)", fontsize=12)
    fig.savefig(HERE / "work_precision.png", dpi=110)


def table(rows, columns=("label", "rtol", "time", "ratio", "steps", "theta_err", "t_inv_err", "result")):
    heads = dict(label="run", rtol="rtol", time="median s", ratio="time / ref-solver",
                 steps="steps", theta_err="max |d theta| (rad)", t_inv_err="|d t_invert| (s)",
                 result="result")
    lines = ["| " + " | ".join(heads[c] for c in columns) + " |",
             "|" + "---|" * len(columns)]
    for r in rows:
        cells = []
        for c in columns:
            v = r.get(c, "")
            if v == "":
                cells.append("")
            elif c in ("rtol", "theta_err", "t_inv_err"):
                cells.append(f"{v:.1e}")
            elif c == "time":
                cells.append(f"{v:.4f}")
            elif c == "ratio":
                cells.append(f"{v:.2f}")
            else:
                cells.append(str(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def add_ratios(rows, base_label):
    base = {r["rtol"]: r["time"] for r in rows if r["label"] == base_label}
    for r in rows:
        if r["rtol"] in base:
            r["ratio"] = r["time"] / base[r["rtol"]]


def main():
    start = time.perf_counter()
    ref_full, rows_full = full_model()
    _, rows_level = routhian_vs_so3()
    ref_stiff, rows_stiff = stiff()
    batch = dict(unsharded=batch_scaling.unsharded(), sharded=batch_scaling.sharded_in_subprocess())
    plot(rows_full, rows_level, rows_stiff)
    add_ratios(rows_full, "Tsit5")
    add_ratios(rows_level, "SO(3) Tsit5")
    add_ratios(rows_stiff, "stiff Kvaerno5")
    total = time.perf_counter() - start
    write_results(ref_full, rows_full, rows_level, ref_stiff, rows_stiff, batch, total)
    print(f"total {total:.0f} s")


def write_results(ref_full, rows_full, rows_level, ref_stiff, rows_stiff, batch, total):
    un, sh = batch["unsharded"], batch["sharded"]
    single = un[0]["kernel_median_s"]
    batch_lines = [
        "| launches | kernel median s | per launch s | per-launch ratio to 1 | kernel compile s |"
        " simulate_batch median s (per call) |",
        "|---|---|---|---|---|---|",
    ]
    for r in un:
        per = r["kernel_median_s"] / r["n"]
        batch_lines.append(
            f"| {r['n']} | {r['kernel_median_s']:.3f} | {per:.4f} | {per / single:.2f} | "
            f"{r['kernel_compile_s']:.1f} | {r['public_median_s']:.2f} |"
        )
    if "error" in sh:
        shard_text = f"The sharded subprocess failed:\n\n```\n{sh['error']}\n```"
    else:
        shard_text = (
            f"Devices: {', '.join(sh['devices'])}. Batch of 32, median of {REPEATS}:\n\n"
            "| | unsharded s | sharded s | sharded / unsharded |\n|---|---|---|---|\n"
            f"| kernel (compiled once) | {sh['kernel_unsharded_s']:.3f} | "
            f"{sh['kernel_sharded_s']:.3f} | "
            f"{sh['kernel_sharded_s'] / sh['kernel_unsharded_s']:.2f} |\n"
            f"| `simulate_batch` (per call) | {sh['public_unsharded_s']:.2f} | "
            f"{sh['public_sharded_s']:.2f} | "
            f"{sh['public_sharded_s'] / sh['public_unsharded_s']:.2f} |"
        )
    compile_lines = ["| function | first call less median (s) |", "|---|---|"]
    compile_lines += [f"| {k} | {v:.1f} |" for k, v in COMPILE.items()]
    machine = (
        f"- processor: `{platform.processor() or platform.machine()}`, "
        f"{os.cpu_count()} cores; `{platform.platform()}`\n"
        f"- jax {jax.__version__}, diffrax {diffrax.__version__}, "
        f"devices `{jax.devices()}`\n- python {platform.python_version()}"
    )
    text = TEMPLATE.format(
        machine=machine,
        total=total,
        t_invert_ref=float(ref_full.t_invert),
        stiff_ref_steps=int(ref_stiff.num_steps),
        full=table(rows_full),
        level=table(rows_level),
        stiff=table(rows_stiff),
        batch="\n".join(batch_lines),
        shard=shard_text,
        compile="\n".join(compile_lines),
        repeats=REPEATS,
        discussion=DISCUSSION,
    )
    HERE.joinpath("RESULTS.md").write_text(text)


DISCUSSION = "(What the numbers show: written by hand after the run; see the committed RESULTS.md.)"

TEMPLATE = """# Benchmark results: work-precision and batch throughput

Made by `PYTHONPATH=. python benchmarks/work_precision.py` (with `benchmarks/batch_scaling.py`),
in {total:.0f} s. Machine:

{machine}

The machine is shared (2 cores) and noisy: absolute CPU times below are indicative only; compare
ratios and medians (each time is the median of {repeats} runs after a first, compiling call, with
`block_until_ready`). Chart: `work_precision.png`.

{discussion}

## 1. Full model: standard top, theta0 = 0.1, spin 100 rad/s, t1 = 8 s, 801 save points

Reference: Dopri8, rtol 1e-13, atol 1e-15 (t_invert = {t_invert_ref:.9f} s). atol = rtol * 1e-2.
"time / ref-solver" is the median time over Tsit5's at the same rtol. float32 rows: the same scene
with `top.astype(jnp.float32)` and a float32 state, error against the float64 reference (simulate
raises the float32 atol to 1e-7).

{full}

## Routhian level vs SO(3) level: theta0 = 0.6, spin 60 rad/s, t1 = 3 s, Tsit5

Reference: SO(3) level, Dopri8 rtol 1e-13. Ratio: time over SO(3) Tsit5 at the same rtol.
No inversion in 3 s, so no t_invert error (nan).

{level}

## 3. Stiff friction: mu = 300 s/m (A/C = 0.9, eps/R = 0.3), theta0 = 0.1, spin 100, t1 = 1 s

Reference: Kvaerno5 rtol 1e-11, atol 1e-13 ({stiff_ref_steps} steps). Ratio: time over Kvaerno5
at the same rtol. max_steps = 1,000,000, throw=False.

{stiff}

## 4. Batch throughput (t1 = 2 s, 201 save points, spin 100, theta0 in [0.1, 0.3], Tsit5)

"kernel": `jax.vmap` of `tj.simulate` under one `eqx.filter_jit`, compiled once.
"simulate_batch": the public function, median of {repeats} calls after a first call.

{batch}

### Sharding over 2 forced host devices (subprocess, `XLA_FLAGS=--xla_force_host_platform_device_count=2`)

{shard}

## Compile times (first call less the median run; indicative)

{compile}
"""


if __name__ == "__main__":
    main()
