"""real_tops: real tops (Coulomb-type friction, Contensou drilling, the stem) on Leine & Glocker's
scene, against the scipy reference `tests/real_top_reference.py` and cardillo's Moreau stepping.

    python benchmarks/real_tops.py --peers --cardillo /work/cardillo \\
        --cardillo-python /work/cardillo-venv/bin/python
    python benchmarks/real_tops.py --batch --n 1000

cardillo (not a dependency): `--cardillo`, a checkout at commit 1c667a30, run by
`--cardillo-python` at `nice`, one run at a time, cached in `--cache`; its times, first order
in dt, are extrapolated to dt -> 0 through the two finest dts.
"""

from __future__ import annotations

import importlib.util
import math
import os
import pathlib
import subprocess
import sys
import warnings

import _harness as h
import diffrax
import numpy as np

import tippejax as tj

ROOT = h.HERE.parent
SUITE = "real_tops.py"
LG_BODY = dict(m=0.006, R=0.015, eps=0.003, A=8e-7, C=7e-7, g=9.81)
R2, A2 = 0.005, 0.016
THETA0, SPIN, MU, RHO, DELTA = 0.1, 180.0, 0.3, 5e-4, 1e-6
T_PEERS = 2.5  # s: the scene of the peers and the batch
MU_LANDING = 1.3  # s/m: a viscous mu that turns the scene's top onto its stem near 1.4 s
T_AFTER = 4.8  # s: past the ball's return to the table (about 4.55 s)
DTS = (1e-3, 5e-4, 2.5e-4, 1e-4)  # cardillo's steps (cached runs)
SOLVERS = {"Dopri8": diffrax.Dopri8, "Tsit5": diffrax.Tsit5, "Kvaerno5": diffrax.Kvaerno5}


# --- the scene ---------------------------------------------------------------------------------


def law(name: str, slip_scale: float = DELTA, rho: float = RHO):
    """The friction law of a row: viscous (mu 0.3 s/m), coulomb, hertz or ellipse."""
    if name == "viscous":
        return tj.Viscous(0.3)
    if name == "coulomb":
        return tj.Coulomb(MU, slip_scale)
    return tj.CoulombContensou(MU, rho, slip_scale, pressure=name)


def lg_top(name="ellipse", *, stem=True, slip_scale=DELTA, rho=RHO, **contact):
    return tj.TippeTop(
        **LG_BODY,
        friction=law(name, slip_scale, rho),
        stem=tj.Stem(R2, A2, **contact) if stem else None,
    )


def lg_run(top, t1, *, saves=None, solver=None, rtol=1e-8, **kw):
    """`simulate` of the scene's launch; `saves` None: every 10 ms."""
    y0 = tj.initial_state(top, theta=THETA0, spin=SPIN)
    ts = np.linspace(0.0, t1, int(round(t1 / 0.01)) + 1) if saves is None else saves
    kw = dict(saveat=ts, solver=solver, rtol=rtol, atol=rtol * 1e-2, throw=False, **kw)
    return tj.simulate(top, y0, t1, max_steps=1_000_000, **kw)


def reference():
    """`tests/real_top_reference.py`, imported by path (it imports no tippejax)."""
    spec = importlib.util.spec_from_file_location(
        "real_top_reference", ROOT / "tests" / "real_top_reference.py"
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules["real_top_reference"] = module
    spec.loader.exec_module(module)
    return module


def ref_run(rr, pressure="ellipse", t1=T_PEERS, **kw):
    kw = {"rho": RHO, "delta": DELTA, **kw}
    return rr.solve(rr.LEINE_GLOCKER, pressure, THETA0, SPIN, t1, mu=MU, **kw)


def ref_events(r) -> dict:
    """The reference's stem touch, the ball's lift-off after it and its return."""
    t_stem = r["t_stem"]
    after = [(t, n) for t, n, _ in r["events"] if np.isfinite(t_stem) and t >= t_stem]
    off = next((t for t, n in after if n == "ball_liftoff"), math.nan)
    again = next((t for t, n in after if n == "ball_touchdown" and t > off), math.nan)
    return dict(t_half=r["t_half"], t_stem=t_stem, theta_stem=r["theta_stem"], ball_return=again)


def tj_events(sol, saves=None) -> dict:
    """tippejax's events; with `saves`, theta at the touch interpolated from the save times."""
    t_stem = float(sol.t_stem)
    theta_stem = math.nan
    if saves is not None and np.isfinite(t_stem):
        theta_stem = float(np.interp(t_stem, saves, np.asarray(sol.theta)))
    return dict(t_half=float(sol.t_invert), t_stem=t_stem, theta_stem=theta_stem)


def theta_error(ts, theta, r, until) -> float:
    """max |theta - theta_reference| at the save times before `until` (the reference's 1 ms
    samples, interpolated linearly)."""
    keep = ts < until
    return float(np.max(np.abs(np.asarray(theta)[keep] - np.interp(ts[keep], r["t"], r["theta"]))))


def f(x, digits=4) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


def g(x, digits=3) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{x:.{digits}g}"


# --- cardillo, in its own python ---------------------------------------------------------------


def cardillo_run(args, dt, t_final):
    """The cached run at dt, else a subprocess run (its log beside the cache file); None
    without `--cardillo` and no cached run."""
    cache = pathlib.Path(args.cache)
    out = cache / f"cardillo_dt{dt:.3g}_t{t_final:g}.npz"
    if not out.exists():
        if not args.cardillo:
            return None
        cache.mkdir(parents=True, exist_ok=True)
        worker = [str(h.HERE / "_cardillo_worker.py"), args.cardillo, repr(dt), repr(t_final)]
        cmd = ["nice", "-n", "10", args.cardillo_python, *worker, str(out)]
        with open(out.with_suffix(".log"), "w") as log:
            env = {**os.environ, "MPLBACKEND": "Agg"}
            subprocess.run(cmd, check=True, stdout=log, stderr=subprocess.STDOUT, env=env)
    return dict(np.load(out))


def cardillo_runs(args, smoke) -> dict:
    """{dt: summary} of the cardillo runs there are (cached: a smoke run reads them too)."""
    runs = {dt: cardillo_run(args, dt, T_PEERS) for dt in ((1e-3,) if smoke else DTS)}
    return {dt: cardillo_summary(r) for dt, r in runs.items() if r is not None}


def _crossing(t, values, start=0):
    """First time after index `start` where `values` goes from < 0 to >= 0 (linear)."""
    idx = np.nonzero((values[start:-1] < 0) & (values[start + 1 :] >= 0))[0]
    if idx.size == 0:
        return math.nan
    i = start + idx[0]
    return float(t[i] - values[i] * (t[i + 1] - t[i]) / (values[i + 1] - values[i]))


def cardillo_summary(run) -> dict:
    """pi/2 crossing, stem touch (the stem's gap reaching 0), theta there, the ball's return."""
    t, gaps = run["t"], run["gaps"]
    theta = np.arccos(np.clip(run["axis"][:, 2], -1, 1))
    t_stem = _crossing(t, -gaps[:, 1])
    i = int(np.searchsorted(t, t_stem)) if np.isfinite(t_stem) else t.size - 1
    off = _crossing(t, gaps[:, 0], i)
    j = int(np.searchsorted(t, off)) if np.isfinite(off) else t.size - 1
    return dict(
        t_half=_crossing(t, theta - math.pi / 2),
        t_stem=t_stem,
        theta_stem=float(np.interp(t_stem, t, theta)) if np.isfinite(t_stem) else math.nan,
        ball_return=_crossing(t, -gaps[:, 0], j),
        wall=float(run["wall"]),
        steps=t.size - 1,
        t=t,
        theta=theta,
    )


def extrapolated(cards: dict, key: str) -> float:
    """`key` at dt -> 0 from the line through the two finest dts (first order)."""
    fine = sorted(cards)[:2]
    if len(fine) < 2:
        return math.nan
    (d0, d1), (v0, v1) = fine, (cards[fine[0]][key], cards[fine[1]][key])
    return float(v0 - d0 * (v1 - v0) / (d1 - d0))


# --- modes ---------------------------------------------------------------------------------------


def peers(args):
    """tippejax, the scipy reference and cardillo on the scene: time and accuracy."""
    rr = reference()
    t1 = 0.3 if args.smoke else T_PEERS
    truth = ref_run(rr, t1=t1, rtol=1e-11, atol=1e-14)  # the accuracy's yardstick
    ev_truth = ref_events(truth)
    until = ev_truth["t_stem"] - 0.01 if np.isfinite(ev_truth["t_stem"]) else t1
    rows = []

    def row(name, wall, ev, err, steps=""):
        touch = f"{f(ev['t_half'], 6)} | {f(ev['t_stem'], 6)}"
        rows.append(f"{name} | {g(wall)} | {g(err)} | {touch} | {steps}")
        return wall, err

    top, saves = lg_top(), np.arange(0.0, t1 + 5e-4, 1e-3)[: int(round(t1 / 1e-3)) + 1]
    fns = {r: (lambda r=r: lg_run(top, t1, saves=saves, rtol=r)) for r in (1e-6, 1e-8, 1e-10)}
    timed = h.interleaved(
        dict(list(fns.items())[:1]) if args.smoke else fns, args.rounds or (1 if args.smoke else 5)
    )
    solver, tj_points = type(tj.default_solver(top)).__name__, {}
    for rtol, (timing, sol) in timed.items():
        err = theta_error(saves, sol.theta, truth, until)
        name = f"tippejax, rtol {rtol:g} ({solver})"
        tj_points[rtol] = row(name, timing.wall, tj_events(sol, saves), err, int(sol.num_steps))
    for rtol in (1e-6,) if args.smoke else (1e-6, 1e-9):
        runs = [ref_run(rr, t1=t1, rtol=rtol) for _ in range(1 if args.smoke else 3)]
        wall, err = (
            float(np.median([r["wall"] for r in runs])),
            theta_error(truth["t"], runs[0]["theta"], truth, until),
        )
        name = f"scipy reference, rtol {rtol:g} (DOP853, then LSODA)"
        row(name, wall, ref_events(runs[0]), err, runs[0]["nfev"])
    cards = cardillo_runs(args, args.smoke)
    for dt, c in cards.items():
        grid = truth["t"][truth["t"] < min(until, c["t"][-1])]
        c["err"] = float(
            np.max(
                np.abs(
                    np.interp(grid, c["t"], c["theta"])
                    - np.interp(grid, truth["t"], truth["theta"])
                )
            )
        )
        row(f"cardillo MoreauClassical, dt {dt:g}", c["wall"], c, c["err"], c["steps"])
    verdict = ""
    if cards:
        finest = cards[min(cards)]
        good = [w for w, e in tj_points.values() if e <= finest["err"]]
        if good:
            ratio = min(good) / finest["wall"]
            verdict = (
                f"\n\nTarget, tippejax at most 1/1000 of cardillo's time at equal or better accuracy: cardillo at dt {min(cards):g} "
                f"({g(finest['wall'])} s, max d theta {g(finest['err'])}) against tippejax's cheapest run at least as accurate: "
                f"{g(ratio)} of its time (1/{1 / ratio:.0f}), {h.verdict(ratio <= 1e-3)}."
            )
    head = "run | wall s | max d theta before touch (rad) | theta = pi/2 s | stem touch s | steps / f-evals"
    h.write(
        f"{SUITE} --peers",
        "Leine & Glocker's top with its stem: tippejax, scipy, cardillo",
        f"Ellipse law, slip scale {DELTA:g} m/s, {t1:g} s; stem touch {f(ev_truth['t_stem'], 6)} s; numba {'on' if rr.HAVE_NUMBA else 'off'}.\n\n{h.table(head, rows)}{verdict}",
        args,
    )


def compiled(timing) -> str:
    """The compile time of a row, or "as above" where the program was compiled for an earlier
    row (the same law class and shapes: the first call costs no more than the timed one)."""
    return g(timing.compile) if timing.compile > 0.05 * timing.first_wall else "as above"


def batch(args):
    """1000 tops with seeded random launches: per top against the viscous law on the scene,
    with the paper's mu (which never turns the top onto its stem in 2.5 s) and with a mu that
    lands it on the stem as the Coulomb-Contensou laws do (the law's own cost, like for like)."""
    n, t1 = (8, 0.5) if args.smoke else (args.n, T_PEERS)
    rng = np.random.default_rng(58)
    theta0, spin = rng.uniform(0.05, 0.3, n), rng.uniform(150.0, 210.0, n)
    rows, per_top = [], {}
    tops = {
        "ellipse": lg_top("ellipse"),
        "hertz": lg_top("hertz"),
        "viscous": lg_top("viscous"),
        "landing": lg_top("viscous").replace(friction=tj.Viscous(MU_LANDING)),
    }
    labels = {"viscous": "viscous, mu 0.3 s/m", "landing": f"viscous, mu {MU_LANDING} s/m"}
    for name, top in tops.items():

        def fn(top=top):
            return tj.simulate_batch(top, theta0, spin, t1, grid=(), summary=True)

        ((timing, sol),) = h.interleaved({name: fn}, args.rounds or 1).values()
        per_top[name] = timing.wall / n
        ok = int(np.sum(np.asarray(sol.result == tj.RESULTS.successful)))
        on_stem = int(np.sum(np.isfinite(np.asarray(sol.t_stem))))
        steps = g(float(np.mean(np.asarray(sol.num_steps))))
        rows.append(
            f"{labels.get(name, name)} | {g(1e3 * timing.wall / n)} | {compiled(timing)} | {ok}/{n} | {on_stem}/{n} | {steps}"
        )
    like = {k: per_top[k] / per_top["landing"] for k in ("ellipse", "hertz")}
    paper = {k: per_top[k] / per_top["viscous"] for k in ("ellipse", "hertz")}
    head = "law | ms per top | compile s | successful | reached the stem | mean steps"
    h.write(
        f"{SUITE} --batch",
        "A batch of tops with the stem, per law",
        f"""
{n} seeded launches, {t1:g} s, `simulate_batch(..., grid=(), summary=True)`.

{h.table(head, rows)}

Target, per top at most 3x the viscous law's cost on the same scene. Against the viscous law
that lands on the stem too (mu {MU_LANDING} s/m, the law's own cost): ellipse {like["ellipse"]:.2f}x,
hertz {like["hertz"]:.2f}x, {h.verdict(max(like.values()) <= 3.0)}. Against the paper's mu 0.3 s/m,
which never reaches the stem (the law's cost and the stem's stiff contact together): ellipse
{paper["ellipse"]:.2f}x, hertz {paper["hertz"]:.2f}x.
""",
        args,
    )


def work_precision(args):
    """Work against precision per law, and of the stem's compliant phase, per solver."""
    scenes = {  # name: (law, stem, t1)
        "viscous": ("viscous", False, 1.2),
        "coulomb": ("coulomb", False, 1.2),
        "hertz": ("hertz", False, 1.2),
        "ellipse": ("ellipse", False, 1.2),
        "ellipse, stem": ("ellipse", True, T_PEERS),
    }
    rtols = (1e-6,) if args.smoke else (1e-6, 1e-8, 1e-10)
    solvers = ("Dopri8",) if args.smoke else tuple(SOLVERS)
    if args.smoke:
        scenes = {"ellipse, stem": ("ellipse", True, 0.3)}
    rows, curves = [], {}
    for scene, (name, stem, t1) in scenes.items():
        top = lg_top(name, stem=stem, slip_scale=1e-3 if name == "coulomb" else DELTA)
        saves = np.linspace(0.0, t1, int(round(t1 / 0.01)) + 1)
        ref = np.asarray(lg_run(top, t1, saves=saves, solver=diffrax.Dopri8(), rtol=1e-12).theta)
        default = type(tj.default_solver(top)).__name__
        fns = {
            (s, r): (lambda s=s, r=r: lg_run(top, t1, saves=saves, solver=SOLVERS[s](), rtol=r))
            for s in solvers
            for r in rtols
            if not (s == "Kvaerno5" and r < 1e-8)  # the slowest by far
        }
        for (s, r), (t, sol) in h.interleaved(fns, args.rounds or (1 if args.smoke else 3)).items():
            ok = bool(sol.result == tj.RESULTS.successful)
            err = float(np.nanmax(np.abs(np.asarray(sol.theta) - ref))) if ok else math.nan
            curves.setdefault((scene, s), []).append((t.wall, err))
            if r == 1e-8 or args.smoke:  # every rtol: the chart
                label = s + (" (default)" if s == default else "")
                rows.append(
                    f"{scene} | {label} | {g(t.wall)} | {int(sol.num_steps)} | {int(sol.num_rejected_steps)} | {g(err, 2)}"
                )
    h.write(
        f"{SUITE} --wp",
        "Work against precision per law, and on the stem",
        f"""
Rows at rtol 1e-8, atol 1e-10; error against Dopri8 at rtol 1e-12. Chart: `real_tops_wp.png`.

{h.table("scene | solver | wall s | steps | rejected | max d theta", rows)}
""",
        args,
    )
    plt = h.pyplot()
    fig, axes = plt.subplots(
        1, len(scenes), figsize=(3.3 * len(scenes), 3.4), constrained_layout=True, squeeze=False
    )
    for ax, scene in zip(axes[0], scenes):
        for s in solvers:
            pts = sorted(curves.get((scene, s), []))
            if pts:
                ax.loglog([p[0] for p in pts], [max(p[1], 1e-16) for p in pts], marker="o", label=s)
        ax.set(title=scene, xlabel="wall s")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("max |theta - theta_ref| (rad)")
    axes[0][0].legend(fontsize=8)
    fig.savefig(h.figure_path("real_tops_wp.png", args), dpi=100)


def slip(args):
    """The slip_scale convergence table: Contensou converges, pure Coulomb does not."""
    rr, rows = reference(), []
    contensou = (1e-4,) if args.smoke else (1e-4, 1e-5, 1e-6)
    coulomb = (1e-2,) if args.smoke else (1e-2, 3e-3, 1e-3, 3e-4)
    for name, deltas in (("ellipse", contensou), ("hertz", contensou), ("coulomb", coulomb)):
        for delta in deltas:
            top = lg_top(name, stem=False, slip_scale=delta)
            y0 = tj.initial_state(top, theta=THETA0, spin=SPIN)
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                t = float(tj.inversion_time(top, y0, t1=30.0, rtol=1e-8, atol=1e-10, throw=False))
            warned = any(
                issubclass(w.category, UserWarning) and "slip_scale" in str(w.message)
                for w in caught
            )
            kw = dict(mu=MU, rho=RHO, delta=delta, stem=False, contact="rigid")
            r = rr.solve(
                rr.LEINE_GLOCKER, name, THETA0, SPIN, 30.0, stop_at_half=True, dt_sample=1e-2, **kw
            )
            rows.append(
                f"{name} | {g(delta)} | {f(t, 7)} | {f(r['t_half'], 7)} | {g(abs(t - r['t_half']), 2)} | {'yes' if warned else 'no'}"
            )
    head = "law | slip scale m/s | tippejax pi/2 s | reference pi/2 s | difference s | UserWarning"
    h.write(
        f"{SUITE} --slip",
        "The first pi/2 crossing against the slip scale",
        f"No stem; `tj.inversion_time` (rtol 1e-8) against the reference (rtol 1e-9).\n\n{h.table(head, rows)}",
        args,
    )


def contact(args):
    """Sensitivity of the motion after the touch to the compliant contacts' parameters."""
    t1 = 1.6 if args.smoke else T_AFTER
    variants = [("E* 5 GPa, c 200 s/m (defaults)", {})]
    if not args.smoke:
        variants += [
            ("E* x 10", dict(contact_modulus=5e10)),
            ("E* / 10", dict(contact_modulus=5e8)),
            ("c x 10", dict(contact_damping=2000.0)),
            ("c / 10", dict(contact_damping=20.0)),
        ]
    saves, at = (
        np.linspace(0.0, t1, int(round(t1 / 0.01)) + 1),
        [tq for tq in (2.5, 4.0) if tq <= t1],
    )
    rows = []
    for name, kw in variants:  # (accuracy only: one run each, no timing rounds)
        sol = lg_run(lg_top(**kw), t1, saves=saves)
        theta = np.asarray(sol.theta)
        on_stem = (saves > float(sol.t_stem)) & ~(saves >= float(sol.t_ball_return))
        top_theta = f(float(np.max(theta[on_stem])) if on_stem.any() else math.nan)
        cells = " | ".join([top_theta, *(f(float(np.interp(tq, saves, theta))) for tq in at)])
        rows.append(
            f"{name} | {f(float(sol.t_stem), 6)} | {f(float(sol.t_ball_return), 4)} | {cells} | {int(sol.num_steps)}"
        )
    rr = reference()
    r = ref_run(rr, t1=t1)
    ev = ref_events(r)
    on = (saves > ev["t_stem"]) & ~(saves >= ev["ball_return"])  # (on the same saves)
    cells = " | ".join(
        [
            f(float(np.max(np.interp(saves[on], r["t"], r["theta"])))),
            *(f(rr.theta_at(r, tq)) for tq in at),
        ]
    )
    rows.append(
        f"reference (E* 5 GPa, c 200 s/m) | {f(ev['t_stem'], 6)} | {f(ev['ball_return'], 4)} | {cells} | {r['nfev']}"
    )
    head = " | ".join(
        [
            "contact",
            "stem touch s",
            "ball returns s",
            "max theta on the stem",
            *(f"theta({tq:g})" for tq in at),
            "steps",
        ]
    )
    h.write(
        f"{SUITE} --contact",
        "Sensitivity to the contact parameters after the touch",
        f"Ellipse law, {t1:g} s, rtol 1e-8, 10 ms saves.\n\n{h.table(head, rows)}",
        args,
    )


def lg(args):
    """Leine & Glocker's figures: the touch angle and time, and their figure 15."""
    rr, rows, t1 = reference(), [], 0.3 if args.smoke else 1.6
    cards = cardillo_runs(args, args.smoke)
    for pressure in ("hertz", "ellipse"):
        sol, ref = lg_run(lg_top(pressure), t1), ref_events(ref_run(rr, pressure, t1=t1))
        angle = _touch_angle(lg_top(pressure), float(sol.t_stem), t1)
        rows.append(
            f"tippejax, {pressure} | {f(float(sol.t_invert), 6)} | {f(float(sol.t_stem), 6)} | {f(angle)}"
        )
        rows.append(
            f"reference, {pressure} | {f(ref['t_half'], 6)} | {f(ref['t_stem'], 6)} | {f(ref['theta_stem'])}"
        )
    if len(cards) >= 2:
        ext = [
            f(extrapolated(cards, k), d)
            for k, d in (("t_half", 6), ("t_stem", 6), ("theta_stem", 4))
        ]
        rows.append("cardillo (ellipse), dt -> 0 | " + " | ".join(ext))
    rows.append(f"geometry, ball on the table |  |  | {f(float(lg_top('hertz').stem_angle))}")
    rows.append("Leine & Glocker 2003 (published) | about 1 | about 1.5 | about 2.45")
    fig15 = []
    for rho in (5e-4,) if args.smoke else (5e-4, 5e-5, 1e-5):
        cells = []
        for pressure in ("hertz", "ellipse"):
            stemless = lg_top(pressure, stem=False, rho=rho)
            saves = np.linspace(0.0, 0.5, 11)
            sol = lg_run(stemless, 0.5, saves=saves, solver=diffrax.Tsit5(), rtol=1e-9)
            kw = dict(mu=MU, rho=rho, delta=DELTA, stem=False, contact="rigid", dt_sample=0.05)
            r = rr.solve(rr.LEINE_GLOCKER, pressure, THETA0, SPIN, 0.5, **kw)
            cells += [f(float(sol.theta[-1])), f(rr.theta_at(r, 0.5))]
        fig15.append(f"{rho * 1e3:g} | " + " | ".join(cells))
    h.write(
        f"{SUITE} --lg",
        "Leine & Glocker's figures",
        f"""
Slip scale {DELTA:g} m/s.

{h.table("run | theta = pi/2 s | stem touch s | theta at touch", rows)}

Their figure 15: theta at 0.5 s against the contact radius (Tsit5, rtol 1e-9).

{h.table("rho mm | tippejax hertz | reference hertz | tippejax ellipse | reference ellipse", fig15)}
""",
        args,
    )


def _touch_angle(top, t_stem, t1):
    """theta at the located touch: a run whose saves include it (same save count)."""
    if not np.isfinite(t_stem):  # no touch in this run (a smoke run's short one)
        return math.nan
    saves = np.linspace(0.0, t1, int(round(t1 / 0.01)) + 1)
    saves = np.sort(np.append(saves[:-1], t_stem))
    return float(lg_run(top, t1, saves=saves).theta[int(np.searchsorted(saves, t_stem))])


MODES = {
    "peers": (peers, "tippejax, the scipy reference and cardillo on the scene: time, accuracy"),
    "batch": (batch, "a batch of launches with the stem, per law, against the viscous law"),
    "wp": (work_precision, "work against precision per law and solver; real_tops_wp.png"),
    "slip": (slip, "the pi/2 crossing against the slip scale: Contensou converges, Coulomb not"),
    "contact": (contact, "sensitivity to the contact parameters after the touch"),
    "lg": (lg, "Leine & Glocker's figures: the touch angle and time, figure 15"),
}


def options(p):
    p.add_argument("--n", type=int, default=1000, help="tops in --batch")
    p.add_argument("--cardillo", help="checkout of cardillo at commit 1c667a30")
    p.add_argument("--cardillo-python", default=sys.executable)
    p.add_argument("--cache", default=str(pathlib.Path.home() / ".cache" / "real_tops_peers"))


if __name__ == "__main__":
    h.run(MODES, h.parse(__doc__, MODES, options))
