"""`fitting.py --laws` and `--mujoco`: which friction law a record obeys (issue 58, item 5).

`--laws`: seeded random records (`fit_law_records.py`: the viscous, Coulomb-Contensou (Hertz
pressure) and regularised Coulomb laws in turn, across the groups IIa, IIb, IIc, III; 2-5 s at
30-240 Hz, noise 0.005-0.02 rad, the first frame one sample after the launch) made by the
independent reference `tests/real_top_reference.py`. Per record:

1. the right law fitted from the truth (`tj.fit`, free eps, spin and the law's parameters that a
   record determines: mu; the patch radius for Contensou laws, the slip scale for Coulomb's).
   A record whose fit from the truth does not pin every free parameter to `MAX_SE_REL` (0.5%,
   so that "within 2%" asks for 4 standard errors, as `fitting.py --table`'s Cramer-Rao cut
   does) is drawn again (the next attempt of `fit_law_records.draw`), up to `MAX_ATTEMPTS`;
2. `tj.compare_laws` with the three laws, sigma given: the right law from its parameters 30% off
   (seeded signs), the other laws from generic guesses (`GENERIC`), eps and the spin 30% off for
   all of them; theta0 held at the truth (a known launch tilt, as in `--table`).

Counted: with the right law, a success is every free parameter within 2% of the truth and 3
standard errors, and a failure must be flagged (`converged=False`); a wrong law "differs by more
than the noise" on a record when its best fit is further than sigma (rms) from the clean signal,
and must then be ruled out; the law chosen (`preferred`) must be the right one. Rows are kept
beside the records' cache as each record finishes, so an interrupted run resumes where it
stopped (`--resume`). `--minutes M` starts no new record after M minutes and writes the
records done (the section says how many).

    python benchmarks/fitting.py --laws --n 48 --resume      # 16 records per law
    python benchmarks/fitting.py --laws --n 48 --minutes 8   # as many as 8 minutes allow
    python benchmarks/fitting.py --mujoco                    # MuJoCo's own top, every law
"""

from __future__ import annotations

import gc
import json
import pathlib
import time

import _harness as h
import fit_law_records as flr
import jax
import numpy as np

import tippejax as tj
from tippejax._fit.params import identifiable

MAX_SE_REL = 0.005
MAX_ATTEMPTS = 6
COMMON = ("eps", "spin")
GENERIC = {  # the wrong laws' starting guesses: a plastic top on a table
    "viscous": dict(mu=0.5),
    "hertz": dict(mu=0.3, patch_radius=5e-4, slip_scale=flr.CONTENSOU_SLIP_SCALE),
    "coulomb": dict(mu=0.3, slip_scale=1e-2),
}
NAMES = {"viscous": "Viscous", "hertz": "CoulombContensou(hertz)", "coulomb": "Coulomb"}
ROWS = flr.CACHE_ROOT / "fit_laws_rows-v1.json"


def law_of(kind: str, fields: dict) -> tj.AbstractFriction:
    """The tippejax law of a record's kind with the given fields."""
    if kind == "viscous":
        return tj.Viscous(fields["mu"])
    if kind == "coulomb":
        return tj.Coulomb(fields["mu"], fields["slip_scale"])
    return tj.CoulombContensou(
        fields["mu"], fields["patch_radius"], fields["slip_scale"], pressure=kind
    )


def top_of(rec, law) -> tj.TippeTop:
    p = rec["params"]
    return tj.TippeTop(m=p["m"], R=p["R"], eps=p["eps"], A=p["A"], C=p["C"], g=p["g"], friction=law)


def truth(rec) -> dict:
    """The true values of every name a fit of the record may free."""
    out = {k: v for k, v in rec["friction"].items() if k != "law"}
    out.update(eps=rec["params"]["eps"], spin=rec["launch"]["spin"])
    return out


def off(rec, names, index) -> dict:
    """Each of `names` 30% off the truth, with seeded signs."""
    rng = np.random.default_rng([index, 30])
    signs = {k: rng.choice([-1.0, 1.0]) for k in names}
    return {k: v * (1.0 + 0.3 * signs[k]) if k in signs else v for k, v in truth(rec).items()}


def score(values, errors, free, want) -> dict:
    values, errors = np.asarray(values, float), np.asarray(errors, float)
    target = np.array([want[k] for k in free])
    return dict(
        rel_error=((values - target) / np.abs(target)).tolist(),
        z=((values - target) / errors).tolist(),
    )


def succeeded(part) -> bool:
    return bool(np.all(np.abs(part["rel_error"]) < 0.02) and np.all(np.abs(part["z"]) < 3))


def accepted(seed, index, verbose=True):
    """The first attempt at record `index` whose fit from the truth pins every free parameter
    to `MAX_SE_REL`, and that fit; the last attempt if none does (marked `weak`)."""
    last = None
    for attempt in range(MAX_ATTEMPTS):
        rec = flr.record(seed, index, attempt)
        if rec is None:
            continue
        law = law_of(rec["law"], rec["friction"])
        top = top_of(rec, law)
        free = COMMON + identifiable(law)
        y0 = tj.initial_state(top, rec["launch"]["theta0"], rec["launch"]["spin"])
        wall, _, res = h.call(
            lambda: tj.fit(top, y0, rec["ts"], rec["theta_obs"], free=free, sigma=rec["sigma"])
        )
        se_rel = np.asarray(res.std_errors) / np.abs(np.asarray(res.values))
        from_truth = dict(
            score(res.values, res.std_errors, free, truth(rec)),
            wall=wall,
            converged=bool(res.converged),
            se_rel=se_rel.tolist(),
            free=free,
        )
        last = (rec, from_truth)
        if verbose:
            print(
                f"  record {index} attempt {attempt}: {rec['law']}, {rec['group']}, "
                f"{rec['rate_hz']:.0f} Hz, {rec['length_s']:.1f} s, sigma {rec['sigma']:.3f}; "
                f"se_rel max {se_rel.max():.2e} ({wall:.0f} s)",
                flush=True,
            )
        if bool(np.all(se_rel <= MAX_SE_REL)):
            return rec, dict(from_truth, weak=False)
    if last is None:
        raise RuntimeError(f"record {index}: every attempt lost contact before 2 s")
    return last[0], dict(last[1], weak=True)


def compare_row(seed, index) -> dict:
    rec, from_truth = accepted(seed, index)
    kind = rec["law"]
    guesses = []
    for other in flr.LAWS:
        if other == kind:
            fields = off(rec, identifiable(law_of(kind, rec["friction"])), index)
            fields = {k: v for k, v in fields.items() if k in GENERIC[kind]}
        else:
            fields = GENERIC[other]
        guesses.append(law_of(other, fields))
    start = off(rec, COMMON, index)
    p = rec["params"]
    top = tj.TippeTop(m=p["m"], R=p["R"], eps=start["eps"], A=p["A"], C=p["C"], g=p["g"], mu=0.3)
    y0 = tj.initial_state(top, rec["launch"]["theta0"], start["spin"])
    wall, _, cmp = h.call(
        lambda: tj.compare_laws(
            top, y0, rec["ts"], rec["theta_obs"], guesses, free=COMMON, sigma=rec["sigma"]
        )
    )
    laws = []
    for i, other in enumerate(flr.LAWS):
        res = cmp.fits[i]
        fit_curve = np.asarray(res.theta_fit, float)
        differs = float(np.sqrt(np.nanmean((fit_curve - rec["theta_clean"]) ** 2)) / rec["sigma"])
        part = dict(
            kind=other,
            free=list(res.free),
            values=np.asarray(res.values).tolist(),
            converged=bool(res.converged),
            message=res.message()[:60],
            chi2_dof=float(cmp.chi2[i] / cmp.dof[i]),
            p=float(cmp.p_value[i]),
            white=bool(cmp.white[i]),
            bic=float(cmp.bic[i]),
            ruled_out=bool(cmp.ruled_out[i]),
            differs=differs,
        )
        if other == kind:
            part.update(score(res.values, res.std_errors, res.free, truth(rec)))
        laws.append(part)
    preferred = None if cmp.preferred_index < 0 else flr.LAWS[cmp.preferred_index]
    return dict(
        index=index,
        seed=seed,
        law=kind,
        group=rec["group"],
        rate=rec["rate_hz"],
        length=rec["length_s"],
        sigma=rec["sigma"],
        attempt=rec["attempt"],
        from_truth=from_truth,
        laws=laws,
        preferred=preferred,
        wall=wall,
    )


def summary(rows) -> str:
    right = {r["index"]: next(x for x in r["laws"] if x["kind"] == r["law"]) for r in rows}
    lines = []
    fit_rows = []
    for kind in (*flr.LAWS, "all"):
        sub = [r for r in rows if kind in ("all", r["law"])]
        if not sub:
            continue
        ok = [succeeded(right[r["index"]]) for r in sub]
        truth_ok = [succeeded(r["from_truth"]) for r in sub]
        bad = [right[r["index"]] for r, s in zip(sub, ok) if not s]
        flagged = sum(not b["converged"] for b in bad)
        fit_rows.append(
            f"{NAMES.get(kind, kind)} | {len(sub)} | {sum(truth_ok)}/{len(sub)} | "
            f"{sum(ok)}/{len(sub)} | {flagged}/{len(bad)} | {len(bad) - flagged} | "
            f"{sum(r['from_truth']['weak'] for r in sub)}"
        )
    lines += [
        "With the right law (success: every free parameter within 2% of the truth and 3 "
        "standard errors):",
        "",
        h.table(
            "law | records | success from truth | success from 30% off | failures "
            "flagged | unflagged failures | records above the 0.5% cut",
            fit_rows,
        ),
        "",
    ]
    pair_rows = []
    total = [0, 0, 0]
    for kind in flr.LAWS:
        cells = []
        for other in flr.LAWS:
            if other == kind:
                cells.append("-")
                continue
            parts = [
                next(x for x in r["laws"] if x["kind"] == other) for r in rows if r["law"] == kind
            ]
            differ = [x for x in parts if x["differs"] > 1.0]
            rejected = sum(x["ruled_out"] for x in differ)
            total[0] += rejected
            total[1] += len(differ)
            total[2] += sum(x["ruled_out"] for x in parts if x["differs"] <= 1.0)
            cells.append(
                f"{rejected}/{len(differ)}"
                + (f" (+{len(parts) - len(differ)} alike)" if len(parts) > len(differ) else "")
            )
        pair_rows.append(f"{NAMES[kind]} | " + " | ".join(cells))
    rate = total[0] / total[1] if total[1] else float("nan")
    lines += [
        f"The wrong law ruled out, on the records where its best fit is further than the "
        f"noise (rms) from the clean signal: {total[0]}/{total[1]} ({rate:.1%}); "
        f"ruled out where it is not (alike): {total[2]}. Rows: the record's law; columns: "
        "the law fitted.",
        "",
        h.table("record's law | " + " | ".join(NAMES[k] for k in flr.LAWS), pair_rows),
        "",
    ]
    choice_rows = []
    for kind in (*flr.LAWS, "all"):
        sub = [r for r in rows if kind in ("all", r["law"])]
        if not sub:
            continue
        chosen = sum(r["preferred"] == r["law"] for r in sub)
        distinct = [
            r for r in sub if all(x["differs"] > 1.0 for x in r["laws"] if x["kind"] != r["law"])
        ]
        none = sum(r["preferred"] is None for r in sub)
        choice_rows.append(
            f"{NAMES.get(kind, kind)} | {chosen}/{len(sub)} | "
            f"{sum(r['preferred'] == r['law'] for r in distinct)}/{len(distinct)} | {none} | "
            f"{np.median([r['wall'] for r in sub]):.0f}"
        )
    lines += [
        "The law chosen (`preferred`: the lowest BIC among the laws not ruled out):",
        "",
        h.table(
            "record's law | chosen right | right where every other law differs | "
            "none chosen | median s / record (one fit per law)",
            choice_rows,
        ),
    ]
    wrong = [r for r in rows if r["preferred"] != r["law"]]
    if wrong:
        lines += ["", "Records where the law chosen is not the record's:"]
        lines += [
            f"- record {r['index']} ({NAMES[r['law']]}, {r['group']}, {r['rate']:.0f} Hz, "
            f"{r['length']:.1f} s, sigma {r['sigma']:.3f}): chose "
            f"{NAMES.get(r['preferred'], r['preferred'])}; "
            + "; ".join(
                f"{NAMES[x['kind']]} chi2/dof {x['chi2_dof']:.2f}, "
                f"{'white' if x['white'] else 'not white'}, differs "
                f"{x['differs']:.2f}"
                for x in r["laws"]
            )
            for r in wrong
        ]
    return "\n".join(lines)


def laws(args):
    """Every record: the right law from the truth, then `compare_laws` from 30% off."""
    n = 1 if args.smoke else args.n
    path = pathlib.Path(str(ROWS).replace(".json", f"-seed{args.seed}.json"))
    rows = json.loads(path.read_text()) if (args.resume and path.exists()) else []
    done = {r["index"] for r in rows}
    start = time.perf_counter()
    budget = getattr(args, "minutes", None)
    stopped = False
    for i in range(n):
        if i in done:
            continue
        if budget is not None and time.perf_counter() - start > 60.0 * budget:
            stopped = True
            break
        jax.clear_caches()
        gc.collect()
        row = compare_row(args.seed, i)
        rows.append(row)
        chosen = "right" if row["preferred"] == row["law"] else f"WRONG ({row['preferred']})"
        print(
            f"record {i} ({row['law']}, {row['group']}): law chosen {chosen}, right law "
            f"{'ok' if succeeded(next(x for x in row['laws'] if x['kind'] == row['law'])) else 'FAIL'}"
            f"; {row['wall']:.0f} s ({time.perf_counter() - start:.0f} s so far)",
            flush=True,
        )
        if not args.smoke:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(rows))
    rows = sorted(rows, key=lambda r: r["index"])[:n] if not args.smoke else rows
    if not rows:
        raise SystemExit(f"--minutes {budget}: no record finished in the time allowed.")
    size = f"{len(rows)} seeded random record{'s' if len(rows) != 1 else ''}"
    if stopped or len(rows) < n:
        size += f" (of the {n} asked for: `--minutes {budget:g}` stopped the run)"
    h.write(
        "fitting.py --laws",
        "Which law does a record obey?",
        f"""
{size} (seed {args.seed}; {", ".join(f"{sum(r['law'] == k for r in rows)} {NAMES[k]}" for k in flr.LAWS)}), made by the independent reference `tests/real_top_reference.py`: 2-5 s at 30-240 Hz, noise 0.005-0.02 rad, the first frame one sample after the launch. Each record is fitted with its own law from the truth, then `tj.compare_laws` fits it with all three laws (sigma given; the record's law from its parameters 30% off, the others from generic guesses; eps and the spin 30% off; theta0 known). Targets: with the right law at least 95% within 2% and 3 SE from 30% off, every failure flagged; the wrong law ruled out on at least 95% of the records where the laws differ by more than the noise; the law chosen right on at least 95%.

{summary(rows)}
""",
        args,
    )


def mujoco(args):
    """MuJoCo's own top (`examples/data/mujoco_tippe_top.csv`): every law on the whole record."""
    data = np.genfromtxt(
        h.HERE.parent / "examples" / "data" / "mujoco_tippe_top.csv", delimiter=",", names=True
    )
    ts, theta = data["t"], data["theta"]
    if args.smoke:
        keep = ts <= 1.0
        ts, theta = ts[keep], theta[keep]
    true = tj.default_top()
    guesses = (tj.Viscous(3.0), tj.Coulomb(0.3, 3e-3), tj.CoulombContensou(0.3, 5e-4, 1e-5))
    y0 = tj.initial_state(true, float(theta[0]), 100.0)
    kw = dict(max_steps=3) if args.smoke else {}
    wall, _, cmp = h.call(
        lambda: tj.compare_laws(true, y0, ts, theta, guesses, free=("eps", "spin"), **kw)
    )
    rows = []
    for name, res in zip(cmp.names, cmp.fits):
        rows.append(
            f"{name} | {', '.join(f'{n} = {float(v):.4g}' for n, v in zip(res.free, np.asarray(res.values)))} | "
            f"{float(res.rms):.4g} | {float(res.noise):.3g} | "
            f"{float(res.rms) / float(res.noise):.2f} | {res.message()[:40] or 'converged'}"
        )
    best = int(np.argmin([float(f.rms) / float(f.noise) for f in cmp.fits]))
    ratio = float(cmp.fits[best].rms) / float(cmp.fits[best].noise)
    h.write(
        "fitting.py --mujoco",
        "MuJoCo's own top: the whole record with every law",
        f"""
`examples/data/mujoco_tippe_top.csv`: the default top in MuJoCo (Coulomb friction 0.3, soft contact, {ts[-1]:.0f} s at 200 Hz), fitted on the whole record with each law (free eps, the spin and the law's parameters; theta0 = 0.1 known), `tj.compare_laws` without sigma ({wall:.0f} s). Noise: each fit's own estimate (`res.noise`, the median of its windows' mean squares). Target: rms at most 1.5x the noise with the best law.

{h.table("law | fitted | rms (rad) | noise (rad) | rms / noise | message", rows)}

Best: {cmp.names[best]}, rms {ratio:.2f}x its noise: target {h.verdict(ratio <= 1.5)}. The comparison's verdict: {cmp.preferred_name or "no law consistent"}{"; ruled out: " + ", ".join(cmp.ruled_out_names) if cmp.ruled_out_names else ""}.
""",
        args,
    )
