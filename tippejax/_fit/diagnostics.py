r"""Is what is left after a fit noise? Tests of the residuals, in numpy, after each fit.

A least-squares fit reports standard errors that hold only if the residuals are the noise:
independent, of one variance, with nothing left of the signal. A fit in a wrong valley of the
loss (the nutation's phase slipped by a cycle, a wrong envelope) leaves signal in the residuals,
and so does a record the model does not describe to its end (a real top whose stem lands).
Two tests catch them, each at a small false-alarm rate $\alpha$:

- **Runs test** (Wald and Wolfowitz) on the signs of the residuals in time order: with $n_+$
  positive and $n_-$ negative residuals ($n = n_+ + n_-$) and $R$ runs of one sign, under
  independence $E[R] = \mu = 2 n_+ n_- / n + 1$ and $\mathrm{Var}[R] = (\mu - 1)(\mu - 2)/(n - 1)$;
  $z = (R - \mu)/\sqrt{\mathrm{Var}[R]}$ is about standard normal. Left-over signal makes long
  runs ($z \ll 0$); an aliased oscillation near the sampling rate, short ones ($z \gg 0$).
- **Windows** of the record: with $W$ windows of $n_w$ samples and mean squares $s_w^2$, under
  the null $n_w s_w^2/\sigma^2 \sim \chi^2_{n_w}$. A window whose $s_w^2/\sigma^2$ exceeds the
  $1 - \alpha/W$ quantile (Bonferroni over the windows) is not described. $\sigma$ is the
  given noise, or the median of the $s_w$ (robust while at least half the windows are
  described), corrected by the median of $\chi^2_{n_w}/n_w$.

- **Ljung-Box test** of the autocorrelations $\rho_k$ of the residuals (in time order, the
  finite ones) at lags $k = 1..h$: $Q = n(n+2)\sum_k \rho_k^2/(n-k) \sim \chi^2_h$ under
  independence. Left-over nutation sampled below its frequency is an aliased oscillation: its
  signs can look random to the runs test, but it is strongly autocorrelated at some lags.

None needs the noise level; the windows also give `describes_until`, the end of the last
window before the first that is not described.
"""

from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np

FALSE_ALARM = 1e-3
_WINDOW_SAMPLES = 40  # at least this many samples per window
_MAX_WINDOWS = 16


def runs_z(residuals: np.ndarray) -> float:
    """z-score of the runs test on the signs of the finite, non-zero residuals (nan if < 20)."""
    r = residuals[np.isfinite(residuals) & (residuals != 0)]
    if r.size < 20:
        return float("nan")
    positive = r > 0
    n_pos = int(positive.sum())
    n_neg = r.size - n_pos
    if n_pos == 0 or n_neg == 0:
        return -float("inf")
    runs = 1 + int(np.sum(positive[1:] != positive[:-1]))
    n = r.size
    mu = 2.0 * n_pos * n_neg / n + 1.0
    var = (mu - 1.0) * (mu - 2.0) / (n - 1.0)
    return float((runs - mu) / math.sqrt(max(var, 1e-300)))


def _chi2_quantile(p: float, nu: float) -> float:
    """Quantile of chi-square with nu degrees of freedom (Wilson-Hilferty)."""
    z = NormalDist().inv_cdf(p)
    a = 2.0 / (9.0 * nu)
    return nu * (1.0 - a + z * math.sqrt(a)) ** 3


def window_test(
    ts: np.ndarray, residuals: np.ndarray, sigma: float | None, *, reference: str = "median"
):
    """Mean squares of the residuals in windows, the noise level, and the end of the record
    the model describes.

    Returns `(noise, describes_until, bad)`: `bad` is True for each window whose mean square
    is too large for noise of level `noise`.
    """
    finite = np.isfinite(residuals)
    idx = np.nonzero(finite)[0]
    if idx.size < 2 * _WINDOW_SAMPLES:
        rms = float(np.sqrt(np.mean(residuals[finite] ** 2))) if idx.size else float("nan")
        noise = float(sigma) if sigma is not None else rms
        return noise, float(ts[-1]), np.zeros(1, bool)
    windows = int(min(_MAX_WINDOWS, idx.size // _WINDOW_SAMPLES))
    groups = np.array_split(idx, windows)
    counts = np.array([g.size for g in groups], float)
    ms = np.array([np.mean(residuals[g] ** 2) for g in groups])
    nu = float(np.median(counts))
    if sigma is None and reference == "quietest":
        # the quietest window, corrected by the expected minimum of `windows` chi-square draws
        q = _chi2_quantile(0.5 / windows, nu) / nu
        noise = math.sqrt(float(np.min(ms)) / q)
    elif sigma is None:
        noise = math.sqrt(float(np.median(ms)) / (_chi2_quantile(0.5, nu) / nu))
    else:
        noise = float(sigma)
    limit = np.array([_chi2_quantile(1.0 - FALSE_ALARM / windows, c) / c for c in counts])
    bad = ms / noise**2 > limit
    if not bad.any():  # described up to the last sample the fit used
        return noise, float(ts[idx[-1]]), bad
    first = int(np.argmax(bad))
    until = float(ts[groups[first - 1][-1]]) if first > 0 else float(ts[groups[0][0]])
    return noise, until, bad


def ljung_box(residuals: np.ndarray, lags: int = 20) -> tuple[float, float]:
    """Ljung-Box statistic Q of the finite residuals and its rejection threshold (nan if < 50)."""
    r = residuals[np.isfinite(residuals)]
    n = r.size
    if n < 50:
        return float("nan"), float("nan")
    h = int(min(lags, n // 10))
    r = r - r.mean()
    denom = float(np.sum(r * r))
    if denom == 0.0:
        return 0.0, 1.0
    rho = np.array([np.sum(r[k:] * r[:-k]) / denom for k in range(1, h + 1)])
    q = float(n * (n + 2) * np.sum(rho**2 / (n - np.arange(1, h + 1))))
    return q, _chi2_quantile(1.0 - FALSE_ALARM, h)


def runs_limit() -> float:
    """|z| above which the runs test rejects independence (two-sided, at `FALSE_ALARM`)."""
    return NormalDist().inv_cdf(1.0 - FALSE_ALARM / 2.0)


def describes(residuals: np.ndarray, ts: np.ndarray, sigma: float | None) -> dict:
    """All diagnostics of one record's residuals (over the samples the fit used)."""
    z = runs_z(residuals)
    q, q_limit = ljung_box(residuals)
    noise, until, bad = window_test(ts, residuals, sigma)
    finite = np.isfinite(residuals)
    rms = float(np.sqrt(np.mean(residuals[finite] ** 2))) if finite.any() else float("nan")
    white = not (abs(z) > runs_limit()) and not (q > q_limit)
    passes = bool(white and not bad.any())
    if sigma is not None and finite.sum() > 0:
        # The given noise level: the mean square must not exceed it beyond chance.
        n = int(finite.sum())
        passes = passes and rms**2 / sigma**2 <= _chi2_quantile(1.0 - FALSE_ALARM, n) / n
    if not passes and until >= ts[-1]:
        # Not noise, and no window stands out against the median: a fit distorted everywhere
        # (by a stretch the model cannot describe). Judge the windows against the quietest one
        # to find where the description ends (what trim=True refits on).
        until = window_test(ts, residuals, sigma, reference="quietest")[1]
    return dict(
        runs_z=z,
        ljung_box=q / q_limit if np.isfinite(q) else float("nan"),
        noise=noise,
        describes_until=until,
        rms=rms,
        passes=passes,
    )


def chi2_sf(x: float, nu: float) -> float:
    r"""$P(\chi^2_\nu > x)$, the upper tail of chi-square with $\nu$ degrees of freedom: the
    regularised upper incomplete gamma function $Q(\nu/2, x/2)$, by its series below
    $x/2 < \nu/2 + 1$ and its continued fraction above (Lentz's method), to about 1e-14
    relative."""
    if not x > 0:
        return 1.0
    if not math.isfinite(x):
        return 0.0
    a, z = 0.5 * nu, 0.5 * x
    log_prefactor = a * math.log(z) - z - math.lgamma(a)
    if z < a + 1.0:  # P(a, z) by its series, Q = 1 - P
        term = total = 1.0 / a
        for k in range(1, 100_000):
            term *= z / (a + k)
            total += term
            if term < total * 1e-16:
                break
        return max(0.0, 1.0 - math.exp(log_prefactor) * total)
    tiny = 1e-300  # Q(a, z) by its continued fraction (modified Lentz)
    b = z + 1.0 - a
    c, d = 1.0 / tiny, 1.0 / b
    h = d
    for k in range(1, 100_000):
        an = -k * (k - a)
        b += 2.0
        d = an * d + b
        d = tiny if abs(d) < tiny else d
        c = b + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        step = d * c
        h *= step
        if abs(step - 1.0) < 1e-16:
            break
    return math.exp(log_prefactor) * h
