"""Leine & Glocker's tippe top (Coulomb-Contensou friction, the stem): the independent scipy model
`tests/real_top_reference.py` and cardillo's Moreau time stepping, side by side.

    python benchmarks/real_tops_peers.py --cardillo /work/cardillo \
        --cardillo-python /work/cardillo-venv/bin/python        # ~15 min, writes RESULTS.md
    python benchmarks/real_tops_peers.py --smoke --cardillo ...  # under a minute, prints only

Scene (Leine & Glocker 2003; cardillo's `examples/tippetop.py` up to commit 1c667a30): m = 6 g,
R = 15 mm, eps = 3 mm, A = 8e-7, C = 7e-7 kg m^2, stem tip r2 = 5 mm at a2 = 16 mm, mu = 0.3,
contact radius 0.5 mm, theta0 = 0.1 rad, 180 rad/s about the axis, ball centre at rest.

cardillo is not a dependency: `--cardillo` is a checkout of that commit and `--cardillo-python`
a python with its requirements (numpy < 2, scipy, matplotlib, tqdm). Each run of the example's
`make_system` with `MoreauClassical` goes to a subprocess (`--worker`) at `nice --nice`, one at
a time, and its trajectory is kept in `--cache` so that a rerun reuses it. cardillo's times
converge at first order in dt once dt is small: they are extrapolated to dt -> 0 by the line
through the two finest dts (and, for comparison, a least-squares line through all of them).
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
import pathlib
import subprocess
import sys
import time

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent
SCRIPT = "real_tops_peers.py"
THETA0, SPIN, MU, RHO = 0.1, 180.0, 0.3, 5e-4
T_CARDILLO = 2.5  # s simulated by cardillo and by the timed reference runs
T_AFTER = 6.0  # s simulated by the reference runs that follow the top after the touch


# --------------------------------------------------------------------------------------------
# cardillo, in its own python
# --------------------------------------------------------------------------------------------


def cardillo_worker(checkout, dt, t_final, out):
    """Run cardillo's tippe-top example with MoreauClassical (as the example does) and save it."""
    root = pathlib.Path(checkout).resolve()
    sys.path.insert(0, str(root))
    import matplotlib

    matplotlib.use("Agg")
    import cardillo.discrete as discrete
    from cardillo.solver import MoreauClassical

    if not hasattr(discrete, "RigidBodyEuler"):  # the example imports it; unused, gone at 1c667a30
        discrete.RigidBodyEuler = type("RigidBodyEuler", (), {})
    spec = importlib.util.spec_from_file_location("cardillo_tippetop",
                                                  root / "examples" / "tippetop.py")
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    system, top, _, _ = example.make_system(discrete.RigidBody)
    start = time.perf_counter()
    sol = MoreauClassical(system, t_final, dt, atol=1e-12).solve()
    wall = time.perf_counter() - start
    axis = np.array([top.A_IK(t, q)[:, 2] for t, q in zip(sol.t, sol.q)])
    gaps = np.array([system.g_N(t, q) for t, q in zip(sol.t, sol.q)])
    np.savez(out, t=sol.t, q=sol.q, u=sol.u, P_N=sol.P_N, axis=axis, gaps=gaps, wall=wall, dt=dt)


def run_cardillo(args, dt, t_final):
    """The cached run at dt, else a subprocess run (its log beside the cache file)."""
    cache = pathlib.Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    out = cache / f"cardillo_dt{dt:.3g}_t{t_final:g}.npz"
    if not out.exists():
        cmd = ["nice", "-n", str(args.nice), args.cardillo_python, str(pathlib.Path(__file__)),
               "--worker", "--cardillo", args.cardillo, "--dt", repr(dt),
               "--t-final", repr(t_final), "--out", str(out)]
        with open(out.with_suffix(".log"), "w") as log:
            subprocess.run(cmd, check=True, stdout=log, stderr=subprocess.STDOUT,
                           env={**os.environ, "MPLBACKEND": "Agg"})
    return dict(np.load(out))


def _crossing(t, f, start=0):
    """First time after index `start` where f goes from < 0 to >= 0 (linear between samples)."""
    idx = np.nonzero((f[start:-1] < 0) & (f[start + 1:] >= 0))[0]
    if idx.size == 0:
        return math.nan
    i = start + idx[0]
    return float(t[i] - f[i] * (t[i + 1] - t[i]) / (f[i + 1] - f[i]))


def cardillo_summary(run):
    """pi/2 crossing, stem touch (stem gap reaching 0), theta there, ball contact afterwards."""
    t, gaps = run["t"], run["gaps"]
    theta = np.arccos(np.clip(run["axis"][:, 2], -1, 1))
    t_stem = _crossing(t, -gaps[:, 1])
    out = {"t_half": _crossing(t, theta - math.pi / 2), "t_stem": t_stem,
           "theta_stem": float(np.interp(t_stem, t, theta)) if np.isfinite(t_stem) else math.nan,
           "wall": float(run["wall"]), "steps": t.size - 1, "t": t, "theta": theta}
    for tq in (0.5, 1.0, 1.25):
        out[f"theta_{tq:g}"] = float(np.interp(tq, t, theta)) if tq <= t[-1] else math.nan
    i = int(np.searchsorted(t, t_stem)) if np.isfinite(t_stem) else t.size - 1
    t_off = _crossing(t, gaps[:, 0], i)
    out["ball_liftoff"] = t_off
    j = int(np.searchsorted(t, t_off)) if np.isfinite(t_off) else t.size - 1
    out["ball_again"] = _crossing(t, -gaps[:, 0], j)
    out["theta_max_stem"] = float(theta[i:].max()) if i < t.size else math.nan
    return out


def first_order_extrapolation(dts, values):
    """(value at dt = 0, slope, max residual) of the least-squares line value = v0 + slope dt."""
    dts, values = np.asarray(dts, float), np.asarray(values, float)
    ok = np.isfinite(values)
    if ok.sum() < 2:
        return math.nan, math.nan, math.nan
    slope, v0 = np.polyfit(dts[ok], values[ok], 1)
    return float(v0), float(slope), float(np.abs(v0 + slope * dts[ok] - values[ok]).max())


# --------------------------------------------------------------------------------------------
# The scipy reference
# --------------------------------------------------------------------------------------------


def reference():
    """`tests/real_top_reference.py`, imported by path (it imports no tippejax)."""
    spec = importlib.util.spec_from_file_location("real_top_reference",
                                                  ROOT / "tests" / "real_top_reference.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["real_top_reference"] = module
    spec.loader.exec_module(module)
    return module


def summary(rr, r):
    """The reference run's events in `cardillo_summary`'s terms."""
    ev = r["events"]
    t_stem = r["t_stem"]
    after = [(t, n) for t, n, _ in ev if np.isfinite(t_stem) and t >= t_stem]
    off = next((t for t, n in after if n == "ball_liftoff"), math.nan)
    again = next((t for t, n in after if n == "ball_touchdown" and t > off), math.nan)
    on_stem = r["t"] >= t_stem if np.isfinite(t_stem) else np.zeros(r["t"].size, bool)
    if np.isfinite(again):
        on_stem &= r["t"] < again
    out = {"t_half": r["t_half"], "t_stem": t_stem, "theta_stem": r["theta_stem"],
           "touchdowns": sum(n == "ball_touchdown" for t, n in after),
           "ball_liftoff": off, "ball_again": again, "wall": r["wall"], "nfev": r["nfev"],
           "theta_max_stem": float(r["theta"][on_stem].max()) if on_stem.any() else math.nan,
           "t": r["t"], "theta": r["theta"]}
    for tq in (0.5, 1.0, 1.25, 2.5, 4.0, 6.0):
        out[f"theta_{tq:g}"] = rr.theta_at(r, tq) if tq <= r["t"][-1] else math.nan
    return out


def lg_run(rr, law, delta, t_end, **kw):
    kw = {"rho": RHO, **kw}
    return summary(rr, rr.solve(rr.LEINE_GLOCKER, law, THETA0, SPIN, t_end, mu=MU, delta=delta,
                                **kw))


def tippejax_run(law, delta, t_end):
    """Hook for tippejax's own column: its run of this scene, or None.

    To be filled in once tippejax has the Coulomb-Contensou laws and the stem: return a dict
    with at least "wall" (seconds for one warm run of t_end seconds), "t_half", "t_stem" and
    "theta_stem" for Leine & Glocker's top launched as above with `law` ("ellipse" or "hertz")
    and slip scale `delta`. Rows are added to the timing and comparison tables when it does.
    """
    return None


# --------------------------------------------------------------------------------------------
# Tables
# --------------------------------------------------------------------------------------------


def _f(x, digits=4):
    return "-" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f"{x:.{digits}f}"


def _g(x, digits=3):
    return "-" if x is None or not np.isfinite(x) else f"{x:.{digits}g}"


def table(headers, rows):
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    return "\n".join(lines + ["| " + " | ".join(str(x) for x in row) + " |" for row in rows])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cardillo", help="checkout of cardillo at commit 1c667a30")
    ap.add_argument("--cardillo-python", default=sys.executable)
    ap.add_argument("--cardillo-commit", default="1c667a30", help="label for the table")
    ap.add_argument("--dts", type=float, nargs="+", default=[1e-3, 5e-4, 2.5e-4])
    ap.add_argument("--cache", default=str(pathlib.Path.home() / ".cache" / "real_tops_peers"))
    ap.add_argument("--nice", type=int, default=10)
    ap.add_argument("--smoke", action="store_true", help="a short run that writes nothing")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--dt", type=float, help=argparse.SUPPRESS)
    ap.add_argument("--t-final", type=float, help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        return cardillo_worker(args.cardillo, args.dt, args.t_final, args.out)
    return report(args)


def report(args):
    rr = reference()
    started = time.perf_counter()
    smoke = args.smoke
    deltas = [1e-5] if smoke else [1e-4, 1e-5, 1e-6]
    laws = ["ellipse"] if smoke else ["ellipse", "hertz"]
    t_after = 1.6 if smoke else T_AFTER
    rr.solve(rr.LEINE_GLOCKER, "hertz", THETA0, SPIN, 0.01, mu=MU, rho=RHO)  # compile
    sections = []

    # 1. the reference on Leine & Glocker's top
    runs = {(law, d): lg_run(rr, law, d, t_after) for law in laws for d in deltas}
    rows = [[law, _g(d), _f(s["t_half"], 7), _f(s["t_stem"], 6), _f(s["theta_stem"]),
             _f(s["ball_liftoff"], 6), _f(s["theta_max_stem"]), _f(s["ball_again"], 6),
             s["touchdowns"], _f(s["theta_0.5"]), _f(s["theta_2.5"]), _f(s["theta_6"]),
             _g(s["wall"])]
            for (law, d), s in runs.items()]
    sections.append(
        f"### The reference on Leine & Glocker's top ({t_after:g} s)\n\n"
        "Published (Leine & Glocker 2003): theta passes pi/2 at about 1 s, the stem touches at "
        "about 1.5 s. 'ball off': first ball lift-off after the touch; 'max theta on stem': "
        "until the ball touches again ('ball again', s); 'touchdowns': the ball's touchdowns "
        f"after the stem touch, up to {t_after:g} s.\n\n"
        + table(["law", "delta m/s", "theta = pi/2 s", "stem touch s", "theta at touch",
                 "ball off s", "max theta on stem", "ball again s", "touchdowns", "theta(0.5)",
                 "theta(2.5)", f"theta({t_after:g})", "wall s"], rows))

    # 2. Leine & Glocker's figure 15: theta at 0.5 s against the contact radius
    rhos = [5e-4] if smoke else [5e-4, 5e-5, 1e-5]
    rows = []
    for rho in rhos:
        row = [f"{rho * 1e3:g}"]
        for law in laws:
            s = lg_run(rr, law, 1e-6, 0.5, rho=rho, stem=False, contact="rigid")
            row.append(_f(s["theta_0.5"]))
        rows.append(row)
    sections.append("### theta at 0.5 s against the contact radius (their figure 15), "
                    "delta = 1e-6 m/s\n\n" + table(["rho mm"] + laws, rows))

    # 3. pure regularised Coulomb: no limit as delta -> 0
    rows = []
    for d in ([1e-2] if smoke else [1e-2, 3e-3, 1e-3, 3e-4, 1e-4]):
        r = rr.solve(rr.LEINE_GLOCKER, "coulomb", THETA0, SPIN, 60.0, mu=MU, delta=d,
                     stem=False, contact="rigid", stop_at_half=True, dt_sample=1e-2)
        rows.append([_g(d), _f(r["t_half"], 3), _g(r["t_half"] * d), _g(r["wall"])])
    sections.append("### Pure regularised Coulomb friction (no Contensou): the pi/2 crossing\n\n"
                    + table(["delta m/s", "theta = pi/2 s", "t * delta (m)", "wall s"], rows))

    # 4. sensitivity of the motion after the touch to the contact model
    base = dict(law="ellipse", delta=1e-6)
    variants = [("baseline: rigid, then Hunt-Crossley E* 5 GPa, c 200 s/m", {})]
    if not smoke:
        variants += [("E* x 10", {"E_star": 5e10}), ("E* / 10", {"E_star": 5e8}),
                     ("c x 10", {"damping": 2000.0}), ("c / 10", {"damping": 20.0}),
                     ("compliant from t = 0", {"contact": "compliant"}),
                     ("switch 1 mm before the touch", {"switch_gap": 1e-3}),
                     ("rtol 1e-10", {"rtol": 1e-10}), ("Radau", {"method_compliant": "Radau"})]
    rows = []
    for name, kw in variants:
        s = lg_run(rr, base["law"], base["delta"], t_after, **kw)
        rows.append([name, _f(s["t_stem"], 5), _f(s["theta_stem"]), _f(s["ball_liftoff"], 5),
                     _f(s["theta_max_stem"]), _f(s["ball_again"]), _f(s["theta_2.5"]),
                     _f(s["theta_4"]), _g(s["wall"])])
    sections.append(
        f"### Sensitivity to the contact model (ellipse, delta = 1e-6 m/s, {t_after:g} s)\n\n"
        + table(["contact", "stem touch s", "theta at touch", "ball off s",
                 "max theta on stem", "ball again s", "theta(2.5)", "theta(4)", "wall s"], rows))

    # 5. cardillo against the reference, extrapolated in dt
    t_card = 0.3 if smoke else T_CARDILLO
    dts = [1e-3] if smoke else sorted(args.dts, reverse=True)
    ref = runs[("ellipse", deltas[-1])]
    cards = {dt: cardillo_summary(run_cardillo(args, dt, t_card)) for dt in dts} if args.cardillo \
        else {}
    keys = ["t_half", "t_stem", "theta_stem", "theta_0.5", "theta_1", "theta_1.25"]
    labels = ["theta = pi/2 s", "stem touch s", "theta at touch", "theta(0.5)", "theta(1.0)",
              "theta(1.25)"]
    rows = []
    for dt, c in cards.items():
        grid = ref["t"][ref["t"] <= min(c["t"][-1], np.nan_to_num(ref["t_stem"], nan=9) - 0.01)]
        err = np.max(np.abs(np.interp(grid, c["t"], c["theta"]) - np.interp(grid, ref["t"],
                                                                           ref["theta"])))
        rows.append([f"cardillo dt {dt:g}"] + [_f(c[k]) for k in keys]
                    + [_f(c["ball_liftoff"]), _g(err), _g(c["wall"])])
    if len(cards) >= 2:
        fine = sorted(cards)[:2]  # first order holds at the finest steps only
        for label, chosen in ((f"cardillo, dt -> 0 from dt {fine[1]:g} and {fine[0]:g}", fine),
                              ("cardillo, dt -> 0, line through all dts", sorted(cards))):
            if label.endswith("all dts") and len(cards) < 3:
                continue
            ex = [first_order_extrapolation(chosen, [cards[d][k] for d in chosen]) for k in keys]
            rows.append([label] + [_f(v0) for v0, _, _ in ex] + ["", "", ""])
            if len(chosen) > 2:
                rows.append(["(its max residual)"] + [_g(res) for _, _, res in ex] + ["", "", ""])
    rows.append([f"reference ellipse, delta {deltas[-1]:g}"] + [_f(ref[k]) for k in keys]
                + [_f(ref["ball_liftoff"]), "0", _g(ref["wall"])])
    for law in laws:
        tj = tippejax_run(law, deltas[-1], t_card)
        if tj is not None:
            rows.append([f"tippejax {law}"] + [_f(tj.get(k)) for k in keys] + ["", "",
                                                                               _g(tj["wall"])])
    sections.append(
        f"### cardillo (Moreau, set-valued Coulomb-Contensou ellipse) and the reference, "
        f"{t_card:g} s\n\n'max dtheta before touch': max |theta_cardillo - theta_reference| "
        "up to 10 ms before the first stem touch.\n\n"
        + table(["run"] + labels + ["ball off s", "max dtheta before touch", "wall s"], rows))

    # 6. wall time per run of T_CARDILLO seconds
    rows = []
    for law in laws:
        walls = [lg_run(rr, law, deltas[-1], t_card)["wall"] for _ in range(1 if smoke else 3)]
        rows.append([f"scipy reference ({law}, delta {deltas[-1]:g}), median of {len(walls)}",
                     _g(float(np.median(walls)))])
    for dt, c in cards.items():
        rows.append([f"cardillo MoreauClassical dt {dt:g} ({c['steps']} steps)", _g(c["wall"])])
    for law in laws:
        tj = tippejax_run(law, deltas[-1], t_card)
        rows.append([f"tippejax ({law})", "pending: no stem or Contensou law yet" if tj is None
                     else _g(tj["wall"])])
    sections.append(f"### Wall time per run of {t_card:g} s\n\n" + table(["run", "wall s"], rows))

    if args.cardillo:
        versions = subprocess.run(
            [args.cardillo_python, "-c", "import numpy, scipy, sys; print(f'python "
             "{sys.version.split()[0]}, numpy {numpy.__version__}, scipy {scipy.__version__}')"],
            capture_output=True, text=True).stdout.strip()
    import scipy

    load = open("/proc/loadavg").read().split()[0] if pathlib.Path("/proc/loadavg").exists() \
        else "?"
    head = (f"## real_tops_peers.py: Leine & Glocker's top, the scipy reference and cardillo\n\n"
            f"`python benchmarks/{SCRIPT} --cardillo <checkout> --cardillo-python <python>` "
            f"({time.perf_counter() - started:.0f} s, 1-minute load average {load} at the end; "
            f"cardillo runs may come from the cache). cardillo {args.cardillo_commit} "
            f"(`examples/tippetop.py`, MoreauClassical, atol 1e-12; "
            f"{versions if args.cardillo else 'not run'}). Reference (numpy {np.__version__}, "
            f"scipy {scipy.__version__}, numba {'yes' if rr.HAVE_NUMBA else 'no'}): "
            "`tests/real_top_reference.py`, DOP853 with the rigid ball until the stem is 0.1 mm "
            "from the table, then LSODA with Hunt-Crossley ball and stem (E* 5 GPa, c 200 s/m), "
            "rtol 1e-9. cardillo runs one at a time at `nice` while other jobs may share the "
            "machine: its wall times vary with that load.")
    sys.path.insert(0, str(HERE))
    import _common

    body = head + "\n\n" + _common.machine_block() + "\n\n" + "\n\n".join(sections)
    print(body)
    if not smoke:
        write_section(body)


def write_section(body):
    """Replace (or append) this script's section of RESULTS.md; the shared header is left as is
    (the machine of this run is in the section itself)."""
    path = HERE / "RESULTS.md"
    text = path.read_text() if path.exists() else ""
    block = f"<!-- {SCRIPT} -->\n{body.strip()}\n<!-- /{SCRIPT} -->"
    start, end = text.find(f"<!-- {SCRIPT} -->"), text.find(f"<!-- /{SCRIPT} -->")
    if start >= 0 and end > start:
        text = text[:start] + block + text[end + len(f"<!-- /{SCRIPT} -->"):]
    else:
        text = text.rstrip("\n") + "\n\n" + block + "\n"
    path.write_text(text)


if __name__ == "__main__":
    main()
