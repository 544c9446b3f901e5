"""levels: the cheaper levels against the full model (error of theta, cost), and the `MEASURED`
table of the `--groups` block that `tippejax/_auto.py` copies and `tests/test_auto.py` checks.

    python benchmarks/levels.py --scenes   # then --groups, which merges the scenes' table
"""

from __future__ import annotations

import functools
import itertools
import math
import re
import statistics

import _harness as h
import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

import tippejax as tj

LEVELS = ("so3", "routhian", "gyroscopic")
INF = float("inf")
GROUP_TOPS = dict(
    Ia=(0.96, 0.02), Ib=(0.7, 0.2), IIa=(0.8, 0.3), IIb=(0.9, 0.3), IIc=(0.99, 0.02), III=(1.5, 0.2)
)
"""(A/C, eps/R) of the top of each group (away from the groups' borders)."""


# --- past the public API, in this one place ------------------------------------------------
# The table auto reads is built with auto's own rules (a launch's regime, whether a level accepts
# it, the cheapest level), and `--spun` judges the gyroscopic slow flow alone (no
# hand-over, launched on its slow manifold): `tj.simulate(model="gyroscopic")` offers neither.


def auto_rules():
    from tippejax import _auto

    return _auto


def slow_flow_t_invert(top, y0, t1=20.0):
    """t_invert of the gyroscopic slow flow alone from `y0` (projected as the level projects a
    launch), Dopri5 at rtol 1e-8: where u = ln tan(theta/2) rises through 0."""
    from tippejax._models.gyroscopic import GyroscopicLevel

    level = GyroscopicLevel()
    y = level.from_state(top, y0)
    term = diffrax.ODETerm(lambda t, y, top: level.vector_field(t, y, top))
    controller = diffrax.PIDController(rtol=1e-8, atol=1e-10, norm=level.error_norm)
    event = diffrax.Event(lambda t, y, args, **kw: y.log_tan_half_theta, optx.Newton(1e-12, 1e-12))
    kw = dict(max_steps=100_000, throw=False, stepsize_controller=controller, event=event)
    sol = diffrax.diffeqsolve(term, diffrax.Dopri5(), 0.0, t1, None, y, top, **kw)
    return float(sol.ts[-1]) if bool(sol.event_mask) else np.nan


# --- one scene in every level --------------------------------------------------------------


@functools.cache
def runner(model):
    return eqx.filter_jit(
        lambda top, y0, t1, ts: tj.simulate(top, y0, t1, model=model, saveat=ts, throw=False)
    )


def ran(sol) -> str:
    """The level(s) a run used (`sol.model`; under `jax.jit` read off `t_chart_switch`)."""
    model = str(sol.model)
    if "(" in model:
        base, rest = model.split("(", 1)
        model = base + (
            "->" + rest.split("->")[1].split()[0] if np.isfinite(float(sol.t_chart_switch)) else ""
        )
    return model


def timed(run, *args, repeats):
    sol = jax.block_until_ready(run(*args))
    return sol, statistics.median(h.call(lambda: run(*args))[0] for _ in range(repeats))


def scene_row(name, top, y0, t1, *, repeats, n_save):
    """Each level from the launch: theta error against the full model, cost, what ran."""
    rules = auto_rules()
    ts, t1_ = jnp.linspace(0.0, t1, n_save), jnp.asarray(t1)
    ref, t_ref = timed(runner("full"), top, y0, t1_, ts, repeats=repeats)
    row = dict(scene=name, regime=rules.launch_regime(top, y0), t_invert=float(ref.t_invert))
    for level in LEVELS:
        if not rules.accepts(level, top, y0):  # auto never picks it here: not run
            row[level] = dict(err=INF, dt=INF, cost=np.nan, model="refused")
            continue
        sol, t = timed(runner(level), top, y0, t1_, ts, repeats=repeats)
        a, b = np.asarray(sol.theta), np.asarray(ref.theta)
        both = np.isfinite(a) & np.isfinite(b)
        err = float(np.max(np.abs(a - b)[both], initial=0.0)) if both.any() else INF
        model = ran(sol)
        if bool(sol.result == tj.RESULTS.no_gyroscopic_balance):  # refused, or stopped on the way
            err, model = INF, "refused" if int(sol.num_steps) == 0 else "stopped"
        dt = INF if err == INF else abs(float(sol.t_invert) - row["t_invert"])
        row[level] = dict(err=err, dt=dt, cost=t / t_ref, model=model)
    return row


def per_regime(rows):
    """{regime: {level: (worst error, median cost)}} over the launches each level accepts
    (none: inf, inf)."""
    measured = {}
    for regime in dict.fromkeys(r["regime"] for r in rows):
        measured[regime] = {}
        for lv in LEVELS:
            used = [r[lv] for r in rows if r["regime"] == regime and r[lv]["model"] != "refused"]
            measured[regime][lv] = (
                (max(x["err"] for x in used), float(np.median([x["cost"] for x in used])))
                if used
                else (INF, INF)
            )
    return measured


def fmt(x, spec=".3g"):
    return "inf" if x == INF else format(x, spec)


def measured_block(name, table_, nested):
    """The table `name` (`tippejax/_auto.py` copies it): a row per (group,) regime, a cell per
    level, worst error / highest cost; `read_block` and `tests/test_auto.py` read it back."""
    groups = table_.items() if nested else [(None, table_)]
    rows = [
        [
            *([g] if nested else []),
            reg,
            *(f"{fmt(m[reg][lv][0])} / {fmt(m[reg][lv][1], '.2f')}" for lv in LEVELS),
        ]
        for g, m in groups
        for reg in m
    ]
    head = [*(["group"] if nested else []), "regime", *LEVELS]
    return f"`{name}`, worst error (rad) / highest cost per level:\n\n{h.table(head, rows)}"


def read_block(name):
    text = h.RESULTS.read_text()
    lines = re.search(rf"^`{name}`.*\n\n((?:\|.*\n?)+)", text, re.M).group(1).splitlines()
    head = [c.strip() for c in lines[0].strip("|").split("|")]
    out = {}
    for line in lines[2:]:
        cells = [c.strip() for c in line.strip("|").split("|")]
        key = cells[: head.index("regime") + 1]
        at = out.setdefault(key[0], {}) if len(key) > 1 else out
        at[key[-1]] = {
            lv: tuple(float(x) for x in c.split(" / "))
            for lv, c in zip(head[len(key) :], cells[len(key) :])
        }
    return out


# --- modes ---------------------------------------------------------------------------------


def spin_for_jellet(top, theta0, jellet):
    return jellet / float(tj.jellet(top, tj.initial_state(top, theta0, 1.0)))


def scenes_mode(args):
    """Scenes of the standard IIb top and its variants, a regime each: the IIb table."""
    std, iib = tj.default_top(), tj.TippeTop.from_ratios(0.9, 0.3, mu=1.0)
    stiff, th = tj.TippeTop.from_ratios(0.9, 0.3, mu=300.0), tj.thresholds(iib)
    mid = 0.5 * (float(th.J1) + float(th.J2))
    s = tj.initial_state
    scenes = [  # (name, top, launch, t1)
        ("n0 100, theta0 0.1", std, s(std, 0.1, 100.0), 10.0),
        ("n0 150, theta0 0.1", std, s(std, 0.1, 150.0), 10.0),
        ("n0 60, theta0 0.02", std, s(std, 0.02, 60.0), 10.0),
        ("n0 80, theta0 0.5, thd 2", std, s(std, 0.5, 80.0, theta_dot=2.0), 10.0),
        ("n0 20 < n1, theta0 0.1", std, s(std, 0.1, 20.0), 5.0),
        ("n0 15, theta0 0.4", std, s(std, 0.4, 15.0), 5.0),
        ("mu 1, J1 < J < J2, theta0 0.1", iib, s(iib, 0.1, spin_for_jellet(iib, 0.1, mid)), 10.0),
        ("mu 1, J1 < J < J2, theta0 0.6", iib, s(iib, 0.6, spin_for_jellet(iib, 0.6, mid)), 10.0),
        ("mu 300, n0 100, theta0 0.1", stiff, s(stiff, 0.1, 100.0), 2.0),
        ("mu 300, n0 60, theta0 0.5", stiff, s(stiff, 0.5, 60.0), 2.0),
        (
            "n0 80, theta0 0.5, thd 2, v (0.2, -0.1)",
            std,
            s(std, 0.5, 80.0, theta_dot=2.0, vx=0.2, vy=-0.1),
            5.0,
        ),
        ("n0 120, theta0 0.2, v (0.1, 0.1)", std, s(std, 0.2, 120.0, vx=0.1, vy=0.1), 5.0),
    ]
    if args.smoke:
        scenes = [(n, top, y0, 0.5) for n, top, y0, _ in scenes[::5]]
    size = dict(repeats=1, n_save=201) if args.smoke else dict(repeats=5, n_save=2001)
    rows = [scene_row(*sc, **size) for sc in scenes]
    measured = per_regime(rows)

    h.write(
        "levels.py --scenes",
        "The levels on scenes of the standard top (group IIb)",
        f"""
{measured_block("MEASURED_IIB_SCENES", measured, nested=False)}
""",
        args,
    )


def groups_mode(args):
    """A grid of launches for one top of every group: the `MEASURED` table auto reads."""
    rules, rows = auto_rules(), []
    grid = (
        ((1.5,), (0.3,), (0.3,))
        if args.smoke
        else ((0.7, 0.9, 1.5, 2.0, 3.0, 5.0, 10.0), (0.05, 0.3, 2.0), (0.15, 0.3, 0.5))
    )
    groups = ("IIb",) if args.smoke else GROUP_TOPS
    size = dict(repeats=1, n_save=201) if args.smoke else dict(repeats=2, n_save=2001)
    for group, factor, mu in itertools.product(groups, grid[0], grid[1]):
        top = tj.TippeTop.from_ratios(*GROUP_TOPS[group], mu=mu)
        th = tj.thresholds(top)
        ref = "n1" if np.isfinite(float(th.n1)) else "n2"
        spin = factor * float(getattr(th, ref))

        def ok(t0):
            return rules.accepts("gyroscopic", top, tj.initial_state(top, t0, spin))

        lo, hi, edge = 0.05, 0.5, None  # the most tilted launch the gyroscopic level accepts
        if ok(lo) and not ok(hi):
            while hi - lo > 1e-4:
                lo, hi = ((lo + hi) / 2, hi) if ok((lo + hi) / 2) else (lo, (lo + hi) / 2)
            edge = lo
        for t0 in (*grid[2], *([edge] if edge else [])):
            name = f"{factor:g} {ref} = {spin:.1f}, mu {mu:g}, theta0 {t0:.3g}"
            row = scene_row(
                name, top, tj.initial_state(top, t0, spin), 0.5 if args.smoke else 8.0, **size
            )
            rows.append(dict(row, group=group))
    measured = {g: per_regime([r for r in rows if r["group"] == g]) for g in groups}
    merged = dict(measured.get("IIb", {}))
    for reg, m in read_block("MEASURED_IIB_SCENES").items():  # the worst error, the highest cost
        old = merged.get(reg, m)
        merged[reg] = {lv: (max(old[lv][0], m[lv][0]), max(old[lv][1], m[lv][1])) for lv in LEVELS}
    measured["IIb"] = merged
    h.write(
        "levels.py --groups",
        'Every group: the table `model="auto"` reads',
        f"""
{len(rows)} launches, {0.5 if args.smoke else 8:g} s; IIb merged with `--scenes`.

{measured_block("MEASURED", measured, nested=True)}
""",
        args,
    )


def spun_mode(args):
    """omega = n a launches: t_invert of the slow flow alone (the launch projection's error)
    and of `model="gyroscopic"` against SO(3), over the spin."""

    def launch(top, theta0, n0):
        y0 = tj.initial_state(top, theta0, n0)
        so3 = tj.simulate(
            top, y0, 20.0, model="so3", summary=True, throw=False, rtol=1e-10, atol=1e-12
        )
        return y0, float(so3.t_invert), slow_flow_t_invert(top, y0)

    def pct(x, ref):
        return f"{100 * (x - ref) / ref:+.3f}%" if np.isfinite(x) and np.isfinite(ref) else "n/a"

    def ends(sol, so3):
        loss = float(sol.t_contact_loss)
        return f"contact lost {loss:.2f} s" if np.isfinite(loss) else pct(float(sol.t_invert), so3)

    top, rows = tj.default_top(), []
    spins_ = (
        (100.0, 150.0) if args.smoke else (100.0, 125.0, 150.0, 175.0, 200.0, 225.0, 250.0, 300.0)
    )
    for n0 in spins_:
        y0, so3, slow = launch(top, 0.1, n0)
        kw = dict(summary=True, throw=False, on_contact_loss="continue")
        gyro = tj.simulate(top, y0, 20.0, model="gyroscopic", **kw)
        switch = float(gyro.t_chart_switch)
        via = f"->full at {switch:.2f} s, " if np.isfinite(switch) else "gyroscopic, "
        rows.append(f"{n0:g} | {so3:.4f} | {pct(slow, so3)} | {via}{ends(gyro, so3)}")
    h.write(
        "levels.py --spun",
        "Spun launches: the launch projection",
        f"""
t_invert of the slow flow alone (Dopri5, rtol 1e-8) against SO(3) (rtol 1e-10), omega = n a launches. Targets: at most 0.5% at 150 rad/s, 0.4% at 225, 0.3% at 300.

{h.table("n0 (rad/s) | SO(3) t_invert (s) | slow flow | model='gyroscopic'", rows)}
""",
        args,
    )


def wp_mode(args):
    """Work-precision per group: the gyroscopic level against SO(3) and the full model; the
    chart gyroscopic_work_precision.png."""
    rtols = (1e-4, 1e-8) if args.smoke else tuple(10.0**-k for k in range(4, 11))
    solvers = {"full": diffrax.Dopri8(), "so3": diffrax.Dopri8(), "gyroscopic": diffrax.Dopri5()}

    def program(m):
        def run(top, y0, r):
            kw = dict(model=m, summary=True, rtol=r, atol=r / 100, solver=solvers[m], throw=False)
            sol = tj.simulate(top, y0, 15.0, **kw)
            return sol.t_invert, sol.theta[-1]

        return eqx.filter_jit(run)

    make = {m: program(m) for m in solvers}
    results, body = {}, []
    for group in ("IIb",) if args.smoke else GROUP_TOPS:
        top = tj.TippeTop.from_ratios(*GROUP_TOPS[group], mu=0.3)
        th = tj.thresholds(top)
        y0 = tj.initial_state(
            top, 0.1, 3.0 * (float(th.n1) if np.isfinite(float(th.n1)) else float(th.n2))
        )
        ref = make["full"](top, y0, jnp.asarray(1e-12))
        k = 0 if np.isfinite(float(ref[0])) else 1  # t_invert where it inverts, else theta(t1)
        res = {m: [] for m in solvers}
        for r in rtols:
            fns = {m: functools.partial(f, top, y0, jnp.asarray(r)) for m, f in make.items()}
            for m, (t, out) in h.interleaved(fns, 1 if args.smoke else 5).items():
                res[m].append((t.wall, abs(float(out[k]) - float(ref[k]))))
        results[group] = (float(y0.omega @ y0.axis), k, res)
        at = rtols.index(1e-8)
        errors = " | ".join(
            " / ".join(
                f"{res[m][i][1]:.1e}" for i in range(len(rtols)) if rtols[i] in (1e-6, 1e-8, 1e-10)
            )
            for m in ("so3", "gyroscopic")
        )
        body.append(
            f"{group} ({results[group][0]:.0f}) | {('t_invert', 'theta(t1)')[k]} | {errors} | {res['so3'][at][0] / res['full'][at][0]:.2f} / {res['gyroscopic'][at][0] / res['full'][at][0]:.2f}"
        )
    h.write(
        "levels.py --wp",
        "Work-precision per group: the gyroscopic level",
        f"""
Error of t_invert where the full model inverts, else of theta(t1), against the full model at rtol 1e-12. Chart: `gyroscopic_work_precision.png`.

{h.table("group (n0 rad/s) | quantity | so3: error at rtol 1e-6 / 1e-8 / 1e-10 | gyroscopic | time vs full at 1e-8 (so3 / gyro)", body)}
""",
        args,
    )
    plt = h.pyplot()
    fig, axes = plt.subplots(2, 3, figsize=(13, 8))
    for ax, (group, (spin, k, res)) in zip(axes.ravel(), results.items()):
        for m, style in zip(solvers, ("o-", "^-", "s-")):
            ax.loglog(
                [w for w, _ in res[m]], [max(e, 1e-16) for _, e in res[m]], style, ms=4, label=m
            )
        ax.set_title(
            f"{group}: A/C {GROUP_TOPS[group][0]}, eps/R {GROUP_TOPS[group][1]}, n0 {spin:.0f} rad/s",
            fontsize=9,
        )
        ax.set(
            xlabel="wall time per run (s)",
            ylabel=("|t_invert error| (s)", "|theta(t1) error| (rad)")[k],
        )
        ax.grid(True, which="both", alpha=0.3)
    axes.ravel()[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(h.figure_path("gyroscopic_work_precision.png", args), dpi=100)


def cost_mode(args):
    """The gyroscopic level's cost against the full model per group and spin, with the share
    of the run in each model (`sol.t_hand_over`), and the eager/jit ratio of every level."""
    t1, n_save = (2.0, 201) if args.smoke else (20.0, 2001)
    rounds = args.rounds or (1 if args.smoke else 3)
    ts = jnp.linspace(0.0, t1, n_save)
    std = tj.default_top()
    scenes = [("standard", std, n0) for n0 in ((100.0,) if args.smoke else (100.0, 150.0, 300.0))]
    for group in () if args.smoke else GROUP_TOPS:
        top = tj.TippeTop.from_ratios(*GROUP_TOPS[group], mu=0.3)
        th = tj.thresholds(top)
        n_ref = float(th.n1) if np.isfinite(float(th.n1)) else float(th.n2)
        scenes.append((group, top, 3.0 * n_ref))

    def program(model):  # the top traced: one program per level for every scene
        return eqx.filter_jit(
            lambda top, y0: tj.simulate(top, y0, t1, model=model, saveat=ts, throw=False)
        )

    jitted = {m: program(m) for m in ("gyroscopic", "full")}
    rows, worst = [], {}
    for name, top, n0 in scenes:
        y0 = tj.initial_state(top, 0.1, n0)
        fns = {m: functools.partial(jitted[m], top, y0) for m in jitted}
        tm = h.interleaved(fns, rounds)
        (tg, sol), (tf, ref) = tm["gyroscopic"], tm["full"]
        hand = float(sol.t_hand_over)
        route = "gyroscopic" + ("->full" if np.isfinite(hand) else "")
        end = float(sol.t_final)
        share = 1.0 if not np.isfinite(hand) else (hand - 0.0) / max(end, 1e-300)
        steps = int(sol.num_steps)
        outcome = (
            ""
            if sol.result == tj.RESULTS.successful
            else f" ({tj.RESULTS.message(sol.result)[:40]}...)"
        )
        ratio = h.paired(tf, tg)[0]
        worst[route] = min(worst.get(route, INF), ratio)
        rows.append(
            f"{name} | {n0:.0f} | {route}{outcome} | {fmt(hand, '.3f') if np.isfinite(hand) else '-'} | {100 * share:.0f}% / {100 * (1 - share):.0f}% | "
            f"{1e3 * tg.wall:.2f} ({steps}) | {1e3 * tf.wall:.2f} ({int(ref.num_steps)}) | **{ratio:.1f}x** | "
            f"{fmt(float(sol.t_invert), '.4f')} / {fmt(float(ref.t_invert), '.4f')}"
        )
    # eager against jit, per level: the standard top at n0 100
    y0 = tj.initial_state(std, 0.1, 100.0)
    eager_rows = []
    for m in ("full", "so3", "routhian", "gyroscopic"):
        jit_m = jitted.get(m) or program(m)
        fns = {
            "jit": functools.partial(jit_m, std, y0),
            "eager": lambda m=m: tj.simulate(std, y0, t1, model=m, saveat=ts, throw=False),
        }
        tm = h.interleaved(fns, rounds)
        r = h.paired(tm["eager"][0], tm["jit"][0])[0]
        eager_rows.append(
            f"{m} | {1e3 * tm['jit'][0].wall:.2f} | {1e3 * tm['eager'][0].wall:.2f} | {r:.2f} {h.verdict(r <= 1.5)}"
        )
    own = [r for r in rows if r.startswith("standard | 100 |")]
    target = float(own[0].split("**")[1][:-1]) if own else math.nan
    h.write(
        "levels.py --cost",
        "The gyroscopic level at its price: cost against the full model, and the hand-over",
        f"""
{t1:g} s, {n_save} saves, {rounds} interleaved rounds. Target at n0 100 (standard top): the gyroscopic level at least 50x cheaper than the full model: {target:.1f}x, {h.verdict(target >= 50)}.

{h.table("top | n0 (rad/s) | route | t_hand_over (s) | share slow / full | gyroscopic ms (steps) | full ms (steps) | full / gyroscopic | t_invert gyro / full (s)", rows)}

Eager against `jax.jit` (standard top, n0 100; target at most 1.5x):

{h.table("level | jit (ms) | eager (ms) | eager / jit", eager_rows)}
""",
        args,
    )


MODES = {
    "scenes": (scenes_mode, "scenes of the standard top; the IIb table"),
    "groups": (groups_mode, "a grid of launches in every group; the MEASURED table"),
    "spun": (spun_mode, "omega = n a launches: the launch projection"),
    "wp": (wp_mode, "work-precision per group; gyroscopic_work_precision.png"),
    "cost": (cost_mode, "the gyroscopic level's cost and hand-over per group and spin"),
}

if __name__ == "__main__":
    h.run(MODES, h.parse(__doc__, MODES))
