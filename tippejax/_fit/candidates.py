"""A fit's candidates: a start refined through a chain of stages, judged, and compared per record."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._cache import to_device
from . import diagnostics
from .result import FIT_RESULTS


def refine(u, setup, stages):
    """Run a chain of stages from the coordinates `u`: `(u, histories, counts, code)` at its
    end."""
    histories, counts, code = [], [], None
    for stage in stages:
        run = stage.run(u, setup)
        u, code = run.u, run.code
        histories += run.histories
        counts += run.counts
    return u, histories, counts, code


def judge(out, setup, obs2, sigma):
    """Diagnostics of each record's residuals over the samples the fit used."""
    theta_fit = np.asarray(out["theta_fit"]).reshape(obs2.shape[0], -1)[:, : obs2.shape[1]]
    residuals = theta_fit - obs2
    verdicts = []
    for b in range(setup.bsize):
        used = setup.mask[b] & setup.fitted[b]
        r = np.where(used, residuals[b], np.nan)
        verdicts.append(diagnostics.describes(r, setup.ts, sigma))
    return residuals, verdicts


def candidate(setup, refined, obs2, sigma):
    """A refined start (`refine`'s output) finished and judged: the dict `better` and
    `select` compare, and the steps it took per record."""
    u, histories, counts, code = refined
    out = setup.finish(u, code, setup.data(tol=setup.tol, final=True))
    residuals, verdicts = judge(out, setup, obs2, sigma)
    steps = np.asarray(sum(np.asarray(c) for c in counts)).reshape(-1)
    cand = dict(
        out=out,
        residuals=residuals,
        verdicts=verdicts,
        u=u,
        history=pack(histories, counts, setup.bsize, setup.cfg.max_steps),
        loss=np.asarray(out["loss"]).reshape(-1),
    )
    return cand, steps


def start_point(setup):
    """The guess's coordinates (all 0: each coordinate is relative to the guess)."""
    p = len(setup.cfg.free)
    return to_device(np.zeros((setup.bsize, p) if setup.batched else (p,)), jnp.result_type(float))


def passing(cand) -> np.ndarray:
    """Per record, whether the candidate's residuals pass the diagnostics."""
    return np.array([v["passes"] for v in cand["verdicts"]])


def widen(cand, idx, bsize, batched):
    """A candidate of the records `idx` of a batch (`candidate`'s dict of a `subset`) as one of
    the whole batch: the other records hold placeholders (loss inf, failing verdicts) that
    `better` never picks over a fit and any later fit replaces."""
    pos = np.zeros(bsize, int)
    pos[idx] = np.arange(idx.size)
    inside = np.zeros(bsize, bool)
    inside[idx] = True

    def rows(x):
        x = np.asarray(x)
        return (x if batched else x[None])[pos]

    def device_rows(x):
        return to_device(rows(x), x.dtype)

    failing = dict(cand["verdicts"][0], passes=False)
    return dict(
        out=jax.tree_util.tree_map(device_rows, cand["out"]),
        residuals=np.asarray(cand["residuals"])[pos],
        verdicts=[cand["verdicts"][pos[b]] if inside[b] else failing for b in range(bsize)],
        u=device_rows(cand["u"]),
        history=np.asarray(cand["history"])[pos],
        loss=np.where(inside, np.asarray(cand["loss"])[pos], np.inf),
    )


def flag(code, where, new, over=(FIT_RESULTS.successful,)):
    """`code` (a `FIT_RESULTS` item, one per record) set to `new` where `where` holds and the
    code is one of `over` (default: `successful` only); in numpy (no small programs to
    compile in a new process)."""
    value = np.asarray(code._value)
    replaceable = np.isin(value, np.asarray([item._value for item in over]))
    hit = np.asarray(where, bool) & replaceable
    flagged = np.where(hit, np.asarray(new._value), value).astype(value.dtype)
    return eqx.tree_at(lambda c: c._value, code, to_device(flagged))


def select(a, b, take_b, bsize):
    """Per record of a batch, the fit in `b` where `take_b`, else the one in `a` (dicts of
    `fit.fit_starts`; keys both have). Loss histories of different lengths are nan-padded."""
    pick = np.asarray(take_b)
    take = lambda x, y: jnp.where(  # noqa: E731
        jnp.asarray(pick).reshape((bsize,) + (1,) * (jnp.ndim(x) - 1)), y, x
    )
    width = max(a["history"].shape[-1], b["history"].shape[-1])

    def wide(h):
        return np.pad(h, ((0, 0), (0, width - h.shape[-1])), constant_values=np.nan)

    out = dict(
        out=jax.tree_util.tree_map(take, a["out"], b["out"]),
        residuals=np.where(pick[:, None], b["residuals"], a["residuals"]),
        verdicts=[b["verdicts"][i] if pick[i] else a["verdicts"][i] for i in range(bsize)],
        history=np.where(pick[:, None], wide(b["history"]), wide(a["history"])),
        u=take(a["u"], b["u"]),
    )
    for key in ("loss", "num_steps", "describes"):
        if key in a and key in b:
            out[key] = np.where(pick, b[key], a[key])
    return out


def merge(a, b, keep_a, bsize):
    """Per record of a batch, `a` where `keep_a`, else `b`."""
    return dict(select(a, b, ~np.asarray(keep_a), bsize), starts=a["starts"])


def better(a, b, bsize):
    """Per record, the fit with the lower loss (the least-squares estimate is the lowest
    minimum found; the diagnostics only say whether to trust it)."""
    # (a loss of inf in `a` is a placeholder of `widen` or a failed fit: any fit replaces it)
    pick = np.array([b["loss"][i] < a["loss"][i] or a["loss"][i] == np.inf for i in range(bsize)])
    if not pick.any():
        a["starts"] = b["starts"]
        return a
    if pick.all():
        return b
    return dict(select(a, b, pick, bsize), starts=b["starts"])


def pack(histories, counts, bsize, max_steps):
    """Each optimisation's losses one after the other, nan-padded to a fixed length."""
    hist = np.concatenate([np.asarray(h) for h in histories], axis=-1).reshape(
        bsize, len(histories), max_steps
    )
    cnt = np.stack([np.asarray(c) for c in counts], -1).reshape(bsize, -1)
    packed = np.full((bsize, len(histories) * max_steps), np.nan)
    for b in range(bsize):
        row = np.concatenate([hist[b, s, : cnt[b, s]] for s in range(len(histories))])
        packed[b, : row.size] = row
    return packed
