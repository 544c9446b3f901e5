"""Trimming: a record's fit refitted on the part of the record the model describes."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .candidates import judge, merge, pack, refine
from .stages import Final
from .stages.windows import window_ends


def trim_records(setup, out, obs2, sigma):
    r"""Refit each record whose whole-record fit fails on the part of it the model describes.

    A fit of the whole record is distorted everywhere by a stretch the model cannot describe
    (a stem landing), so its own residuals do not say where the description ends. Instead the
    windows of `Windows` grow from the guess, each fitted from the last, while the residuals
    of the window pass the diagnostics; the last window that passes is trusted. Its parameters
    predict the rest of the record, and the windowed chi-square test of that prediction
    (`describes_until`) says how far the description reaches; the record is fitted again up to
    there, and kept if it passes (else the last window that passed is kept). Records whose
    whole-record fit passes are left as they are.
    """
    ts = setup.ts
    bsize = setup.bsize
    passed = np.array([v["passes"] for v in out["verdicts"]])
    ends = np.full(bsize, ts[-1])
    if passed.all():
        return out, ends

    def per_record(mask_b, a, b):  # a where mask_b, else b (u has shape (*batch, p))
        if not setup.batched:
            return a if bool(mask_b[0]) else b
        return jnp.where(jnp.asarray(mask_b)[:, None], a, b)

    def fit_to(u, fit_ends, stages):
        setup.fitted = ts[None, :] <= fit_ends[:, None] + 1e-12
        u, histories, counts, code = refine(u, setup, stages)
        cand = setup.finish(u, code, setup.data(tol=setup.tol, final=True))
        residuals, verdicts = judge(cand, setup, obs2, sigma)
        return u, cand, residuals, verdicts, histories, counts

    u = per_record(passed, out["u"], jnp.zeros_like(out["u"]))
    growing = ~passed
    u_ok, end_ok = u, np.where(passed, ts[-1], np.nan)
    histories, counts = [], []
    for end in window_ends(ts)[:-1]:
        if not growing.any():
            break
        fit_ends = np.where(growing, end, end_ok)
        fit_ends = np.where(np.isfinite(fit_ends), fit_ends, end)
        u, _, _, verdicts, hist, cnt = fit_to(u, fit_ends, (Final(final=False),))
        histories += hist
        counts += cnt
        ok = np.array([v["passes"] for v in verdicts])
        now_ok = growing & ok
        u_ok = per_record(now_ok, u, u_ok)
        end_ok = np.where(now_ok, end, end_ok)
        growing = growing & ok
    trimmed = ~passed & np.isfinite(end_ok)
    if not trimmed.any():
        return out, ends
    # How far does the last trusted window's description reach?
    setup.fitted = np.ones_like(setup.mask)
    reach = setup.finish(u_ok, out["out"]["result"], setup.data(tol=setup.tol, final=True))
    _, verdicts = judge(reach, setup, obs2, sigma)
    until = np.array([v["describes_until"] for v in verdicts])
    until = np.where(np.isfinite(until), np.maximum(until, end_ok), end_ok)
    fit_ends = np.where(trimmed, until, ts[-1])
    u, cand, residuals, verdicts, hist, cnt = fit_to(u_ok, fit_ends, (Final(final=False), Final()))
    ok = np.array([v["passes"] for v in verdicts])
    if np.any(trimmed & ~ok):  # the reach was too long: the last trusted window alone
        fit_ends = np.where(trimmed & ~ok, end_ok, fit_ends)
        u, cand, residuals, verdicts, hist2, cnt2 = fit_to(
            per_record(trimmed & ~ok, u_ok, u), fit_ends, (Final(),)
        )
        hist += hist2
        cnt += cnt2
    histories += hist
    counts += cnt
    steps = np.asarray(sum(np.asarray(c) for c in counts)).reshape(-1)
    new = dict(
        out=cand,
        residuals=residuals,
        verdicts=verdicts,
        u=u,
        history=pack(histories, counts, bsize, setup.cfg.max_steps),
        loss=np.asarray(cand["loss"]).reshape(-1),
        starts=out["starts"],
        num_steps=out["num_steps"] + steps,
        describes=np.array([v["describes_until"] for v in verdicts]),
    )
    if (~trimmed).any():  # records not trimmed keep their whole-record fit
        new = merge(out, new, ~trimmed, bsize)
    return new, np.where(trimmed, fit_ends, ts[-1])
