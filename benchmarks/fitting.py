"""Fitting on records it was not tuned to: success, honesty of the error bars, cost.

Records: `fit_records.draw_records(n, seed)` (seeded, random: tops in groups IIa, IIb, IIc and
III, spins 1.5-8 n1, tilted and upright launches, 3-20 s at 20-500 Hz, noise 0.002-0.03 rad,
some gaps), made by the independent integrator `tests/vector_reference.py`, each with its
Cramer-Rao bound (CRB) on the free parameters (mu, eps, spin; plus theta_dot for upright
launches).

Each record is fitted from two starts: the truth, and every free parameter 30% off (a random
sign per parameter, seeded). A fit **succeeds** when every free parameter is within 2% of the
truth and within 3 of its own standard errors. A fit that does not succeed must be flagged
(`converged=False`); a wrong answer that says `converged` is the failure that counts most.

Reported per group and per sampling rate: success from the truth and from 30% off, flagged
failures, unflagged failures; SE / CRB; the coverage |estimate - truth| / SE; time per fit.
With `--compare K`, the first K records are also fitted from 30% off with the other
strategies (`search`, `levels`, `windows`, `plain`) and with `scipy.optimize.least_squares` over
`tj.simulate` (finite-difference Jacobian, the whole record), in the same run.

Run from the repository root:
`python benchmarks/fitting.py [--n 60] [--seed 0] [--compare 8]`. Rows are appended to
`benchmarks/fitting_rows.json` as fits finish (a partial run is usable: `--report` re-reads it),
and the summary goes to its section of benchmarks/RESULTS.md and to benchmarks/fitting.png.
"""

from __future__ import annotations

import argparse
import gc
import json
import pathlib
import sys
import time

import jax
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from _common import HERE, table, write_section
from fit_records import draw_records

import tippejax as tj

ROWS = HERE / "fitting_rows.json"
COVERAGE_ROWS = HERE / "fitting_coverage.json"
RATE_BINS = ((20, 60), (60, 150), (150, 500.1))


def start_of(record, start: str, index: int):
    """The guess of a start: the truth, or each free parameter 30% off (seeded signs)."""
    free = record["free"]
    factors = {k: 1.0 for k in free}
    if start == "off":
        rng = np.random.default_rng([index, 30])
        factors = {k: 1.0 + rng.choice([-1.0, 1.0]) * 0.3 for k in free}
    params = dict(record["params"])
    params["mu"] *= factors.get("mu", 1.0)
    params["eps"] *= factors.get("eps", 1.0)
    top = tj.TippeTop(**params)
    launch = record["launch"]
    y0 = tj.initial_state(
        top, launch["theta0"], launch["spin"] * factors.get("spin", 1.0),
        theta_dot=launch["theta_dot"] * factors.get("theta_dot", 1.0), phi_dot=launch["phi_dot"],
    )
    return top, y0


def start_spin(record, index) -> float:
    """The spin factor of start `index`'s 30%-off guess."""
    y0 = start_of(record, "off", index)[1]
    return float(np.abs(np.sum(np.asarray(y0.omega) * np.asarray(y0.axis)))) / record["launch"]["spin"]


def fit_row(record, index, start, strategy="global"):
    top, y0 = start_of(record, start, index)
    t = time.perf_counter()
    res = tj.fit(top, y0, record["ts"], record["theta_obs"], free=record["free"],
                 strategy=strategy)
    wall = time.perf_counter() - t
    free = list(record["free"])
    values = np.asarray(res.values, float)
    se = np.asarray(res.std_errors, float)
    truth = np.array([record["truth"][k] for k in free])
    crb = np.array([record["crb"][k] for k in free])
    return dict(
        index=index, start=start, strategy=strategy, group=record["group"],
        upright=bool(record["upright"]), rate=float(record["rate_hz"]),
        length=float(record["length_s"]), sigma=float(record["sigma"]), free=free,
        rel_error=((values - truth) / np.abs(truth)).tolist(),
        z=((values - truth) / se).tolist(), se_over_crb=(se / crb).tolist(),
        converged=bool(res.converged), message=res.message()[:40], starts=int(res.starts),
        runs_z=float(res.runs_z), rms_over_sigma=float(res.rms) / float(record["sigma"]),
        described=bool(float(res.describes_until) >= float(record["ts"][-1]) - 1e-9),
        wall=wall,
    )


def scipy_row(record, index):
    """scipy.optimize.least_squares over tj.simulate (the simplest alternative a user has)."""
    from scipy.optimize import least_squares

    top0, y00 = start_of(record, "off", index)
    free = list(record["free"])
    ts, obs = record["ts"], record["theta_obs"]
    mask = np.isfinite(obs)
    launch = record["launch"]
    theta_dot0 = float(tj.euler_rates(y00)[0])
    x0 = np.array([float(top0.mu), float(top0.eps), float(np.sum(np.asarray(y00.omega) * np.asarray(y00.axis)))] + ([theta_dot0] if "theta_dot" in free else []))

    def residuals(x):
        try:
            top = tj.TippeTop(**{**{k: float(getattr(top0, k)) for k in ("m", "R", "A", "C", "g")},
                                 "mu": x[0], "eps": x[1]})
            y0 = tj.initial_state(top, launch["theta0"], x[2],
                                  theta_dot=x[3] if len(x) > 3 else launch["theta_dot"])
            sol = tj.simulate(top, y0, float(ts[-1]), saveat=ts, throw=False)
            theta = np.asarray(sol.theta)
            return np.where(np.isfinite(theta), theta, np.pi)[mask] - obs[mask]
        except Exception:  # an invalid trial (eps >= R...)
            return np.full(mask.sum(), np.pi)

    t = time.perf_counter()
    out = least_squares(residuals, x0, x_scale=np.abs(x0), max_nfev=200)
    wall = time.perf_counter() - t
    truth = np.array([record["truth"][k] for k in free])
    return dict(index=index, start="off", strategy="scipy", group=record["group"],
                rate=float(record["rate_hz"]), rel_error=((out.x - truth) / np.abs(truth)).tolist(),
                converged=bool(out.success), wall=wall, nfev=int(out.nfev))


def succeeded(row) -> bool:
    within = np.all(np.abs(row["rel_error"]) < 0.02)
    if "z" not in row:
        return bool(within)
    return bool(within and np.all(np.abs(row["z"]) < 3))


def summarise(rows) -> str:
    main = [r for r in rows if r["strategy"] == "global"]
    lines = []

    def rate_bin(r):
        for lo, hi in RATE_BINS:
            if lo <= r["rate"] < hi:
                return f"{lo:g}-{hi:.0f} Hz"
        return "?"

    def line(label, subset):
        truth = [r for r in subset if r["start"] == "truth"]
        off = [r for r in subset if r["start"] == "off"]
        ok_t = sum(succeeded(r) for r in truth)
        ok_o = sum(succeeded(r) for r in off)
        bad = [r for r in subset if not succeeded(r)]
        flagged = sum(not r["converged"] for r in bad)
        within3 = [r for r in truth if np.all(np.abs(r["z"]) < 3)]
        walls = [r["wall"] for r in subset]
        good = [r for r in subset if succeeded(r)]
        ratio = np.concatenate([r["se_over_crb"] for r in good]) if good else np.array([])
        z = np.abs(np.concatenate([r["z"] for r in subset])) if subset else np.array([])
        return [label, f"{ok_t}/{len(truth)}", f"{len(within3)}/{len(truth)}", f"{ok_o}/{len(off)}",
                f"{flagged}/{len(bad)}", f"{len(bad) - flagged}",
                f"{np.median(ratio):.2f}" if ratio.size else "-",
                f"{np.mean(z < 2):.0%}" if z.size else "-",
                f"{np.median(walls):.1f}" if walls else "-"]

    head = ["records", "success from truth", "truth within 3 SE", "success from 30% off",
            "failures flagged", "unflagged failures", "SE / CRB (successes, median)",
            "error / SE within 2 (all fits)", "median s/fit"]
    body = [line("all", main)]
    for g in ("IIa", "IIb", "IIc", "III"):
        body.append(line(g, [r for r in main if r["group"] == g]))
    body.append(line("upright launches", [r for r in main if r["upright"]]))
    for lo, hi in RATE_BINS:
        body.append(line(f"{lo:g}-{hi:.0f} Hz", [r for r in main if lo <= r["rate"] < hi]))
    lines.append(table(head, body))
    ok = [r for r in main if succeeded(r)]
    if ok:
        ratio = np.concatenate([r["se_over_crb"] for r in ok])
        z = np.abs(np.concatenate([r["z"] for r in ok]))
        lines.append("")
        lines.append(
            f"Over the {len(ok)} successful fits: SE / CRB median {np.median(ratio):.2f} "
            f"(5-95%: {np.percentile(ratio, 5):.2f}-{np.percentile(ratio, 95):.2f}); "
            f"|estimate - truth| / SE median {np.median(z):.2f}, 95th percentile "
            f"{np.percentile(z, 95):.2f}, {np.mean(z < 2):.0%} below 2 (normal: 95%)."
        )
    described = [r for r in main if "described" in r]
    if described:
        lines.append(
            f"describes_until at the record's end (so trim=True would cut nothing) in "
            f"{sum(r['described'] for r in described)} of {len(described)} fits; among the "
            f"successful ones, {sum(r['described'] for r in described if succeeded(r))} of "
            f"{sum(succeeded(r) for r in described)}."
        )
    lines += coverage_lines(main)
    allz = np.abs(np.concatenate([r["z"] for r in main])) if main else np.array([])
    if allz.size:
        lines.append(
            f"Over all {len(main)} fits: {np.mean(allz < 2):.0%} of |estimate - truth| / SE "
            "below 2."
        )
    if COVERAGE_ROWS.exists():  # the same records with fresh noise: many z per record
        cov = json.loads(COVERAGE_ROWS.read_text())
        z = np.abs(np.concatenate([np.asarray(r["z"]).ravel() for r in cov]))
        lines.append(
            f"One z per record and parameter cannot tell 93% from 95% (the spread between the "
            f"parameters above is as large). Over repeated noise on {len(cov)} of these records "
            f"({z.size} estimates, `--coverage`, section below): **{np.mean(z < 2):.1%}** below 2 "
            "(normal: 95.4%)."
        )
    others = [r for r in rows if r["strategy"] != "global"]
    if others:
        lines.append("")
        lines.append("Candidates from 30% off on the same records (same run):")
        head2 = ["strategy", "success", "flagged of failures", "median s/fit"]
        body2 = []
        strategies = ["global"] + sorted({r["strategy"] for r in others})
        indices = {r["index"] for r in others}
        for s in strategies:
            sub = [r for r in rows if r["strategy"] == s and r["start"] == "off" and r["index"] in indices]
            if not sub:
                continue
            bad = [r for r in sub if not succeeded(r)]
            body2.append([s, f"{sum(succeeded(r) for r in sub)}/{len(sub)}",
                          f"{sum(not r['converged'] for r in bad)}/{len(bad)}",
                          f"{np.median([r['wall'] for r in sub]):.1f}"])
        lines.append(table(head2, body2))
    flagged_ok = [r for r in main if succeeded(r) and not r["converged"]]
    if flagged_ok:
        lines.append("")
        lines.append(
            f"Successful but flagged (`converged=False`; counted as successes above, their "
            f"SE widened by the phase check, so SE / CRB > 1): {len(flagged_ok)}"
        )
        for r in flagged_ok:
            lines.append(
                f"- record {r['index']} ({r['group']}, {r['rate']:.0f} Hz) from {r['start']}: "
                f"rel. errors {np.round(r['rel_error'], 4).tolist()}, SE/CRB "
                f"{np.round(r['se_over_crb'], 1).tolist()}, {r['message']!r}"
            )
    fails = [r for r in main if not succeeded(r)]
    if fails:
        lines.append("")
        lines.append("Fits that did not succeed:")
        for r in fails:
            lines.append(
                f"- record {r['index']} ({r['group']}{', upright' if r['upright'] else ''}, "
                f"{r['rate']:.0f} Hz, {r['length']:.1f} s, noise {r['sigma']:.3g}) from "
                f"{r['start']}: rel. errors {np.round(r['rel_error'], 4).tolist()}, "
                f"|err|/SE {np.round(np.abs(r['z']), 1).tolist()}, {r['message']!r}, "
                f"runs z {r['runs_z']:.1f}"
            )
    return "\n".join(lines)


def coverage_lines(main):
    """The coverage per free parameter over the fits from the truth, one per record, so that
    the samples are independent (the parameters of one fit are correlated, and the two starts
    of a record usually end at the same minimum): the fraction with |z| < 2 and a
    Kolmogorov-Smirnov test of z against N(0, 1). With n records the fraction's own spread
    is sqrt(0.95 x 0.05 / n) (2.8% for n = 60)."""
    from scipy import stats

    truth = [r for r in main if r["start"] == "truth"]
    if len(truth) < 5:
        return []
    out = ["", f"Coverage of the fits from the truth, one per record ({len(truth)} records): "
               "per free parameter, the share of |estimate - truth| / SE below 2 (95% for a "
               "normal z) and a Kolmogorov-Smirnov test of z against N(0, 1):"]
    for k, name in enumerate(("mu", "eps", "spin", "theta_dot")):
        z = np.array([r["z"][k] for r in truth if len(r["z"]) > k and r["free"][k] == name])
        if z.size < 5:
            continue
        ks = stats.kstest(z, "norm")
        out.append(f"- {name}: {np.mean(np.abs(z) < 2):.0%} of {z.size} below 2; mean z "
                   f"{np.mean(z):+.2f}, sd {np.std(z, ddof=1):.2f}; KS D = {ks.statistic:.3f}, "
                   f"p = {ks.pvalue:.2f}")
    return out


def chart(rows):
    main = [r for r in rows if r["strategy"] == "global"]
    if not main:
        return
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    z = np.concatenate([r["z"] for r in main])
    z = z[np.isfinite(z)]
    axes[0].hist(np.clip(z, -8, 8), bins=np.linspace(-8, 8, 41), density=True, alpha=0.7,
                 label="fits")
    x = np.linspace(-8, 8, 400)
    axes[0].plot(x, np.exp(-x**2 / 2) / np.sqrt(2 * np.pi), "k-", label="N(0, 1)")
    axes[0].set_xlabel("(estimate - truth) / SE (clipped to +-8)")
    axes[0].set_title("coverage of the standard errors")
    axes[0].legend()
    for r in main:
        ratio = np.asarray(r["se_over_crb"])
        axes[1].scatter(np.full(ratio.size, r["rate"]), ratio, s=8,
                        color="tab:green" if succeeded(r) else "tab:red")
    axes[1].set_xscale("log")
    axes[1].set_yscale("log")
    axes[1].axhline(1.0, color="k", linewidth=0.8)
    axes[1].axhline(1.5, color="k", linestyle="--", linewidth=0.8)
    axes[1].set_xlabel("sampling rate (Hz)")
    axes[1].set_ylabel("SE / Cramer-Rao bound")
    axes[1].set_title("error bars against the bound (red: failed fits)")
    fig.tight_layout()
    fig.savefig(HERE / "fitting.png", dpi=110)


def speed():
    """A 10 s record at 100 Hz (the issue's case): the first call (compilation included) and
    a second call on another noise draw from the same guess (30% off), a third from another
    guess (other signs of the 30%: another spin, which must not compile again), against
    scipy's least_squares over tj.simulate from the first guess on the same record, in one
    process."""
    import vector_reference as ref

    top = tj.TippeTop.from_ratios(1.2, 0.2, m=0.03, R=0.02, mu=0.4)
    spin = 3.0 * float(tj.thresholds(top).n1)
    ts = np.arange(0.0, 10.0, 0.01)
    clean = np.asarray(ref.solve(ref.params_of(top), 0.1, spin, ts)["theta"])
    record = dict(params={k: float(getattr(top, k)) for k in ("m", "R", "eps", "A", "C", "g", "mu")},
                  launch=dict(theta0=0.1, spin=spin, theta_dot=0.0, phi_dot=0.0), ts=ts,
                  free=("mu", "eps", "spin"), truth=dict(mu=float(top.mu), eps=float(top.eps), spin=spin),
                  crb=dict(mu=1.0, eps=1.0, spin=1.0), group=tj.classify(top), upright=False,
                  rate_hz=100.0, length_s=10.0, sigma=0.01)
    rows = []
    for seed in (0, 1):  # the same guess (start 0), two noise draws
        record["theta_obs"] = clean + 0.01 * np.random.default_rng(seed).standard_normal(ts.size)
        rows.append(fit_row(record, 0, "off"))
    rows.append(fit_row(record, 1, "off"))  # start 1: other signs of the 30%
    rows.append(scipy_row(record, 0))
    lines = [
        f"10 s at 100 Hz ({record['group']} top, spin {spin:.0f} rad/s, noise 0.01), from 30% off: "
        f"first call {rows[0]['wall']:.1f} s (compilation included; this process had no "
        f"persistent cache entries only if the cache was cleared), second call "
        f"{rows[1]['wall']:.1f} s ({'ok' if succeeded(rows[1]) else 'FAILED'}), a guess with "
        f"other signs of the 30% (spin factor {start_spin(record, 1):.1f}) "
        f"{rows[2]['wall']:.1f} s ({'ok' if succeeded(rows[2]) else 'FAILED'}); "
        f"scipy.optimize.least_squares over tj.simulate: {rows[3]['wall']:.1f} s "
        f"({rows[3]['nfev']} evaluations, {'ok' if succeeded(rows[3]) else 'not within 2%'}, "
        f"errors {np.round(rows[3]['rel_error'], 4).tolist()})."
    ]
    print("\n".join(lines))
    return "\n".join(lines)


def coverage(records, copies: int, seed: int):
    """The coverage of the standard errors over repeated noise: each record's clean signal
    (the independent integrator's) with `copies` fresh noise draws at the record's sigma and
    gaps, fitted from the truth with the default strategy in one batched call (each draw
    gets the fit it would get alone: `test_a_batch_fits_each_record_as_it_would_be_fitted_alone`). For a record
    whose error bars are right, z = (estimate - truth) / SE is N(0, 1) across the draws, so the
    share of |z| < 2 is 95.4% with a spread of sqrt(0.954 x 0.046 / n) over n fits; the 60
    records of the main benchmark give one z per record and parameter, too few to tell 93%
    from 95%. Returns one row per record."""
    rows = []
    for rec in records:
        jax.clear_caches()
        gc.collect()
        top, y0 = start_of(rec, "truth", rec["index"])
        mask = np.isfinite(rec["theta_obs"])
        noise = np.random.default_rng([seed, rec["index"], 7]).standard_normal(
            (copies, rec["ts"].size))
        obs = np.where(mask, rec["theta_clean"] + rec["sigma"] * noise, np.nan)
        free = list(rec["free"])
        truth = np.array([rec["truth"][k] for k in free])
        crb = np.array([rec["crb"][k] for k in free])
        t = time.perf_counter()
        fits = tj.fit(top, y0, rec["ts"], obs, free=free)
        wall = time.perf_counter() - t
        values = np.asarray(fits.values, float)
        se = np.asarray(fits.std_errors, float)
        z = (values - truth) / se
        row = dict(index=rec["index"], group=rec["group"], upright=bool(rec["upright"]),
                   rate=float(rec["rate_hz"]), length=float(rec["length_s"]),
                   sigma=float(rec["sigma"]), free=free, z=z.tolist(),
                   converged=np.asarray(fits.converged).tolist(),
                   se_over_crb=np.median(se / crb, axis=0).tolist(),
                   scatter_over_crb=(np.std(values, axis=0, ddof=1) / crb).tolist(),
                   wall=wall)
        rows.append(row)
        print(f"record {rec['index']} ({rec['group']}, {rec['rate_hz']:.0f} Hz): {copies} "
              f"draws in {wall:.1f} s, converged {np.mean(row['converged']):.0%}, mean z "
              f"{np.round(z.mean(0), 2).tolist()}, sd z {np.round(z.std(0, ddof=1), 2).tolist()}, "
              f"|z| < 2: {np.round(np.mean(np.abs(z) < 2, axis=0), 2).tolist()}", flush=True)
    return rows


def coverage_summary(rows, copies) -> str:
    """Per record and pooled: mean and sd of z, the share of |z| < 2 with its binomial spread."""
    head = ["record", "group", "Hz", "free", "converged", "mean z", "sd z", "|z| < 2",
            "SE / CRB", "scatter / CRB"]
    body = []
    for r in rows:
        z = np.asarray(r["z"])
        body.append([str(r["index"]), r["group"] + (" upright" if r["upright"] else ""),
                     f"{r['rate']:.0f}", ", ".join(r["free"]), f"{np.mean(r['converged']):.0%}",
                     " ".join(f"{v:+.2f}" for v in z.mean(0)),
                     " ".join(f"{v:.2f}" for v in z.std(0, ddof=1)),
                     " ".join(f"{v:.0%}" for v in np.mean(np.abs(z) < 2, axis=0)),
                     " ".join(f"{v:.2f}" for v in r["se_over_crb"]),
                     " ".join(f"{v:.2f}" for v in r["scatter_over_crb"])])
    lines = [table(head, body), ""]
    allz = np.concatenate([np.asarray(r["z"]).ravel() for r in rows])
    conv = np.concatenate([np.repeat(np.asarray(r["converged"]), np.asarray(r["z"]).shape[1])
                           for r in rows])
    share = np.mean(np.abs(allz) < 2)
    spread = np.sqrt(0.954 * 0.046 / allz.size)
    lines.append(
        f"Pooled over {len(rows)} records x {copies} draws ({allz.size} parameter estimates, "
        f"{np.mean(conv):.0%} of fits converged): |estimate - truth| / SE below 2 for "
        f"**{share:.1%}** (a normal z: 95.4%, +-{spread:.1%} for this many independent "
        f"estimates; the parameters of one fit are correlated, so the real spread is larger); "
        f"below 3 for {np.mean(np.abs(allz) < 3):.1%} (99.7%); mean z {allz.mean():+.3f}, "
        f"sd {allz.std(ddof=1):.3f}.")
    conv_z = allz[conv]
    every = np.concatenate([np.all(np.abs(np.asarray(r["z"])) < 2, axis=1) for r in rows])
    independent = np.mean(np.concatenate([np.full(len(r["z"]), 0.9545 ** len(r["free"]))
                                          for r in rows]))
    lines.append(
        f"Over the converged fits only ({conv_z.size} estimates): {np.mean(np.abs(conv_z) < 2):.1%} "
        f"below 2. Fits with every free parameter below 2: {np.mean(every):.1%} (normal z "
        f"that were independent: {independent:.1%}; the estimates of one fit are correlated, "
        "which raises it).")
    for name in ("mu", "eps", "spin", "theta_dot"):
        z = np.concatenate([np.asarray(r["z"])[:, r["free"].index(name)] for r in rows
                            if name in r["free"]] or [np.zeros(0)])
        if z.size:
            lines.append(f"- {name}: {z.size} estimates, |z| < 2 for {np.mean(np.abs(z) < 2):.1%}, "
                         f"mean {z.mean():+.3f}, sd {z.std(ddof=1):.3f}")
    subsets = [(g, lambda r, g=g: r["group"] == g) for g in ("IIa", "IIb", "IIc", "III")]
    subsets += [("upright launches", lambda r: r["upright"])]
    subsets += [(f"{lo}-{hi:.0f} Hz", lambda r, lo=lo, hi=hi: lo <= r["rate"] < hi)
                for lo, hi in RATE_BINS]
    for label, keep in subsets:
        z = np.concatenate([np.asarray(r["z"]).ravel() for r in rows if keep(r)] or [np.zeros(0)])
        if z.size:
            lines.append(f"- {label}: {z.size} estimates, |z| < 2 for "
                         f"{np.mean(np.abs(z) < 2):.1%}, sd {z.std(ddof=1):.3f}")
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=60)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--compare", type=int, default=8,
                        help="records also fitted with the other strategies and scipy")
    parser.add_argument("--report", action="store_true", help="summarise fitting_rows.json only")
    parser.add_argument("--resume", action="store_true",
                        help="skip fits (or with --coverage, records) already in the rows")
    parser.add_argument("--first", type=int, default=0,
                        help="start at this record (a second process can take the far end)")
    parser.add_argument("--rows", type=pathlib.Path, default=ROWS,
                        help="where this process writes its rows (--report reads every "
                             "fitting_rows*.json beside the default)")
    parser.add_argument("--speed", action="store_true",
                        help="time one 10 s, 100 Hz fit (twice) against scipy, and stop")
    parser.add_argument("--coverage", type=int, default=0, metavar="N",
                        help="the coverage over repeated noise on the first N records, and stop")
    parser.add_argument("--copies", type=int, default=32,
                        help="noise draws per record for --coverage")
    args = parser.parse_args()
    if args.coverage:
        records = draw_records(args.coverage, args.seed)
        rows = []
        if args.resume and COVERAGE_ROWS.exists():  # (rows of the same copies and records)
            rows = [r for r in json.loads(COVERAGE_ROWS.read_text())
                    if r["index"] < args.coverage and len(r["z"]) == args.copies]
        done_before = {r["index"] for r in rows}
        for rec in records + [None]:  # the rows and the section are written after each record
            if rec is not None:
                if rec["index"] in done_before:
                    continue
                rows += coverage([rec], args.copies, args.seed)
                rows.sort(key=lambda r: r["index"])
                COVERAGE_ROWS.write_text(json.dumps(rows, indent=0))
            done = "" if len(rows) == len(records) else f" (partial: {len(rows)} done)"
            write_section(
                "fitting.py --coverage",
                "## Coverage of the standard errors over repeated noise "
                f"(`python benchmarks/fitting.py --coverage {args.coverage} --copies "
                f"{args.copies}`)\n\n"
                f"The first {args.coverage} records of the benchmark (seed {args.seed}){done}: "
                "each record's clean signal from the independent integrator, with "
                f"{args.copies} fresh noise draws at its own sigma (and its gap), each fitted "
                "by `tj.fit` from the truth with the default strategy. Columns with one "
                "number per free parameter, in the order of `free`. "
                f"{sum(r['wall'] for r in rows):.0f} s of fits in all.\n\n"
                + coverage_summary(rows, args.copies) + "\n")
        print(coverage_summary(rows, args.copies))
        return
    if args.speed:
        speed()
        return
    rows = json.loads(args.rows.read_text()) if args.resume and args.rows.exists() else []
    if args.report:
        seen = {}
        for path in sorted(HERE.glob("fitting_rows*.json")):
            for r in json.loads(path.read_text()):
                seen[(r["index"], r["start"], r["strategy"])] = r
        rows = sorted(seen.values(), key=lambda r: r["index"])
    else:
        records = draw_records(args.n, args.seed)
        done = {(r["index"], r["start"], r["strategy"]) for r in rows}
        jobs = []
        for i in range(args.first, args.n):  # record by record: a partial run is a usable sample
            jobs += [(i, s, "global") for s in ("truth", "off")]
            if i < args.compare:
                jobs += [(i, "off", s) for s in ("search", "levels", "windows", "plain", "scipy")]
        last = None
        for i, s, strategy in jobs:
            if (i, s, strategy) in done:
                continue
            if i != last:
                # Each record brings new shapes, so new programs; a process that keeps them
                # all runs into the kernel's limit on memory maps (vm.max_map_count, 65530)
                # after some 30 records and LLVM fails to allocate. Drop them between records.
                jax.clear_caches()
                gc.collect()
                last = i
            if strategy == "scipy":
                row = scipy_row(records[i], i)
            else:
                row = fit_row(records[i], i, s, strategy)
            rows.append(row)
            args.rows.write_text(json.dumps(rows, indent=0))
            print(f"[{len(rows)}/{len(jobs)}] record {i} {s} {strategy}: "
                  f"{'ok' if succeeded(row) else 'FAIL'} {np.round(row['rel_error'], 4).tolist()} "
                  f"{row.get('message', '')!r} {row['wall']:.1f} s", flush=True)
    body = summarise(rows)
    print(body)
    chart(rows)
    n_records = len({r["index"] for r in rows})
    write_section(
        "fitting.py",
        "## Fitting on records it was not tuned to (`python benchmarks/fitting.py`)\n\n"
        f"{n_records} seeded random records (`fit_records.py`, seed {args.seed}) from the "
        "independent vector-form integrator, each fitted from the truth and from every free "
        "parameter 30% off. Success: every free parameter within 2% of the truth and within 3 "
        "standard errors. Times include compilation where a record brings a new shape bucket.\n\n"
        + body + "\n\n![fitting](fitting.png)\n",
    )


if __name__ == "__main__":
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent / "tests"))
    main()
