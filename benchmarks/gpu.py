"""gpu: the batch of `speed.py` (the scene of `_peers.py`, rtol 1e-8) on one GPU, 1e4 to 1e6
tops: the plain script (vmap, shared steps) against `tj.simulate_batch`. A compiling call, then
two timed ones (at 1e6 only the goal's rows); runs past `--budget` seconds are skipped.

    python benchmarks/gpu.py --ladder --out gpu.json   # on the GPU machine
    python benchmarks/gpu.py --report gpu.json         # anywhere: its block of RESULTS.md
"""

from __future__ import annotations

import json
import os
import statistics
import time

import _harness as h

RTOL, ATOL, REF_MEMBERS = 1e-8, 1e-10, 256
ORDER = (
    "tippejax so3, shared",
    "plain diffrax, shared steps",
    "plain diffrax, shared steps, unrolled",
    "tippejax so3, per member",
    "plain diffrax, vmap",
    "plain diffrax, vmap, unrolled",
    "tippejax full, shared",
    "tippejax full, per member",
)
GOAL = ("tippejax so3, shared", "plain diffrax, shared steps")
COMPILE_EVENTS = (
    "/jax/core/compile/jaxpr_trace_duration",
    "/jax/core/compile/jaxpr_to_mlir_module_duration",
    "/jax/core/compile/backend_compile_duration",
)


def runs():
    """{row: run(spins) -> (finals, steps, solution or None)}."""
    import _peers as p
    import diffrax
    import jax
    import jax.numpy as jnp

    import tippejax as tj

    # Past the public API: the plain script with Dopri8's stages written out as tippejax's engine
    # writes them on accelerators (an engine internal, no public solver) is the strongest peer.
    from tippejax._engine.unrolled import UnrolledERK

    out = {}
    for suffix, solver in (("", None), (", unrolled", UnrolledERK(diffrax.Dopri8()))):
        vmapped = jax.jit(
            jax.vmap(lambda s, solver=solver: p.plain_solve(s, RTOL, ATOL, solver=solver))
        )
        shared = jax.jit(lambda s, solver=solver: p.plain_shared(s, RTOL, ATOL, solver=solver))
        out[f"plain diffrax, vmap{suffix}"] = lambda s, f=vmapped: (*f(jnp.asarray(s)), None)
        out[f"plain diffrax, shared steps{suffix}"] = lambda s, f=shared: (*f(jnp.asarray(s)), None)
    for model in ("so3", "full"):
        for steps in ("per_member", "shared"):

            def run(s, model=model, steps=steps):
                kw = dict(model=model, summary=True, rtol=RTOL, atol=ATOL, steps=steps)
                sol = tj.simulate_batch(p.TOP, p.THETA0, s, p.T1, grid=("spin",), **kw)
                axis, omega = sol.states.axis, sol.states.omega  # summary: (N, 3), or (N, 1, 3)
                axis, omega = (x[:, -1] if x.ndim == 3 else x for x in (axis, omega))
                return jnp.concatenate([axis, omega], axis=1), sol.num_steps, sol

            out[f"tippejax {model}, {steps.replace('_', ' ')}"] = run
    return out, jax.jit(jax.vmap(lambda s: p.plain_solve(s, 1e-12, 1e-14)[0]))


def ladder(args):
    import _peers as p
    import jax
    import numpy as np

    import tippejax as tj

    if jax.devices()[0].platform == "cpu" and not (args.allow_cpu or args.smoke):
        raise SystemExit("gpu.py: no GPU here (jax.devices() is CPU); --allow-cpu for a dry run")
    sizes = [64, 128] if args.smoke else [int(float(x)) for x in args.sizes.split(",")]
    rows = [ORDER[int(i)] for i in args.rows.split(",")] if args.rows else ORDER
    start, device = time.perf_counter(), jax.devices()[0]
    info = dict(device=str(getattr(device, "device_kind", device.platform)), rows=[], skipped=[])
    info.update(machine=h.machine_line(), command=h.command(args), errors=[])
    compiling = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, secs, **_: compiling.append(secs) if event in COMPILE_EVENTS else None
    )
    fns, reference = runs()

    def save():
        info["elapsed"] = time.perf_counter() - start
        if args.out:
            with open(args.out, "w") as f:
                json.dump(info, f, indent=1)

    for n in sizes:
        spins = p.spins(n)
        idx = np.unique(np.linspace(0, n - 1, REF_MEMBERS).round().astype(int))
        ref = np.asarray(reference(spins[idx]))
        for name in (r for r in ORDER if r in rows):
            if time.perf_counter() - start > args.budget:
                info["skipped"].append(f"{name}, N={n}")
                continue
            try:
                compiling.clear()
                first, _, out = h.call(lambda name=name: fns[name](spins))
                compile_s = sum(compiling)
                calls = 2 if n < 10**6 else (args.timed if name in GOAL else 0)
                times = [h.call(lambda name=name: fns[name](spins))[0] for _ in range(calls)]
                times = times or [first - compile_s]
            except Exception as e:  # noqa: BLE001 - record it and go on
                info["errors"].append(f"{name}, N={n}: {type(e).__name__}: {str(e)[:2000]}")
                save()
                if n == sizes[0]:
                    raise
                continue
            final, steps, sol = np.asarray(out[0]), np.asarray(out[1]), out[2]
            row = dict(name=name, n=n, first=first, compile=compile_s, times=times)
            row["steps_max"] = int(steps.max())
            if sol is not None:
                row["contact_lost"] = int(np.sum(np.asarray(sol.result == tj.RESULTS.contact_lost)))
                final = np.where(
                    np.asarray(sol.result == tj.RESULTS.successful)[:, None], final, np.nan
                )
            if "full" not in name:
                row["error"] = p.state_error(final[idx], ref)
            info["rows"].append(row)
            print(json.dumps(row), flush=True)
            save()
    save()
    if args.smoke:
        report_from(info, args)


def report_from(info, args):
    by, rows = {(r["n"], r["name"]): r for r in info["rows"]}, []
    top_n = max((n for n, _ in by), default=0)  # the largest batch run: the goal's size
    for (n, name), r in sorted(by.items(), key=lambda kv: (kv[0][0], ORDER.index(kv[0][1]))):
        if n != top_n:
            continue
        t, plain = statistics.median(r["times"]), by.get((n, "plain diffrax, vmap"))
        vs = f"{t / statistics.median(plain['times']):.2f}" if plain else ""
        err = f"{r['error']:.1e}" if "error" in r else ""
        rows.append(
            f"{n:,} | {name} | {t:.2f} | {vs} | {r['first']:.1f} | {r['compile']:.1f} | {r['steps_max']} | {err} | {r.get('contact_lost', '')}"
        )
    goal = by.get((10**6, "tippejax so3, shared"))
    goal_text = (
        f"{statistics.median(goal['times']):.1f} s on {info['device']}"
        if goal
        else "not run at 1e6"
    )
    h.write(
        "gpu.py",
        f"The batch on one GPU ({info['device']})",
        f"""
{info["elapsed"]:.0f} s. Error: the largest over {REF_MEMBERS} members against the plain script at rtol 1e-12. Goal, 1e6 tops x 20 s in float64 within 20 s on one H100: {goal_text}.

{h.table("N | run | s | x plain vmap | first call s | compile s | steps (max) | error | contact lost", rows)}
{"".join(f"{chr(10)}{k.capitalize()}: " + "; ".join(info[k]) for k in ("skipped", "errors") if info[k])}
""",
        args,
        header=f"`{info['command']}` ({info['machine']})",
    )


def options(prs):
    prs.add_argument("--out", default=None, help="where the run's JSON goes (not committed)")
    prs.add_argument("--report", metavar="JSON", help="write the block from a run's JSON")
    prs.add_argument("--sizes", default="10000,1000000,100000")
    prs.add_argument("--rows", default=None, help="indices into ORDER, e.g. 0,1 (the goal's)")
    prs.add_argument("--timed", type=int, default=2, help="timed calls of the goal's rows at 1e6")
    prs.add_argument("--budget", type=float, default=420.0, help="seconds before runs are skipped")
    prs.add_argument("--allow-cpu", action="store_true", help="run on the CPU (a dry run)")


MODES = {"ladder": (ladder, "the GPU run (--out FILE); --report FILE writes its block")}

if __name__ == "__main__":
    os.environ.setdefault("TIPPEJAX_HOST_DEVICES", "1")
    ARGS = h.parse(__doc__, MODES, options)
    if ARGS.report:
        with open(ARGS.report) as f:
            report_from(json.load(f), ARGS)
    else:
        h.run(MODES, ARGS)
