"""`tippejax fit`: fit a top and its launch to a measured tilt read from a CSV file."""

from __future__ import annotations

import csv
import math
import os
import sys
import time

import numpy as np

from .._fit import fit
from .._plot import fit_figure
from .._state import initial_state
from .common import fmt, mu_text, save, top_from_options, use_agg

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
    finite = np.isfinite(theta)
    first = t[finite][: max(5, int(0.02 * finite.sum()))]
    guess = float(np.mean(theta[finite][: first.size]))
    return min(max(guess, FIT_MIN_THETA0), math.pi - FIT_MIN_THETA0)


def write_fit_outputs(result, out: str) -> list[str]:
    """Write `fit.png` (`fit_figure`) and `fit.csv` (t, theta_obs, theta_fit, residual; recording
    0 of a batched fit) to the folder `out`; returns their paths."""
    use_agg()
    os.makedirs(out, exist_ok=True)
    paths = [save(fit_figure(result), os.path.join(out, "fit.png"))]
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
    top = top_from_options(args)
    theta0 = args.theta0
    if theta0 is None:
        # Not given: free it (unless --free leaves it out on purpose with --theta0), starting
        # from the smoothed start of the record, away from the poles.
        theta0 = launch_tilt_guess(t, theta)
        if "theta0" not in free and args.theta_dot is None:
            free = free + ("theta0",)
    theta_dot = 0.0 if args.theta_dot is None else args.theta_dot
    y0 = initial_state(top, theta0, args.spin, theta_dot=theta_dot)
    n_used = int(np.isfinite(theta).sum())
    print(
        f"data: {args.data}: {t.size} samples from t = {t[0]:g} to {t[-1]:g} s "
        f"({n_used} with theta{', with phi' if phi is not None else ''})"
    )
    print(
        f"guess: m = {float(top.m):.4g} kg, R = {float(top.R):.4g} m, eps = {float(top.eps):.4g} m "
        f"(eps/R = {float(top.eps / top.R):.4g}), A/C = {float(top.A / top.C):.4g}, "
        f"{mu_text(top)}; launch theta0 = {theta0:.4g} rad, "
        f"theta_dot = {theta_dot:g} rad/s, spin = {args.spin:g} rad/s"
    )
    print(
        f"fitting {', '.join(free) or '(nothing)'} (model {args.model}, "
        f"strategy {args.strategy}, method {args.method}) ..."
    )
    start = time.perf_counter()
    result = fit(
        top,
        y0,
        t,
        theta,
        free=free,
        phi_obs=phi,
        model=args.model,
        method=args.method,
        strategy=args.strategy,
        max_steps=args.max_steps,
        sigma=args.sigma,
        trim=args.trim,
        t0=args.t0,
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
        note = (
            f"  (of {t[-1]:g} s: the model stops describing the data there; try --t-max or "
            "another model)"
        )
    print(f"describes until: {fmt(describes, '.4g')} s{note}")
    print(
        f"rms residual:    {float(result.rms):.4g} rad over the whole record, "
        f"{float(result.rms_fitted):.4g} rad over the fitted part (to "
        f"{float(result.fitted_until):.4g} s)"
    )
    print(f"converged:       {bool(result.converged)} ({result.message()})")
    print(f"wall time:       {wall:.1f} s (including compilation)")
    for path in write_fit_outputs(result, args.out):
        print(f"wrote {path}")
    return 0


def run(args) -> int:
    try:
        return _run_fit(args)
    except (ValueError, TypeError, OSError) as err:  # bad input: a message, not a traceback
        print(f"error: {err}", file=sys.stderr)
        return 2
