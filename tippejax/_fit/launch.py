"""Is a failed fit's launch time wrong? A score test of freeing `t0` at the fit."""

from __future__ import annotations

import numpy as np

from .candidates import passing
from .diagnostics import FALSE_ALARM, _chi2_quantile

SHARE = 0.5
"""A failed fit is put down to its launch time when freeing it would remove at least this share
of the residuals' excess over the noise (and a significant amount, at `FALSE_ALARM`)."""


def launch_time_suspects(setup, best, sigma) -> np.ndarray:
    r"""Per record, whether a fit whose residuals fail the diagnostics would pass, to first
    order, if its launch time were free.

    The score (Lagrange multiplier) test of one more parameter: with $r$ the weighted residuals
    at the fit, $J$ their Jacobian in the free coordinates and $j$ the column of the launch
    time $t_0$ (the motion shifted in time), freeing $t_0$ and refitting the others lowers the
    residual sum of squares, to first order, by

    $$\Delta = \frac{(r^\top P j)^2}{j^\top P j},\qquad P = 1 - J (J^\top J)^{-1} J^\top.$$

    The launch time is the likely cause when $\Delta/s^2$ exceeds the chi-square quantile of
    one degree of freedom at `FALSE_ALARM` and at least `SHARE` of the excess
    $\mathrm{RSS}/s^2 - (N - p)$, with $s$ = `sigma` or the fit's noise estimate. Evaluated only
    for failing records of a fit whose `t0` is not free (one more compiled evaluation with
    `t0` free); the others get False.
    """
    out = np.zeros(setup.bsize, bool)
    failing = ~passing(best)
    if "t0" in setup.cfg.free or not failing.any():
        return out
    idx = np.flatnonzero(failing)
    sub = setup if idx.size == setup.bsize else setup.subset(idx)
    ext = sub.with_free(setup.cfg.free + ("t0",))
    p = len(setup.cfg.free)
    u = np.asarray(best["u"]).reshape(setup.bsize, p)[idx]
    u = np.concatenate([u, np.zeros((idx.size, 1))], axis=1)
    value, jac, _ = ext.evaluate(u if ext.batched else u[0], ext.data(tol=ext.tol, final=True))
    value = np.asarray(value).reshape(idx.size, -1)
    jac = np.asarray(jac).reshape(idx.size, value.shape[1], p + 1)
    for k, b in enumerate(idx):
        r, others, column = value[k], jac[k, :, :p], jac[k, :, p]
        coef, *_ = np.linalg.lstsq(others, column, rcond=None)
        column = column - others @ coef  # the part of j the other parameters cannot make
        norm = float(column @ column)
        if not norm > 0:
            continue
        drop = float(r @ column) ** 2 / norm
        used = setup.mask[b] & setup.fitted[b]
        noise = sigma if sigma is not None else best["verdicts"][b]["noise"]
        s2 = noise**2 * float(np.mean(setup.w[b][used]))
        n = int(used.sum())
        excess = float(r @ r) / s2 - (n - p)
        out[b] = drop / s2 > max(_chi2_quantile(1.0 - FALSE_ALARM, 1), SHARE * excess)
    return out
