"""peers.py's batch on one GPU: 1e4, 1e5 and 1e6 tops (issue 18, item 4).

The scene of `peers.py` and `shared_steps.py`: the standard top, theta0 0.1, N spins
linspace(140, 160, N) rad/s, 20 s, the SO(3) equations, summary mode (final state), float64,
rtol 1e-8 (atol 1e-10) for every run. The runs, each on the default JAX device:

- plain diffrax, vmap: `peers.plain_solve` (Dopri8, PIDController, no events) under `jax.vmap`;
- plain diffrax, shared steps: `peers.plain_shared_solve`, ONE solve whose state is the batch;
- `tj.simulate_batch(..., steps="per_member")` (the default) and `steps="shared"`, at the SO(3)
  and full levels, events on.

Each run is called once to compile (its time is the "first call"; JAX's monitoring events give
the part of it spent tracing, lowering and compiling) and then timed twice; at 1e6 members only
the goal's rows (so3 and the plain script, shared steps) are called again, the others' time
is their first call less its compilation, so that the script ends inside a device lease (a
run is skipped once `--budget` seconds have passed). Error: the largest over 256 evenly spaced members of
`peers.state_error` of the final state against the plain script at rtol 1e-12 on those
members (SO(3) rows; the full model's rows are compared with the full model's other path).
Throughput: `peers.flops_per_member_step()` (a lower bound on the arithmetic of one step of the
plain script) x steps x members / time, against the card's float64 peak.

    python benchmarks/gpu.py --out gpu.json [--sizes 10000,1000000,100000] [--budget 420]
                             [--rows 0,1]  # only these rows of ORDER (0,1: the goal's)
                             [--timed 2]   # timed calls of the goal's rows at 1e6
    python benchmarks/gpu.py --report gpu.json    # anywhere: RESULTS.md section from the JSON

The first form needs a GPU (`--allow-cpu` runs it on the CPU, for a dry run at small sizes);
the second writes the section "gpu.py" of benchmarks/RESULTS.md from its output.
"""

from __future__ import annotations

import json
import os
import statistics
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
RTOL, ATOL = 1e-8, 1e-10
REF_MEMBERS = 256
ORDER = ("tippejax so3, shared", "plain diffrax, shared steps",
         "plain diffrax, shared steps, unrolled", "tippejax so3, per member",
         "plain diffrax, vmap", "plain diffrax, vmap, unrolled", "tippejax full, shared",
         "tippejax full, per member", "tippejax so3, shared, unrolled",
         "tippejax so3, per member, unrolled")
UNROLLED = " unrolled"
"""Rows whose name ends so run Dopri8's stages written out (`tippejax._engine.unrolled`)."""
GOAL_ROWS = ("tippejax so3, shared", "plain diffrax, shared steps")
COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration",
                  "/jax/core/compile/jaxpr_to_mlir_module_duration",
                  "/jax/core/compile/backend_compile_duration")
FP64_PEAK = {"H100": 34e12, "H200": 34e12}  # vector (non-tensor) float64, vendor datasheets


def _arg(name, default):
    return sys.argv[sys.argv.index(name) + 1] if name in sys.argv else default


def measure(sizes, budget, out_path, rows=None, timed_1e6=2):
    import jax
    import jax.numpy as jnp
    import numpy as np

    sys.argv = sys.argv[:1]
    import peers  # the scene; enables float64

    import tippejax as tj

    start = time.perf_counter()
    device = jax.devices()[0]
    info = dict(device=str(getattr(device, "device_kind", device.platform)),
                platform=device.platform, jax=jax.__version__,
                diffrax=__import__("diffrax").__version__,
                equinox=__import__("equinox").__version__, rows=[], skipped=[], errors=[])
    try:
        info["flops_per_member_step"] = peers.flops_per_member_step()["step"]
    except Exception as e:  # cost analysis is a nicety
        info["flops_per_member_step"] = None
        info["errors"].append(f"flops: {e!r}")
    # JAX's own timings of tracing, lowering and compiling, summed over a first call
    compiling = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, secs, **_: compiling.append(secs) if event in COMPILE_EVENTS else None)
    top = tj.default_top()
    from tippejax._engine.unrolled import UnrolledERK

    unrolled = UnrolledERK(__import__("diffrax").Dopri8())
    plain_vmap = jax.jit(jax.vmap(lambda s: peers.plain_solve(s, RTOL, ATOL)))
    plain_shared = jax.jit(lambda s: peers.plain_shared_solve(s, RTOL, ATOL))
    plain_vmap_u = jax.jit(jax.vmap(lambda s: peers.plain_solve(s, RTOL, ATOL, solver=unrolled)))
    plain_shared_u = jax.jit(lambda s: peers.plain_shared_solve(s, RTOL, ATOL, solver=unrolled))
    reference = jax.jit(jax.vmap(lambda s: peers.plain_solve(s, 1e-12, 1e-14)[0]))

    def tj_run(model, steps, solver=None):
        def run(spins):
            sol = tj.simulate_batch(top, theta0=peers.THETA0, spin=spins, t1=peers.T1,
                                    model=model, summary=True, rtol=RTOL, atol=ATOL,
                                    grid=("spin",), steps=steps, solver=solver)
            final = jnp.concatenate([sol.states.axis[:, -1], sol.states.omega[:, -1]], axis=1)
            return final, sol.num_steps, sol
        return run

    runs = {
        "plain diffrax, vmap": lambda s: plain_vmap(jnp.asarray(s)),
        "plain diffrax, shared steps": lambda s: plain_shared(jnp.asarray(s)),
        "plain diffrax, vmap, unrolled": lambda s: plain_vmap_u(jnp.asarray(s)),
        "plain diffrax, shared steps, unrolled": lambda s: plain_shared_u(jnp.asarray(s)),
    }
    for model in ("so3", "full"):
        for steps in ("per_member", "shared"):
            runs[f"tippejax {model}, {steps.replace('_', ' ')}"] = tj_run(model, steps)
            runs[f"tippejax {model}, {steps.replace('_', ' ')}, unrolled"] = tj_run(
                model, steps, unrolled)

    def save():
        info["elapsed"] = time.perf_counter() - start
        if out_path:
            with open(out_path, "w") as f:
                json.dump(info, f, indent=1)

    for n in sizes:
        spins = np.linspace(140.0, 160.0, n)
        idx = np.unique(np.linspace(0, n - 1, REF_MEMBERS).round().astype(int))
        ref = None
        if time.perf_counter() - start < budget:
            ref = np.asarray(reference(jnp.asarray(spins[idx])))
        finals = {}
        for name in ORDER:
            if rows and name not in rows:
                continue
            if time.perf_counter() - start > budget:
                info["skipped"].append(f"{name}, N={n}")
                print(f"skipped (budget): {name}, N={n}", flush=True)
                continue
            fn = runs[name]
            try:
                compiling.clear()
                begin = time.perf_counter()
                out = jax.block_until_ready(fn(spins))
                first = time.perf_counter() - begin
                compile_s = sum(compiling)
                times = []
                goal = name.removesuffix("," + UNROLLED) in GOAL_ROWS
                calls = 2 if n < 10**6 else (timed_1e6 if goal else 0)
                for _ in range(calls):
                    begin = time.perf_counter()
                    out = jax.block_until_ready(fn(spins))
                    times.append(time.perf_counter() - begin)
                if not times:  # the first call less its tracing and compilation
                    times = [first - compile_s]
            except Exception as e:
                info["errors"].append(f"{name}, N={n}: {type(e).__name__}: {str(e)[:2000]}")
                save()
                if n == sizes[0]:  # fail fast: the first size is the smoke test
                    raise
                print(f"error: {name}, N={n}: {e!r}"[:3000], flush=True)
                continue
            final, steps = np.asarray(out[0]), np.asarray(out[1])
            finals[name] = final
            if len(out) > 2:  # only the members that ran to t1 (result code 0)
                finals[name] = np.where(np.asarray(out[2].result._value)[:, None] == 0,
                                        final, np.nan)
            row = dict(name=name, n=n, first=first, compile=compile_s, times=times,
                       timed_calls=calls,
                       per_top_us=1e6 * statistics.median(times) / n,
                       steps_max=int(steps.max()), steps_median=float(np.median(steps)),
                       finite=int(np.isfinite(final).all(axis=1).sum()))
            if len(out) > 2:
                codes = np.asarray(out[2].result._value)
                row["results"] = {str(int(c)): int((codes == c).sum()) for c in np.unique(codes)}
                row["inverted"] = int(np.isfinite(np.asarray(out[2].t_invert)).sum())
            if ref is not None and "full" not in name:
                row["error"] = max(peers.state_error(final[i], r) for i, r in zip(idx, ref))
            if "full" in name and name.endswith("per member") and "tippejax full, shared" in finals:
                a, b = finals["tippejax full, shared"], finals[name]
                both = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
                row["full_paths_diff"] = float(np.max(np.abs(a - b)[both] / np.maximum(
                    1.0, np.abs(b[both])), initial=0.0))
            if info["flops_per_member_step"]:
                # the steps every member takes in a lock-step batch: the most any member takes
                work = info["flops_per_member_step"] * row["steps_max"] * n
                row["gflops"] = work / statistics.median(times) / 1e9
            info["rows"].append(row)
            print(json.dumps(row), flush=True)
            save()
    save()
    return info


def report(paths):
    """The section from the first JSON; the goal's rows of each further JSON (another card,
    `--rows 0,1`) are added as lines."""
    sys.path.insert(0, HERE)
    from _common import table, write_section

    infos = []
    for path in paths.split(","):
        with open(path) as f:
            infos.append(json.load(f))
    info = infos[0]
    peak = next((v for k, v in FP64_PEAK.items() if k in info["device"]), None)
    by = {(r["n"], r["name"]): r for r in info["rows"]}
    sizes = sorted({r["n"] for r in info["rows"]})
    lines = [
        "## gpu.py: peers.py's batch on one GPU",
        "",
        f"`python benchmarks/gpu.py --out gpu.json` on {info['device']} (jax {info['jax']}, "
        f"diffrax {info['diffrax']}, equinox {info['equinox']}), {info['elapsed']:.0f} s; "
        "section written by `--report`. Scene of peers.py: standard top, theta0 0.1, N spins "
        "140-160 rad/s, 20 s, SO(3) equations, summary mode, float64, rtol 1e-8 (atol 1e-10) "
        "for every run. Time: the median of 2 timed calls after a compiling call (at 1e6 "
        "members, rows other than the goal's: the first call less JAX's own tracing and "
        "compiling time); first call s: with compilation (compile s: JAX's part of it); error: largest over 256 evenly spaced members against "
        "the plain script at rtol 1e-12 (SO(3) rows). GFLOP/s: a lower bound on the plain "
        "script's arithmetic per member-step ("
        + (f"{info['flops_per_member_step']:.0f} flop" if info["flops_per_member_step"]
           else "n/a")
        + ") x the largest member's steps x N / time"
        + (f", against the card's float64 vector peak {peak / 1e12:.0f} TFLOP/s" if peak else "")
        + ".",
        "",
    ]
    if info.get("note"):
        lines += [info["note"], ""]
    for other in infos:
        rows_of = {(r["n"], r["name"]): r for r in other["rows"]}
        goal = rows_of.get((10**6, "tippejax so3, shared"))
        plain = rows_of.get((10**6, "plain diffrax, shared steps"))
        if goal:
            total = statistics.median(goal["times"])
            card = "an H100" if "H100" in other["device"] else "another card than the goal's"
            lines += [
                f"Goal (1e6 tops x 20 s in float64 within 20 s on one H100): tippejax so3 with "
                f"`steps=\"shared\"` {total:.1f} s on {other['device']} ("
                + ("met" if total <= 20 else "missed") + f" on {card}; first call with "
                f"compilation {goal['first']:.1f} s"
                + (f"; the plain shared-step script {statistics.median(plain['times']):.1f} s, "
                   f"{total / statistics.median(plain['times']):.2f}x" if plain else "")
                + (f"; {other['note']}" if other is not info and other.get("note") else "")
                + ").", ""]
    rows = []
    for n in sizes:
        plain = by.get((n, "plain diffrax, vmap"))
        for name in ORDER:
            r = by.get((n, name))
            if r is None:
                continue
            t = statistics.median(r["times"])
            rows.append([
                f"{n:,}", name, f"{t:.2f}", f"{r['per_top_us']:.2f}",
                f"{t / statistics.median(plain['times']):.2f}" if plain else "",
                f"{r['first']:.1f}", f"{r.get('compile', float('nan')):.1f}",
                f"{r['steps_max']}",
                f"{r['error']:.1e}" if "error" in r else
                (f"paths {r['full_paths_diff']:.1e}" if "full_paths_diff" in r else ""),
                f"{r['gflops']:.0f}" if "gflops" in r else "",
                f"{r['finite']}/{n}",
                # RESULTS.contact_lost (code 2): the full model's R_n reaches 0 (fast spins)
                str(r["results"].get("2", 0)) if "results" in r else ""])
    lines.append(table(["N", "run", "s (median)", "us per top", "x plain vmap",
                        "first call s", "compile s", "steps (max)", "error", "GFLOP/s", "finite",
                        "contact lost"], rows))
    for key in ("skipped", "errors"):
        if info[key]:
            lines += ["", f"{key.capitalize()}: " + "; ".join(info[key])]
    lines.append("")
    write_section("gpu.py", "\n".join(lines))
    print("\n".join(lines))


def main():
    if "--report" in sys.argv:
        report(_arg("--report", None))
        return
    sys.path.insert(0, HERE)
    os.environ.setdefault("TIPPEJAX_HOST_DEVICES", "1")
    import jax

    if jax.devices()[0].platform == "cpu" and "--allow-cpu" not in sys.argv:
        sys.exit("gpu.py: no GPU here (jax.devices() is CPU); --allow-cpu for a dry run.")
    sizes = [int(float(x)) for x in _arg("--sizes", "10000,1000000,100000").split(",")]
    rows = _arg("--rows", None)
    if rows is not None:
        rows = [ORDER[int(i)] for i in rows.split(",")]
    measure(sizes, float(_arg("--budget", "420")), _arg("--out", None), rows,
            int(_arg("--timed", "2")))


if __name__ == "__main__":
    main()
