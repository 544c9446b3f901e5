r"""Seeded random records of tops with every friction law, for `fitting.py --laws` (issue 58).

The clean tilt comes from `tests/real_top_reference.py` (Newton-Euler in the space frame, numpy,
scipy and numba; its own friction laws, the Hertz disc by quadrature; no tippejax physics), with
the ball held on the table (`contact="rigid"`, no stem). tippejax is imported only for
`classify` and `thresholds` (through `fit_records._draw_top`, which checks both against the
paper's closed forms).

How a record is drawn (record i of seed s, attempt k uses `default_rng([s, i, k, 58])`; the
caller, `fitting.py --laws`, moves to the next attempt while a record fails its filter):

- Law: `LAWS[i % 3]`, the viscous law, Coulomb-Contensou with the Hertz pressure, and the
  regularised Coulomb law in turn. Group: `GROUPS[(i // 3) % 4]`, so that every law meets every
  group. (The ellipse pressure of Coulomb-Contensou approximates the Hertz law; telling the two
  apart is not what a user asks of a record, and each law compared costs a fit per record.)
- Top: as `fit_records._draw_top` (A/C, eps/R of the group, n1 < 150 rad/s; m 5-60 g, R 10-30
  mm). The law's parameters: the viscous mu log-uniform in 0.1-1.5 s/m; the Coulomb laws' mu
  uniform in 0.15-0.5 (dimensionless); the patch radius log-uniform in 0.2-1 mm; slip scale
  1e-5 m/s for the Contensou laws (converged: `docs/friction.md`), log-uniform in 3e-3 to 3e-2
  m/s for the Coulomb law (its rise is creep below the slip scale: the law is defined by it).
- Launch: theta0 uniform in (0.05, 0.5) rad with w = n0 a, n0 = k n1 with k log-uniform in
  (1.5, 6).
- Camera: rate log-uniform in 30-240 Hz, length uniform in 2-5 s, noise sigma log-uniform in
  0.005-0.02 rad. The first frame is one sample after the launch (t = 1/rate, 2/rate, ...), as
  a camera started before the release sees it; fits launch at t0 = 0.
- Contact loss (the rigid phase ends where R_n would turn negative): the record ends before it
  if that leaves >= 2 s, else the attempt is rejected.

Records are cached under ~/.cache/tippejax-bench/ (one .npz per attempt, keyed by a hash of this
file and of the reference model); nothing there is committed.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import pathlib
import sys

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))
import fit_records as fr  # noqa: E402
import real_top_reference as rr  # noqa: E402

VERSION = 2
LAWS = ("viscous", "hertz", "coulomb")
GROUPS = fr.GROUPS
CONTENSOU_SLIP_SCALE = 1e-5
RTOL = 1e-10
MIN_LENGTH = 2.0
CACHE_ROOT = fr.CACHE_ROOT
_ARRAYS = ("ts", "theta_clean", "theta_obs")


def law_of(index: int) -> str:
    return LAWS[index % len(LAWS)]


def group_of(index: int) -> str:
    return GROUPS[(index // len(LAWS)) % len(GROUPS)]


def draw(seed: int, index: int, attempt: int) -> dict | None:
    """One attempt at record `index` of `seed`: a dict, or None if it is rejected (contact lost
    before `MIN_LENGTH` s, or the reference failed)."""
    rng = np.random.default_rng([seed, index, attempt, 58])
    law, group = law_of(index), group_of(index)
    params, n1 = fr._draw_top(rng, group)
    params.pop("mu")
    friction = dict(law=law)
    if law == "viscous":
        friction["mu"] = float(math.exp(rng.uniform(math.log(0.1), math.log(1.5))))
    else:
        friction["mu"] = float(rng.uniform(0.15, 0.5))
    if law in ("hertz", "ellipse"):
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
    n = int(math.floor(length * rate))
    try:
        out = rr.solve(
            params,
            law,
            theta0,
            spin_factor * n1,
            (n + 0.5) / rate,
            mu=friction["mu"],
            rho=friction.get("patch_radius", 5e-4),
            delta=friction.get("slip_scale", 1e-6),
            stem=False,
            contact="rigid",
            dt_sample=1.0 / rate,
            rtol=RTOL,
        )
    except RuntimeError as err:
        print(f"law record {index} attempt {attempt}: {err}", file=sys.stderr)
        return None
    t, theta = out["t"], out["theta"]
    keep = (t > 0.5 / rate) & (t <= n / rate + 1e-9)  # frames 1..n: the first after the launch
    ts, clean = t[keep], theta[keep]
    if ts.size < 2 or ts[-1] < MIN_LENGTH:
        return None  # contact lost too early
    obs = clean + sigma * np.random.default_rng(noise_seed).standard_normal(ts.size)
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
        ts=ts,
        theta_clean=clean,
        theta_obs=obs,
        sigma=sigma,
        rate_hz=rate,
        length_s=float(ts[-1]),
        contact_lost=bool(ts[-1] < (n - 0.5) / rate),
        t_half=float(out["t_half"]),
    )


def _source_hash() -> str:
    h = hashlib.sha256()
    for path in (pathlib.Path(__file__), pathlib.Path(rr.__file__)):
        h.update(path.read_bytes())
    return h.hexdigest()[:12]


def cache_dir(seed: int) -> pathlib.Path:
    return CACHE_ROOT / f"fit_law_records-v{VERSION}-{_source_hash()}" / f"seed{seed}"


def record(seed: int, index: int, attempt: int) -> dict | None:
    """`draw`, cached (a rejected attempt is cached as rejected)."""
    path = cache_dir(seed) / f"{index:05d}-{attempt:03d}.npz"
    if path.exists():
        with np.load(path, allow_pickle=False) as f:
            meta = json.loads(str(f["meta"]))
            if meta is None:
                return None
            for k in _ARRAYS:
                meta[k] = f[k]
        return meta
    rec = draw(seed, index, attempt)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    if rec is None:
        np.savez(tmp, meta=np.array(json.dumps(None)))
    else:
        meta = {k: v for k, v in rec.items() if k not in _ARRAYS}
        np.savez(tmp, meta=np.array(json.dumps(meta)), **{k: rec[k] for k in _ARRAYS})
    os.replace(tmp, path)
    return record(seed, index, attempt)
