"""Command line: `tippejax classify | diagram | demo | fit`.

- `classify`: the group and thresholds of a top, and a map of the groups.
- `diagram`: the six bifurcation diagrams (the paper's Fig. 1) and the map of the groups.
- `demo`: the analysis of the default top launched near upright (and, later, its simulation).
- `fit`: fit parameters of a top and its launch to a measured tilt theta(t) read from a CSV file
  (columns `t`, `theta` and optionally `phi`; see `read_fit_csv`), with `tippejax.fit`; prints
  the fitted values and writes `fit.png` (`fit_figure`) and `fit.csv`.
- `map`: outcome maps of a top (`tippejax.outcome_map`): where a grid of launches ends, with the
  linear-theory boundaries, and a map over (A/C, eps/R) beside the group map.
- `animate`: simulate a launch (default: the demo's) and write a 3-D animation with
  `tippejax.animate` (GIF, or MP4 with ffmpeg).

Run as `tippejax ...` (console script) or `python -m tippejax._cli ...`.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import sys
import time
from collections.abc import Sequence

DEFAULT_OUT = "tippejax-out"

# One representative (A/C, eps/R) per group, well inside it (distance to the nearest other group
# in the (A/C, eps/R) plane in brackets; Groups Ia and IIc are thin). Checked with `classify`.
REPRESENTATIVES: dict[str, tuple[float, float]] = {
    "Ia": (0.91, 0.035),  # (0.035)
    "Ib": (0.65, 0.15),  # (0.15)
    "IIa": (0.69, 0.38),  # (0.05)
    "IIb": (0.95, 0.45),  # (0.2)
    "IIc": (0.976, 0.04),  # (0.012)
    "III": (1.6, 0.2),  # (0.4)
}

_THRESHOLD_UNITS = (
    ("n1", "rad/s"),
    ("n2", "rad/s"),
    ("J1", "kg m^2/s"),
    ("J2", "kg m^2/s"),
    ("theta_c", "rad"),
    ("x_b", ""),
    ("theta_b", "rad"),
)


def _fmt(value: float, spec: str = ".6g") -> str:
    """A number, or "-" for nan."""
    value = float(value)
    return "-" if math.isnan(value) else format(value, spec)


def _print_top(top) -> str:
    import jax

    import tippejax as tj
    from tippejax._analysis.groups import group_index

    th = jax.jit(tj.thresholds)(top)  # one compilation instead of one per elementwise op
    group = tj.GROUPS[int(jax.jit(group_index)(top))]
    print(
        f"top: m = {float(top.m):.4g} kg, R = {float(top.R):.4g} m, eps = {float(top.eps):.4g} m, "
        f"A = {float(top.A):.4g} kg m^2, C = {float(top.C):.4g} kg m^2, mu = {float(top.mu):.4g} s/m"
    )
    print(f"A/C = {float(top.A / top.C):.4g}, eps/R = {float(top.eps / top.R):.4g}: Group {group}")
    print("thresholds (- = undefined for this group):")
    for name, unit in _THRESHOLD_UNITS:
        print(f"  {name:8s} = {_fmt(getattr(th, name)):>12s} {unit}")
    return group


def _save(fig, path: str) -> str:
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=130)
    plt.close(fig)
    return path


def _agg():
    import matplotlib

    matplotlib.use("Agg")


def write_group_map(out: str, points=None) -> str:
    """Write `group_map.png` to the folder `out`; returns its path."""
    _agg()
    from ._plot import group_map

    ax = group_map(points=points)
    return _save(ax.figure, os.path.join(out, "group_map.png"))


def representative_tops() -> dict:
    """`{group: TippeTop}` for `REPRESENTATIVES`, each checked to be in its group."""
    import tippejax as tj

    tops = {}
    for name, (a, e) in REPRESENTATIVES.items():
        top = tj.TippeTop.from_ratios(a, e)
        got = tj.classify(top)
        if got != name:  # pragma: no cover - guards the table above
            raise RuntimeError(f"Representative of Group {name} (A/C={a}, eps/R={e}) is in {got}.")
        tops[name] = top
    return tops


def write_diagrams(out: str) -> list[str]:
    """Write `bifurcation_diagrams.png` and `group_map.png` to the folder `out`."""
    _agg()
    from ._plot import bifurcation_diagrams

    fig = bifurcation_diagrams(representative_tops())
    paths = [_save(fig, os.path.join(out, "bifurcation_diagrams.png"))]
    paths.append(write_group_map(out, points=REPRESENTATIVES))
    return paths


def default_spin(top) -> float:
    r"""A launch spin above the inversion threshold: $1.5\max(n_1, n_2(R+\epsilon)/(R-\epsilon))$,
    rounded up to a whole rad/s (ignoring undefined thresholds; 100 rad/s if both are)."""
    import numpy as np

    import tippejax as tj

    th = tj.thresholds(top)
    lever = float((top.R + top.eps) / (top.R - top.eps))
    candidates = [v for v in (float(th.n1), float(th.n2) * lever) if not math.isnan(v)]
    if not candidates:
        return 100.0
    return float(np.ceil(1.5 * max(candidates)))


def _demo_analysis(top, theta0: float, spin: float):
    r"""Print the analysis of a launch: group, thresholds, Jellet and steady states at that Jellet.

    $J = C n_0(R\cos\theta_0 - \epsilon)$ for a launch without precession (eq. Jellet); the steady
    states are those of `tj.steady_states` (vertical: $W'' > 0$ at the pole; intermediate:
    $g(\cos\theta_0) > 0$).

    **Arguments:**

    - `top`: the `TippeTop`.
    - `theta0`: launch tilt (rad).
    - `spin`: launch spin $n_0$ (rad/s).

    **Returns:** the Jellet $J$ (a JAX scalar, kg m^2/s).
    """
    import jax
    import numpy as np

    import tippejax as tj

    _print_top(top)
    y0 = tj.initial_state(top, theta=theta0, spin=spin)
    J = tj.jellet(top, y0)
    th = jax.jit(tj.thresholds)(top)
    print(f"launch: theta0 = {theta0:.4g} rad, spin n0 = {spin:.6g} rad/s")
    print(f"Jellet J = {float(J):.6g} kg m^2/s  (J1 = {_fmt(th.J1)}, J2 = {_fmt(th.J2)})")
    states = tj.steady_states(top, J)
    print("steady states at this J:")
    for theta, spin_v, stable in zip(
        np.asarray(states.vertical_theta),
        np.asarray(states.vertical_spin),
        np.asarray(states.vertical_stable),
    ):
        name = "theta = 0 " if theta == 0 else "theta = pi"
        print(
            f"  vertical     {name}      spin n = {spin_v:9.4g} rad/s  "
            f"{'stable' if stable else 'unstable'}"
        )
    valid = np.asarray(states.intermediate_valid)
    if not valid.any():
        print("  intermediate none")
    for theta, g, stable, ok in zip(
        np.asarray(states.intermediate_theta),
        np.asarray(states.intermediate_g),
        np.asarray(states.intermediate_stable),
        valid,
    ):
        if ok:
            print(
                f"  intermediate theta = {theta:.6g} rad ({math.degrees(theta):.2f} deg)  "
                f"g = {g:.4g}  {'stable' if stable else 'unstable'}"
            )
    return J


def _demo_simulation(top, theta0: float, spin: float, out: str):
    """Simulate the demo launch (full model), print a summary and write `out/demo.png`.

    **Returns:** the path of the figure.
    """
    from ._demo import run_demo_simulation

    return run_demo_simulation(top, theta0, spin, out)


def _cmd_classify(args) -> int:
    import tippejax as tj

    if (args.A_over_C is None) != (args.eps_over_R is None):
        raise SystemExit("classify: give both --A-over-C and --eps-over-R, or neither.")
    if args.A_over_C is None:
        top = tj.default_top()
    else:
        top = tj.TippeTop.from_ratios(args.A_over_C, args.eps_over_R)
    group = _print_top(top)
    os.makedirs(args.out, exist_ok=True)
    point = {f"this top ({group})": (float(top.A / top.C), float(top.eps / top.R))}
    print(f"wrote {write_group_map(args.out, points=point)}")
    return 0


def _cmd_diagram(args) -> int:
    os.makedirs(args.out, exist_ok=True)
    for name, (a, e) in REPRESENTATIVES.items():
        print(f"Group {name:3s}: A/C = {a:g}, eps/R = {e:g}")
    for path in write_diagrams(args.out):
        print(f"wrote {path}")
    return 0


def _cmd_demo(args) -> int:
    import tippejax as tj

    top = tj.default_top()
    spin = args.spin if args.spin is not None else default_spin(top)
    _demo_analysis(top, args.theta0, spin)
    # Simulation of the same launch.
    _demo_simulation(top, args.theta0, spin, args.out)
    return 0


# ---------------------------------------------------------------------------------------------
# tippejax fit


FIT_DEFAULT_SPIN = 100.0  # rad/s: launch spin guess of `tippejax fit`
FIT_MIN_THETA0 = 0.02  # rad: the launch tilt guess from the data is at least this


def _cell(text: str, column: str, row: int, path: str) -> float:
    """One CSV cell as a float: empty or "nan" is a missing sample (NaN)."""
    text = text.strip()
    if text == "" or text.lower() == "nan":
        return math.nan
    try:
        return float(text)
    except ValueError:
        raise ValueError(
            f"{path}, line {row}: column {column!r} holds {text!r}, which is not a number "
            f"(leave the cell empty or write nan for a missing sample)."
        ) from None


def read_fit_csv(path: str):
    """Read the data of `tippejax fit`: a CSV file with a header row naming the columns.

    Columns `t` (s) and `theta` (rad) are required, `phi` (rad) is optional; other columns are
    ignored. An empty cell or `nan` is a missing sample (NaN), except in `t`, which must be a
    number on every row.

    **Returns:** `(t, theta, phi)`, numpy arrays (`phi` is `None` without a `phi` column).
    """
    import numpy as np

    if not os.path.isfile(path):
        raise ValueError(f"data file {path!r} not found.")
    with open(path, newline="", encoding="utf-8-sig") as handle:  # -sig: a spreadsheet's BOM
        reader = csv.reader(handle)
        header = next(reader, None)
        if header is None:
            raise ValueError(f"{path} is empty; it needs a header row with columns t and theta.")
        names = [h.strip().lower() for h in header]
        missing = [c for c in ("t", "theta") if c not in names]
        if missing:
            raise ValueError(
                f"{path} has no column {' or '.join(repr(c) for c in missing)} in its header "
                f"row {header}; the data need columns t (s) and theta (rad), optionally phi (rad)."
            )
        wanted = ["t", "theta"] + (["phi"] if "phi" in names else [])
        index = {c: names.index(c) for c in wanted}
        columns = {c: [] for c in wanted}
        for row_number, row in enumerate(reader, start=2):
            if not row or all(not cell.strip() for cell in row):
                continue  # blank line
            for c in wanted:
                text = row[index[c]] if index[c] < len(row) else ""
                columns[c].append(_cell(text, c, row_number, path))
    t = np.asarray(columns["t"], dtype=float)
    if t.size < 2:
        raise ValueError(f"{path} holds {t.size} data rows; a fit needs more.")
    if not np.all(np.isfinite(t)):
        bad = int(np.flatnonzero(~np.isfinite(t))[0])
        raise ValueError(
            f"{path}: the time t of data row {bad + 1} is missing; every row needs a t."
        )
    theta = np.asarray(columns["theta"], dtype=float)
    phi = np.asarray(columns["phi"], dtype=float) if "phi" in columns else None
    return t, theta, phi


def launch_tilt_guess(t, theta) -> float:
    """A guess of the launch tilt from the record: the mean of the samples in its first 2% (at
    least 5 samples), which averages the noise of one sample, kept away from the poles."""
    import numpy as np

    finite = np.isfinite(theta)
    first = t[finite][:max(5, int(0.02 * finite.sum()))]
    guess = float(np.mean(theta[finite][: first.size]))
    return min(max(guess, FIT_MIN_THETA0), math.pi - FIT_MIN_THETA0)


def fit_guess(args):
    """The starting top of `tippejax fit`: `default_top()` with the given fields replaced.

    `--m`, `--R`, `--eps`, `--mu` replace those fields. `--A-over-C` and/or `--eps-over-R`
    rebuild the top with `TippeTop.from_ratios` (keeping m, R, mu; the ratio not given is kept
    from the top so far; C = 0.4 m R^2, a homogeneous sphere).
    """
    import tippejax as tj

    if args.eps is not None and args.eps_over_R is not None:
        raise ValueError("give the eccentricity once: --eps (m) or --eps-over-R, not both.")
    top = tj.default_top()
    fields = {f: float(getattr(top, f)) for f in ("m", "R", "eps", "A", "C", "g", "mu")}
    for name in ("m", "R", "eps", "mu"):
        value = getattr(args, name)
        if value is not None:
            fields[name] = float(value)
    if args.A_over_C is not None or args.eps_over_R is not None:
        a_over_c = args.A_over_C if args.A_over_C is not None else fields["A"] / fields["C"]
        eps_over_r = args.eps_over_R if args.eps_over_R is not None else fields["eps"] / fields["R"]
        return tj.TippeTop.from_ratios(
            a_over_c, eps_over_r, m=fields["m"], R=fields["R"], mu=fields["mu"], g=fields["g"]
        )
    return tj.TippeTop(**fields)


def write_fit_outputs(result, out: str) -> list[str]:
    """Write `fit.png` (`fit_figure`) and `fit.csv` (t, theta_obs, theta_fit, residual; recording
    0 of a batched fit) to the folder `out`; returns their paths."""
    import numpy as np

    _agg()
    from ._plot import fit_figure

    os.makedirs(out, exist_ok=True)
    paths = [_save(fit_figure(result), os.path.join(out, "fit.png"))]
    columns = [np.asarray(result.ts)] + [
        np.asarray(x).reshape(-1, np.asarray(result.ts).size)[0]
        for x in (result.theta_obs, result.theta_fit, result.residuals)
    ]
    path = os.path.join(out, "fit.csv")
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["t", "theta_obs", "theta_fit", "residual"])
        for row in zip(*columns):
            writer.writerow([format(float(v), ".10g") for v in row])
    paths.append(path)
    return paths


def _run_fit(args) -> int:
    import numpy as np

    import tippejax as tj

    t, theta, phi = read_fit_csv(args.data)
    if args.no_phi:
        phi = None
    if args.t_max is not None:
        keep = t <= args.t_max
        if keep.sum() < 2:
            raise ValueError(
                f"--t-max {args.t_max:g} s leaves {keep.sum()} samples (t starts at {t[0]:g} s)."
            )
        t, theta = t[keep], theta[keep]
        phi = phi[keep] if phi is not None else None
    if not np.any(np.isfinite(theta)):
        raise ValueError(f"{args.data}: every theta sample is missing.")
    free = tuple(name.strip() for name in args.free.split(",") if name.strip())
    top = fit_guess(args)
    theta0 = args.theta0
    if theta0 is None:
        # Not given: free it (unless --free leaves it out on purpose with --theta0), starting
        # from the smoothed start of the record, away from the poles.
        theta0 = launch_tilt_guess(t, theta)
        if "theta0" not in free and args.theta_dot is None:
            free = free + ("theta0",)
    theta_dot = 0.0 if args.theta_dot is None else args.theta_dot
    y0 = tj.initial_state(top, theta0, args.spin, theta_dot=theta_dot)
    n_used = int(np.isfinite(theta).sum())
    print(
        f"data: {args.data}: {t.size} samples from t = {t[0]:g} to {t[-1]:g} s "
        f"({n_used} with theta{', with phi' if phi is not None else ''})"
    )
    print(
        f"guess: m = {float(top.m):.4g} kg, R = {float(top.R):.4g} m, eps = {float(top.eps):.4g} m "
        f"(eps/R = {float(top.eps / top.R):.4g}), A/C = {float(top.A / top.C):.4g}, "
        f"mu = {float(top.mu):.4g} s/m; launch theta0 = {theta0:.4g} rad, "
        f"theta_dot = {theta_dot:g} rad/s, spin = {args.spin:g} rad/s"
    )
    print(
        f"fitting {', '.join(free) or '(nothing)'} (model {args.model}, "
        f"strategy {args.strategy}, method {args.method}) ..."
    )
    start = time.perf_counter()
    result = tj.fit(
        top, y0, t, theta, free=free, phi_obs=phi, model=args.model, method=args.method,
        strategy=args.strategy, max_steps=args.max_steps, sigma=args.sigma, trim=args.trim,
    )
    wall = time.perf_counter() - start
    print(result.table())
    describes = float(result.describes_until)
    print(f"model:           {result.model}")
    if math.isnan(describes):
        note = "  (undefined: too few finite residuals)"
    elif describes >= t[-1]:
        note = "  (the whole record)"
    else:
        note = (f"  (of {t[-1]:g} s: the model stops describing the data there; try --t-max or "
                "another model)")
    print(f"describes until: {_fmt(describes, '.4g')} s{note}")
    print(f"rms residual:    {float(result.rms):.4g} rad over the whole record, "
          f"{float(result.rms_fitted):.4g} rad over the fitted part (to "
          f"{float(result.fitted_until):.4g} s)")
    print(f"converged:       {bool(result.converged)} ({result.message()})")
    print(f"wall time:       {wall:.1f} s (including compilation)")
    for path in write_fit_outputs(result, args.out):
        print(f"wrote {path}")
    return 0


def _cmd_fit(args) -> int:
    try:
        return _run_fit(args)
    except (ValueError, TypeError, OSError) as err:  # bad input: a message, not a traceback
        print(f"error: {err}", file=sys.stderr)
        return 2


# ---------------------------------------------------------------------------------------------
# tippejax animate

ANIMATE_DEFAULT_OUT = os.path.join(DEFAULT_OUT, "animation.gif")
ANIMATE_SAVES_PER_SECOND = 200  # save times of the simulation (frames are resampled from them)


def _cmd_animate(args) -> int:
    """Simulate one launch (the top of `fit_guess`, default: the demo's) and render it."""
    import numpy as np

    import tippejax as tj

    try:
        top = fit_guess(args)
        spin = args.spin if args.spin is not None else default_spin(top)
        y0 = tj.initial_state(top, args.theta0, spin)
        ts = np.linspace(0.0, args.t1, max(2, int(round(args.t1 * ANIMATE_SAVES_PER_SECOND)) + 1))
        print(f"simulating: theta0 = {args.theta0:g} rad, spin = {spin:g} rad/s, "
              f"t1 = {args.t1:g} s, model {args.model} ...")
        sol = tj.simulate(top, y0, args.t1, model=args.model, saveat=ts, throw=False)
        print(f"  model used: {sol.model}; inversion time: {_fmt(sol.t_invert, '.4g')} s")
        start = time.perf_counter()
        path = tj.animate(
            sol, top, args.out, fps=args.fps, speed=args.speed, duration=args.duration,
            frames=args.frames, t_start=args.t_start, t_end=args.t_end, dpi=args.dpi,
            follow=args.follow,
        )
    except (ValueError, TypeError, OSError, RuntimeError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"wrote {path} ({os.path.getsize(path) / 1e6:.2f} MB, "
          f"{time.perf_counter() - start:.1f} s to render)")
    return 0


# ---------------------------------------------------------------------------------------------
# tippejax map

MAP_GROUP_TOPS = ("standard", *REPRESENTATIVES)


def _map_top(args):
    """The top of `tippejax map`: `--group` (a representative of a group, or the standard top),
    then the fields given on the command line (as `fit_guess`)."""
    import tippejax as tj

    if args.group not in (None, "standard"):
        a_over_c, eps_over_r = REPRESENTATIVES[args.group]
        args.A_over_C = a_over_c if args.A_over_C is None else args.A_over_C
        args.eps_over_R = eps_over_r if args.eps_over_R is None else args.eps_over_R
    for name in ("m", "R", "eps"):
        setattr(args, name, getattr(args, name, None))
    top = fit_guess(args)
    return top, tj.classify(top)


def _cmd_map(args) -> int:
    """Outcome maps of one top: launch plane (theta0 x spin) and the plane of (A/C, eps/R)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    import tippejax as tj
    from tippejax._plot import outcome_map_figure

    try:
        top, group = _map_top(args)
        if min(args.n_theta, args.n_spin) < 2:
            raise ValueError("--n-theta and --n-spin must be at least 2.")
        theta0 = np.linspace(args.theta_min, args.theta_max, args.n_theta)
        spin_max = args.spin_max if args.spin_max is not None else 6.0 * float(tj.thresholds(top).n1)
        spin = np.linspace(args.spin_min, spin_max, args.n_spin)
        os.makedirs(args.out, exist_ok=True)
        print(f"top: Group {group}, A/C = {float(top.A_over_C):.4g}, "
              f"eps/R = {float(top.eps_over_R):.4g}, mu = {float(top.mu):.4g} s/m")
        start = time.perf_counter()
        om = tj.outcome_map(top, theta0, spin, t1=args.t1, model=args.model,
                            tolerance=args.tolerance)
        elapsed = time.perf_counter() - start
        n = theta0.size * spin.size
        print(om.summary())
        print(f"{n} launches in {elapsed:.1f} s ({n / elapsed:.1f} launches/s, compilation "
              f"included) on {len(__import__('jax').devices())} device(s)")
        paths = []
        fig = outcome_map_figure(om)
        paths.append(os.path.join(args.out, "outcome_map.png"))
        fig.savefig(paths[-1], dpi=110)
        plt.close(fig)
        np.savez(
            os.path.join(args.out, "outcome_map.npz"), theta0=theta0, spin=spin,
            outcome=np.asarray(om.outcome), settled=np.asarray(om.settled),
            theta_final=np.asarray(om.theta_final), t_invert=np.asarray(om.t_invert),
            jellet=np.asarray(om.jellet), outcomes=np.array(tj.OUTCOMES),
        )
        paths.append(os.path.join(args.out, "outcome_map.npz"))
        if args.tops:
            a = np.linspace(0.55, 1.6, args.n_tops)
            e = np.linspace(0.04, 0.7, max(2, (3 * args.n_tops) // 4))
            spin_tops = args.spin_tops if args.spin_tops is not None else float(spin[len(spin) // 2])
            start = time.perf_counter()
            omt = tj.outcome_map_tops(top, a, e, theta0=args.theta0_tops, spin=spin_tops,
                                      t1=args.t1, model="full" if args.model == "auto" else args.model)
            print(omt.summary())
            print(f"{a.size * e.size} tops in {time.perf_counter() - start:.1f} s")
            fig = outcome_map_figure(omt)
            paths.append(os.path.join(args.out, "outcome_map_tops.png"))
            fig.savefig(paths[-1], dpi=110)
            plt.close(fig)
    except (ValueError, TypeError, OSError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for path in paths:
        print(f"wrote {path}")
    return 0


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tippejax", description="Steady states and groups of the tippe top (tippejax)."
    )
    sub = parser.add_subparsers(dest="command", required=True)

    def out_option(p):
        p.add_argument(
            "--out", metavar="DIR", default=DEFAULT_OUT,
            help=f"output folder (default ./{DEFAULT_OUT})",
        )

    p = sub.add_parser("classify", help="group and thresholds of a top; writes group_map.png")
    p.add_argument("--A-over-C", dest="A_over_C", type=float, default=None, help="A/C (>= 0.5)")
    p.add_argument("--eps-over-R", dest="eps_over_R", type=float, default=None, help="eps/R in (0, 1)")
    out_option(p)
    p.set_defaults(func=_cmd_classify)

    p = sub.add_parser("diagram", help="writes bifurcation_diagrams.png and group_map.png")
    out_option(p)
    p.set_defaults(func=_cmd_diagram)

    p = sub.add_parser("demo", help="steady states of the default top launched near upright")
    out_option(p)
    p.add_argument(
        "--spin", type=float, default=None,
        help="launch spin n0 (rad/s); default 1.5 x the inversion threshold, rounded up",
    )
    p.add_argument("--theta0", type=float, default=0.1, help="launch tilt (rad), default 0.1")
    p.set_defaults(func=_cmd_demo)

    from ._fit import FREE_NAMES, METHODS, STRATEGIES

    p = sub.add_parser(
        "fit",
        help="fit a top's parameters to a measured tilt theta(t) in a CSV file",
        description=(
            "Fit free parameters of the top and its launch to a measured tilt theta(t) with "
            "tippejax.fit. DATA.csv has a header row with columns t (s) and theta (rad), "
            "optionally phi (rad, the precession angle, fitted too); an empty cell or nan is a "
            "missing sample. The starting guess is the default top (A/C 0.9, eps/R 0.3, "
            "m 0.02 kg, R 0.025 m, mu 0.3 s/m) with the fields given below replaced. Prints the "
            "fitted values with standard errors and writes fit.png and fit.csv "
            "(t, theta_obs, theta_fit, residual) to --out."
        ),
    )
    p.add_argument("data", metavar="DATA.csv", help="the data: columns t, theta[, phi]")
    p.add_argument(
        "--free", metavar="NAMES", default="mu,eps,spin",
        help=f"comma-separated names of the parameters to fit (default mu,eps,spin), from: "
             f"{','.join(FREE_NAMES)}",
    )
    guess = p.add_argument_group("starting guess (default: the default top)")
    guess.add_argument("--m", type=float, default=None, help="mass (kg), default 0.02")
    guess.add_argument(
        "--R", type=float, default=None, help="radius of the sphere (m), default 0.025"
    )
    guess.add_argument("--eps", type=float, default=None,
                       help="centre of sphere to centre of mass (m), default 0.0075")
    guess.add_argument("--A-over-C", dest="A_over_C", metavar="X", type=float, default=None,
                       help="A/C, default 0.9. --A-over-C or --eps-over-R rebuild the top with "
                            "TippeTop.from_ratios (keeping m, R, mu; C = 0.4 m R^2)")
    guess.add_argument("--eps-over-R", dest="eps_over_R", metavar="Y", type=float, default=None,
                       help="eps/R in (0, 1), default 0.3 (not together with --eps)")
    guess.add_argument(
        "--mu", type=float, default=None, help="viscous friction coefficient (s/m), default 0.3"
    )
    guess.add_argument("--theta0", metavar="TH", type=float, default=None,
                       help="launch tilt (rad) at the first time, held fixed unless --free names "
                            "theta0; default: free, starting from the mean of the record's first "
                            f"samples (at least {FIT_MIN_THETA0:g})")
    guess.add_argument("--theta-dot", dest="theta_dot", metavar="W", type=float, default=None,
                       help="launch tilt rate (rad/s), default 0; for a top launched upright give "
                            "--theta0 0 --theta-dot W and free theta_dot")
    guess.add_argument("--spin", metavar="N", type=float, default=FIT_DEFAULT_SPIN,
                       help=f"launch spin (rad/s), default {FIT_DEFAULT_SPIN:g}")
    p.add_argument("--model", default="full", choices=("full", "so3", "routhian"),
                   help="level of model to fit with (default full)")
    p.add_argument("--strategy", default="global", choices=tuple(STRATEGIES),
                   help="fitting strategy (default global: a batch of starts ranked by the "
                        "smoothed tilt, then the best refined until its residuals are noise)")
    p.add_argument("--sigma", type=float, default=None,
                   help="noise of theta (rad), if known: the residuals are tested against it")
    p.add_argument("--trim", action="store_true",
                   help="refit on the part of the record the model describes (a stem landing)")
    p.add_argument("--method", default="levenberg_marquardt", choices=METHODS,
                   help="optimiser (default levenberg_marquardt)")
    p.add_argument("--max-steps", dest="max_steps", metavar="K", type=int, default=100,
                   help="optimiser steps per optimisation (default 100)")
    p.add_argument("--t-max", dest="t_max", metavar="T", type=float, default=None,
                   help="use only the samples with t <= T (s): the part of the record the "
                        "model describes")
    p.add_argument("--no-phi", dest="no_phi", action="store_true",
                   help="ignore a phi column (fit theta only)")
    out_option(p)
    p.set_defaults(func=_cmd_fit)

    from ._simulate import MODELS

    p = sub.add_parser(
        "animate",
        help="simulate a launch and write a 3-D animation (GIF or MP4)",
        description=(
            "Simulate one launch (default: the default top of `tippejax demo`, theta0 0.1 rad, "
            "spin 1.5 x the inversion threshold) and render it with tippejax.animate: the sphere, "
            "its stem, the spin marker and the contact-point trace. Real time by default; the "
            "spin (~100 rad/s) aliases at any frame rate a GIF can show, so pass --speed 0.2 "
            "(slow motion) to watch it."
        ),
    )
    top_group = p.add_argument_group("the top (default: the default top)")
    top_group.add_argument("--m", type=float, default=None, help="mass (kg), default 0.02")
    top_group.add_argument("--R", type=float, default=None, help="radius (m), default 0.025")
    top_group.add_argument("--eps", type=float, default=None,
                           help="centre of sphere to centre of mass (m), default 0.0075")
    top_group.add_argument("--A-over-C", dest="A_over_C", metavar="X", type=float, default=None,
                           help="A/C, default 0.9 (rebuilds the top with TippeTop.from_ratios)")
    top_group.add_argument("--eps-over-R", dest="eps_over_R", metavar="Y", type=float,
                           default=None, help="eps/R in (0, 1), default 0.3")
    top_group.add_argument("--mu", type=float, default=None,
                           help="viscous friction coefficient (s/m), default 0.3")
    p.add_argument("--theta0", type=float, default=0.1, help="launch tilt (rad), default 0.1")
    p.add_argument("--spin", type=float, default=None,
                   help="launch spin n0 (rad/s); default 1.5 x the inversion threshold")
    p.add_argument("--t1", type=float, default=12.0, help="simulated time (s), default 12")
    p.add_argument("--model", default="full", choices=MODELS, help="level of model (default full)")
    p.add_argument("--fps", type=float, default=20.0, help="frames per second (default 20)")
    timing = p.add_mutually_exclusive_group()
    timing.add_argument("--speed", type=float, default=None,
                        help="seconds simulated per second shown (default 1; < 1: slow motion)")
    timing.add_argument("--duration", type=float, default=None,
                        help="seconds of animation for the whole span")
    timing.add_argument("--frames", type=int, default=None, help="number of frames")
    p.add_argument("--t-start", dest="t_start", type=float, default=None,
                   help="first time shown (s), default 0")
    p.add_argument("--t-end", dest="t_end", type=float, default=None,
                   help="last time shown (s), default the end of the run")
    p.add_argument("--dpi", type=float, default=80.0, help="dots per inch (5 x 5 in frames)")
    p.add_argument("--follow", action="store_true",
                   help="keep the sphere in the middle of the view")
    p.add_argument("--out", metavar="PATH", default=ANIMATE_DEFAULT_OUT,
                   help=f"output file, .gif or .mp4 (needs ffmpeg); default {ANIMATE_DEFAULT_OUT}")
    p.set_defaults(func=_cmd_animate)

    p = sub.add_parser(
        "map",
        help="outcome maps: where launches end over theta0 x spin, and over (A/C, eps/R)",
        description=(
            "Simulate a grid of launches theta0 x spin of one top with tippejax.outcome_map and "
            "plot where each ends (upright, inverted, intermediate, contact lost, failed) with "
            "the linear-theory boundaries; then a grid of tops over (A/C, eps/R) for one launch "
            "beside the group map. Writes outcome_map.png, outcome_map.npz and "
            "outcome_map_tops.png to --out."
        ),
    )
    p.add_argument("--group", choices=MAP_GROUP_TOPS, default="standard",
                   help="the top: the standard top (default) or a representative of a group")
    p.add_argument("--A-over-C", dest="A_over_C", metavar="X", type=float, default=None,
                   help="A/C (replaces the group's)")
    p.add_argument("--eps-over-R", dest="eps_over_R", metavar="Y", type=float, default=None,
                   help="eps/R (replaces the group's)")
    p.add_argument("--mu", type=float, default=None, help="friction (s/m), default 0.3")
    p.add_argument("--n-theta", dest="n_theta", type=int, default=12, help="launch tilts (12)")
    p.add_argument("--n-spin", dest="n_spin", type=int, default=24, help="launch spins (24)")
    p.add_argument("--theta-min", dest="theta_min", type=float, default=0.02)
    p.add_argument("--theta-max", dest="theta_max", type=float, default=1.5)
    p.add_argument("--spin-min", dest="spin_min", type=float, default=10.0)
    p.add_argument("--spin-max", dest="spin_max", type=float, default=None,
                   help="default 6 x n1 of the top")
    p.add_argument("--t1", type=float, default=30.0, help="simulated time (s), default 30")
    p.add_argument("--model", default="full", choices=MODELS, help="level of model (full)")
    p.add_argument("--tolerance", type=float, default=None,
                   help="for --model auto: largest theta error (rad) a level may make")
    p.add_argument("--no-tops", dest="tops", action="store_false",
                   help="skip the map over (A/C, eps/R)")
    p.add_argument("--n-tops", dest="n_tops", type=int, default=16,
                   help="A/C values of the top map (eps/R gets 3/4 as many)")
    p.add_argument("--theta0-tops", dest="theta0_tops", type=float, default=0.1,
                   help="launch tilt of the top map (rad), default 0.1")
    p.add_argument("--spin-tops", dest="spin_tops", type=float, default=None,
                   help="launch spin of the top map (default: the middle of the spin range)")
    p.add_argument("--out", metavar="DIR", default=DEFAULT_OUT,
                   help=f"output folder, default {DEFAULT_OUT}")
    p.set_defaults(func=_cmd_map)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `tippejax` console script.

    **Returns:** the exit status: 0, or 2 for bad input to `fit` (the message goes to stderr).
    """
    args = _parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    raise SystemExit(main())
