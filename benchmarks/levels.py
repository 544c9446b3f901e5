"""The model ladder: error of each cheaper level against the full model, and its cost.

Scenes of the standard IIb top (and variants), grouped by the regime `model="auto"` reads off a
launch (`tippejax._auto.launch_regime`: stiff friction, moving centre of mass, or where the
launch's Jellet sends the top). For each scene, runs the full, SO(3) and Routhian levels from the
same state (default solver, rtol 1e-8), and the gyroscopic level (slow flow for theta alone; it may
refuse a launch or stop where gyroscopic balance fails: "refused"/"stopped", unusable, error inf),
and reports max |theta_level(t) - theta_full(t)| (rad),
the difference in inversion time, and the median wall time after compilation relative to the
full model (one jitted function per level, all scenes through it). Then, for the gyroscopic
level: its error against the SO(3) and full models as a function of the spin (with the fitted
power law of the t_invert error) and of mu, and its speed against the full model over a 20 s run.
Writes benchmarks/LEVELS.md; the worst error and median cost per regime go into group IIb of
`tippejax/_auto.py`'s `MEASURED`, merged with the per-group scenes of `levels_groups.py`.

    python benchmarks/levels.py             # everything (rewrites LEVELS.md)
    python benchmarks/levels.py --spun      # the spun-launch section only (levels_spun.py)
    python benchmarks/levels.py --groups    # the section on every group only (and MEASURED)
"""

from __future__ import annotations

import pathlib
import platform
import statistics
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import tippejax as tj
from tippejax._auto import accepts, launch_regime

HERE = pathlib.Path(__file__).parent
LEVELS = ("so3", "routhian", "gyroscopic")
FALLBACK = {"so3": "so3", "routhian": "so3", "gyroscopic": "full"}
N_SAVE = 2001
REPEATS = 5
IIB_SCENES_NAME = "MEASURED_IIB_SCENES"
"""The per-regime table of these (group IIb) scenes in LEVELS.md; `--groups` merges it into
group IIb of the `MEASURED` table it writes."""


def _spin_for_jellet(top, theta0, J):
    probe = tj.initial_state(top, theta0, 1.0)  # J is linear in the spin when phi_dot = 0
    return J / float(tj.jellet(top, probe))


def scenes():
    std = tj.default_top()
    iib = tj.TippeTop.from_ratios(0.9, 0.3, mu=1.0)
    th = tj.thresholds(iib)
    j_mid = 0.5 * (float(th.J1) + float(th.J2))
    stiff = tj.TippeTop.from_ratios(0.9, 0.3, mu=300.0)
    s = tj.initial_state
    return [
        ("inverting (n0=100, theta0=0.1)", std, s(std, 0.1, 100.0), 10.0),
        ("inverting (n0=150, theta0=0.1)", std, s(std, 0.1, 150.0), 10.0),
        ("near the pole (n0=60, theta0=0.02)", std, s(std, 0.02, 60.0), 10.0),
        ("inverting, nutating (n0=80, theta0=0.5, thd=2)", std, s(std, 0.5, 80.0, theta_dot=2.0), 10.0),
        ("upright (n0=20 < n1, theta0=0.1)", std, s(std, 0.1, 20.0), 5.0),
        ("upright (n0=15, theta0=0.4)", std, s(std, 0.4, 15.0), 5.0),
        ("to intermediate (mu=1, J mid, theta0=0.1)", iib, s(iib, 0.1, _spin_for_jellet(iib, 0.1, j_mid)), 10.0),
        ("to intermediate (mu=1, J mid, theta0=0.6)", iib, s(iib, 0.6, _spin_for_jellet(iib, 0.6, j_mid)), 10.0),
        ("stiff (mu=300, n0=100, theta0=0.1)", stiff, s(stiff, 0.1, 100.0), 2.0),
        ("stiff (mu=300, n0=60, theta0=0.5)", stiff, s(stiff, 0.5, 60.0), 2.0),
        ("moving CM (theta0=0.5, thd=2, v=(0.2,-0.1))", std, s(std, 0.5, 80.0, theta_dot=2.0, vx=0.2, vy=-0.1), 5.0),
        ("moving CM (theta0=0.2, n0=120, v=(0.1,0.1))", std, s(std, 0.2, 120.0, vx=0.1, vy=0.1), 5.0),
    ]


def make_run(model):
    def run(top, y0, t1, ts):
        return tj.simulate(top, y0, t1, model=model, saveat=ts, throw=False)

    return eqx.filter_jit(run)


def timed(run, *args, repeats=None):
    sol = jax.block_until_ready(run(*args))
    times = []
    for _ in range(REPEATS if repeats is None else repeats):
        start = time.perf_counter()
        sol = jax.block_until_ready(run(*args))
        times.append(time.perf_counter() - start)
    return sol, statistics.median(times)


BATCH = 256


def batch_costs():
    """Cost per launch of each level in a vmapped batch (summary mode), relative to full.

    A single top on a CPU costs the solver's fixed work per step; in a batch that is shared
    by the members and the arithmetic of the state and right-hand side counts for more.
    """
    top = tj.default_top()
    thetas = jnp.linspace(0.05, 0.3, BATCH)
    spins = jnp.linspace(100.0, 150.0, BATCH)
    out = {}
    for model in ("full", *LEVELS):
        @eqx.filter_jit
        def run(thetas, spins, model=model):
            def one(th, n):
                sol = tj.simulate(top, tj.initial_state(top, th, n), 3.0, model=model,
                                  summary=True, throw=False)
                return sol.theta[-1], sol.num_steps
            return jax.vmap(one)(thetas, spins)

        (_, steps), t = timed(run, thetas, spins)
        out[model] = (t, int(np.max(steps)))
    return out


INF = float("inf")


def _fmt(x, spec=".2e"):
    return "inf" if x == INF else format(x, spec)


def _py(x, spec=".3g"):
    return 'float("inf")' if x == INF else format(x, spec)


def scene_row(runs, name, top, y0, t1, *, repeats=None):
    """One scene in every level: theta error against the full model, cost (median of
    `repeats`, default `REPEATS`, timed runs after a first one, relative to the full model)."""
    regime = launch_regime(top, y0)
    ts = jnp.linspace(0.0, t1, N_SAVE)
    t1_ = jnp.asarray(t1)
    ref, t_ref = timed(runs["full"], top, y0, t1_, ts, repeats=repeats)
    row = dict(scene=name, regime=regime, t_invert_full=float(ref.t_invert),
               ok_full=bool(ref.result == tj.RESULTS.successful), steps_full=int(ref.num_steps))
    for level in LEVELS:
        if not accepts(level, top, y0):
            # outside the level's chart at launch: auto never picks it for this launch (the
            # level itself would run the full model from the start): not run
            row[level] = dict(theta_err=INF, t_invert_err=INF, cost=float("nan"),
                              model="refused", steps=0, ok=False)
            continue
        sol, t_level = timed(runs[level], top, y0, t1_, ts, repeats=repeats)
        both = np.isfinite(np.asarray(sol.theta)) & np.isfinite(np.asarray(ref.theta))
        err = float(np.max(np.abs(np.asarray(sol.theta)[both] - np.asarray(ref.theta)[both]),
                           initial=0.0)) if both.any() else INF
        switched = bool(np.isfinite(float(sol.t_chart_switch)))
        label = f"{level}->{FALLBACK[level]}" if switched else level
        if bool(sol.result == tj.RESULTS.no_gyroscopic_balance):
            # stopped on the way (a level without a hand-over): unusable here
            if int(sol.num_steps) == 0:
                label = "refused"
            else:
                t_stop = float(np.max(np.asarray(ts)[np.isfinite(np.asarray(sol.theta))],
                                      initial=0.0))
                label = f"stopped at t={t_stop:.2f}"
            err = INF
        row[level] = dict(
            theta_err=err,
            t_invert_err=INF if err == INF else abs(float(sol.t_invert) - float(ref.t_invert)),
            cost=t_level / t_ref,
            model=label,
            steps=int(sol.num_steps),
            ok=bool(sol.result == tj.RESULTS.successful),
        )
    return row


# --- the gyroscopic level against the SO(3) and full models --------------------------------

GYRO_THETA0 = 0.1
GYRO_SPINS = (60.0, 80.0, 100.0, 140.0, 200.0)
GYRO_MUS = (0.1, 0.3, 1.0, 3.0)
SMOOTH_PERIODS = 3


def on_slow_manifold(top, theta, J):
    """The state on the gyroscopic slow manifold at theta for the Jellet J (no nutation)."""
    from tippejax._models.gyroscopic import GyroscopicLevel, GyroscopicLevelState

    y = GyroscopicLevelState.from_theta(jnp.asarray(theta, jnp.float64), phi=0.0, psi=0.0,
                                        nutation=jnp.log(1e-12), jellet=J)
    return GyroscopicLevel().to_state(top, y)


def smoothed(theta, dt, period):
    """Moving average of theta over SMOOTH_PERIODS nutation periods; nan where the window
    does not fit (edges, or nan inside it)."""
    w = max(1, int(round(SMOOTH_PERIODS * period / dt)))
    out = np.full_like(theta, np.nan)
    if w >= len(theta):
        return out
    c = np.convolve(theta, np.ones(w) / w, mode="valid")
    start = w // 2
    out[start:start + len(c)] = c
    return out


def gyro_compare(runs, top, y0, t1):
    """Errors of the gyroscopic level against so3 and full from y0 (single runs)."""
    from tippejax._models.gyroscopic import nutation_frequency

    ts = jnp.linspace(0.0, t1, N_SAVE)
    dt = t1 / (N_SAVE - 1)
    t1_ = jnp.asarray(t1)
    sols = {m: runs[m](top, y0, t1_, ts) for m in ("gyroscopic", "so3", "full")}
    g = sols["gyroscopic"]
    stopped = bool(g.result == tj.RESULTS.no_gyroscopic_balance)
    status = "ok" if bool(g.result == tj.RESULTS.successful) else (
        ("refused" if int(g.num_steps) == 0 else "stopped") if stopped else "failed")
    out = dict(result=status, steps=int(g.num_steps),
               t_invert={m: float(s.t_invert) for m, s in sols.items()})
    J = float(tj.jellet(top, y0))
    theta0 = float(np.arccos(np.clip(float(y0.axis[2]), -1.0, 1.0)))
    nu = float(nutation_frequency(top, theta0, J))
    period = 2 * np.pi / nu
    out["nutation_period"] = period
    th_g = np.asarray(g.theta)
    for ref in ("so3", "full"):
        th_r = np.asarray(sols[ref].theta)
        both = np.isfinite(th_g) & np.isfinite(th_r)
        out[f"theta_err_{ref}"] = float(np.max(np.abs(th_g - th_r)[both])) if both.any() else INF
        sm = smoothed(th_r, dt, period)
        both = np.isfinite(th_g) & np.isfinite(sm)
        out[f"theta_err_avg_{ref}"] = float(np.max(np.abs(th_g - sm)[both])) if both.any() else INF
        out[f"t_invert_err_{ref}"] = out["t_invert"]["gyroscopic"] - out["t_invert"][ref]
    out["ok"] = bool(g.result == tj.RESULTS.successful)
    return out


def power_law(xs, errs):
    xs, errs = np.asarray(xs, float), np.abs(np.asarray(errs, float))
    good = np.isfinite(errs) & (errs > 0)
    if good.sum() < 2:
        return float("nan")
    return float(np.polyfit(np.log(xs[good]), np.log(errs[good]), 1)[0])


def with_mu(top, mu):
    return eqx.tree_at(lambda t: t.mu, top, jnp.asarray(mu, jnp.asarray(top.mu).dtype))


def gyro_vs_spin(runs):
    top = tj.default_top()
    rows = []
    for n0 in GYRO_SPINS:
        launch = tj.initial_state(top, GYRO_THETA0, n0)
        J = float(tj.jellet(top, launch))
        a = gyro_compare(runs, top, launch, 10.0)
        b = gyro_compare(runs, top, on_slow_manifold(top, GYRO_THETA0, J), 10.0)
        rows.append(dict(n0=n0, launch=a, manifold=b))
        print("spin", n0, a, b, flush=True)
    return rows


def gyro_vs_mu(runs):
    base = tj.default_top()
    rows = []
    for mu in GYRO_MUS:
        top = with_mu(base, mu)
        t1 = max(10.0, 2.0 * 5.7 * 0.3 / mu)  # the rise time scales as 1/mu
        launch = tj.initial_state(top, GYRO_THETA0, 100.0)
        J = float(tj.jellet(top, launch))
        a = gyro_compare(runs, top, launch, t1)
        b = gyro_compare(runs, top, on_slow_manifold(top, GYRO_THETA0, J), t1)
        rows.append(dict(mu=mu, t1=t1, regime=launch_regime(top, launch), launch=a, manifold=b))
        print("mu", mu, a, b, flush=True)
    return rows


SPEED_T1 = 20.0
SPEED_REPEATS = 7


def gyro_speed():
    """Wall time of a jitted summary-mode run, gyroscopic against full, 20 s, rtol 1e-8,
    default top, theta0 0.1, spin 100 (interleaved repeats), and the split into a fixed
    per-call cost and a per-step cost (from a short run of each)."""
    top = tj.default_top()
    y0 = tj.initial_state(top, GYRO_THETA0, 100.0)
    fns = {}
    for model in ("gyroscopic", "full"):
        @eqx.filter_jit
        def run(top, y0, t1, model=model):
            sol = tj.simulate(top, y0, t1, model=model, summary=True, rtol=1e-8, throw=False)
            return sol.t_invert, sol.num_steps
        fns[model] = run
    out = {}
    for t1 in (SPEED_T1, 0.01):
        t1_ = jnp.asarray(t1)
        times = {m: [] for m in fns}
        steps = {}
        for m, f in fns.items():
            _, steps[m] = jax.block_until_ready(f(top, y0, t1_))
        for _ in range(SPEED_REPEATS):
            for m, f in fns.items():
                start = time.perf_counter()
                jax.block_until_ready(f(top, y0, t1_))
                times[m].append(time.perf_counter() - start)
        out[t1] = {m: (statistics.median(times[m]), int(steps[m])) for m in fns}
    print("speed", out, flush=True)
    return out


def regime_lines(measured, *, indent):
    return [
        f'{indent}"{regime}": {{'
        + ", ".join(f'"{lv}": ({_py(m[lv][0])}, {_py(m[lv][1], ".2f")})' for lv in LEVELS)
        + "},"
        for regime, m in measured.items()
    ]


def per_regime(rows):
    """{regime: {level: (worst theta error, median cost)}} over the rows of each regime."""
    regimes = sorted({r["regime"] for r in rows}, key=[r["regime"] for r in rows].index)
    measured = {}
    for regime in regimes:
        sel = [r for r in rows if r["regime"] == regime]
        measured[regime] = {}
        for lv in LEVELS:
            # auto picks a level only for a launch it accepts (`choose_model` checks `in_chart`):
            # its error and cost are over the scenes of the regime it accepts; a scene where it
            # stopped on the way counts (inf). None accepted (not run): inf, cost inf.
            used = [r for r in sel if r[lv]["model"] != "refused"]
            measured[regime][lv] = (
                (max(r[lv]["theta_err"] for r in used),
                 float(np.median([r[lv]["cost"] for r in used]))) if used else (INF, INF))
    return measured


def main():
    t_start = time.perf_counter()
    batch = batch_costs()
    print("batch", batch, flush=True)
    runs = {m: make_run(m) for m in ("full", *LEVELS)}
    rows = []
    for name, top, y0, t1 in scenes():
        row = scene_row(runs, name, top, y0, t1)
        rows.append(row)
        print(name, row["regime"], {k: v for k, v in row.items() if k not in ("scene", "regime")},
              flush=True)
    spin_rows = gyro_vs_spin(runs)
    mu_rows = gyro_vs_mu(runs)
    speed = gyro_speed()
    measured = per_regime(rows)
    lines = [
        "# The model ladder: error of each level against the full model",
        "",
        "Made by `python benchmarks/levels.py` (float64, rtol 1e-8, atol 1e-10, default solver "
        f"(Dopri8; Tsit5 for the stiff scenes), {N_SAVE} save points). Machine: "
        f"{platform.machine()}, {jax.devices()[0].platform}, jax {jax.__version__}. Error: max "
        "over the save times of |theta_level - theta_full| (rad); inversion: |t_invert_level - "
        "t_invert_full| (s, nan when neither inverts); cost: median wall time of "
        f"{REPEATS} runs after compilation, relative to the full model in the same run (a "
        "ratio; absolute times on this shared machine mean little). Regime: what "
        "`tippejax._auto.launch_regime` reads off the launch. The gyroscopic level refuses a "
        "launch it cannot describe, or stops where gyroscopic balance fails or the nutation "
        "it drops grows (`RESULTS.no_gyroscopic_balance`): shown as refused/stopped, error inf. "
        "Its theta error is mostly the nutation it drops (see the section below).",
        "",
        "| scene | regime | t_invert full (s) | so3 theta err | so3 t_invert err | so3 cost | routhian theta err | routhian t_invert err | routhian cost | gyro theta err | gyro t_invert err | gyro cost | steps full/so3/routhian/gyro | routhian used | gyro used |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        s, r, g = row["so3"], row["routhian"], row["gyroscopic"]
        lines.append(
            f"| {row['scene']} | {row['regime']} | {row['t_invert_full']:.4f} | "
            f"{s['theta_err']:.2e} | {s['t_invert_err']:.2e} | {s['cost']:.2f} | "
            f"{r['theta_err']:.2e} | {r['t_invert_err']:.2e} | {r['cost']:.2f} | "
            f"{_fmt(g['theta_err'])} | {_fmt(g['t_invert_err'])} | {g['cost']:.2f} | "
            f"{row['steps_full']}/{s['steps']}/{r['steps']}/{g['steps']} | {r['model']} | {g['model']} |"
        )
    lines += [
        "",
        "Per regime (worst theta error over its scenes, median cost): the group IIb entries of "
        "`tippejax/_auto.py` `MEASURED`, merged there with the IIb scenes of the section on "
        "every group below (`--groups`). For the gyroscopic level, over the scenes of the regime "
        "it accepts (`model=\"auto\"` only picks it for a launch it accepts: `choose_model` "
        "checks `in_chart`); a scene where it stopped on the way counts as inf. The error is the "
        "same metric as for the other levels, max |theta - theta_full| over the run, which is "
        "what `tolerance` bounds: for the gyroscopic level it includes the nutation it drops "
        "(0.1-0.3 rad for these launches with omega = n a), so auto picks it only at a loose "
        "tolerance, or in the stiff regime.",
        "",
        "| regime | so3 worst err | so3 cost | routhian worst err | routhian cost | gyro worst err | gyro cost | gyro scenes accepted |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for regime, m in measured.items():
        sel = [r for r in rows if r["regime"] == regime]
        accepted = sum(r["gyroscopic"]["model"] != "refused" for r in sel)
        lines.append(
            f"| {regime} | {m['so3'][0]:.3g} | {m['so3'][1]:.2f} | {m['routhian'][0]:.3g} | "
            f"{m['routhian'][1]:.2f} | {_fmt(m['gyroscopic'][0], '.3g')} | {m['gyroscopic'][1]:.2f} "
            f"| {accepted}/{len(sel)} |"
        )
    lines += [
        "",
        f"Vmapped batch of {BATCH} inverting launches (theta0 0.05-0.3, spin 100-150, 3 s, "
        "summary mode), median wall time relative to the full model: "
        + ", ".join(f"{m} {t / batch['full'][0]:.2f} (max steps {n})" for m, (t, n) in batch.items())
        + ".",
        "",
        "Why the Routhian level is not the cheap level off the stiff regime: it has 6 states "
        "against 9 (SO(3)) and 13 (full), and it drops the spin phase, but its step count is "
        "set by the nutation of theta, which it must resolve like the others (see the steps "
        "column), and on a CPU a step of a system this small costs the solver's fixed work "
        "(~20-30 us per step against ~0.1 us for a right-hand side evaluation), so fewer "
        "states buy little; in a batch its right-hand side (autodiff of the Routhian terms, "
        "about twice the SO(3) one) makes it dearer than the SO(3) level. Under stiff friction "
        "it is the cheapest level (fewer stability-limited steps), and `auto` uses it there "
        "when the tolerance allows. The gyroscopic level drops the nutation, so its steps "
        "follow the slow rise of theta alone (tens of steps instead of thousands); what it "
        "costs here is mostly the fixed cost of a call and of writing the save points.",
    ]
    lines += gyro_sections(spin_rows, mu_rows, speed)
    lines += [
        "",
        "```python",
        f"{IIB_SCENES_NAME} = {{",
        *regime_lines(measured, indent="    "),
        "}",
        "```",
    ]
    (HERE / "LEVELS.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"elapsed {time.perf_counter() - t_start:.0f} s")


def gyro_sections(spin_rows, mu_rows, speed):
    lines = [
        "",
        "## The gyroscopic level against the SO(3) and full models",
        "",
        f"Standard top (`tj.default_top()`), theta0 = {GYRO_THETA0}, 10 s, {N_SAVE} save points, "
        "rtol 1e-8. Two launches at each spin: **launch** = `tj.initial_state` (omega = n a, "
        "which carries nutation: the level starts from its linear projection onto the slow "
        "manifold), and **on manifold** = the state on the gyroscopic slow manifold at theta0 "
        "for the same Jellet J (no nutation to drop: the error is the slow flow's own). "
        "dt_inv = t_invert_gyro - t_invert_ref (s). theta err = max |theta_gyro - theta_ref|, "
        "dominated by the nutation the slow flow drops; theta err (avg) = max |theta_gyro - "
        f"<theta_ref>| against the reference smoothed by a moving average over {SMOOTH_PERIODS} "
        "nutation periods (2 pi/nu at the launch), over the times where the window fits: the "
        "fair comparison. so3-full: the difference of the two reference models in t_invert, "
        "the floor below which the gyroscopic error against either means little.",
        "",
        "| n0 (rad/s) | launch | gyro steps | result | dt_inv vs so3 | dt_inv vs full | so3-full dt_inv | theta err vs so3 | theta err (avg) vs so3 | theta err (avg) vs full |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]

    def res(x):
        return x["result"]

    for r in spin_rows:
        for key, label in (("launch", "omega = n a"), ("manifold", "on manifold")):
            x = r[key]
            ti = x["t_invert"]
            lines.append(
                f"| {r['n0']:.0f} | {label} | {x['steps']} | {res(x)} | {x['t_invert_err_so3']:+.2e} | "
                f"{x['t_invert_err_full']:+.2e} | {ti['so3'] - ti['full']:+.2e} | "
                f"{_fmt(x['theta_err_so3'])} | {_fmt(x['theta_err_avg_so3'])} | "
                f"{_fmt(x['theta_err_avg_full'])} |"
            )
    spins = [r["n0"] for r in spin_rows]
    rates = {
        (key, ref): power_law(spins, [r[key][f"t_invert_err_{ref}"] for r in spin_rows])
        for key in ("launch", "manifold") for ref in ("so3", "full")
    }
    avg_rates = {
        key: power_law(spins, [r[key]["theta_err_avg_so3"] for r in spin_rows])
        for key in ("launch", "manifold")
    }
    lines += [
        "",
        "Fitted power law |dt_inv| ~ n0^k (least squares in log-log over the spins above): "
        f"on manifold k = {rates[('manifold', 'so3')]:.2f} vs so3, "
        f"{rates[('manifold', 'full')]:.2f} vs full; launch (omega = n a) "
        f"k = {rates[('launch', 'so3')]:.2f} vs so3, {rates[('launch', 'full')]:.2f} vs full. "
        f"Averaged theta error: k = {avg_rates['manifold']:.2f} (on manifold), "
        f"{avg_rates['launch']:.2f} (launch), vs so3.",
        "",
        f"Error vs mu at n0 = 100 rad/s, theta0 = {GYRO_THETA0} (t1 = max(10, 3.4/mu) s, the "
        "rise time scales as 1/mu), same columns:",
        "",
        "| mu (s/m) | regime | launch | gyro steps | result | t_invert so3 (s) | dt_inv vs so3 | dt_inv vs full | so3-full dt_inv | theta err vs so3 | theta err (avg) vs so3 | theta err (avg) vs full |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in mu_rows:
        for key, label in (("launch", "omega = n a"), ("manifold", "on manifold")):
            x = r[key]
            ti = x["t_invert"]
            lines.append(
                f"| {r['mu']:g} | {r['regime']} | {label} | {x['steps']} | {res(x)} | {ti['so3']:.3f} | "
                f"{x['t_invert_err_so3']:+.2e} | {x['t_invert_err_full']:+.2e} | "
                f"{ti['so3'] - ti['full']:+.2e} | {_fmt(x['theta_err_so3'])} | "
                f"{_fmt(x['theta_err_avg_so3'])} | {_fmt(x['theta_err_avg_full'])} |"
            )
    long, short = speed[SPEED_T1], speed[0.01]
    (tg, ng), (tf, nf) = long["gyroscopic"], long["full"]
    (sg, _), (sf, _) = short["gyroscopic"], short["full"]
    per_step_g = (tg - sg) / max(ng, 1)
    per_step_f = (tf - sf) / max(nf, 1)
    lines += [
        "",
        f"**Speed** (goal: >= 50x cheaper than the full model at rtol 1e-8 over a {SPEED_T1:.0f} s "
        "run). Default top, theta0 0.1, n0 100 rad/s, jitted `simulate(..., summary=True)`, median "
        f"of {SPEED_REPEATS} interleaved runs after compilation, one CPU core: full "
        f"{tf * 1e3:.2f} ms ({nf} steps), gyroscopic {tg * 1e3:.3f} ms ({ng} steps): "
        f"**{tf / tg:.0f}x** cheaper. Split (from a 0.01 s run of each): fixed cost per call "
        f"{sg * 1e3:.3f} ms (gyroscopic), {sf * 1e3:.3f} ms (full); per step "
        f"{per_step_g * 1e6:.1f} us (gyroscopic), {per_step_f * 1e6:.1f} us (full). The ratio "
        "moves with the machine's load (the full run is 50x longer and suffers more from it): "
        "compare it within one run only. With many save points the ratio falls (diffrax "
        "interpolates each save inside the step loop: 8-40x with 201 saves, "
        "`benchmarks/RESULTS.md`, engine section). Work-precision of this level against the full "
        "model at rtol 1e-4..1e-10 (t_invert error against wall time): "
        "`python benchmarks/gyroscopic_wp.py`, chart `gyroscopic_work_precision.png`.",
        "",
        "What the speed is made of (profile, `jax.make_jaxpr`/compiled HLO and ablations timed "
        "side by side): before, 47 Dopri8 steps of 43 us and 0.32 ms per call (17x). (1) The "
        "level integrated theta, which grows and decays exponentially near the poles; it now "
        "integrates u = ln tan(theta/2), whose rate is (G3)'s theta_dot/sin(theta), nearly "
        "constant there (Dopri5: 54 steps against 118 in theta; the steps left are where the "
        "top turns over). (2) Dopri8's step and dense output (14 stages in a loop, evaluated "
        "at 7 points a step by the event watch) cost ~30 us a step on this 5-state flow, "
        "Dopri5's ~10 us and Tsit5's ~12 us (its dense output is dearer): the level's default "
        "solver is Dopri5 (`AbstractLevel.slow_flow`). (3) The nutation damping sigma, in the "
        "right-hand side and in the chart condition, was autodiff (jvp) of five functions "
        "(545 jaxpr equations); written out in closed form it is ~130 (checked against "
        "autodiff in the tests). The balance root is already the closed-form root of the "
        "quadratic (G2), no iterative solve. What is left per step is about half the engine "
        "(Dopri5 stages, controller, event watch on the dense output) and half this level's "
        "arithmetic (sigma in 6 stages, the conditions at 9 points a step), and per call the "
        "fixed cost of the engine (projection of the launch, initial step, locating "
        "t_invert).",
    ]
    return lines


def write_section(mark, lines):
    """Replace the section of LEVELS.md that starts with `mark` (up to the next "## "), or
    append it; the rest of the file is left as it is."""
    path = HERE / "LEVELS.md"
    text = path.read_text()
    if mark in text:
        head, tail = text.split(mark, 1)
        nxt = tail.find("\n## ")
        rest = tail[nxt + 1:] if nxt >= 0 else ""
        text = head + "\n".join(lines) + ("\n" + rest if rest else "")
    else:
        text = text.rstrip("\n") + "\n\n" + "\n".join(lines)
    path.write_text(text)


if __name__ == "__main__":
    import sys

    if "--spun" in sys.argv[1:]:
        from levels_spun import write_spun_section

        write_spun_section()
    elif "--groups" in sys.argv[1:]:
        from levels_groups import write_groups_section

        write_groups_section()
    else:
        main()
        from levels_spun import write_spun_section

        write_spun_section()
        from levels_groups import write_groups_section

        write_groups_section()
