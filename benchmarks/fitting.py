"""fitting: `tj.fit` and `tj.compare_laws` on seeded random records from independent integrators
(`tests/fit_records.py`): success from the truth and from 30% off, honest error bars, cost, the law.

A fit succeeds when every free parameter is within 2% of the truth and 3 standard errors; one that
does not must be flagged (`converged=False`). Rows are cached beside the records (`--resume`).

    python benchmarks/fitting.py --table --n 60
    python benchmarks/fitting.py --coverage --n 60 --copies 4
    python benchmarks/fitting.py --laws --n 48 --resume   # or --minutes M: stop after M minutes
    python benchmarks/fitting.py --quick                  # every mode, tiny, writes nothing
"""

from __future__ import annotations

import gc
import json
import pathlib
import sys
import time

import _harness as h
import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(h.HERE.parent / "tests"))
import fit_records as fr  # noqa: E402

import tippejax as tj  # noqa: E402

ROWS = fr.CACHE_ROOT / "fitting_rows.json"
LAW_ROWS = fr.CACHE_ROOT / "fit_laws_rows-v1.json"
MAX_SE_REL, MAX_ATTEMPTS, COMMON = 0.005, 100, ("eps", "spin")
FREE = {"viscous": ("mu",), "hertz": ("mu", "patch_radius"), "coulomb": ("mu", "slip_scale")}
"""The law's parameters a record determines (not the slip scale of a law with drilling torque:
the motion converges as it goes to 0, `docs/friction.md`)."""
GENERIC = {  # the wrong laws' starting guesses: a plastic top on a table
    "viscous": dict(mu=0.5),
    "hertz": dict(mu=0.3, patch_radius=5e-4, slip_scale=fr.CONTENSOU_SLIP_SCALE),
    "coulomb": dict(mu=0.3, slip_scale=1e-2),
}
NAMES = {"viscous": "Viscous", "hertz": "CoulombContensou(hertz)", "coulomb": "Coulomb"}


def off_factors(index, names) -> dict:
    """1 +- 0.3 for each of `names`, with seeded signs."""
    rng = np.random.default_rng([index, 30])
    return {k: 1.0 + rng.choice([-1.0, 1.0]) * 0.3 for k in names}


def score(values, se, truth) -> dict:
    values, truth = np.asarray(values, float), np.asarray(truth, float)
    out = dict(rel_error=((values - truth) / np.abs(truth)).tolist())
    if se is not None:
        out["z"] = ((values - truth) / np.asarray(se, float)).tolist()
    return out


def succeeded(row) -> bool:
    """Every free parameter within 2% of the truth and (given standard errors) 3 of them."""
    ok = np.all(np.abs(row["rel_error"]) < 0.02)
    return bool(ok and ("z" not in row or np.all(np.abs(row["z"]) < 3)))


def start_of(record, start, index):
    """The guess of a start: the truth, or each free parameter 30% off (seeded signs)."""
    f = off_factors(index, record["free"]) if start == "off" else {}
    p, la = record["params"], record["launch"]
    top = tj.TippeTop(**dict(p, mu=p["mu"] * f.get("mu", 1.0), eps=p["eps"] * f.get("eps", 1.0)))
    spin, theta_dot = la["spin"] * f.get("spin", 1.0), la["theta_dot"] * f.get("theta_dot", 1.0)
    y0 = tj.initial_state(top, la["theta0"], spin, theta_dot=theta_dot, phi_dot=la["phi_dot"])
    return top, y0


def fit_row(record, index, start, max_steps=100):
    top, y0 = start_of(record, start, index)
    kw = dict(free=record["free"], max_steps=max_steps)
    wall, _, res = h.call(lambda: tj.fit(top, y0, record["ts"], record["theta_obs"], **kw))
    values, se = np.asarray(res.values, float), np.asarray(res.std_errors, float)
    free = list(record["free"])
    out = dict(index=index, start=start, strategy="global", group=str(record["group"]))
    out.update(upright=bool(record["upright"]), rate=float(record["rate_hz"]), free=free)
    out.update(score(values, se, [record["truth"][k] for k in free]))
    out.update(converged=bool(res.converged), wall=wall)
    out["se_over_crb"] = (se / np.array([record["crb"][k] for k in free])).tolist()
    return out


def counts(rows) -> str:
    """'successes/n | flagged/failures | unflagged' of fit rows."""
    bad = [r for r in rows if not succeeded(r)]
    flagged = sum(not r["converged"] for r in bad)
    return f"{len(rows) - len(bad)}/{len(rows)} | {flagged}/{len(bad)} | {len(bad) - flagged}"


def summary(rows) -> str:
    main = [r for r in rows if r["strategy"] == "global"]

    def line(label, subset):
        truth, off = ([r for r in subset if r["start"] == s] for s in ("truth", "off"))
        ratio = np.concatenate([r["se_over_crb"] for r in subset if succeeded(r)] or [[np.nan]])
        z = np.abs(np.concatenate([r["z"] for r in subset] or [[np.nan]]))
        wall = np.median([r["wall"] for r in subset]) if subset else np.nan
        within = sum(np.all(np.abs(r["z"]) < 3) for r in truth)
        bad = [r for r in subset if not succeeded(r)]
        flagged = sum(not r["converged"] for r in bad)
        return (
            f"{label} | {sum(map(succeeded, truth))}/{len(truth)} | {within}/{len(truth)} | "
            f"{sum(map(succeeded, off))}/{len(off)} | {flagged}/{len(bad)} | {len(bad) - flagged} | "
            f"{np.median(ratio):.2f} | {np.mean(z < 2):.0%} | {wall:.1f}"
        )

    subsets = {g: [r for r in main if r["group"] == g] for g in fr.GROUPS}
    subsets["upright launches"] = [r for r in main if r["upright"]]
    body = [line("all", main)] + [line(k, v) for k, v in subsets.items() if v]
    head = "records | success from truth | truth within 3 SE | success from 30% off | failures flagged | unflagged failures | SE / CRB | \\|error\\| / SE < 2 | median s / fit"
    return h.table(head, body)


def cached_rows(path, args):
    return json.loads(path.read_text()) if args.resume and path.exists() else []


def keep(path, rows, args):
    if not args.smoke:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(rows))


def table(args):
    """Every record from the truth and from 30% off; the chart fitting.png."""
    n, steps = (1, 3) if args.smoke else (args.n, 100)
    records, rows = fr.draw_records(n, args.seed), cached_rows(ROWS, args)
    done = {(r["index"], r["start"], r["strategy"]) for r in rows}
    for i, rec in enumerate(records):
        jax.clear_caches()  # each record brings new shapes: keep the process's memory maps bounded
        gc.collect()
        for start in (x for x in ("truth", "off") if (i, x, "global") not in done):
            rows.append(fit_row(rec, i, start, steps))
            print(f"record {i} {start}: {'ok' if succeeded(rows[-1]) else 'FAIL'}", flush=True)
            keep(ROWS, rows, args)
    h.write(
        "fitting.py --table",
        "Fitting on records it was not tuned to",
        f"{len(records)} seeded random records (seed {args.seed}).\n\n{summary(rows)}\n\n![fitting](fitting.png)",
        args,
    )
    main, plt = [r for r in rows if r["strategy"] == "global"], h.pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    z, x = np.concatenate([r["z"] for r in main]), np.linspace(-8, 8, 400)
    bins = np.linspace(-8, 8, 41)
    axes[0].hist(
        np.clip(z[np.isfinite(z)], -8, 8), bins=bins, density=True, alpha=0.7, label="fits"
    )
    axes[0].plot(x, np.exp(-(x**2) / 2) / np.sqrt(2 * np.pi), "k-", label="N(0, 1)")
    axes[0].set(
        xlabel="(estimate - truth) / SE (clipped to +-8)", title="coverage of the standard errors"
    )
    axes[0].legend()
    for r in main:
        color = "tab:green" if succeeded(r) else "tab:red"
        axes[1].scatter(
            np.full(len(r["se_over_crb"]), r["rate"]), r["se_over_crb"], s=8, color=color
        )
    axes[1].set(
        xscale="log", yscale="log", xlabel="sampling rate (Hz)", ylabel="SE / Cramer-Rao bound"
    )
    axes[1].set_title("error bars against the bound (red: failed fits)")
    for y, style in ((1.0, "-"), (1.5, "--")):
        axes[1].axhline(y, color="k", linestyle=style, linewidth=0.8)
    fig.tight_layout()
    fig.savefig(h.figure_path("fitting.png", args), dpi=110)


def coverage(args):
    """The coverage of the standard errors over repeated noise: each record's clean signal with
    fresh noise draws at its own sigma and gap, fitted from the truth in one batched call."""
    n, copies = (1, 2) if args.smoke else (args.n, args.copies)
    z_all, conv, wall = [], [], 0.0
    for rec in fr.draw_records(n, args.seed):
        jax.clear_caches()
        top, y0 = start_of(rec, "truth", rec["index"])
        noise = np.random.default_rng([args.seed, rec["index"], 7]).standard_normal(
            (copies, rec["ts"].size)
        )
        obs = np.where(
            np.isfinite(rec["theta_obs"]), rec["theta_clean"] + rec["sigma"] * noise, np.nan
        )
        kw = dict(free=rec["free"], max_steps=3 if args.smoke else 100)
        t, _, fits = h.call(lambda: tj.fit(top, y0, rec["ts"], obs, **kw))
        wall += t
        truth = np.array([rec["truth"][k] for k in rec["free"]])
        z = (np.asarray(fits.values, float) - truth) / np.asarray(fits.std_errors, float)
        z_all.append(z.ravel())
        conv.append(np.repeat(np.asarray(fits.converged), z.shape[1]))
    z, conv = np.concatenate(z_all), np.concatenate(conv)
    sd = z.std(ddof=1) if z.size > 1 else np.nan
    h.write(
        "fitting.py --coverage",
        "Coverage of the standard errors over repeated noise",
        f"""
The first {n} records (seed {args.seed}) x {copies} noise draws, from the truth ({wall:.0f} s of fits). Honest error bars: |z| < 2 for 95.4%.

Over {z.size} parameter estimates ({np.mean(conv):.0%} of fits converged): |z| < 2 for **{np.mean(np.abs(z) < 2):.1%}** (+-{np.sqrt(0.954 * 0.046 / z.size):.1%} if independent), |z| < 3 for {np.mean(np.abs(z) < 3):.1%}; mean z {z.mean():+.3f}, sd {sd:.3f}; over the converged fits {np.mean(np.abs(z[conv]) < 2):.1%}.
""",
        args,
    )


# --- which law does a record obey (--laws) --------------------------------------------------


def law_of(kind: str, fields: dict) -> tj.AbstractFriction:
    if kind == "viscous":
        return tj.Viscous(fields["mu"])
    if kind == "coulomb":
        return tj.Coulomb(fields["mu"], fields["slip_scale"])
    return tj.CoulombContensou(
        fields["mu"], fields["patch_radius"], fields["slip_scale"], pressure=kind
    )


def law_truth(rec) -> dict:
    """The true values of every name a fit of the record may free."""
    out = {k: v for k, v in rec["friction"].items() if k != "law"}
    return dict(out, eps=rec["params"]["eps"], spin=rec["launch"]["spin"])


def law_top(rec, law, eps=None) -> tj.TippeTop:
    p = dict(rec["params"], eps=rec["params"]["eps"] if eps is None else eps)
    return tj.TippeTop(**{k: p[k] for k in ("m", "R", "eps", "A", "C", "g")}, friction=law)


def law_crb_rel(d) -> np.ndarray:
    """The Cramer-Rao bound of each free parameter of draw `d` (`fr.law_draw`) relative to its
    value: the noise through the model's sensitivities at the truth (`jax.jacfwd` of
    `tj.simulate`'s tilt at the record's frames). inf where the run loses contact before 2 s."""
    free = COMMON + FREE[d["law"]]
    truth = law_truth(d)
    ts = np.arange(1, d["n"] + 1) / d["rate_hz"]
    n = ts.size  # (padded with its last frame to a multiple of 256: fewer programs to compile)
    ts = jnp.asarray(np.concatenate([ts, np.full(-n % 256, ts[-1])]))

    def theta(rel):  # the tilt at the frames, each free parameter at truth * (1 + rel)
        vals = dict(truth, **{k: truth[k] * (1.0 + r) for k, r in zip(free, rel)})
        top = law_top(d, law_of(d["law"], vals), eps=vals["eps"])
        y0 = tj.initial_state(top, d["launch"]["theta0"], vals["spin"])
        return tj.simulate(top, y0, ts[-1], saveat=ts, throw=False).theta

    jac = np.asarray(jax.jacfwd(theta)(jnp.zeros(len(free))))[:n]
    rows = np.all(np.isfinite(jac), axis=1)
    if not rows.any() or float(ts[:n][rows][-1]) < 2.0:
        return np.full(len(free), np.inf)
    try:
        return fr.cramer_rao(jac, d["sigma"], rows)
    except np.linalg.LinAlgError:  # a parameter the record does not see at all
        return np.full(len(free), np.inf)


def accepted(seed, index):
    """The first attempt at law record `index` whose Cramer-Rao bound pins every free parameter
    to `MAX_SE_REL` (`law_crb_rel`, so that "within 2%" asks for 4 standard errors), and its fit
    from the truth; the last attempt integrated if none does (marked `weak`)."""
    last = None
    for attempt in range(MAX_ATTEMPTS):
        crb = law_crb_rel(fr.law_draw(seed, index, attempt))
        pinned = bool(np.all(crb <= MAX_SE_REL))
        if not pinned and (last is not None or attempt < MAX_ATTEMPTS - 1):
            continue  # (the last attempt is integrated if no earlier one was)
        rec = fr.law_record(seed, index, attempt)
        if rec is None:
            continue
        top, free = law_top(rec, law_of(rec["law"], rec["friction"])), COMMON + FREE[rec["law"]]
        y0 = tj.initial_state(top, rec["launch"]["theta0"], rec["launch"]["spin"])
        kw = dict(free=free, sigma=rec["sigma"])
        wall, _, res = h.call(lambda: tj.fit(top, y0, rec["ts"], rec["theta_obs"], **kw))
        se_rel = np.asarray(res.std_errors) / np.abs(np.asarray(res.values))
        want = law_truth(rec)
        last = rec, dict(score(res.values, res.std_errors, [want[k] for k in free]), wall=wall)
        last[1].update(converged=bool(res.converged), se_rel=se_rel.tolist(), free=free)
        last[1].update(crb_rel=crb.tolist())
        print(
            f"  record {index} attempt {attempt}: {rec['law']}, {rec['group']}; crb_rel max {crb.max():.2e}, se_rel max {se_rel.max():.2e}",
            flush=True,
        )
        if pinned:
            return rec, dict(last[1], weak=False)
    if last is None:
        raise RuntimeError(f"record {index}: every attempt lost contact before 2 s")
    return last[0], dict(last[1], weak=True)


def compare_row(seed, index) -> dict:
    """`tj.compare_laws` with the three laws, sigma given: the record's law from its parameters
    30% off, the others from `GENERIC`; eps and the spin 30% off; theta0 known."""
    rec, from_truth = accepted(seed, index)
    kind, truth = rec["law"], law_truth(rec)
    f = off_factors(index, FREE[kind])
    right = {k: v * f.get(k, 1.0) for k, v in truth.items() if k in GENERIC[kind]}
    guesses = [law_of(k, right if k == kind else GENERIC[k]) for k in fr.LAWS]
    f = off_factors(index, COMMON)
    top = law_top(rec, tj.Viscous(0.3), eps=truth["eps"] * f["eps"])
    y0 = tj.initial_state(top, rec["launch"]["theta0"], truth["spin"] * f["spin"])
    kw = dict(free=COMMON, sigma=rec["sigma"])
    wall, _, cmp = h.call(
        lambda: tj.compare_laws(top, y0, rec["ts"], rec["theta_obs"], guesses, **kw)
    )
    laws = []
    for i, other in enumerate(fr.LAWS):
        res = cmp.fits[i]
        rms = np.sqrt(np.nanmean((np.asarray(res.theta_fit, float) - rec["theta_clean"]) ** 2))
        part = dict(
            kind=other, converged=bool(res.converged), chi2_dof=float(cmp.chi2[i] / cmp.dof[i])
        )
        part.update(
            white=bool(cmp.white[i]),
            ruled_out=bool(cmp.ruled_out[i]),
            differs=float(rms / rec["sigma"]),
        )
        if other == kind:
            part.update(score(res.values, res.std_errors, [truth[k] for k in res.free]))
        laws.append(part)
    preferred = None if cmp.preferred_index < 0 else fr.LAWS[cmp.preferred_index]
    return dict(
        index=index,
        law=kind,
        group=rec["group"],
        rate=rec["rate_hz"],
        length=rec["length_s"],
        sigma=rec["sigma"],
        from_truth=from_truth,
        laws=laws,
        preferred=preferred,
        wall=wall,
    )


def law_summary(rows) -> str:
    def part(r, kind):
        return next(x for x in r["laws"] if x["kind"] == kind)

    def subsets():
        for kind in (*fr.LAWS, "all"):
            sub = [r for r in rows if kind in ("all", r["law"])]
            if sub:
                yield NAMES.get(kind, kind), sub

    fit_rows = []
    for name, sub in subsets():
        right = [part(r, r["law"]) for r in sub]
        truth_ok = sum(succeeded(r["from_truth"]) for r in sub)
        s, flagged, unflagged = counts(right).split(" | ")
        fit_rows.append(
            f"{name} | {len(sub)} | {truth_ok}/{len(sub)} | {s} | {flagged} | {unflagged}"
        )
    total = [0, 0, 0]
    for kind in fr.LAWS:
        for other in (k for k in fr.LAWS if k != kind):
            parts = [part(r, other) for r in rows if r["law"] == kind]
            differ = [x for x in parts if x["differs"] > 1.0]
            total[0] += sum(x["ruled_out"] for x in differ)
            total[1] += len(differ)
            total[2] += sum(x["ruled_out"] for x in parts if x["differs"] <= 1.0)
    rate = total[0] / total[1] if total[1] else float("nan")
    choice_rows = []
    for name, sub in subsets():
        distinct = [
            r for r in sub if all(x["differs"] > 1.0 for x in r["laws"] if x["kind"] != r["law"])
        ]
        chosen, right = (
            sum(r["preferred"] == r["law"] for r in sub),
            sum(r["preferred"] == r["law"] for r in distinct),
        )
        none = sum(r["preferred"] is None for r in sub)
        choice_rows.append(f"{name} | {chosen}/{len(sub)} | {right}/{len(distinct)} | {none}")
    lines = [
        "With the right law (success: within 2% of the truth and 3 SE):",
        "",
        h.table(
            "law | records | success from truth | success from 30% off | failures flagged | unflagged failures",
            fit_rows,
        ),
        "",
        f"The wrong law ruled out where its best fit is further than the noise (rms) from the clean signal: {total[0]}/{total[1]} ({rate:.1%}); where it is not (alike): {total[2]}.",
        "",
        "The law chosen (`preferred`: the lowest BIC among the laws not ruled out):",
        "",
        h.table(
            "record's law | chosen right | right where every other law differs | none chosen",
            choice_rows,
        ),
    ]
    wrong = [r for r in rows if r["preferred"] != r["law"]]
    lines += ["", "Records where the law chosen is not the record's:"] if wrong else []
    lines += [
        f"- record {r['index']} ({NAMES[r['law']]}, {r['group']}, {r['rate']:.0f} Hz, {r['length']:.1f} s, sigma {r['sigma']:.3f}): chose {NAMES.get(r['preferred'], r['preferred'])}; "
        + "; ".join(
            f"{NAMES[x['kind']]} chi2/dof {x['chi2_dof']:.2f}, {'white' if x['white'] else 'not white'}, differs {x['differs']:.2f}"
            for x in r["laws"]
        )
        for r in wrong
    ]
    return "\n".join(lines)


def laws(args):
    """Records of every friction law: the right law from the truth, then `compare_laws`."""
    n, start, budget = 1 if args.smoke else args.n, time.perf_counter(), args.minutes
    path = pathlib.Path(str(LAW_ROWS).replace(".json", f"-seed{args.seed}.json"))
    rows, stopped = cached_rows(path, args), False
    for i in sorted(set(range(n)) - {r["index"] for r in rows}):
        if budget is not None and time.perf_counter() - start > 60.0 * budget:
            stopped = True
            break
        jax.clear_caches()
        gc.collect()
        rows.append(compare_row(args.seed, i))
        print(
            f"record {i}: chose {rows[-1]['preferred']} ({rows[-1]['law']}); {time.perf_counter() - start:.0f} s",
            flush=True,
        )
        keep(path, rows, args)
    rows = sorted(rows, key=lambda r: r["index"])[:n]
    if not rows:
        raise SystemExit(f"--minutes {budget}: no record finished in the time allowed.")
    size = f"{len(rows)} seeded random record{'s' if len(rows) != 1 else ''}"
    if stopped or len(rows) < n:
        size += f" (of the {n} asked for: `--minutes {budget:g}` stopped the run)"
    mix = ", ".join(f"{sum(r['law'] == k for r in rows)} {NAMES[k]}" for k in fr.LAWS)
    h.write(
        "fitting.py --laws",
        "Which law does a record obey?",
        f"""
{size} (seed {args.seed}; {mix}).

{law_summary(rows)}
""",
        args,
    )


def mujoco(args):
    """MuJoCo's own top (`examples/data/mujoco_tippe_top.csv`): every law on the whole record."""
    path = h.HERE.parent / "examples" / "data" / "mujoco_tippe_top.csv"
    data = np.genfromtxt(path, delimiter=",", names=True)
    ts, theta = data["t"], data["theta"]
    if args.smoke:
        ts, theta = ts[ts <= 1.0], theta[ts <= 1.0]
    true = tj.default_top()
    guesses = (tj.Viscous(3.0), tj.Coulomb(0.3, 3e-3), tj.CoulombContensou(0.3, 5e-4, 1e-5))
    y0 = tj.initial_state(true, float(theta[0]), 100.0)
    kw = dict(free=COMMON, **(dict(max_steps=3) if args.smoke else {}))
    wall, _, cmp = h.call(lambda: tj.compare_laws(true, y0, ts, theta, guesses, **kw))
    rows = []
    for name, res in zip(cmp.names, cmp.fits):
        fitted = ", ".join(
            f"{n} = {float(v):.4g}" for n, v in zip(res.free, np.asarray(res.values))
        )
        rms, noise = float(res.rms), float(res.noise)
        rows.append(f"{name} | {fitted} | {rms:.4g} | {noise:.3g} | {rms / noise:.2f}")
    # One yardstick for every law: each fit estimates the noise from its own residuals, which a
    # fit distorted everywhere inflates, so the lowest of the estimates is the record's noise.
    rms = [float(f.rms) for f in cmp.fits]
    floor = min(float(f.noise) for f in cmp.fits)
    best = int(np.argmin(rms))
    ratio = rms[best] / floor
    ruled_out = "; ruled out: " + ", ".join(cmp.ruled_out_names) if cmp.ruled_out_names else ""
    h.write(
        "fitting.py --mujoco",
        "MuJoCo's own top: the whole record with every law",
        f"""
{ts[-1]:.0f} s at 200 Hz, `tj.compare_laws` without sigma ({wall:.0f} s). Target: rms at most 1.5x the noise with the best law.

{h.table("law | fitted | rms (rad) | noise (rad) | rms / noise", rows)}

Best (the lowest rms): {cmp.names[best]}, {ratio:.2f}x the lowest noise level the fits estimate ({floor:.4g} rad): target {h.verdict(ratio <= 1.5)}; {cmp.names[0]} {rms[0] / floor:.2f}x. The comparison's verdict: {cmp.preferred_name or "no law consistent"}{ruled_out}.
""",
        args,
    )


def options(prs):
    prs.add_argument("--quick", dest="smoke", action="store_true", help="the same as --smoke")
    prs.add_argument("--n", type=int, default=60, help="records")
    prs.add_argument("--seed", type=int, default=0)
    prs.add_argument("--copies", type=int, default=4, help="--coverage: noise draws per record")
    prs.add_argument("--resume", action="store_true", help="--table, --laws: keep the fits made")
    prs.add_argument("--minutes", type=float, default=None, help="--laws: stop after M minutes")


MODES = {
    "table": (table, "every record from the truth and 30% off; fitting.png"),
    "laws": (laws, "records of every friction law: which law a record obeys"),
    "mujoco": (mujoco, "MuJoCo's own top, the whole record with every law"),
    "coverage": (coverage, "the coverage of the error bars over repeated noise"),
}

if __name__ == "__main__":
    h.run(MODES, h.parse(__doc__, MODES, options))
