"""The simulation engine on one top: work-precision against scipy, compile time, the event watch.

Scenes (standard top `tj.default_top()`, group IIb):

1. launch `initial_state(top, 0.1, 150.0)`, t1 = 20 s (inverts at ~5.70 s, settles near
   theta = pi), 201 save points. Reference: tippejax Dopri8 at rtol 1e-13, atol 1e-15, per
   model; the full reference is checked once against scipy at rtol 1e-12.
   tippejax: full and so3 models x Dopri8, Tsit5 and the default solver, rtol 1e-4..1e-10
   (atol = rtol * 1e-2); median of 5 calls of `tj.simulate` after a compiling call. The
   gyroscopic level (default solver) at the same rtols, timed beside the full model, is on the
   chart by its t_invert error against the full model's reference (its theta(t) lacks the
   nutation).
   Baseline: `scipy.integrate.solve_ivp(method="DOP853")` on the same vector-form model in
   numpy (`_common.VectorModel`), same rtol/atol, `t_eval` = the save grid, t_invert from a
   scipy event on a_Z.
2. away from the poles, for the independent Euler-angle baseline (`tests/euler_reference.py`):
   theta0 = 2.0 with the precession rate and spin of the intermediate state of J = 5e-6
   (theta stays in [2.0, 2.30]).

Then: first-call compile time per level (fresh processes), the cost of the event watch
(`event_pieces`, and a plain `diffrax.diffeqsolve` of the same field), event exactness, a
long run against `max_steps`, and Tsit5/Dopri8/Kvaerno5 under stiff friction (the thresholds
of `default_solver`). Writes its section of benchmarks/RESULTS.md and
benchmarks/work_precision.png.

    python benchmarks/engine.py
"""

from __future__ import annotations

import functools
import json
import math
import os
import pathlib
import re
import statistics
import subprocess
import sys
import time

import diffrax
import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import matplotlib
import matplotlib.ticker
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import tippejax as tj  # noqa: E402
from tippejax._engine.watch import WatchedSolver, event_root_finder  # noqa: E402
from tippejax._models.levels import LEVELS  # noqa: E402

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _common import (  # noqa: E402
    VectorModel,
    interleaved,
    interp_loglog,
    machine_line,
    standard_params,
    table,
    timed,
    verdict,
    write_section,
)

REPEATS = 5
RTOLS = (1e-4, 1e-6, 1e-8, 1e-10)
SCIPY_RTOLS = (1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11)
T1 = 20.0
TS = np.linspace(0.0, T1, 201)
SOLVERS = {"Dopri8": diffrax.Dopri8(), "Tsit5": diffrax.Tsit5(), "default": None}
REF_RTOL, REF_ATOL = 1e-13, 1e-15
LOG: list[str] = []
LOAD = os.getloadavg()


def say(text=""):
    print(text, flush=True)
    LOG.append(text)


def run_tj(top, y0, model, solver, rtol, *, ts=TS, t1=T1, **kwargs):
    return tj.simulate(
        top, y0, t1, model=model, saveat=ts, rtol=rtol, atol=rtol * 1e-2 if rtol > REF_RTOL
        else REF_ATOL, solver=solver, throw=False, **kwargs
    )


def theta_error(theta, ref):
    theta, ref = np.asarray(theta, float), np.asarray(ref, float)
    if not np.all(np.isfinite(theta)):
        return math.nan
    return float(np.max(np.abs(theta - ref)))


def result_name(sol):
    return tj.RESULTS[sol.result] or "ok"


# ----------------------------------------------------------------------------------------------
# 1. work-precision
# ----------------------------------------------------------------------------------------------


def make_row(who, model, solver, rtol, timing, theta, t_inv, steps, rejected=None, result="ok",
             nfev=None):
    return dict(who=who, model=model, solver=solver, rtol=rtol, wall=timing.wall,
                cpu=timing.cpu, compile=timing.compile, steps=steps, rejected=rejected,
                nfev=nfev, theta=np.asarray(theta, float), t_inv=t_inv, result=result)


def add_errors(rows, ref):
    for r in rows:
        r["theta_err"] = theta_error(r["theta"], ref["theta"])
        r["t_inv_err"] = (abs(r["t_inv"] - ref["t_invert"]) if np.isfinite(ref["t_invert"])
                          else math.nan)
        say(f"  {r['who']:8s} {r['model']:4s} {r['solver']:8s} rtol={r['rtol']:.0e} "
            f"wall={r['wall']:.4f}s cpu={r['cpu']:.4f}s steps={r['steps']} "
            f"theta_err={r['theta_err']:.2e} t_inv_err={r['t_inv_err']:.2e} {r['result']}")


def sweep(model, fns_at, rtols):
    """Rows of every runner of `fns_at(rtol)` ({(who, solver): (callable, reader)}), timed
    side by side at each rtol."""
    rows = []
    for rtol in rtols:
        fns = fns_at(rtol)
        timings = interleaved({k: f for k, (f, _) in fns.items()}, REPEATS)
        for (who, solver), (timing, out) in timings.items():
            rows.append(make_row(who, model, solver, rtol, timing, **fns[(who, solver)][1](out)))
    return rows


def read_tj(sol):
    return dict(theta=sol.theta, t_inv=float(sol.t_invert), steps=int(sol.num_steps),
                rejected=int(sol.num_rejected_steps), result=result_name(sol))


def read_scipy(out):
    theta, t_inv, nfev, steps = out
    return dict(theta=theta, t_inv=t_inv, steps=steps, nfev=nfev)


def reference(top, y0, model, t1=T1, ts=TS):
    sol = run_tj(top, y0, model, diffrax.Dopri8(), REF_RTOL, t1=t1, ts=ts)
    return dict(theta=np.asarray(sol.theta), t_invert=float(sol.t_invert),
                steps=int(sol.num_steps), result=result_name(sol), sol=sol)


def equal_error_ratios(tj_rows, scipy_rows):
    """For each tippejax point: scipy's time at the same max |theta| error, by linear
    interpolation of log(scipy time) against log(scipy error) between the two scipy runs whose
    errors bracket it (linear extrapolation in log-log from the nearest two otherwise); for
    wall-clock and for CPU time."""
    errs = [r["theta_err"] for r in scipy_rows]
    out = []
    for r in tj_rows:
        t_wall, extrapolated = interp_loglog(r["theta_err"], errs, [s["wall"] for s in scipy_rows])
        t_cpu, _ = interp_loglog(r["theta_err"], errs, [s["cpu"] for s in scipy_rows])
        out.append(dict(r, scipy_wall=t_wall, ratio=t_wall / r["wall"], ratio_cpu=t_cpu / r["cpu"],
                        extrapolated=extrapolated))
    return out


def scene_standard():
    top = tj.default_top()
    y0 = tj.initial_state(top, 0.1, 150.0)
    params = standard_params()
    say("Scene 1: standard top, theta0 = 0.1, spin 150 rad/s, t1 = 20 s, 201 save points")
    rows, scipy_rows, refs, checks = [], {}, {}, {}
    for model in ("full", "so3"):
        vm = VectorModel(params, model)
        z0 = vm.y0(0.1, 150.0)

        def fns_at(rtol, model=model, vm=vm, z0=z0):
            fns = {}
            if rtol in RTOLS:
                for name, solver in SOLVERS.items():
                    fns[("tippejax", name)] = (
                        functools.partial(run_tj, top, y0, model, solver, rtol), read_tj)
            fns[("scipy", "DOP853")] = (
                functools.partial(vm.solve, z0, T1, TS, rtol=rtol, atol=rtol * 1e-2), read_scipy)
            return fns

        model_rows = sweep(model, fns_at, SCIPY_RTOLS)
        refs[model] = ref = reference(top, y0, model)
        say(f"  reference {model}: Dopri8 rtol 1e-13 atol 1e-15, t_invert = "
            f"{ref['t_invert']:.10f} s, theta(20) = {ref['theta'][-1]:.9f}, "
            f"{ref['steps']} steps, {ref['result']}")
        theta, t_inv, nfev, _ = vm.solve(z0, T1, TS, rtol=1e-12, atol=1e-14)
        checks[model] = (theta_error(theta, ref["theta"]), abs(t_inv - ref["t_invert"]), nfev)
        say(f"  scipy DOP853 rtol 1e-12 atol 1e-14 vs the tippejax reference ({model}): "
            f"max|d theta| = {checks[model][0]:.2e} rad, |d t_invert| = {checks[model][1]:.2e} s")
        if not checks[model][0] < 1e-8:
            raise RuntimeError(f"numpy {model} model disagrees with tippejax: {checks[model][0]}")
        add_errors(model_rows, ref)
        rows += [r for r in model_rows if r["who"] == "tippejax"]
        scipy_rows[model] = [r for r in model_rows if r["who"] == "scipy"]
    rhs = rhs_agreement(top, params)
    say(f"  numpy right-hand side vs tippejax vector field at 20 random states: max relative "
        f"difference full {rhs['full']:.1e}, so3 {rhs['so3']:.1e}")
    say("  gyroscopic level (default solver), timed side by side with the full model (default)")

    def fns_gyro(rtol):
        return {(model, "default"): (functools.partial(run_tj, top, y0, model, None, rtol), read_tj)
                for model in ("gyroscopic", "full")}

    gyro_rows = sweep("gyroscopic", fns_gyro, RTOLS)
    for r in gyro_rows:  # sweep's "who" is the level here; errors against the full reference
        r["model"], r["who"] = r["who"], "tippejax"
    add_errors(gyro_rows, refs["full"])
    return dict(refs=refs, checks=checks, rhs=rhs, rows=rows, scipy=scipy_rows, gyro=gyro_rows)


def rhs_agreement(top, params):
    rng = np.random.default_rng(0)
    worst = {}
    for model in ("full", "so3"):
        vm, level, w = VectorModel(params, model), LEVELS[model], 0.0
        for _ in range(20):
            s = tj.initial_state(
                top, rng.uniform(0.05, 3.1), rng.uniform(-200, 200),
                theta_dot=rng.uniform(-5, 5), phi_dot=rng.uniform(-30, 30),
                phi=rng.uniform(0, 6), vx=rng.uniform(-0.3, 0.3), vy=rng.uniform(-0.3, 0.3),
            )
            d = level.vector_field(0.0, level.from_state(top, s), top)
            if model == "full":
                z = np.concatenate([s.position, s.velocity, s.axis, s.omega])
                ref = np.concatenate([d.position, d.velocity, d.axis, d.omega])
            else:
                z = np.concatenate([s.axis, s.omega])
                ref = np.concatenate([d.axis, d.omega])
            w = max(w, float(np.max(np.abs(vm.rhs(0.0, z) - ref)) / np.max(np.abs(ref))))
        worst[model] = w
    return worst


def scene_euler():
    """Away from the poles: the independent Euler-angle baseline can follow it."""
    try:
        sys.path.insert(0, str(HERE.parent / "tests"))
        import euler_reference
    except ImportError:
        say("Scene 2 skipped: tests/euler_reference.py is absent.")
        return None
    top = tj.default_top()
    params = standard_params()
    # The intermediate state of J = 5e-6: run a launch into it and read its rates.
    C, R, eps = params["C"], params["R"], params["eps"]
    settle = tj.simulate(top, tj.initial_state(top, 0.5, 5e-6 / (C * (R * math.cos(0.5) - eps))),
                         20.0, saveat=TS)
    phi_dot, spin = float(settle.phi_dot[-1]), float(settle.spin[-1])
    theta_star = float(settle.theta[-1])
    theta0 = 2.0
    y0 = tj.initial_state(top, theta0, spin, phi_dot=phi_dot)
    say(f"Scene 2: theta0 = {theta0}, phi_dot0 = {phi_dot:.4f} rad/s, spin {spin:.4f} rad/s "
        f"(the rates of the intermediate state theta* = {theta_star:.4f} of J = 5e-6), "
        f"t1 = 20 s, 201 save points")
    vm = VectorModel(params, "full")
    z0 = vm.y0(theta0, spin, phi_dot=phi_dot)

    def read_euler(out):
        return dict(theta=out["theta"], t_inv=math.nan, steps=None, nfev=int(out["nfev"]))

    def fns_at(rtol):
        fns = {}
        if rtol in RTOLS:
            for name in ("Dopri8", "Tsit5"):
                fns[("tippejax", name)] = (
                    functools.partial(run_tj, top, y0, "full", SOLVERS[name], rtol), read_tj)
        fns[("scipy", "DOP853")] = (
            functools.partial(vm.solve, z0, T1, TS, rtol=rtol, atol=rtol * 1e-2), read_scipy)
        fns[("euler", "DOP853")] = (
            functools.partial(euler_reference.solve, params, theta0, spin, TS, phi_dot=phi_dot,
                              variant="full", rtol=rtol, atol=rtol * 1e-2), read_euler)
        return fns

    rows = sweep("full", fns_at, SCIPY_RTOLS)
    ref = reference(top, y0, "full")
    lo, hi = float(ref["theta"].min()), float(ref["theta"].max())
    inside = 0.1 <= lo and hi <= math.pi - 0.1
    say(f"  reference (tippejax full Dopri8 1e-13): theta in [{lo:.4f}, {hi:.4f}] "
        f"({'inside' if inside else 'NOT inside'} [0.1, pi - 0.1]), "
        f"J = {float(ref['sol'].jellet[0]):.4e}, theta(20) = {ref['theta'][-1]:.6f}, "
        f"{ref['steps']} steps")
    out = euler_reference.solve(params, theta0, spin, TS, phi_dot=phi_dot, variant="full",
                                rtol=1e-12, atol=1e-14)
    check = theta_error(out["theta"], ref["theta"])
    say(f"  euler_reference (DOP853 1e-12) vs tippejax reference: max|d theta| = {check:.2e}")
    add_errors(rows, ref)
    return dict(rows=[r for r in rows if r["who"] == "tippejax"],
                vector=[r for r in rows if r["who"] == "scipy"],
                euler=[r for r in rows if r["who"] == "euler"], check=check, range=(lo, hi),
                inside=inside, theta0=theta0, phi_dot=phi_dot, spin=spin)


# ----------------------------------------------------------------------------------------------
# 2. compile time per level, in fresh processes
# ----------------------------------------------------------------------------------------------

COMPILE_SNIPPET = r"""
import json, statistics, sys, time
import jax, numpy as np
import tippejax as tj
model = sys.argv[1]
top = tj.default_top()
y0 = jax.block_until_ready(tj.initial_state(top, 0.1, 150.0))
ts = np.linspace(0.0, 20.0, 201)
def call():
    sol = tj.simulate(top, y0, 20.0, model=model, saveat=ts, rtol=1e-8, atol=1e-10, throw=False)
    return jax.block_until_ready(sol)
t, c = time.perf_counter(), time.process_time(); sol = call()
first, first_cpu = time.perf_counter() - t, time.process_time() - c
walls, cpus = [], []
for _ in range(3):
    t, c = time.perf_counter(), time.process_time(); call()
    walls.append(time.perf_counter() - t); cpus.append(time.process_time() - c)
print(json.dumps(dict(first=first, first_cpu=first_cpu, median=statistics.median(walls),
                      median_cpu=statistics.median(cpus), model=sol.model,
                      steps=int(sol.num_steps))))
"""


def compile_times():
    out = {}
    for model in ("full", "so3", "routhian"):
        proc = subprocess.run([sys.executable, "-c", COMPILE_SNIPPET, model],
                              capture_output=True, text=True, check=True)
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        r["compile"] = r["first"] - r["median"]
        r["compile_cpu"] = r["first_cpu"] - r["median_cpu"]
        out[model] = r
        say(f"  compile {model:8s}: first call {r['first']:.2f} s, median {r['median']:.3f} s, "
            f"compile = {r['compile']:.2f} s wall, {r['compile_cpu']:.2f} s CPU "
            f"({r['model']}, {r['steps']} steps)")
    return out


# ----------------------------------------------------------------------------------------------
# 3. the event watch, and where the time of a step goes
# ----------------------------------------------------------------------------------------------

def plain_solve(top, y0, rtol, atol, ts, *, flat, watched=False, event=False):
    """A plain `diffrax.diffeqsolve` of the full level's field, Dopri8, PID controller with the
    level's error norm, `SaveAt(ts)`, nothing else; `flat=False` as a user would write it (the
    level's pytree state, diffrax's default stage loop), `flat=True` as `segment.py` calls it
    (state flattened to one vector, `scan_kind="checkpointed"`). Optionally with the watch
    wrapper (`WatchedSolver`, 8 samples, same conditions) and/or the terminating Event."""
    level = LEVELS["full"]
    y = level.from_state(top, y0)
    solver = diffrax.Dopri8()
    if flat:
        y, unravel = jax.flatten_util.ravel_pytree(y)
        solver = diffrax.Dopri8(scan_kind="checkpointed")

        def field(t, y, top):
            return jax.flatten_util.ravel_pytree(level.vector_field(t, unravel(y), top))[0]

        def norm(e):
            return level.error_norm(unravel(e))
    else:
        unravel = None
        field, norm = level.vector_field, level.error_norm

    def conditions(names):
        def fn(y, top):
            c = level.conditions(top, unravel(y) if flat else y)
            return jnp.stack([c.get(name) for name in names]).astype(jnp.float64)

        return fn

    if watched:
        solver = WatchedSolver(solver, conditions(("singular", "contact", "upright")), (2,),
                               pieces=1)
    ev = None
    if event:
        cond = conditions(("singular", "contact"))
        ev = diffrax.Event(lambda t, y, args, **kw: jnp.min(cond(y, args)),
                           event_root_finder(jnp.float64), direction=False)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field), solver, 0.0, T1, None, y, top,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol, norm=norm),
        event=ev, max_steps=1_000_000, throw=False,
    )
    return sol.ys, sol.stats["num_steps"]


def hlo_size(fn, *args):
    """(instructions, flops of one pass) of the optimised HLO of `eqx.filter_jit(fn)(*args)`."""
    compiled = eqx.filter_jit(fn).lower(*args).compile().compiled
    text = compiled.as_text()
    instructions = sum(1 for line in text.splitlines() if re.match(r"\s+(ROOT )?\S+ = ", line))
    return instructions, float(compiled.cost_analysis().get("flops", math.nan))


def watch_cost():
    top = tj.default_top()
    y0 = tj.initial_state(top, 0.1, 150.0)
    level = LEVELS["full"]
    ts = jnp.asarray(TS)
    rtol = 1e-8
    r_, a_ = jnp.asarray(rtol), jnp.asarray(rtol * 1e-2)
    fns = {}
    for pieces in (1, 2, 4):
        fns[f"tj.simulate, event_pieces={pieces}"] = functools.partial(
            run_tj, top, y0, "full", diffrax.Dopri8(), rtol, event_pieces=pieces)
    fns["tj.simulate summary=True (no save grid), event_pieces=1"] = lambda: tj.simulate(
        top, y0, T1, rtol=rtol, atol=rtol * 1e-2, solver=diffrax.Dopri8(), summary=True,
        throw=False)
    # The same jitted call returning only the final theta, or only t_invert: what the located
    # (observed) event costs when it is asked for.
    for what in ("theta", "t_invert"):
        fn = eqx.filter_jit(lambda top, y0, r, a, what=what: getattr(tj.simulate(
            top, y0, T1, rtol=r, atol=a, solver=diffrax.Dopri8(), summary=True, throw=False),
            what))
        fns[f"jit(simulate summary) returning only {what}"] = functools.partial(
            fn, top, y0, r_, a_)
    plain = {
        "plain diffeqsolve, pytree state (as a user writes it), no event, no watch":
            (False, False, False),
        "plain diffeqsolve, flat state (as segment.py), no event, no watch": (True, False, False),
        "plain flat + terminating diffrax.Event (contact, singular)": (True, False, True),
        "plain flat + WatchedSolver (8 samples), no Event": (True, True, False),
    }
    for label, (flat, watched, event) in plain.items():
        fn = eqx.filter_jit(functools.partial(plain_solve, flat=flat, watched=watched,
                                              event=event))
        fns[label] = functools.partial(fn, top, y0, r_, a_, ts)
    results = interleaved(fns, REPEATS + 2)
    rows = []
    for label, (timing, out) in results.items():
        if isinstance(out, tj.Solution):
            steps, rejected, t_inv = int(out.num_steps), int(out.num_rejected_steps), float(out.t_invert)
        elif label.startswith("jit(simulate"):
            steps, rejected, t_inv = None, None, math.nan
        else:
            steps, rejected, t_inv = int(out[1]), None, math.nan  # plain: (ys, steps)
        rows.append(dict(what=label, wall=timing.wall, cpu=timing.cpu, compile=timing.compile,
                         steps=steps, rejected=rejected, t_invert=t_inv))
        say(f"  {label}: wall {timing.wall:.4f}s cpu {timing.cpu:.4f}s steps {steps} "
            f"rejected {rejected} (first-call extra {timing.compile:.1f}s)")
    # The right-hand side inside an XLA loop: the floor of a step's cost.
    n_eval = 13_000

    @jax.jit
    def rhs_loop(y, top):
        def body(i, y):
            d = level.vector_field(0.0, y, top)
            return jax.tree_util.tree_map(lambda a, b: a + 1e-9 * b, y, d)

        return jax.lax.fori_loop(0, n_eval, body, y)

    timing, _ = timed(rhs_loop, level.from_state(top, y0), top, repeats=REPEATS)
    rhs_in_loop = timing.cpu / n_eval
    # Size of the compiled programs (one pass through every loop body).
    sizes = {
        "plain diffeqsolve": hlo_size(functools.partial(plain_solve, flat=True), top, y0, r_,
                                      a_, ts),
        "tj.simulate (full, 201 saves)": hlo_size(
            lambda top, y0, r, a, ts: tj.simulate(top, y0, T1, saveat=ts, rtol=r, atol=a,
                                                  solver=diffrax.Dopri8(), throw=False).theta,
            top, y0, r_, a_, ts),
    }
    say(f"  vector field inside a fori_loop: {1e6 * rhs_in_loop:.2f} us per evaluation (CPU)")
    for k, (n, f) in sizes.items():
        say(f"  {k}: {n} HLO instructions, cost_analysis flops (loop bodies once) {f:.0f}")
    return dict(rows=rows, rtol=rtol, rhs_in_loop=rhs_in_loop, sizes=sizes)


# ----------------------------------------------------------------------------------------------
# 4. exactness of events, and max_steps
# ----------------------------------------------------------------------------------------------


def exactness():
    top = tj.default_top()
    y0 = tj.initial_state(top, 0.1, 150.0)
    coarse = run_tj(top, y0, "full", None, 1e-8, ts=np.array([0.5, 1.0, 2.0, 5.0, 10.0, 20.0]))
    fine = run_tj(top, y0, "full", None, 1e-8)
    summary = tj.simulate(top, y0, T1, rtol=1e-8, atol=1e-10, summary=True, throw=False)
    out = dict(coarse=float(coarse.t_invert), fine=float(fine.t_invert),
               summary=float(summary.t_invert))
    say(f"  t_invert (default solver, rtol 1e-8): 6-point grid {out['coarse']:.12f} s, "
        f"201-point grid {out['fine']:.12f} s, summary {out['summary']:.12f} s; difference "
        f"{abs(out['coarse'] - out['fine']):.1e} s")
    y200 = tj.initial_state(top, 0.1, 200.0)
    lost = tj.simulate(top, y200, 7.0, solver=diffrax.Dopri8(), rtol=1e-6, atol=1e-8,
                       throw=False)
    lost_ref = tj.simulate(top, y200, 7.0, solver=diffrax.Dopri8(), rtol=1e-12, atol=1e-14,
                           throw=False)
    lost_cont = tj.simulate(top, y200, 7.0, solver=diffrax.Dopri8(), rtol=1e-6, atol=1e-8,
                            throw=False, on_contact_loss="continue")
    out.update(t_loss=float(lost.t_contact_loss), t_loss_ref=float(lost_ref.t_contact_loss),
               t_loss_continue=float(lost_cont.t_contact_loss), loss_result=result_name(lost),
               loss_steps=int(lost.num_steps))
    say(f"  spin 200, theta0 0.1, t1 7, Dopri8 rtol 1e-6: t_contact_loss = {out['t_loss']:.6f} s "
        f"({out['loss_result'][:40]}...), rtol 1e-12: {out['t_loss_ref']:.6f} s, "
        f"on_contact_loss='continue': {out['t_loss_continue']:.6f} s")
    # This launch leaves the table during its rise (at ~4.8 s, like spin 200): with the
    # default on_contact_loss="stop" the run ends there; "continue" integrates all 40 s.
    y300 = tj.initial_state(top, 0.1, 300.0)
    stop = tj.simulate(top, y300, 40.0, rtol=1e-10, atol=1e-12, summary=True, throw=False)
    timing, long = timed(lambda: tj.simulate(top, y300, 40.0, rtol=1e-10, atol=1e-12,
                                             summary=True, throw=False,
                                             on_contact_loss="continue"), repeats=1)
    out.update(long_steps=int(long.num_steps), long_time=timing.wall,
               long_result=result_name(long), long_t_final=float(long.t_final),
               long_rejected=int(long.num_rejected_steps), long_t_loss=float(long.t_contact_loss),
               long_j_drift=abs(float(long.jellet[0]) / float(tj.jellet(top, y300)) - 1),
               stop_t_final=float(stop.t_final), stop_steps=int(stop.num_steps))
    say(f"  40 s, spin 300, rtol 1e-10, on_contact_loss='continue': t_final "
        f"{out['long_t_final']}, {out['long_steps']} steps ({out['long_rejected']} rejected), "
        f"{timing.wall:.2f} s, t_contact_loss {out['long_t_loss']:.4f} s, |J/J0 - 1| = "
        f"{out['long_j_drift']:.1e}; with 'stop' it ends at {out['stop_t_final']:.4f} s")
    return out


# ----------------------------------------------------------------------------------------------
# 5. stiff friction: where the default solver changes
# ----------------------------------------------------------------------------------------------


def stiff():
    """Tsit5, Dopri8, Kvaerno5 as friction grows (backs STIFF_RATE and IMPLICIT_RATE).

    Standard top with mu = 300, 3000, 30000 s/m, theta0 0.1, spin 100, t1 = 0.5 s, rtol 1e-8,
    201 saves (the save-grid length of the sweeps above, so Tsit5 and Dopri8 reuse their
    compilations); error against Kvaerno5 at rtol 1e-11."""
    from tippejax._engine.solver_choice import IMPLICIT_RATE, STIFF_RATE

    rows = []
    t1 = 0.5
    ts = np.linspace(0.0, t1, 201)
    solvers = {"Tsit5": diffrax.Tsit5(), "Dopri8": diffrax.Dopri8(),
               "Kvaerno5": diffrax.Kvaerno5()}
    for mu in (300.0, 3000.0, 30000.0):
        top = tj.TippeTop.from_ratios(0.9, 0.3, mu=mu)
        y0 = tj.initial_state(top, 0.1, 100.0)
        kw = dict(saveat=ts, throw=False, max_steps=2_000_000)
        ref = tj.simulate(top, y0, t1, rtol=1e-11, atol=1e-13, solver=diffrax.Kvaerno5(), **kw)
        fns = {name: functools.partial(tj.simulate, top, y0, t1, rtol=1e-8, atol=1e-10,
                                       solver=solver, **kw) for name, solver in solvers.items()}
        timings = interleaved(fns, repeats=2)
        default = type(tj.default_solver(top)).__name__
        for name, (timing, sol) in timings.items():
            rows.append(dict(mu=mu, rate=float(tj.friction_rate(top)), solver=name,
                             wall=timing.wall, cpu=timing.cpu, steps=int(sol.num_steps),
                             err=theta_error(sol.theta, ref.theta), result=result_name(sol),
                             default=default))
            say(f"  stiff mu={mu:g} rate={rows[-1]['rate']:.3g}/s {name}: wall "
                f"{timing.wall:.3f}s cpu {timing.cpu:.3f}s steps {rows[-1]['steps']} err "
                f"{rows[-1]['err']:.1e} {rows[-1]['result'][:20]} (default: {default})")
    return dict(rows=rows, stiff_rate=STIFF_RATE, implicit_rate=IMPLICIT_RATE)


# ----------------------------------------------------------------------------------------------
# chart and report
# ----------------------------------------------------------------------------------------------

STYLE = {
    ("full", "Dopri8"): dict(color="C1", marker="s"),
    ("full", "Tsit5"): dict(color="C0", marker="o"),
    ("full", "default"): dict(color="C1", marker="x", linestyle=":", markersize=9),
    ("so3", "Dopri8"): dict(color="C3", marker="s", linestyle="--"),
    ("so3", "Tsit5"): dict(color="C2", marker="o", linestyle="--"),
    ("so3", "default"): dict(color="C3", marker="x", linestyle=":", markersize=9),
    ("scipy", "full"): dict(color="k", marker="^"),
    ("scipy", "so3"): dict(color="0.5", marker="v", linestyle="--"),
    ("euler", "full"): dict(color="C4", marker="D"),
    ("gyroscopic", "default"): dict(color="C5", marker="*", markersize=11),
}


def _curve(ax, rows, key, label, style):
    rows = [r for r in rows if np.isfinite(r[key])]
    if not rows:
        return
    x = [r["wall"] for r in rows]
    y = [max(r[key], 1e-16) for r in rows]
    ax.loglog(x, y, label=label, **{"markersize": 6, **style})
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())


def chart(std, euler):
    fig, axes = plt.subplots(1, 3 if euler else 2, figsize=(19 if euler else 13, 6.5),
                             constrained_layout=True)
    for ax, key, ylabel in ((axes[0], "theta_err", "max |theta - theta_ref| over 201 saves (rad)"),
                            (axes[1], "t_inv_err", "|t_invert - t_invert_ref| (s)")):
        for (model, solver), style in STYLE.items():
            if model in ("scipy", "euler", "gyroscopic"):
                continue
            sel = [r for r in std["rows"] if r["model"] == model and r["solver"] == solver]
            name = "default (=Dopri8)" if solver == "default" else solver
            _curve(ax, sel, key, f"tippejax {model} {name}", style)
        for model in ("full", "so3"):
            _curve(ax, std["scipy"][model], key, f"scipy DOP853, numpy {model} model",
                   STYLE[("scipy", model)])
        if key == "t_inv_err":
            # theta(t) of the slow flow differs from the full model's by the nutation it drops
            # (~0.1 rad at any tolerance): it is compared on the inversion time only
            sel = [r for r in std["gyro"] if r["model"] == "gyroscopic"]
            _curve(ax, sel, key, "tippejax gyroscopic level (default = Dopri5), vs the full "
                   "reference", STYLE[("gyroscopic", "default")])
        ax.set_xlabel("median wall time per run (s)")
        ax.set_ylabel(ylabel)
        ax.grid(True, which="major", alpha=0.3)
        ax.legend(fontsize=7)
    axes[0].set_title("scene 1: theta0 0.1, spin 150, 20 s (inverts): theta error", fontsize=10)
    axes[1].set_title("scene 1: inversion time error (every curve against its model's "
                      "reference; gyroscopic against the full one)", fontsize=10)
    if euler:
        ax = axes[2]
        for solver in ("Dopri8", "Tsit5"):
            sel = [r for r in euler["rows"] if r["solver"] == solver]
            _curve(ax, sel, "theta_err", f"tippejax full {solver}", STYLE[("full", solver)])
        _curve(ax, euler["vector"], "theta_err", "scipy DOP853, numpy vector form",
               STYLE[("scipy", "full")])
        _curve(ax, euler["euler"], "theta_err", "scipy DOP853, Euler angles (euler_reference)",
               STYLE[("euler", "full")])
        ax.set_title("scene 2: theta0 2.0, near the intermediate state (no pole), full model",
                     fontsize=10)
        ax.set_xlabel("median wall time per run (s)")
        ax.set_ylabel("max |theta - theta_ref| over 201 saves (rad)")
        ax.grid(True, which="major", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"Work-precision, standard top; {machine_line()}; atol = rtol/100; medians of "
                 f"{REPEATS} runs timed side by side (shared, loaded machine)", fontsize=10)
    fig.savefig(HERE / "work_precision.png", dpi=110)
    plt.close(fig)


def fmt(x, spec=".2e"):
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "nan" if x is not None else ""
    return format(x, spec)


SAVES_NOTE = (
    "With 201 save points the gyroscopic run is dominated by writing them (diffrax interpolates"
    " each save time inside the step loop, ~15 us a point on this CPU, against ~1 ms for the wh"
    "ole 20 s summary-mode run): the ratios here are 8-40x, against 55-80x in summary mode (`benchmarks/LEVELS.md`, speed)."
)


def gyro_lines(std):
    """The gyroscopic level's curve of the chart, against the full model timed beside it."""
    gyro = {r["rtol"]: r for r in std["gyro"] if r["model"] == "gyroscopic"}
    full = {r["rtol"]: r for r in std["gyro"] if r["model"] == "full"}
    rows = [[fmt(rtol, ".0e"), fmt(g["wall"], ".5f"), fmt(full[rtol]["wall"], ".4f"),
             fmt(full[rtol]["wall"] / g["wall"], ".0f"), fmt(full[rtol]["cpu"] / g["cpu"], ".0f"),
             g["steps"], full[rtol]["steps"], fmt(g["t_inv_err"]), fmt(full[rtol]["t_inv_err"]),
             fmt(g["theta_err"]), g["result"]] for rtol, g in gyro.items()]
    return [
        "",
        "### The gyroscopic level on the chart (scene 1)",
        "",
        "The slow flow for theta alone (`model=\"gyroscopic\"`, its default solver Dopri5, 201 "
        "saves) and the full model (default solver) timed side by side at each rtol. Its curve "
        "(middle panel of `work_precision.png`) is the error in **t_invert against the full "
        "model's reference** (Dopri8, rtol 1e-13): theta(t) of the slow flow differs from the "
        "full model's by the nutation it drops (last column, about 0.1 rad at any tolerance), "
        "so it is compared on the inversion time only. Its error flattens at the level's model "
        "error (the slow-manifold approximation and the projection of this omega = n a launch, "
        "`benchmarks/LEVELS.md`), which no tolerance removes. " + SAVES_NOTE,
        "",
        table(["rtol", "gyro wall s", "full wall s", "full/gyro wall", "full/gyro CPU",
               "gyro steps", "full steps", "gyro d t_invert (s)", "full d t_invert (s)",
               "gyro max d theta (rad)", "gyro result"], rows),
    ]


def report(std, euler, compiles, watch, exact, stiff_res, elapsed):
    ratios = []
    for model in ("full", "so3"):
        sel = [r for r in std["rows"] if r["model"] == model]
        ratios += equal_error_ratios(sel, std["scipy"][model])
    judged = [r for r in ratios if r["solver"] == "default" and 1e-10 <= r["rtol"] <= 1e-6]
    in_range = [r for r in ratios if 1e-10 <= r["rtol"] <= 1e-6]
    worst = min(judged, key=lambda r: r["ratio"])
    best = max(in_range, key=lambda r: r["ratio"])
    worst_compile = max(c["compile"] for c in compiles.values())
    plain = next(r for r in watch["rows"] if r["what"].startswith("plain diffeqsolve, flat"))
    tj8 = next(r for r in watch["rows"] if r["what"] == "tj.simulate, event_pieces=1")
    only = {w: next(r for r in watch["rows"] if r["what"].endswith(f"only {w}"))
            for w in ("theta", "t_invert")}
    watched = next(r for r in watch["rows"] if "WatchedSolver" in r["what"])
    evented = next(r for r in watch["rows"] if "diffrax.Event" in r["what"])
    scipy_full = std["scipy"]["full"]
    scipy_step = statistics.median(r["wall"] / r["steps"] for r in scipy_full)
    scipy_eval = statistics.median(r["wall"] / r["nfev"] for r in scipy_full)
    lines = [
        "## engine.py: one top, work-precision against scipy, compile time, events",
        "",
        f"`python benchmarks/engine.py` ({elapsed:.0f} s). Chart: `work_precision.png`. "
        "Timings: medians of repeated calls after a first, compiling call, with "
        "`jax.block_until_ready`; runs compared in a ratio are timed side by side (interleaved "
        "rounds), and both wall-clock and process CPU time are kept: the machine is shared "
        f"(1-minute load average {LOAD[0]:.1f} at the start, {os.getloadavg()[0]:.1f} at the "
        "end, 2 cores), and other work inflates wall time by a factor that varies from run to "
        "run; CPU time is not inflated by waiting.",
        "",
        "### Targets",
        "",
        "| target | measured | verdict |",
        "|---|---|---|",
        "| scipy/tippejax time at equal error >= 50x, rtol 1e-6..1e-10 | default solver "
        "(Dopri8): "
        + ", ".join(f"{r['model']} {r['rtol']:.0e}: {r['ratio']:.1f}x" for r in judged)
        + " (wall); CPU time: "
        + ", ".join(f"{r['ratio_cpu']:.1f}x" for r in judged)
        + f". Best of any solver: {best['ratio']:.1f}x ({best['model']} {best['solver']} "
        f"{best['rtol']:.0e}) | {verdict(worst['ratio'] >= 50)}: "
        f"{worst['ratio']:.1f}x at worst, {50 / worst['ratio']:.0f}x short |",
        "| first-call compile <= 5 s per level | "
        + ", ".join(f"{m} {c['compile']:.1f} s (CPU {c['compile_cpu']:.1f} s)"
                    for m, c in compiles.items())
        + " | " + ", ".join(f"{m} {verdict(c['compile'] <= 5)}" for m, c in compiles.items())
        + ("" if worst_compile <= 5 else f" ({worst_compile / 5:.1f}x over at worst: the "
           "Routhian level compiles two segments, itself and its SO(3) fallback)") + " |",
        f"| t_invert independent of the save grid | 6-point grid {exact['coarse']:.12f} s, "
        f"201-point {exact['fine']:.12f} s (diff {abs(exact['coarse'] - exact['fine']):.1e} s) "
        f"| {verdict(abs(exact['coarse'] - exact['fine']) < 1e-9)} |",
        f"| spin-200 contact loss found at 5.1865 s (Dopri8, rtol 1e-6) | {exact['t_loss']:.6f} s "
        f"(rtol 1e-12: {exact['t_loss_ref']:.6f} s) | "
        f"{verdict(abs(exact['t_loss'] - 5.1865) < 5e-5)} |",
        f"| 40 s run, spin 300, rtol 1e-10 finishes (no max_steps) | t_final "
        f"{exact['long_t_final']} (on_contact_loss='continue'), {exact['long_steps']} steps, "
        f"{exact['long_time']:.1f} s | {verdict(exact['long_t_final'] == 40.0)} |",
        "",
        "**Why the 50x target is missed (profile; wall-clock unless said).** Both codes run an "
        "8th-order Dormand-Prince pair (Dopri8 / DOP853) and, at equal error, about the same "
        "number of steps, so the ratio is a ratio of costs per step. scipy's DOP853 costs "
        f"{1e6 * scipy_step:.0f} us per step ({1e6 * scipy_eval:.1f} us per right-hand-side "
        "call, 12 calls per step: most of a step is scipy's own Python bookkeeping). A "
        f"tippejax step (`tj.simulate`, rtol {watch['rtol']:.0e}) costs "
        f"{1e6 * tj8['wall'] / tj8['steps']:.0f} us; a plain `diffrax.diffeqsolve` of the same "
        f"field (flat state, no events, no watch) {1e6 * plain['wall'] / plain['steps']:.0f} us, "
        f"of which the 13 right-hand-side evaluations take only "
        f"{13e6 * watch['rhs_in_loop']:.1f} us ({1e6 * watch['rhs_in_loop']:.2f} us each inside "
        "an XLA loop). The rest of a diffrax step is bookkeeping on 13-element arrays "
        "(controller, error norm, dense output, save grid, event check) that XLA:CPU runs as a "
        f"sequence of small kernels (the compiled plain solve has "
        f"{watch['sizes']['plain diffeqsolve'][0]} HLO instructions, tippejax's "
        f"{watch['sizes']['tj.simulate (full, 201 saves)'][0]}; XLA's cost analysis counts "
        f"{watch['sizes']['plain diffeqsolve'][1]:.0f} flops for one pass through the plain "
        "solve's loop bodies). A single 13-dimensional trajectory has too little arithmetic per "
        "step for a compiled loop to beat an interpreted one by 50x: even a plain diffrax step "
        f"is only {scipy_step / (plain['wall'] / plain['steps']):.1f}x cheaper than scipy's, and "
        f"tippejax's engine adds {tj8['wall'] / plain['wall']:.2f}x on top (event watch "
        f"{watched['wall'] / plain['wall']:.2f}x, terminating Event "
        f"{evented['wall'] / plain['wall']:.2f}x, the rest in locating the observed events and "
        "observing the saved states). The large factors come from batches "
        "(`benchmarks/batch.py`).",
        "",
        "**CPU time is ~2x wall time for `tj.simulate`** (the table below): a jitted summary "
        f"solve returning only the final theta takes {only['theta']['wall']:.4f} s wall, "
        f"{only['theta']['cpu']:.4f} s CPU; the same solve returning t_invert "
        f"{only['t_invert']['wall']:.4f} s wall but {only['t_invert']['cpu']:.4f} s CPU. When the "
        "observed event is located from its step's stored dense output after the solve, XLA "
        "keeps a second thread busy for the whole solve without making it faster. On an idle "
        "machine this costs little wall time; on a loaded one (or next to other work) it "
        "costs up to 2x (the 'ratio CPU' column shows the ratios in CPU time).",
        "",
        "### Scene 1: standard top, theta0 = 0.1, spin 150 rad/s, t1 = 20 s, 201 saves",
        "",
    ]
    refs, checks = std["refs"], std["checks"]
    lines += [
        f"Reference: tippejax Dopri8, rtol 1e-13, atol 1e-15, per model: full t_invert = "
        f"{refs['full']['t_invert']:.10f} s ({refs['full']['steps']} steps), so3 t_invert = "
        f"{refs['so3']['t_invert']:.10f} s. Against scipy DOP853 at rtol 1e-12, atol 1e-14 on "
        f"the numpy model: full max|d theta| = {checks['full'][0]:.1e} rad, |d t_invert| = "
        f"{checks['full'][1]:.1e} s; so3 {checks['so3'][0]:.1e} rad, {checks['so3'][1]:.1e} s. "
        f"The numpy right-hand side agrees with tippejax's vector field to "
        f"{max(std['rhs'].values()):.0e} (relative, 20 random states). scipy's state has no "
        "body vector (it does not enter the dynamics), so its RMS error norm runs over 10 "
        "(full) / 6 (so3) components instead of tippejax's 13 / 9.",
        "",
        "The default solver of the standard top is Dopri8 (friction rate "
        f"{float(tj.friction_rate(tj.default_top())):.1f}/s < 1000/s): the 'default' rows run "
        "the same compiled function as the Dopri8 rows; they are the ones the target is "
        "judged on (the spread between the two is the machine's noise).",
        "",
        "'scipy s at same error': `log(scipy time)` interpolated linearly in "
        "`log(scipy max|d theta|)` between the two scipy runs (rtol 1e-3..1e-11) whose errors "
        "bracket tippejax's, or extrapolated from the nearest two if none do (marked *). "
        "'ratio' = that time / tippejax's time (wall; 'ratio CPU' the same with CPU times); "
        "'ratio @rtol' = scipy / tippejax at the same rtol (wall). 'compile s' = first call "
        "less the median (in the first row of each model and solver; later rtols reuse the "
        "compilation since rtol/atol are traced).",
        "",
    ]
    scipy_at = {(m, r["rtol"]): r for m in ("full", "so3") for r in std["scipy"][m]}
    rows = []
    for r in ratios:
        s = scipy_at.get((r["model"], r["rtol"]))
        rows.append([
            r["model"], r["solver"], fmt(r["rtol"], ".0e"), fmt(r["wall"], ".4f"),
            fmt(r["cpu"], ".4f"), fmt(r["compile"], ".1f") if r["rtol"] == RTOLS[0] else "",
            r["steps"], r["rejected"], fmt(r["theta_err"]), fmt(r["t_inv_err"]),
            fmt(r["scipy_wall"], ".3f") + ("*" if r["extrapolated"] else ""),
            fmt(r["ratio"], ".1f"), fmt(r["ratio_cpu"], ".1f"),
            fmt(s["wall"] / r["wall"], ".1f") if s else "", r["result"],
        ])
    lines.append(table(
        ["model", "solver", "rtol", "wall s", "CPU s", "compile s", "steps", "rejected",
         "max d theta", "d t_invert", "scipy s at same error", "ratio", "ratio CPU",
         "ratio @rtol", "result"], rows))
    lines += ["", "scipy baseline (`solve_ivp(method='DOP853')`, numpy vector-form model, "
              "`_common.VectorModel`):", ""]
    rows = []
    for m in ("full", "so3"):
        for r in std["scipy"][m]:
            rows.append([m, fmt(r["rtol"], ".0e"), fmt(r["wall"], ".4f"), fmt(r["cpu"], ".4f"),
                         r["nfev"], r["steps"], fmt(1e6 * r["cpu"] / r["steps"], ".0f"),
                         fmt(r["theta_err"]), fmt(r["t_inv_err"])])
    lines.append(table(["model", "rtol", "wall s", "CPU s", "nfev", "steps", "CPU us/step",
                        "max d theta", "d t_invert"], rows))
    lines += gyro_lines(std)
    if euler:
        lines += [
            "",
            "### Scene 2: away from the poles (independent Euler-angle baseline)",
            "",
            "The scene suggested in the brief (theta0 = 0.1 with J = 5e-6) does not stay away "
            "from the poles: launched with theta_dot = 0 it first nutates down to theta ~ 0.003 "
            "rad, where `euler_reference` stops (chart singular). Used instead: "
            f"theta0 = {euler['theta0']}, phi_dot0 = {euler['phi_dot']:.4f} rad/s, spin "
            f"{euler['spin']:.4f} rad/s (the precession rate and spin of the intermediate "
            "state of J = 5e-6, read off a run that settles into it). It nutates around the "
            f"intermediate state: theta in [{euler['range'][0]:.3f}, {euler['range'][1]:.3f}] "
            f"({'inside' if euler['inside'] else 'NOT inside'} [0.1, pi - 0.1]). Reference: "
            "tippejax full Dopri8 1e-13; `euler_reference.solve` at rtol 1e-12 agrees with it "
            f"to {euler['check']:.1e} rad.",
            "",
        ]
        rows = []
        ratio_v = equal_error_ratios(euler["rows"], euler["vector"])
        ratio_e = equal_error_ratios(euler["rows"], euler["euler"])
        for rv, re_ in zip(ratio_v, ratio_e):
            rows.append([rv["solver"], fmt(rv["rtol"], ".0e"), fmt(rv["wall"], ".4f"),
                         fmt(rv["cpu"], ".4f"), rv["steps"], fmt(rv["theta_err"]),
                         fmt(rv["ratio"], ".1f") + ("*" if rv["extrapolated"] else ""),
                         fmt(re_["ratio"], ".1f") + ("*" if re_["extrapolated"] else ""),
                         fmt(re_["ratio_cpu"], ".1f")])
        lines.append(table(["tippejax full", "rtol", "wall s", "CPU s", "steps", "max d theta",
                            "scipy vector / tippejax (equal error, wall)",
                            "scipy Euler / tippejax (equal error, wall)",
                            "scipy Euler / tippejax (CPU)"], rows))
        lines += [""]
        rows = [[w, fmt(r["rtol"], ".0e"), fmt(r["wall"], ".4f"), fmt(r["cpu"], ".4f"),
                 r["nfev"], fmt(r["theta_err"])]
                for w, sel in (("numpy vector form", euler["vector"]),
                               ("Euler angles (euler_reference)", euler["euler"]))
                for r in sel]
        lines.append(table(["scipy DOP853 on", "rtol", "wall s", "CPU s", "nfev",
                            "max d theta"], rows))
    else:
        lines += ["", "Scene 2 skipped: `tests/euler_reference.py` is absent."]
    lines += [
        "",
        "### First-call compile time per level",
        "",
        "Each level in a fresh process: `tj.simulate(top, y0, 20.0, model=..., saveat=201 "
        "points, rtol=1e-8, throw=False)` with the default solver (Dopri8); compile = first "
        "call minus the median of 3 later calls (wall; CPU the same with process time).",
        "",
        table(["level", "first call s", "median s", "compile s (wall)", "compile s (CPU)",
               "model run", "steps"],
              [[m, fmt(c["first"], ".2f"), fmt(c["median"], ".3f"), fmt(c["compile"], ".2f"),
                fmt(c["compile_cpu"], ".2f"), c["model"], c["steps"]]
               for m, c in compiles.items()]),
        "",
        "The Routhian level compiles two segments (Routhian, then its SO(3) fallback) and so "
        "about twice the code of a single level.",
        "",
        "### Cost of the event watch and of the rest of the engine",
        "",
        f"Scene 1, full model, Dopri8, rtol {watch['rtol']:.0e}, 201 saves; all rows timed side "
        f"by side ({REPEATS + 2} interleaved rounds).",
        "",
    ]
    rows = [[r["what"], fmt(r["wall"], ".4f"), fmt(r["cpu"], ".4f"),
             fmt(r["cpu"] / plain["cpu"], ".2f"), "" if r["steps"] is None else r["steps"],
             "" if r["rejected"] is None else r["rejected"],
             fmt(r["compile"], ".1f"), fmt(r["t_invert"], ".10f")]
            for r in watch["rows"]]
    lines.append(table(["run", "wall s", "CPU s", "CPU / plain diffeqsolve", "steps",
                        "rejected", "first-call extra s", "t_invert"], rows))
    lines += [
        "",
        "'first-call extra' is 0 where an earlier part of the script compiled the same function "
        "(event_pieces=1 is the function of the work-precision sweep).",
        "",
        "### Events and max_steps",
        "",
        f"- t_invert (default solver, rtol 1e-8): 6-point grid [0.5, 1, 2, 5, 10, 20] "
        f"{exact['coarse']:.12f} s, 201-point grid {exact['fine']:.12f} s, summary mode "
        f"{exact['summary']:.12f} s.",
        f"- Contact loss, spin 200, theta0 0.1, t1 7, Dopri8 rtol 1e-6, throw=False: "
        f"t_contact_loss = **{exact['t_loss']:.6f} s** ({exact['loss_steps']} steps); rtol "
        f"1e-12: {exact['t_loss_ref']:.6f} s; with on_contact_loss='continue': "
        f"{exact['t_loss_continue']:.6f} s.",
        f"- 40 s at rtol 1e-10 (atol 1e-12), spin 300, theta0 0.1, summary mode, default "
        f"max_steps = 1e6: this launch leaves the table during its rise; with the default "
        f"on_contact_loss='stop' the run ends at t = {exact['stop_t_final']:.4f} s "
        f"({exact['stop_steps']} steps). With on_contact_loss='continue' all 40 s are "
        f"integrated: t_final = {exact['long_t_final']}, {exact['long_steps']} steps "
        f"({exact['long_rejected']} rejected), {exact['long_time']:.2f} s wall, result "
        f"'{exact['long_result'][:30]}...' (the contact loss at {exact['long_t_loss']:.4f} s is "
        f"flagged), |J/J0 - 1| = {exact['long_j_drift']:.1e}.",
    ]
    lines += [
        "",
        "### Stiff friction: where the default solver changes",
        "",
        f"Standard top with larger mu, theta0 0.1, spin 100 rad/s, t1 = 0.5 s, rtol 1e-8, 201 "
        f"saves; error max |d theta| against Kvaerno5 at rtol 1e-11; 2 interleaved rounds. "
        f"`default_solver`: Dopri8 below a friction rate of {stiff_res['stiff_rate']:g}/s, "
        f"Tsit5 up to {stiff_res['implicit_rate']:g}/s, Kvaerno5 above.",
        "",
        table(["mu (s/m)", "friction rate (1/s)", "solver", "wall s", "CPU s", "steps",
               "max d theta", "result", "default picks"],
              [[f"{r['mu']:g}", f"{r['rate']:.3g}", r["solver"], fmt(r["wall"], ".3f"),
                fmt(r["cpu"], ".3f"), r["steps"], fmt(r["err"], ".1e"), r["result"][:30],
                r["default"]] for r in stiff_res["rows"]]),
    ]
    return "\n".join(lines), ratios


def main():
    start = time.perf_counter()
    say(machine_line())
    std = scene_standard()
    euler = scene_euler()
    say("Compile time per level (fresh processes)")
    compiles = compile_times()
    say("Event watch")
    watch = watch_cost()
    say("Events and max_steps")
    exact = exactness()
    say("Stiff friction")
    stiff_res = stiff()
    chart(std, euler)
    body, ratios = report(std, euler, compiles, watch, exact, stiff_res,
                          time.perf_counter() - start)
    say("\nscipy/tippejax at equal error (wall, CPU):")
    for r in ratios:
        say(f"  {r['model']:4s} {r['solver']:8s} rtol {r['rtol']:.0e}: {r['ratio']:.2f}x, "
            f"{r['ratio_cpu']:.2f}x{' (extrapolated)' if r['extrapolated'] else ''}")
    write_section("engine.py", body)
    say(f"done in {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
