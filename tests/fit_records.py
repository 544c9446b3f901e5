r"""Seeded random records of the tilt for `benchmarks/fitting.py`, from the reference integrators.

`draw_records(n, seed)` (`--table`, `--coverage`): viscous tops of the groups IIa, IIb, IIc, III
in turn, clean tilt from `tests/vector_reference.py`, each with the Cramer-Rao bound (CRB) of its
free parameters; a draw whose bound on mu, eps or spin exceeds `MAX_CRB_REL` of the value, or that
loses contact before 3 s, is redrawn. `law_record(seed, i, attempt)` (`--laws`): the friction laws
`LAWS[i % 3]` over the groups, from `tests/real_top_reference.py` (ball on the table, no stem).
tippejax is used only for `classify` and `thresholds`, each checked against the paper's closed
forms. The ranges drawn are in `benchmarks/README.md` (`tests/test_vector_reference.py` checks
them). Records are cached per record under `CACHE_ROOT` (keyed by a hash of this file and of the
integrators), never in the repository.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import pathlib
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import real_top_reference as rr  # noqa: E402
import vector_reference as vr  # noqa: E402

VERSION, LAW_VERSION = 1, 2
GROUPS = ("IIa", "IIb", "IIc", "III")
LAWS = ("viscous", "hertz", "coulomb")  # --laws: record i obeys LAWS[i % 3]
N1_MAX = 150.0  # rad/s: spins up to 8 n1 = 1200 rad/s
UPRIGHT_FRACTION, GAP_FRACTION = 0.2, 1.0 / 3.0
# Central differences of solves sharing one step sequence converge as the step shrinks; 100x
# larger steps are not small enough on records whose bound is ~1e-5 of the value.
FD_STEPS = {
    "mu": ("rel", 1e-6),
    "eps": ("rel", 1e-6),
    "spin": ("rel", 1e-7),
    "theta_dot": ("abs", 1e-5),
}
CUT_ON = ("mu", "eps", "spin")  # max_crb_rel applies to these (theta_dot's bound is reported)
RTOL_DATA, RTOL_FD, LAW_RTOL = 1e-12, 1e-10, 1e-10
MAX_CRB_REL = 0.005
CONTENSOU_SLIP_SCALE = 1e-5
CACHE_ROOT = pathlib.Path(
    os.environ.get("TIPPEJAX_BENCH_CACHE", pathlib.Path.home() / ".cache" / "tippejax-bench")
)
_ARRAYS = ("ts", "theta_clean", "theta_obs")


def _classify_numpy(a, e):
    """Group of tops with A/C = a, eps/R = e (paper Sec. 5), numpy; used to cross-check tj."""
    a, e = np.asarray(a, float), np.asarray(e, float)
    disc = 1.0 - a - e**2
    with np.errstate(invalid="ignore", divide="ignore"):
        x_b = (e - np.sqrt(3.0) / 3.0 * np.sqrt(a) * np.sqrt(np.where(disc > 0, disc, 1.0))) / (
            np.where(disc > 0, 1.0 - a, 1.0)
        )
    out = np.where(
        disc > 0, np.where(np.abs(x_b) < 1, "IIa", np.where(x_b < -1, "IIc", "IIb")), "IIb"
    ).astype(object)
    out[a - 1.0 > e] = "III"
    out[a - 1.0 < -e] = np.where(x_b[a - 1.0 < -e] < -1, "Ia", "Ib")
    return out


def _n1(p):
    """Turn-over threshold n1 (eq. n1): theta = 0 is unstable for |n| > n1 (Groups II, III)."""
    a, e = p["A"] / p["C"], p["eps"] / p["R"]
    return math.sqrt(p["m"] * p["g"] * p["eps"] / (p["C"] * (a - 1.0 + e))) * (1.0 - e)


def _draw_top(rng, group):
    """Draw top parameters in `group` (rejection on A/C, eps/R); returns (params, n1)."""
    import tippejax as tj

    for _ in range(100):
        k = 256
        a = rng.uniform(0.5, 1.6, k)
        e = rng.uniform(0.05, 0.5, k)
        m = np.exp(rng.uniform(math.log(0.005), math.log(0.06), k))
        R = rng.uniform(0.010, 0.030, k)
        C = 0.4 * m * R**2 * rng.uniform(0.8, 1.2, k)
        mu = np.exp(rng.uniform(math.log(0.05), math.log(2.0), k))
        top = tj.TippeTop(m=m, R=R, eps=e * R, A=a * C, C=C, g=9.81, mu=mu)
        groups = np.asarray(tj.classify(top)).astype(object)
        n1 = np.asarray(tj.thresholds(top).n1, float)
        if np.any(groups != _classify_numpy(a, e)):
            raise AssertionError("tj.classify disagrees with the paper's closed forms")
        ok = np.nonzero((groups == group) & (n1 < N1_MAX))[0]
        if ok.size:
            i = ok[0]
            params = dict(
                m=float(m[i]),
                R=float(R[i]),
                eps=float(e[i] * R[i]),
                A=float(a[i] * C[i]),
                C=float(C[i]),
                g=9.81,
                mu=float(mu[i]),
            )
            if abs(_n1(params) - n1[i]) > 1e-9 * n1[i]:
                raise AssertionError("tj.thresholds(top).n1 disagrees with eq. n1")
            return params, float(n1[i])
    raise RuntimeError(f"no top of group {group} drawn")


def _perturbed(params, launch, name, delta):
    p, lau = dict(params), dict(launch)
    if name in p:
        p[name] += delta
    else:
        lau[name] += delta
    return p, lau


def _truth_value(params, launch, name):
    return params[name] if name in params else launch[name]


def _fd_step(value, name, scale=1.0):
    kind, h = FD_STEPS[name]
    return scale * (h * abs(value) if kind == "rel" else h)


def sensitivities(params, launch, free, ts, *, rtol=RTOL_FD, step_scale=1.0):
    """theta at ts (nominal) and J = d theta / d p (len(ts), len(free)) by central differences,
    all solves in one batch (shared step sequence)."""
    plist, ylist, steps = [params], [vr.initial_vector(**launch)], []
    for name in free:
        h = _fd_step(_truth_value(params, launch, name), name, step_scale)
        steps.append(h)
        for sign in (1.0, -1.0):
            p, lau = _perturbed(params, launch, name, sign * h)
            plist.append(p)
            ylist.append(vr.initial_vector(**lau))
    ys, _ = vr.solve_batch(plist, ylist, ts, rtol=rtol, atol=rtol * 1e-2)
    a = ys[:, :, 4:7]
    theta = np.arctan2(np.hypot(a[..., 0], a[..., 1]), a[..., 2])  # (T, K)
    jac = np.stack(
        [(theta[:, 1 + 2 * j] - theta[:, 2 + 2 * j]) / (2 * h) for j, h in enumerate(steps)], axis=1
    )
    return theta[:, 0], jac


def cramer_rao(jac, sigma, mask, *, covariance=False):
    """sqrt(diag(F^-1)), F = J^T J / sigma^2 over the samples where mask is True (and F^-1 if
    `covariance`)."""
    J = jac[mask]
    fisher = J.T @ J / sigma**2
    cov = np.linalg.inv(fisher)
    std = np.sqrt(np.diag(cov))
    return (std, cov) if covariance else std


def _draw_one(seed, index, max_crb_rel):
    rng = np.random.default_rng([seed, index])
    group = GROUPS[index % len(GROUPS)]
    rejected = {"solver_failed": 0, "contact_lost_before_3s": 0, "crb_above_max": 0}
    # the record's kind is drawn once, so that redraws keep the mix of launches and gaps
    upright = bool(rng.uniform() < UPRIGHT_FRACTION)
    has_gap = bool(rng.uniform() < GAP_FRACTION)
    for attempt in range(200):
        params, n1 = _draw_top(rng, group)
        spin_factor = math.exp(rng.uniform(math.log(1.5), math.log(8.0)))
        spin = spin_factor * n1
        if upright:
            launch = dict(
                theta0=0.0, spin=spin, theta_dot=float(rng.uniform(0.2, 2.0)), phi_dot=0.0
            )
        else:
            launch = dict(
                theta0=float(rng.uniform(0.02, 0.5)), spin=spin, theta_dot=0.0, phi_dot=0.0
            )
        length = float(rng.uniform(3.0, 20.0))
        rate = float(math.exp(rng.uniform(math.log(20.0), math.log(500.0))))
        sigma = float(math.exp(rng.uniform(math.log(0.002), math.log(0.03))))
        gap_frac, gap_pos = float(rng.uniform(0.02, 0.10)), float(rng.uniform())
        noise_seed = int(rng.integers(2**31))
        ts = np.arange(int(math.floor(length * rate)) + 1) / rate
        try:
            sol = vr.solve(
                params,
                launch["theta0"],
                spin,
                ts,
                theta_dot=launch["theta_dot"],
                phi_dot=launch["phi_dot"],
                rtol=RTOL_DATA,
                atol=1e-14,
                stop_at_contact_loss=True,
            )
        except RuntimeError as err:
            rejected["solver_failed"] += 1
            print(f"record {index}: draw {attempt} rejected: {err}", file=sys.stderr)
            continue
        t_loss = sol["t_contact_loss"]
        bad = np.nonzero(~(sol["normal_force"] > 0))[0]
        if bad.size:
            t_loss = min(t_loss, ts[bad[0]]) if np.isfinite(t_loss) else ts[bad[0]]
        contact_lost = bool(np.isfinite(t_loss))
        keep = ts < t_loss if contact_lost else np.ones(ts.size, bool)
        if contact_lost and ts[keep][-1] < 3.0:
            rejected["contact_lost_before_3s"] += 1
            continue  # too short before the contact loss: redraw everything
        ts, theta_clean = ts[keep], sol["theta"][keep]
        normal = sol["normal_force"][keep]
        obs = theta_clean + sigma * np.random.default_rng(noise_seed).standard_normal(ts.size)
        gap = None
        if has_gap:
            n_gap = max(1, int(round(gap_frac * ts.size)))
            lo = int(round(0.05 * ts.size))
            hi = max(lo, int(round(0.95 * ts.size)) - n_gap)
            start = lo + int(round(gap_pos * (hi - lo)))
            obs[start : start + n_gap] = np.nan
            gap = (float(ts[start]), float(ts[min(start + n_gap, ts.size) - 1]))
        free = ("mu", "eps", "spin") + (("theta_dot",) if upright else ())
        truth = {name: float(_truth_value(params, launch, name)) for name in free}
        theta_fd, jac = sensitivities(params, launch, free, ts)
        mask = np.isfinite(obs)
        crb, cov = cramer_rao(jac, sigma, mask, covariance=True)
        crb_rel = {k: float(c / abs(truth[k])) for k, c in zip(free, crb)}
        if max_crb_rel is not None and max(crb_rel[k] for k in CUT_ON) > max_crb_rel:
            rejected["crb_above_max"] += 1
            continue  # the data do not pin the parameters down: redraw everything
        t_inv = sol["t_invert"]
        return dict(
            index=index,
            seed=seed,
            group=group,
            params=params,
            n1=n1,
            spin_over_n1=spin_factor,
            launch=launch,
            upright=upright,
            ts=ts,
            theta_clean=theta_clean,
            theta_obs=obs,
            sigma=sigma,
            rate_hz=rate,
            length_s=float(ts[-1]),
            gap=gap,
            free=free,
            truth=truth,
            crb=dict(zip(free, map(float, crb))),
            crb_rel=crb_rel,
            crb_cov=cov.tolist(),
            crb_corr=(cov / np.outer(crb, crb)).tolist(),
            t_invert=None if not np.isfinite(t_inv) or t_inv > ts[-1] else float(t_inv),
            contact_lost=contact_lost,
            t_contact_loss=float(t_loss) if contact_lost else None,
            min_normal_force=float(normal.min()),
            fd_data_gap=float(np.max(np.abs(theta_fd - theta_clean))),
            attempts=attempt + 1,
            rejected=rejected,
            max_crb_rel=max_crb_rel,
        )
    raise RuntimeError(
        f"record {index}: no draw in 200 kept contact for 3 s with crb_rel <= {max_crb_rel}"
    )


def _source_hash(reference) -> str:
    h = hashlib.sha256()
    for path in (pathlib.Path(__file__), pathlib.Path(reference.__file__)):
        h.update(path.read_bytes())
    return h.hexdigest()[:12]


def _save(path, rec):
    """A record (None: a rejected attempt) as .npz: its arrays and its metadata as JSON."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp, arrays = path.with_suffix(".tmp.npz"), {} if rec is None else {k: rec[k] for k in _ARRAYS}
    meta = None if rec is None else {k: v for k, v in rec.items() if k not in _ARRAYS}
    np.savez(tmp, meta=np.array(json.dumps(meta)), **arrays)
    os.replace(tmp, path)


def _load(path):
    with np.load(path, allow_pickle=False) as f:
        rec = json.loads(str(f["meta"]))
        if rec is not None:
            rec.update({k: f[k] for k in _ARRAYS})
    return rec


def draw_records(n: int, seed: int, *, max_crb_rel=MAX_CRB_REL, cache=True, verbose=False):
    """Records 0..n-1 of `seed`, cached per record; `max_crb_rel` None keeps every draw.

    Each record: group, params (m, R, eps, A, C, g, mu), n1, spin_over_n1, launch (theta0, spin,
    theta_dot, phi_dot), upright, ts, theta_clean, theta_obs (noise, gap as NaN), sigma, rate_hz,
    length_s, gap ((t_start, t_end) or None), free, truth, crb (per free parameter), crb_rel,
    crb_cov, crb_corr, t_invert, contact_lost, t_contact_loss, min_normal_force."""
    if not (isinstance(n, int) and n >= 0):
        raise ValueError(f"n must be a non-negative int, got {n!r}")
    if not isinstance(seed, int):
        raise ValueError(f"seed must be an int, got {seed!r}")
    cut = "all" if max_crb_rel is None else f"crb{max_crb_rel:g}"
    folder = CACHE_ROOT / f"fit_records-v{VERSION}-{_source_hash(vr)}" / f"seed{seed}-{cut}"
    records = []
    for index in range(n):
        path = folder / f"{index:05d}.npz"
        if cache and path.exists():
            rec = dict(_load(path), from_cache=True)
        else:
            if not (vr.HAVE_NUMBA or records or index):
                print("fit_records: without numba the reference runs far slower", file=sys.stderr)
            t0 = time.perf_counter()
            rec = dict(_draw_one(seed, index, max_crb_rel), seconds=time.perf_counter() - t0)
            if cache:
                _save(path, rec)
                rec = _load(path)
            if verbose:
                print(f"  record {index}: {rec['group']}, {rec['seconds']:.2f} s", file=sys.stderr)
        rec["free"] = tuple(rec["free"])
        rec["gap"] = tuple(rec["gap"]) if rec["gap"] is not None else None
        records.append(rec)
    return records


def law_draw(seed: int, index: int, attempt: int) -> dict:
    """What attempt `attempt` at law record `index` draws, before any integration: the top,
    its law, the launch, the sampling (`n` frames at `rate_hz`, the first one sample after the
    launch) and the noise. A caller can judge the draw (its Cramer-Rao bound) before paying
    for the record (`law_record`)."""
    rng = np.random.default_rng([seed, index, attempt, 58])
    law, group = LAWS[index % len(LAWS)], GROUPS[(index // len(LAWS)) % len(GROUPS)]
    params, n1 = _draw_top(rng, group)
    params.pop("mu")
    friction = dict(law=law)
    if law == "viscous":
        friction["mu"] = float(math.exp(rng.uniform(math.log(0.1), math.log(1.5))))
    else:
        friction["mu"] = float(rng.uniform(0.15, 0.5))
    if law == "hertz":
        friction["patch_radius"] = float(math.exp(rng.uniform(math.log(2e-4), math.log(1e-3))))
        friction["slip_scale"] = CONTENSOU_SLIP_SCALE
    if law == "coulomb":
        friction["slip_scale"] = float(math.exp(rng.uniform(math.log(3e-3), math.log(3e-2))))
    spin_factor = math.exp(rng.uniform(math.log(1.5), math.log(6.0)))
    theta0 = float(rng.uniform(0.05, 0.5))
    rate = float(math.exp(rng.uniform(math.log(30.0), math.log(240.0))))
    length = float(rng.uniform(2.0, 5.0))
    sigma = float(math.exp(rng.uniform(math.log(0.005), math.log(0.02))))
    noise_seed = int(rng.integers(2**31))
    return dict(
        index=index,
        seed=seed,
        attempt=attempt,
        law=law,
        group=group,
        params=params,
        friction=friction,
        n1=n1,
        spin_over_n1=spin_factor,
        launch=dict(theta0=theta0, spin=spin_factor * n1),
        rate_hz=rate,
        n=int(math.floor(length * rate)),
        sigma=sigma,
        noise_seed=noise_seed,
    )


def _draw_law(seed: int, index: int, attempt: int) -> dict | None:
    """Attempt `attempt` at law record `index` (`law_draw`) integrated by the reference; None
    if contact is lost before 2 s."""
    d = law_draw(seed, index, attempt)
    law, friction, n, rate, sigma = d["law"], d["friction"], d["n"], d["rate_hz"], d["sigma"]
    kw = dict(rho=friction.get("patch_radius", 5e-4), delta=friction.get("slip_scale", 1e-6))
    try:
        out = rr.solve(
            d["params"],
            law,
            d["launch"]["theta0"],
            d["launch"]["spin"],
            (n + 0.5) / rate,
            mu=friction["mu"],
            stem=False,
            contact="rigid",
            dt_sample=1.0 / rate,
            rtol=LAW_RTOL,
            **kw,
        )
    except RuntimeError as err:
        print(f"law record {index} attempt {attempt}: {err}", file=sys.stderr)
        return None
    t, theta = out["t"], out["theta"]
    keep = (t > 0.5 / rate) & (t <= n / rate + 1e-9)  # frames 1..n: the first after the launch
    ts, clean = t[keep], theta[keep]
    if ts.size < 2 or ts[-1] < 2.0:
        return None  # contact lost too early
    obs = clean + sigma * np.random.default_rng(d["noise_seed"]).standard_normal(ts.size)
    keys = ("index", "seed", "attempt", "law", "group", "params", "friction", "n1")
    return dict(
        {k: d[k] for k in keys},
        spin_over_n1=d["spin_over_n1"],
        launch=d["launch"],
        ts=ts,
        theta_clean=clean,
        theta_obs=obs,
        sigma=sigma,
        rate_hz=rate,
        length_s=float(ts[-1]),
        contact_lost=bool(ts[-1] < (n - 0.5) / rate),
        t_half=float(out["t_half"]),
    )


def law_record(seed: int, index: int, attempt: int) -> dict | None:
    """`_draw_law`, cached (a rejected attempt is cached as rejected)."""
    folder = CACHE_ROOT / f"fit_law_records-v{LAW_VERSION}-{_source_hash(rr)}" / f"seed{seed}"
    path = folder / f"{index:05d}-{attempt:03d}.npz"
    if not path.exists():
        _save(path, _draw_law(seed, index, attempt))
    return _load(path)
