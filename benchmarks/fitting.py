"""Fitting: success rate and cost of each strategy and optimiser from poor starting guesses.

Synthetic data: the standard top (A/C 0.9, eps/R 0.3, mu 0.3) launched at theta0 = 0.1 with
spin 100 rad/s, tilt sampled at 100 Hz for 8 s (it inverts at 5.70 s), Gaussian noise 0.01 rad.
Free: mu, eps and the spin. Each starting guess puts every free parameter 25-30% off (random
sign). A fit succeeds when every parameter is within 2% of the truth and within 3 standard
errors. The fits run with `trim=False` (a failed fit is not refitted on part of the record).
Each guess is one fit (a loop: on a CPU that beats one vmapped batch, whose members step
together); the easy problem below runs as batches.

Also: one unbatched fit timed after compilation, and the simplest alternative a user has:
`scipy.optimize.least_squares` (finite-difference Jacobian) over `tj.simulate`, the whole record.

Run from the repository root: `python benchmarks/fitting.py [--n 20]`. Writes its section of
benchmarks/RESULTS.md and benchmarks/fitting.png.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from _common import HERE, table, write_section
from scipy.optimize import least_squares

import tippejax as tj

FREE = ("mu", "eps", "spin")
CONFIGS = [
    ("levenberg_marquardt", "levels"),
    ("levenberg_marquardt", "windows"),
    ("levenberg_marquardt", "plain"),
    ("gauss_newton", "levels"),
    ("adam", "levels"),
]


def data(seed=0):
    top = tj.default_top()
    y0 = tj.initial_state(top, 0.1, 100.0)
    ts = np.linspace(0.0, 8.0, 801)
    sol = tj.simulate(top, y0, 8.0, saveat=ts)
    obs = np.asarray(sol.theta) + 0.01 * np.random.default_rng(seed).standard_normal(ts.shape)
    truth = np.array([float(top.mu), float(top.eps), 100.0])
    return top, ts, obs, truth


def guesses(n, seed=1):
    rng = np.random.default_rng(seed)
    return 1.0 + rng.choice([-1.0, 1.0], (n, 3)) * rng.uniform(0.25, 0.30, (n, 3))


def batched_guess(top, factors):
    guess = tj.TippeTop(
        m=top.m, R=top.R, eps=top.eps * factors[:, 1], A=top.A, C=top.C,
        mu=top.mu * factors[:, 0],
    )
    y0 = tj.initial_state(guess, 0.1, 100.0 * factors[:, 2])
    return guess, y0


def single_guess(top, factor):
    guess = tj.TippeTop(m=top.m, R=top.R, eps=top.eps * factor[1], A=top.A, C=top.C,
                        mu=top.mu * factor[0])
    return guess, tj.initial_state(guess, 0.1, 100.0 * float(factor[2]))


def success(res, truth):
    values, errors = np.asarray(res.values), np.asarray(res.std_errors)
    rel = np.abs(values - truth) / truth
    within = np.abs(values - truth) <= 3 * errors
    return np.all(rel < 0.02, -1) & np.all(within, -1), rel


def scipy_fit(top, ts, obs, factors):
    """What a user writes first: scipy least squares over simulate, FD Jacobian, whole record."""
    def residuals(x):
        trial = tj.TippeTop(m=top.m, R=top.R, eps=x[1], A=top.A, C=top.C, mu=x[0])
        sol = tj.simulate(trial, tj.initial_state(trial, 0.1, x[2]), 8.0, saveat=ts, throw=False)
        theta = np.asarray(sol.theta)
        return np.where(np.isfinite(theta), theta - obs, np.pi)

    x0 = np.array([float(top.mu), float(top.eps), 100.0]) * factors
    t = time.perf_counter()
    out = least_squares(residuals, x0, x_scale=x0, bounds=([1e-4, 1e-5, 1.0],
                                                           [10.0, 0.9 * float(top.R), 1e4]))
    return out.x, time.perf_counter() - t, out.nfev


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--n", type=int, default=20, help="starting guesses per configuration")
    parser.add_argument("--scipy", type=int, default=5, help="guesses for the scipy baseline")
    parser.add_argument("--adam", type=int, default=5, help="guesses for Adam (slow)")
    parser.add_argument("--gn", type=int, default=20, help="guesses for Gauss-Newton")
    parser.add_argument("--slow-max-steps", type=int, default=200,
                        help="max_steps per stage for Gauss-Newton and Adam")
    parser.add_argument("--configs", default="all",
                        help="comma-separated row numbers of CONFIGS to run (0-4); rows not run "
                             "are taken from benchmarks/fitting_rows.json (an earlier run)")
    args = parser.parse_args()
    top, ts, obs, truth = data()
    factors = guesses(args.n)
    rows, results, failures = [], {}, {}
    cache = HERE / "fitting_rows.json"
    saved = json.loads(cache.read_text()) if cache.exists() else {}
    chosen = range(len(CONFIGS)) if args.configs == "all" else [int(c) for c in args.configs.split(",")]
    for index, (method, strategy) in enumerate(CONFIGS):
        key = f"{method}/{strategy}"
        if index not in chosen:
            if key in saved:
                rows.append(saved[key]["row"])
                failures[(method, strategy)] = saved[key]["failures"]
            continue
        n = {"adam": args.adam, "gauss_newton": args.gn}.get(method, args.n)
        max_steps = 200 if method == "levenberg_marquardt" else args.slow_max_steps
        oks, rels, steps, conv, walls = [], [], [], [], []
        for i in range(n):
            guess, y0 = single_guess(top, factors[i])
            t = time.perf_counter()
            res = tj.fit(guess, y0, ts, obs, free=FREE, method=method, strategy=strategy,
                         trim=False, max_steps=max_steps)
            walls.append(time.perf_counter() - t)
            ok, rel = success(res, truth)
            oks.append(bool(ok))
            rels.append(float(np.max(rel)))
            steps.append(int(res.num_steps))
            conv.append(bool(res.converged))
            if not ok:
                failures.setdefault((method, strategy), []).append(
                    f"guess x({', '.join(f'{f:.2f}' for f in factors[i])}) -> "
                    f"({', '.join(f'{v:.4g}' for v in np.asarray(res.values))}), "
                    f"rms {float(res.rms):.3g}"
                )
        results[(method, strategy)] = res
        # The first fit of a configuration compiles; the median is over the others.
        rows.append([
            method, strategy, f"{sum(oks)}/{n}", f"{sum(conv)}/{n}", f"{np.median(steps):.0f}",
            f"{np.median(rels):.2%}", f"{statistics.median(walls[1:] or walls):.1f}",
            f"{walls[0]:.0f}", f"{max_steps}",
        ])
        saved[key] = {"row": rows[-1], "failures": failures.get((method, strategy), [])}
        cache.write_text(json.dumps(saved, indent=1))
        print(rows[-1], flush=True)

    # An easier problem: 3 s of the rise only (no inversion), guesses 5% off, windows.
    easy_rows = []
    ts_easy = ts[ts <= 3.0]
    obs_easy = obs[: ts_easy.size]
    easy_factors = 1.0 + np.random.default_rng(5).choice([-1.0, 1.0], (args.n, 3)) * 0.05
    for method in ("levenberg_marquardt", "gauss_newton", "adam"):
        n = args.adam if method == "adam" else args.n
        guess, y0 = batched_guess(top, easy_factors[:n])
        t = time.perf_counter()
        res = tj.fit(guess, y0, ts_easy, np.tile(obs_easy, (n, 1)), free=FREE, method=method,
                     strategy="windows", trim=False)
        wall = time.perf_counter() - t
        # The reference is the best fit (LM from the truth), not the truth: 3 s of data pin
        # the parameters less tightly than 2%.
        if method == "levenberg_marquardt":
            ref = tj.fit(*batched_guess(top, np.ones((1, 3))), ts_easy, obs_easy[None],
                         free=FREE, strategy="windows", trim=False)
            best = np.asarray(ref.values)[0]
            best_loss = np.nanmin(np.asarray(ref.loss_history)[0])
        rel = np.abs(np.asarray(res.values) - best) / np.asarray(res.std_errors)
        final_loss = np.array([np.nanmin(h) for h in np.asarray(res.loss_history)])
        reached = np.sum(final_loss < best_loss * 1.001)
        easy_rows.append([method, f"{reached}/{n}", f"{np.asarray(res.converged).sum()}/{n}",
                          f"{np.median(np.asarray(res.num_steps)):.0f}",
                          f"{np.median(np.max(rel, -1)):.2g}", f"{wall:.0f}"])
        print(easy_rows[-1], flush=True)

    # One unbatched fit, compiled first, then timed.
    single = {}
    g1, y1 = single_guess(top, factors[0])
    t = time.perf_counter()
    tj.fit(g1, y1, ts, obs, free=FREE)
    single["first call (compiles)"] = time.perf_counter() - t
    times = []
    for _ in range(2):
        t = time.perf_counter()
        res1 = tj.fit(g1, y1, ts, obs, free=FREE)
        times.append(time.perf_counter() - t)
    single["later calls (median of 2)"] = statistics.median(times)
    print(single, res1.table(), flush=True)

    # The scipy baseline on the first guesses.
    scipy_rows = []
    for i in range(min(args.scipy, args.n)):
        x, wall, nfev = scipy_fit(top, ts, obs, factors[i])
        rel = np.abs(x - truth) / truth
        scipy_rows.append((bool(np.all(rel < 0.02)), wall, nfev, float(rel.max())))
        print("scipy", i, x, wall, nfev, flush=True)

    # Figure: loss histories of the first guess for each configuration.
    fig, ax = plt.subplots(figsize=(7, 4))
    for (method, strategy), res in results.items():  # the configurations run this time
        hist = np.atleast_2d(np.asarray(res.loss_history))[0]
        ax.semilogy(hist[np.isfinite(hist)], label=f"{method}, {strategy}")
    ax.axhline(0.5 * ts.size * 0.01**2, color="k", lw=0.8, ls=":", label="noise floor")
    ax.set(xlabel="optimiser step (all stages)", ylabel="loss", title="Fit of mu, eps, spin from a guess 25-30% off")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(HERE / "fitting.png", dpi=120)

    n_ok = sum(r[0] for r in scipy_rows)
    scipy_line = (
        f"scipy.optimize.least_squares over `tj.simulate` (FD Jacobian, whole record, bounds) on "
        f"the first {len(scipy_rows)} guesses: {n_ok}/{len(scipy_rows)} within 2%; median wall "
        f"{statistics.median(r[1] for r in scipy_rows):.1f} s, median "
        f"{statistics.median(r[2] for r in scipy_rows):.0f} simulations; worst relative errors "
        f"{', '.join(f'{r[3]:.1%}' for r in scipy_rows)}."
    ) if scipy_rows else "(scipy baseline not run)"
    body = "\n".join([
        "## Fitting (`benchmarks/fitting.py`)",
        "",
        "Standard top, theta0 0.1, spin 100 rad/s, 801 samples over 8 s, noise 0.01 rad; free mu, "
        f"eps, spin, each 25-30% off at the start ({args.n} random guesses, {args.adam} for Adam; "
        "single fits in a loop, the fastest way on a CPU). Success: every parameter within 2% of the truth and within 3 standard errors.",
        "",
        table(["method", "strategy", "success", "converged", "median steps",
               "median worst rel. error", "median wall per fit (s)", "first fit, compiling (s)",
               "max steps per stage"],
              rows),
        "",
        "Failed fits (guess factors for mu, eps, spin -> fitted mu, eps, spin):",
        "",
        *[f"- {m}, {st}: " + "; ".join(v) for (m, st), v in failures.items() if st != "plain"],
        "",
        "An easier problem: the first 3 s only (the slow rise, 301 samples), guesses 5% off, "
        "strategy `windows` (with `plain`, even 5% off in the spin slips the nutation by cycles "
        "over 3 s and no method reached the best fit). Reached: final loss within 0.1% of the best fit's; distance to it in "
        "standard errors.",
        "",
        table(["method", "reached best loss", "converged", "median steps",
               "median worst distance (SE)", "wall (s, whole batch)"], easy_rows),
        "",
        "One unbatched fit (levels + LM, guess 0): "
        + ", ".join(f"{k}: {v:.1f} s" for k, v in single.items()) + ".",
        "",
        scipy_line,
        "",
        "![loss histories](fitting.png)",
    ])
    write_section("fitting.py", body)
    print(body)


if __name__ == "__main__":
    main()
