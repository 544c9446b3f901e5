"""speed: tippejax against the peers a user has on one scene (`_peers.py`), at equal error: each
peer at the rtol that gives the plain diffrax script's error at rtol 1e-8, timed in interleaved
rounds; ratios are medians of the round-by-round ratios.

    python benchmarks/speed.py --one-top      # one top; the chart peers.png
    python benchmarks/speed.py --batch --big  # batches of 1000 (and 1e4), 1 device and every core
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import subprocess
import sys
import time

# One JAX device here, unless the mode is about devices or every core (set before JAX starts).
if not {"--numba", "--worker"} & set(sys.argv):
    os.environ.setdefault("TIPPEJAX_HOST_DEVICES", "1")

import _harness as h  # noqa: E402
import _peers as p  # noqa: E402
import diffrax  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import tippejax as tj  # noqa: E402

TOP, THETA0, SPIN, T1 = p.TOP, p.THETA0, p.SPIN, p.T1
TARGET = 1e-8  # equal error: the plain script's error at this rtol
NUMBA, PLAIN, SCIPY = "numba DOP853 (CyRK)", "plain diffrax", "scipy DOP853"
PLAIN_PI, GYRO = "plain diffrax, PI controller", "tippejax gyroscopic"


def final(sol):
    return jnp.concatenate([sol.states.axis[..., -1, :], sol.states.omega[..., -1, :]], axis=-1)


def tj_one(level, spin, rtol):
    """One top as a user runs it: `tj.simulate(..., summary=True)`; (final state, steps)."""
    y0 = tj.initial_state(TOP, THETA0, spin)
    kw = dict(model=level, rtol=rtol, atol=rtol * 1e-2, throw=False, summary=True)
    sol = tj.simulate(TOP, y0, T1, **kw)
    return final(sol), sol.num_steps


@functools.cache
def tj_single(level):
    return jax.jit(functools.partial(tj_one, level))


@functools.cache
def tj_vmap(level, options=False, n_devices=None):
    """`tj.simulate` in the user's own `jax.jit(jax.vmap(...))` (with `tj.compiler_options()`)."""
    batched = jax.vmap(functools.partial(tj_one, level), in_axes=(0, None))
    devices = jax.devices()[: n_devices or None]
    return p.over_devices(batched, 2, devices, tj.compiler_options() if options else None)


def tj_eager_vmap(level):
    return lambda s, r: jax.vmap(functools.partial(tj_one, level), in_axes=(0, None))(s, r)


def tj_batch(level, steps="per_member", shard=True):
    """`tj.simulate_batch`, the public batch function."""

    def run(s, rtol):
        kw = dict(summary=True, grid=(), model=level, steps=steps, shard=shard)
        sol = tj.simulate_batch(TOP, THETA0, np.asarray(s), T1, rtol=rtol, atol=rtol / 100, **kw)
        return final(sol), sol.num_steps

    return run


def singles(levels) -> dict:
    """{peer: run(rtol) -> (final, steps)} on the single top."""
    nb = p.numba_batch()
    runs = {
        NUMBA: lambda r: tuple(x[0] for x in nb(np.array([SPIN]), r, r * 1e-2)),
        PLAIN: lambda r: p.plain_single()(SPIN, r, r * 1e-2),
        PLAIN_PI: lambda r: p.plain_single("pi")(SPIN, r, r * 1e-2),
    }
    for level in levels:
        runs[f"tippejax {level}"] = functools.partial(tj_single(level), SPIN)
    return runs


def references(names) -> dict:
    """The SO(3) equations at rtol 1e-13 (numba); each tippejax level against itself at 1e-12
    (the full model has other equations), but the gyroscopic level against the SO(3) equations
    (its error is its model error)."""
    so3 = np.asarray(p.numba_batch()(np.array([SPIN]), 1e-13, 1e-15)[0][0])
    out = {}
    for name in names:
        level = name.split()[-1] if name.startswith("tippejax") else None
        own = level not in (None, "gyroscopic")
        out[name] = np.asarray(tj_single(level)(SPIN, 1e-12)[0]) if own else so3
    return out


def equal_error(levels, args) -> tuple[dict, float]:
    """{peer: rtol at the plain script's error at rtol TARGET}, and that error."""
    rtols = (1e-7, 1e-8) if args.smoke else (1e-7, 3e-8, 1e-8, 3e-9)
    runs = singles(levels)
    refs = references(runs)
    errs = {n: [p.state_error(run(r)[0], refs[n]) for r in rtols] for n, run in runs.items()}
    target = errs[PLAIN][rtols.index(TARGET)]
    return {n: h.interp_loglog(target, e, rtols) for n, e in errs.items()}, target


rounds = h.rounds


def batch_size(args):
    return 8 if args.smoke else 1000


# --- modes -------------------------------------------------------------------------------------


def one_top(args):
    """One top: every peer's rtol ladder, then the JAX peers at equal error in interleaved
    rounds; compile time per level; the chart peers.png."""
    levels = ("so3", "gyroscopic") if args.smoke else ("so3", "full", "routhian", "gyroscopic")
    ladder = (1e-6, 1e-8) if args.smoke else (1e-6, 1e-7, 1e-8, 1e-9, 1e-10)
    runs, vm = singles(levels), p.VectorModel("so3")
    runs[SCIPY] = lambda r: vm.solve(vm.y0(THETA0, SPIN), T1, rtol=r, atol=r / 100)[::2]
    rows, compile_s = {}, {}
    for name, run in runs.items():
        rows[name] = []
        for r in ladder[::2] if name == SCIPY and len(ladder) > 2 else ladder:
            t, (fin, steps) = h.interleaved(
                {0: functools.partial(run, r)}, 1 + 2 * (name != SCIPY)
            )[0]
            rows[name].append(dict(rtol=r, fin=fin, steps=int(steps), wall=t.wall, cpu=t.cpu))
            compile_s.setdefault(name, t.compile)
    refs = references(runs)
    for name, rs in rows.items():
        for x in rs:
            x["error"] = p.state_error(x.pop("fin"), refs[name])
    target = rows[PLAIN][ladder.index(TARGET)]["error"]
    eq = {
        n: {
            k: h.interp_loglog(target, [x["error"] for x in rs], [x[k] for x in rs])
            for k in ("rtol", "steps", "wall")
        }
        for n, rs in rows.items()
        if n != GYRO
    }
    eq[GYRO] = dict(rows[GYRO][ladder.index(TARGET)])  # its error is its model error: at 1e-8
    fns = {
        n: functools.partial(runs[n], eq[n]["rtol"]) for n in runs if n not in (NUMBA, SCIPY, GYRO)
    }
    timed = h.interleaved(fns, rounds(args, 21))
    base, body = timed[PLAIN][0], []
    for n, v in eq.items():
        if n in timed:
            t, (_, steps) = timed[n]
            v.update(steps=int(steps), wall=t.wall, ratio=h.paired(t, base)[0])
        v.setdefault("ratio", v["wall"] / base.wall)
        comp = f"{compile_s[n]:.1f}" if n.startswith("tippejax") else ""
        body.append(
            f"{n} | {v['rtol']:.2e} | {v['steps']:.0f} | {v['steps'] / eq[PLAIN]['steps']:.2f} | {1e3 * v['wall']:.3g} | {v['ratio']:.2f} | {comp}"
        )
    so3, full = eq["tippejax so3"], eq.get("tippejax full", eq["tippejax so3"])
    steps = so3["steps"] / eq[PLAIN]["steps"]
    h.write(
        "speed.py --one-top",
        "One top at equal error",
        f"""
Equal error {target:.2e} (the plain script's at rtol {TARGET:g}); {rounds(args, 21)} interleaved rounds; numba, scipy and the gyroscopic level (at rtol 1e-8; its model error {eq[GYRO]["error"]:.1e}) from the ladders. Chart: `peers.png`.

{h.table("peer | rtol | steps | vs plain steps | ms | vs plain | compile s", body)}

Targets: steps at equal error <= 1.05x the plain script: {steps:.2f}x, {h.verdict(steps <= 1.05)}; one top <= 1.2x (so3): {so3["ratio"]:.2f}x, {h.verdict(so3["ratio"] <= 1.2)}; full <= 1.3x so3: {full["ratio"] / so3["ratio"]:.2f}x, {h.verdict(full["ratio"] <= 1.3 * so3["ratio"])}.
""",
        args,
    )
    plt = h.pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for n, rs in rows.items():
        for ax, key in zip(axes, ("cpu", "steps")):
            if n != GYRO:
                ax.loglog([x["error"] for x in rs], [x[key] for x in rs], "o-", ms=3, label=n)
    for ax, label in zip(axes, ("CPU s per solve", "steps")):
        ax.axvline(target, color="grey", lw=0.8, ls=":")
        ax.set(xlabel="error of the final state", ylabel=label)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle("Standard top, SO(3) equations, 20 s: work against error")
    fig.tight_layout()
    fig.savefig(h.figure_path("peers.png", args), dpi=110)


def batch_fns(n, eq, n_devices, smoke):
    """{row: zero-argument call -> (finals, steps)} of the batch modes."""
    s, r = jnp.asarray(p.spins(n)), eq[PLAIN]  # numba: the --numba mode
    fns = {
        PLAIN: lambda: p.plain("vmap", n_devices)(s, r, r / 100),
        "plain diffrax in blocks, tj.compiler_options()": lambda: p.plain("blocks", n_devices)(
            s, r, r / 100
        ),
    }
    for lv in ("so3",) if smoke else ("so3", "full"):
        rl = eq[f"tippejax {lv}"]
        fns[f"tj.simulate {lv} in jit(vmap)"] = functools.partial(
            tj_vmap(lv, False, n_devices), s, rl
        )
        fns[f"tj.simulate {lv} in jit(vmap), tj.compiler_options()"] = functools.partial(
            tj_vmap(lv, True, n_devices), s, rl
        )
        if n_devices == 1:
            fns[f"tj.simulate {lv} in an eager vmap"] = functools.partial(tj_eager_vmap(lv), s, rl)
        fns[f"tj.simulate_batch {lv}"] = functools.partial(tj_batch(lv, shard=n_devices > 1), s, rl)
    return fns


def time_batch(n, eq, n_devices, args) -> dict:
    fns, out = batch_fns(n, eq, n_devices, args.smoke), {}
    if args.smoke and n_devices > 1:  # the every-core path, on the rows its targets read
        fns = {k: fns[k] for k in (PLAIN, "tj.simulate_batch so3")}
    for name, (t, (_, steps)) in h.interleaved(fns, rounds(args, 5)).items():
        steps = np.asarray(steps if steps is not None else np.zeros(n))
        out[name] = dict(walls=t.walls or [t.first_wall], wall=t.wall, steps_sum=int(steps.sum()))
        out[name]["steps_median"] = float(np.median(steps))
    return out


def batch(args):
    """Batches of 1000 (`--big`: and 1e4) at equal error, on one device and on every core."""
    if args.worker:  # the every-core half, in a process of its own
        job = json.loads(args.worker)
        print("JSON" + json.dumps(time_batch(job["n"], job["eq"], len(jax.devices()), args)))
        return
    eq, target = equal_error(("so3",) if args.smoke else ("so3", "full"), args)
    cores, text, targets = os.cpu_count() or 1, [], []
    for n in [8] if args.smoke else [1000, 10_000] if args.big else [1000]:
        one = time_batch(n, eq, 1, args)
        env = dict(os.environ, TIPPEJAX_HOST_DEVICES=str(cores))
        cmd = [sys.executable, __file__, "--batch", "--worker", json.dumps(dict(n=n, eq=eq))]
        out = subprocess.run(
            cmd + ["--smoke"] * args.smoke, env=env, capture_output=True, text=True
        )
        line = [x for x in out.stdout.splitlines() if x.startswith("JSON")]
        if not line:
            raise RuntimeError(out.stderr[-3000:])
        every = json.loads(line[0][4:])

        def ratio(res, a, b=PLAIN):
            return float(np.median(np.asarray(res[a]["walls"]) / np.asarray(res[b]["walls"])))

        rows = []
        for name, v in one.items():
            w = every.get(name)
            cell = f"{1e3 * w['wall'] / n:.3g} | {ratio(every, name):.2f}" if w else " | "
            per_step = f"{1e6 * v['wall'] / v['steps_sum']:.3g}" if v["steps_sum"] else ""
            rows.append(
                f"{name} | {v['steps_median']:.0f} | {1e3 * v['wall'] / n:.3g} | {ratio(one, name):.2f} | {cell} | {per_step}"
            )
        text += [
            f"**N = {n}**",
            "",
            h.table(
                f"run | steps median | 1 device ms | vs plain | {cores} devices ms | vs plain | us per member-step (1 device)",
                rows,
            ),
            "",
        ]
        for label, res in (
            (("1 device", one), (f"{cores} devices", every)) if n == 1000 or args.smoke else ()
        ):
            sb = ratio(res, "tj.simulate_batch so3")
            targets.append(
                f"batch of {n} <= 1.2x the plain script, {label} (`simulate_batch` so3) | {sb:.2f}x | {h.verdict(sb <= 1.2)}"
            )
            for what in (
                "tj.simulate_batch {}",
                "tj.simulate {} in jit(vmap)",
                "tj.simulate {} in jit(vmap), tj.compiler_options()",
            ):
                if what.format("full") in res:
                    f = ratio(res, what.format("full"), what.format("so3"))
                    targets.append(
                        f"full <= 1.3x so3, {label}: {what.format('...')} | {f:.2f}x | {h.verdict(f <= 1.3)}"
                    )
    vm, k = p.VectorModel("so3"), 2 if args.smoke else 20
    start = time.perf_counter()
    for s in p.spins(1000)[:: 1000 // k][:k]:
        vm.solve(vm.y0(THETA0, s), T1, rtol=eq[NUMBA], atol=eq[NUMBA] / 100)
    scipy_ms = 1e3 * (time.perf_counter() - start) / k
    h.write(
        "speed.py --batch",
        "Batches on one device and on every core",
        f"""
Equal-error rtols (error {target:.2e}): {", ".join(f"{k} {v:.2e}" for k, v in eq.items())}; {rounds(args, 5)} interleaved rounds; every core: {cores} host devices. scipy DOP853, a loop over the tops: {scipy_ms:.0f} ms per top.

{chr(10).join(text)}
{h.table("target | measured | verdict", targets)}
""",
        args,
    )


def numba_goal(args):
    """`simulate_batch` against numba per core and on every core, per member and with shared
    steps, and the plain shared-step script; every run's error measured."""
    n, (eq, target) = batch_size(args), equal_error(("so3",), args)
    s, nb, cores = p.spins(n), p.numba_batch(), len(jax.devices())
    r3, rn = eq["tippejax so3"], eq[NUMBA]
    fns = {
        "numba, 1 thread": lambda: nb(s, rn, rn / 100, threads=1),
        "simulate_batch, 1 device": functools.partial(tj_batch("so3", shard=False), s, r3),
        "simulate_batch shared steps, 1 device": functools.partial(
            tj_batch("so3", "shared", False), s, r3
        ),
        f"numba, {cores} threads (prange)": lambda: nb(s, rn, rn / 100),
        f"simulate_batch, {cores} devices": functools.partial(tj_batch("so3"), s, r3),
        f"simulate_batch shared steps, {cores} devices": functools.partial(
            tj_batch("so3", "shared"), s, r3
        ),
        f"plain diffrax shared steps (rtol 1e-8), {cores} devices": lambda: p.plain("shared")(
            jnp.asarray(s), 1e-8, 1e-10
        ),
    }
    ref = np.asarray(p.plain("vmap")(jnp.asarray(s), 1e-12, 1e-14)[0])
    timed = h.interleaved(fns, rounds(args, 9))
    rows = []
    for k, (t, out) in timed.items():
        base = timed["numba, 1 thread" if "1 device" in k else f"numba, {cores} threads (prange)"]
        base = base[0]
        med = h.paired(t, base)[0]
        goal = f"{med:.3f} {h.verdict(med <= 1)}" if k.startswith("simulate_batch") else ""
        rows.append(f"{k} | {1e3 * t.wall / n:.3f} | {p.state_error(out[0], ref):.1e} | {goal}")
    h.write(
        "speed.py --numba",
        "The numba goal: per core and on every core",
        f"""
Batch of {n}, summary, equal error {target:.2e} (numba rtol {rn:.2e}, tippejax so3 {r3:.2e}), {rounds(args, 9)} interleaved rounds, {cores} host devices. Goal: at or below numba on the same cores (median of the paired ratios).

{h.table("run | ms per top | error | / numba on the same cores", rows)}
""",
        args,
    )


def wp(args):
    """Work-precision of one top against scipy DOP853 on the same model in numpy; the chart
    work_precision.png."""
    top, ts, y0 = TOP, np.linspace(0.0, T1, 201), tj.initial_state(TOP, 0.1, 150.0)
    rtols = (1e-4, 1e-8) if args.smoke else (1e-4, 1e-6, 1e-8, 1e-10)
    scipy_rtols = (1e-4, 1e-8) if args.smoke else tuple(10.0**-k for k in range(3, 12))
    solvers = {"Dopri8": diffrax.Dopri8(), "default": None} | (
        {} if args.smoke else {"Tsit5": diffrax.Tsit5()}
    )

    def run(model, solver, rtol):
        kw = dict(model=model, saveat=ts, rtol=rtol, atol=rtol / 100, solver=solver, throw=False)
        sol = tj.simulate(top, y0, T1, **kw)
        return np.asarray(sol.theta), float(sol.t_invert), int(sol.num_steps)

    curves, body, refs = {}, [], {m: run(m, diffrax.Dopri8(), 1e-13) for m in ("full", "so3")}
    for model in ("full", "so3"):
        vm, (ref, ref_t, _) = p.VectorModel(model), refs[model]
        sc = curves[f"scipy DOP853, {model}"] = []
        for r in scipy_rtols:
            wall, _, (theta, t_inv, _) = h.call(
                lambda r=r: vm.solve(vm.y0(0.1, 150.0), T1, rtol=r, atol=r / 100, t_eval=ts)
            )
            sc.append((wall, float(np.max(np.abs(theta - ref))), abs(t_inv - ref_t)))
        for name, solver in solvers.items():
            curves[f"{model} {name}"] = []
            for r in rtols:
                t, (theta, t_inv, steps) = h.interleaved(
                    {0: functools.partial(run, model, solver, r)}, rounds(args, 5)
                )[0]
                err, t_err = float(np.max(np.abs(theta - ref))), abs(t_inv - ref_t)
                curves[f"{model} {name}"].append((t.wall, err, t_err))
                at = h.interp_loglog(err, [x[1] for x in sc], [x[0] for x in sc])
                shown = r in {"Dopri8": (1e-6, 1e-8, 1e-10), "Tsit5": (1e-8,)}.get(name, rtols)
                if shown and (
                    name != "default" or type(tj.default_solver(top)) is not diffrax.Dopri8
                ):
                    body.append(
                        f"{model} | {name} | {r:.0e} | {1e3 * t.wall:.3g} | {steps} | {err:.2e} | {t_err:.2e} | {at / t.wall:.1f}"
                    )
    curves["gyroscopic (t_invert only)"] = []
    for r in rtols:
        t, (_, t_inv, steps) = h.interleaved(
            {0: functools.partial(run, "gyroscopic", None, r)}, rounds(args, 5)
        )[0]
        curves["gyroscopic (t_invert only)"].append((t.wall, np.nan, abs(t_inv - refs["full"][1])))
    h.write(
        "speed.py --wp",
        "Work-precision of one top against scipy",
        f"""
Errors against tippejax Dopri8 at rtol 1e-13 of the same model; 'scipy / tippejax': scipy DOP853's time at tippejax's error over tippejax's. Chart: `work_precision.png`.

{h.table("model | solver | rtol | ms | steps | max d theta | d t_invert | scipy / tippejax", body)}
""",
        args,
    )
    plt = h.pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.5), constrained_layout=True)
    for ax, k, label in (
        (axes[0], 1, "max |theta - theta_ref| (rad)"),
        (axes[1], 2, "|t_invert - t_invert_ref| (s)"),
    ):
        for name, pts in curves.items():
            pts = [x for x in pts if np.isfinite(x[k])]
            if pts:
                style = "k^--" if name.startswith("scipy") else "o-"
                ax.loglog(
                    [x[0] for x in pts], [max(x[k], 1e-16) for x in pts], style, ms=4, label=name
                )
        ax.set(xlabel="wall time per run (s)", ylabel=label)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.savefig(h.figure_path("work_precision.png", args), dpi=110)


def stiff(args):
    """Tsit5, Dopri8 and Kvaerno5 as friction grows: where `default_solver` changes."""
    ts, rows = np.linspace(0.0, 0.5, 201), []
    solvers = {"Tsit5": diffrax.Tsit5(), "Dopri8": diffrax.Dopri8(), "Kvaerno5": diffrax.Kvaerno5()}
    for mu in (300.0,) if args.smoke else (300.0, 3000.0, 30000.0):
        top = tj.TippeTop.from_ratios(0.9, 0.3, mu=mu)
        y0, kw = (
            tj.initial_state(top, 0.1, 100.0),
            dict(saveat=ts, throw=False, max_steps=2_000_000),
        )
        ref = tj.simulate(top, y0, 0.5, rtol=1e-11, atol=1e-13, solver=diffrax.Kvaerno5(), **kw)
        ref = np.asarray(ref.theta)
        fns = {
            n: functools.partial(tj.simulate, top, y0, 0.5, rtol=1e-8, atol=1e-10, solver=s, **kw)
            for n, s in solvers.items()
        }
        cells = [
            f"{t.wall:.3f} / {int(sol.num_steps)} / {np.max(np.abs(np.asarray(sol.theta) - ref)):.1e}"
            for t, sol in h.interleaved(fns, rounds(args, 2)).values()
        ]
        rows.append(
            f"{mu:g} | {float(tj.friction_rate(top)):.3g} | {' | '.join(cells)} | {type(tj.default_solver(top)).__name__}"
        )
    h.write(
        "speed.py --stiff",
        "Stiff friction: where the default solver changes",
        f"""
{rounds(args, 2)} interleaved rounds. Wall s / steps / max d theta:

{h.table("mu (s/m) | friction rate (1/s) | Tsit5 | Dopri8 | Kvaerno5 | default picks", rows)}
""",
        args,
    )


MODES = {
    "one-top": (one_top, "one top: every peer's ladder and equal error; peers.png"),
    "batch": (batch, "batches of 1000 (--big: 1e4) on one device and on every core"),
    "numba": (numba_goal, "the numba goal, per member and shared steps"),
    "wp": (wp, "work-precision against scipy; work_precision.png"),
    "stiff": (stiff, "solvers under stiff friction"),
}


def options(parser):
    parser.add_argument("--big", action="store_true", help="--batch: also 1e4 tops")
    parser.add_argument("--worker", default=None, help=argparse.SUPPRESS)


if __name__ == "__main__":
    h.run(MODES, h.parse(__doc__, MODES, options))
