"""First call in a fresh process, with and without the persistent compilation cache.

Each case runs in its own new Python process, three times: with the cache off
(`TIPPEJAX_COMPILATION_CACHE=0`), with an empty cache directory (cold: compiles and stores), and
again with that directory (warm: a second process on the same machine). Reported per case: the
import, the first call (trace + compile or cache load + run) and a second call in the same
process (the run alone, already compiled); "first - second" is what a new process pays on top
of the run.

Cases: `simulate` (default top, theta0 = 0.1, 100 rad/s, 10 s, default save grid; the full
model, and `simulate:<level>` the same call at each other level: issue 18's "compilation at
most 2 s per level"), `grad` of
`t_invert` over an 8 s summary run (reverse mode; called eagerly, in `jax.jit`, and in `jax.jit`
with `tj.compiler_options()`), `fit` (`tj.fit` on a 120-sample synthetic
record, mu, eps and spin free, from a guess 20-30% off, `strategy="plain"`, 5 optimiser steps:
the compilations of a fit with less of its run time), and a `saveat` of a new length in a
warm process (same bucket, other bucket).

    python benchmarks/compile_cache.py          # writes its section of benchmarks/RESULTS.md
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import machine_line, table, write_section  # noqa: E402

LEVELS = ("so3", "routhian", "gyroscopic")  # besides the default call's full model

CASE = r"""
import json, sys, time
t = time.perf_counter()
import jax, numpy as np
import tippejax as tj
t_import = time.perf_counter() - t
case = sys.argv[1]
top = tj.default_top()

def block(x):
    return jax.block_until_ready(x)

if case.startswith("simulate"):
    model = case.partition(":")[2] or "full"
    y0 = tj.initial_state(top, 0.1, 100.0)
    call = lambda: block(tj.simulate(top, y0, 10.0, model=model).theta)
elif case == "grad" or case.startswith("jit(grad)"):
    y0 = tj.initial_state(top, 0.1, 100.0)
    g = lambda top: tj.simulate(top, y0, 8.0, summary=True).t_invert
    if case == "grad":
        gradient = jax.grad(g)  # eager
    else:
        options = tj.compiler_options() if case.endswith("options") else None
        gradient = jax.jit(jax.grad(g), compiler_options=options)
    call = lambda: block(gradient(top))
elif case == "fit":
    ts = np.linspace(0.0, 6.0, 120)
    truth = tj.simulate(top, tj.initial_state(top, 0.1, 120.0), 6.0, saveat=ts)
    theta_obs = np.asarray(truth.theta) + 0.002 * np.random.default_rng(0).normal(size=ts.size)
    guess = top.replace(mu=0.38, eps_over_R=0.24)
    y_guess = tj.initial_state(guess, 0.1, 100.0)
    call = lambda: block(tj.fit(guess, y_guess, ts, theta_obs, free=("mu", "eps", "spin"),
                                strategy="plain", max_steps=5).top.mu)
elif case == "saveat":
    y0 = tj.initial_state(top, 0.1, 100.0)
    block(tj.simulate(top, y0, 10.0, saveat=np.linspace(0, 10, 100)).theta)  # bucket 128
    t = time.perf_counter()
    block(tj.simulate(top, y0, 10.0, saveat=np.linspace(0, 10, 120)).theta)  # same bucket
    same = time.perf_counter() - t
    t = time.perf_counter()
    block(tj.simulate(top, y0, 10.0, saveat=np.linspace(0, 10, 300)).theta)  # bucket 512
    other = time.perf_counter() - t
    t = time.perf_counter()
    block(tj.simulate(top, y0, 10.0, saveat=np.linspace(0, 10, 310)).theta)  # compiled: run only
    run = time.perf_counter() - t
    print(json.dumps(dict(import_s=t_import, first_s=same, second_s=run, other_s=other)))
    sys.exit(0)
t = time.perf_counter(); call(); first = time.perf_counter() - t
t = time.perf_counter(); call(); second = time.perf_counter() - t
print(json.dumps(dict(import_s=t_import, first_s=first, second_s=second)))
"""


def run(case: str, mode: str, cache_dir: str) -> dict:
    env = dict(os.environ)
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    env["TIPPEJAX_COMPILATION_CACHE"] = "0" if mode == "off" else cache_dir
    out = subprocess.run([sys.executable, "-c", CASE, case], env=env, capture_output=True,
                         text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main() -> None:
    rows, results = [], {}
    for case in ("simulate", *(f"simulate:{m}" for m in LEVELS), "grad", "jit(grad)",
                 "jit(grad), options", "fit"):
        with tempfile.TemporaryDirectory() as cache_dir:
            for mode in ("off", "cold", "warm"):
                r = run(case, mode, cache_dir)
                results[(case, mode)] = r
                print(case, mode, {k: round(v, 2) for k, v in r.items()}, flush=True)
                rows.append([case, mode, f"{r['import_s']:.1f}", f"{r['first_s']:.2f}",
                             f"{r['second_s']:.2f}", f"{r['first_s'] - r['second_s']:.2f}"])
    with tempfile.TemporaryDirectory() as cache_dir:
        run("simulate", "cold", cache_dir)
        r = run("saveat", "warm", cache_dir)
        print("saveat", {k: round(v, 2) for k, v in r.items()}, flush=True)
    warm_sim = results[("simulate", "warm")]["first_s"]
    per_level = {m: results[(f"simulate:{m}" if m != "full" else "simulate", "warm")]
                 for m in ("full", *LEVELS)}
    warm_fit = results[("fit", "warm")]["first_s"]
    body = "\n".join([
        "## Compilation cache: the first call in a fresh process (`benchmarks/compile_cache.py`)",
        "",
        machine_line(),
        "",
        "Each row is a new Python process. off: `TIPPEJAX_COMPILATION_CACHE=0`; cold: an empty "
        "cache directory (compiles and stores); warm: a second process with that directory. "
        "first: the first call (trace, compile or load, run); second: the same call again in "
        "that process (run only); first - second: what a new process pays for compiling. "
        "A warm process loads both the XLA programs (JAX's persistent cache) and the traced "
        "programs of `simulate`, `fit` and an eager gradient's Jacobian of the solve "
        "(`jax.export`, `tippejax/_cache.py`); a gradient in `jax.jit` is traced again (the "
        "differentiated function is the caller's). `grad`: `jax.grad` of "
        "`t_invert` (8 s summary run) called eagerly; `jit(grad)`: the same in `jax.jit` with "
        "XLA's default options; `jit(grad), options`: with "
        "`compiler_options=tj.compiler_options()`.",
        "",
        table(["case", "cache", "import (s)", "first call (s)", "second call (s)",
               "first - second (s)"], rows),
        "",
        f"Targets: warm simulate < 1 s: {warm_sim:.2f} s; warm fit < 3 s: {warm_fit:.2f} s. "
        "Issue 18, compilation at most 2 s per level where JAX can cache it (first call less "
        "the second, warm cache): " + ", ".join(
            f"{m} {r['first_s'] - r['second_s']:.2f} s" for m, r in per_level.items())
        + " (" + ("met" if all(r["first_s"] - r["second_s"] <= 2 for r in per_level.values())
                  else "missed") + "); with no cache (off rows) it is the compile itself. "
        "Issue 18, a gradient compiled in at most 10 s (first call less the second): "
        + "; ".join(f"{case} " + ", ".join(
            f"{mode} {results[(case, mode)]['first_s'] - results[(case, mode)]['second_s']:.2f} s"
            for mode in ("off", "cold", "warm"))
            for case in ("grad", "jit(grad)", "jit(grad), options")) + ".",
        "",
        "A save grid of a new length in a warm process (cache warm for the default grid): "
        f"{r['first_s']:.2f} s for a length in an already compiled bucket (120 after 100, both "
        f"padded to 128), {r['other_s']:.2f} s for a new bucket (300 -> 512, compiled), against "
        f"{r['second_s']:.2f} s for the run itself (310, same bucket as 300).",
    ])
    write_section("compile_cache.py", body)
    print(body)


if __name__ == "__main__":
    main()
