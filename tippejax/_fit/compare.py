"""`compare_laws`: which friction law a record of the tilt rules out, and which it prefers."""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import numpy as np
from jaxtyping import ArrayLike

from .._friction.base import AbstractFriction
from .._state import State
from .._top import TippeTop
from . import diagnostics
from .fit import fit
from .inputs import FIT_MODELS, check_law, check_model
from .params import LAW_FIELDS, identifiable, law_options, units
from .result import FitResult

SEARCHES = ("shared", "every")
"""How `compare_laws` spends `fit`'s search for starts over the laws (`search=`)."""

CRITERIA = ("bic", "aic")
"""The information criteria `compare_laws(criterion=...)` ranks the laws by."""

LEVEL = 1e-3
"""The default level of `compare_laws`'s chi-square test (the false-alarm rate of the fit's own
tests of its residuals)."""


def law_name(law: AbstractFriction) -> str:
    """A short name of a law: its class, with its static options (`CoulombContensou(hertz)`)."""
    options = ", ".join(str(v) for _, v in law_options(law))
    return type(law).__name__ + (f"({options})" if options else "")


class LawComparison(eqx.Module):
    r"""The result of `compare_laws`: one fit per friction law of one record, and the verdict.

    `print(comparison)` shows the table (`table()`); `comparison.preferred` is the law the
    record prefers (the fitted law, or None when it rules out every law), `ruled_out_names`
    the laws it rules out.

    **Fields** (one entry per law, in the order given):

    - `names`: the laws' short names (`law_name`).
    - `fits`: the `FitResult` of each law (`fits[i].top.friction` is the fitted law).
    - `searched`: whether the law's fit ran `fit`'s whole strategy (its search for starts);
      with `search="shared"` a law is searched only while no law has passed (see
      `compare_laws`).
    - `num_params`: $k$, the free parameters of each fit; `num_samples`: $N$, the samples used.
    - `rss`: $\sum_k w_k r_k^2$ over the record ($w_k = 1$ without `weights`).
    - `sigma`: the noise level $s$ the record is judged against: the given `sigma`, or, if
      none was given, $\hat s^2 = \min_l \mathrm{RSS}_l/(N - k_l)$ (`sigma_given` says which).
    - `chi2` $= \mathrm{RSS}/s^2$, with `dof` $= N - k$ degrees of freedom, and `p_value`
      $= P(\chi^2_{N-k} > \chi^2)$: the chance of residuals at least this large if the law
      were right and the noise Gaussian of level $s$.
    - `white`: whether the fit's residuals pass its tests of independence and of their level
      in windows of the record (`fit`'s runs test, Ljung-Box and windowed chi-square, each at
      a false-alarm rate of 1e-3).
    - `deviance`: $-2\ln L$ up to a constant shared by the laws: $\chi^2$ with a known
      `sigma`, $N\ln(\mathrm{RSS}/N)$ (the likelihood maximised over the noise level) without.
    - `aic` $=$ deviance $+ 2k$, `bic` $=$ deviance $+ k\ln N$.
    - `likelihood_ratio`: $2\ln(L_{best}/L_l)$ = deviance $-$ the lowest deviance ($\ge 0$).
    - `ruled_out`: `p_value < level` or not `white` (the rule of `compare_laws`).
    - `preferred_index`: the law with the lowest `criterion` among those not ruled out; -1
      when the record rules out every law.
    """

    names: tuple[str, ...] = eqx.field(static=True)
    fits: tuple[FitResult, ...]
    searched: np.ndarray
    num_params: np.ndarray
    num_samples: int = eqx.field(static=True)
    rss: np.ndarray
    sigma: float = eqx.field(static=True)
    sigma_given: bool = eqx.field(static=True)
    chi2: np.ndarray
    dof: np.ndarray
    p_value: np.ndarray
    white: np.ndarray
    deviance: np.ndarray
    aic: np.ndarray
    bic: np.ndarray
    likelihood_ratio: np.ndarray
    ruled_out: np.ndarray
    preferred_index: int = eqx.field(static=True)
    level: float = eqx.field(static=True)
    criterion: str = eqx.field(static=True)

    @property
    def laws(self) -> tuple[AbstractFriction, ...]:
        """The fitted laws (`fits[i].top.friction`)."""
        return tuple(f.top.friction for f in self.fits)

    @property
    def preferred(self) -> AbstractFriction | None:
        """The fitted law the record prefers, or None if it rules out every law."""
        return None if self.preferred_index < 0 else self.laws[self.preferred_index]

    @property
    def preferred_name(self) -> str | None:
        """The name of the preferred law, or None."""
        return None if self.preferred_index < 0 else self.names[self.preferred_index]

    @property
    def ruled_out_names(self) -> tuple[str, ...]:
        """The names of the laws the record rules out."""
        return tuple(n for n, out in zip(self.names, self.ruled_out) if out)

    def table(self) -> str:
        """The comparison as a text table: per law its fitted parameters (with standard errors
        and units), rms/sigma, chi-square and its p-value, the information criteria, the
        likelihood ratio against the best, and the verdict; then the rule's outcome."""
        source = "given" if self.sigma_given else "estimated from the best law's residuals"
        lines = [
            f"{len(self.names)} friction laws on one record of N = {self.num_samples} samples; "
            f"noise sigma = {self.sigma:.4g} rad ({source}); level {self.level:g}",
            f"  {'law':<24}{'k':>3}{'rms/sigma':>11}{'chi2/dof':>10}{'p':>10}{'AIC':>11}"
            f"{'BIC':>11}{'2 ln LR':>10}  verdict",
        ]
        for i, name in enumerate(self.names):
            verdict = "ruled out" if self.ruled_out[i] else "consistent"
            if i == self.preferred_index:
                verdict = "preferred"
            if self.ruled_out[i] and not self.white[i]:
                verdict += " (residuals not white)"
            if self.ruled_out[i] and not self.searched[i]:
                verdict += " (not searched)"
            if not bool(np.all(np.asarray(self.fits[i].converged))):
                verdict += f" (fit flagged: fits[{i}].message())"
            rms = math.sqrt(float(self.rss[i]) / self.num_samples) / self.sigma
            lines.append(
                f"  {name:<24}{int(self.num_params[i]):>3}{rms:>11.3f}"
                f"{float(self.chi2[i]) / float(self.dof[i]):>10.3f}{float(self.p_value[i]):>10.2g}"
                f"{float(self.aic[i]):>11.1f}{float(self.bic[i]):>11.1f}"
                f"{float(self.likelihood_ratio[i]):>10.1f}  {verdict}"
            )
        lines.append("  fitted parameters (value +- standard error, units):")
        for name, res in zip(self.names, self.fits):
            law = res.top.friction
            parts = [
                f"{n} = {float(v):.5g} +- {float(e):.2g} {units(n, law)}"
                for n, v, e in zip(res.free, np.asarray(res.values), np.asarray(res.std_errors))
            ]
            lines.append(f"  {name:<24}{'; '.join(parts)}")
        if self.preferred_index >= 0:
            lines.append(
                f"The record prefers {self.preferred_name} (lowest "
                f"{self.criterion.upper()} of the laws it does not rule out)."
            )
        else:
            lines.append(
                "The record rules out every law compared (or their fits failed: see "
                "each fit's message())."
            )
        if self.ruled_out.any():
            lines.append(f"It rules out: {', '.join(self.ruled_out_names)}.")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return self.table()

    __str__ = __repr__


def compare_laws(
    top_guess: TippeTop,
    y0_guess: State,
    ts: ArrayLike,
    theta_obs: ArrayLike,
    laws: Sequence[AbstractFriction],
    *,
    free: Sequence[str] = ("eps", "spin", "theta0"),
    sigma: float | None = None,
    level: float = LEVEL,
    criterion: str = "bic",
    weights: ArrayLike | None = None,
    search: str = "shared",
    **fit_options,
) -> LawComparison:
    r"""Fit one record of the tilt with each of several friction laws and say which laws the
    record rules out and which it prefers.

    Each law is fitted by `fit`, from `top_guess` with that law (the law as given is the
    guess of its parameters) and `y0_guess`, with `free` plus the law's own parameters that a
    record determines (`mu` for every law, `patch_radius` for `CoulombContensou`,
    `slip_scale` for `Coulomb`).

    **The rule.** With Gaussian noise of level $s$ (`sigma`), a law that describes the
    record leaves residuals with $\chi^2 = \mathrm{RSS}/s^2 \sim \chi^2_{N-k}$ ($N$ samples,
    $k$ free parameters), white in time. The record **rules out** a law when

    - its residuals are too large for the noise: $P(\chi^2_{N-k} > \chi^2) <$ `level`
      (default 1e-3), or
    - they are not white: the fit's runs test, Ljung-Box test or windowed chi-square test
      rejects them (each at a false-alarm rate of 1e-3; `fit`'s diagnostics), which catches a
      law that leaves structure below the noise's level.

    The chance that the right law is ruled out is then a few times 1e-3 (if its fit finds the
    least-squares minimum: a fit stuck in a local minimum leaves residuals that are not noise,
    and its law is ruled out with it). A fit flagged for another reason (`converged` False: a
    phase ambiguity, `max_steps`) is judged by its residuals all the same; the table marks it,
    and its `message()` says what to trust.
    Among the laws not ruled out, the record **prefers** the one with the lowest information
    criterion (`criterion`: `"bic"`, $-2\ln L + k\ln N$, default, or `"aic"`, $-2\ln L + 2k$),
    which charges a law for its extra parameters; the table also gives the likelihood ratio
    $2\ln(L_{best}/L_l)$ against the best law. Without `sigma` the noise is estimated from the
    law that fits best, $\hat s^2 = \min_l \mathrm{RSS}_l/(N - k_l)$, so a law can only be
    ruled out against the others (the best one passes the level test by construction), and
    $-2\ln L = N\ln(\mathrm{RSS}/N)$: give `sigma` when it is known.

    **Arguments:**

    - `top_guess`, `y0_guess`, `ts`, `theta_obs`: as for `fit` (one record: `theta_obs` of
      shape `(N,)`; NaN marks a missing sample). The law of `top_guess` is not used.
    - `laws`: the friction laws to compare, each an `AbstractFriction` whose fields are the
      guess of its parameters (e.g. `tj.Viscous(0.3)`, `tj.CoulombContensou(0.3, 5e-4,
      1e-5)`, `tj.CoulombContensou(0.3, 5e-4, 1e-5, pressure="ellipse")`).
    - `free`: the top's and launch's parameters freed for every law (not the laws' own: they
      are added per law). Default `("eps", "spin", "theta0")`.
    - `sigma`: the noise level of `theta_obs` (rad), if known (recommended).
    - `level`: the level of the chi-square test (default 1e-3).
    - `criterion`: `"bic"` (default) or `"aic"`.
    - `weights`: optional weight per sample, as for `fit`; the chi-square is then
      $\sum_k w_k r_k^2/s^2$ (with $w_k = 1/\sigma_k^2$, pass `sigma=1.0`).
    - `search`: how `fit`'s search for starts (its `strategy`, `"global"` by default) is spent
      over the laws. `"shared"` (default): every law is first fitted from its guess alone
      (`strategy="windows"`, a few simulations of the record); while no law's residuals pass,
      the law with the lowest residual sum of squares that has not been searched is fitted
      with the whole strategy, in turn; once a law passes, each law that does not is fitted
      once more from the passing fit's top and launch (its own parameters from its guess),
      and keeps the lower of its fits. A wrong law then costs a few fits from good starts
      instead of a search that cannot succeed. `"every"`: every law is fitted with the whole
      strategy (as many searches as laws that fail). The table marks a law ruled out without
      a search `(not searched)`.
    - `fit_options`: passed to `fit` for every law (`model`, `strategy`, `t0`, `max_steps`,
      ...), except `trim` and `phi_obs` (every law is judged on the same samples of the tilt).

    **Returns:** a `LawComparison`: per law its `FitResult` and statistics, `ruled_out`,
    `preferred`; `print()` it for the table.
    """
    for name in ("trim", "phi_obs"):
        if fit_options.get(name) not in (None, False):
            raise ValueError(
                f"compare_laws does not take {name}=: every law is judged on the same samples "
                "of the tilt. Fit a law alone with tj.fit for that."
            )
    fit_options.pop("trim", None)
    fit_options.pop("phi_obs", None)
    if search not in SEARCHES:
        raise ValueError(f"search must be one of {SEARCHES}, got {search!r}.")
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {CRITERIA}, got {criterion!r}.")
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be between 0 and 1 (a false-alarm rate), got {level}.")
    if sigma is not None and not (np.isfinite(sigma) and sigma > 0):
        raise ValueError(f"sigma must be a positive noise level (rad), got {sigma}.")
    if not isinstance(top_guess, TippeTop):
        raise TypeError(f"top_guess must be a tippejax.TippeTop, got {type(top_guess).__name__}.")
    laws = tuple(laws)
    if len(laws) < 2:
        raise ValueError(f"compare_laws needs at least two laws to compare, got {len(laws)}.")
    for law in laws:
        if not isinstance(law, AbstractFriction):
            raise TypeError(
                "laws must be friction laws (tj.Viscous, tj.Coulomb, tj.CoulombContensou, ...), "
                f"got {type(law).__name__}."
            )
    if isinstance(free, str):
        raise ValueError(f"free must be a sequence of names, e.g. ({free!r},), not a string.")
    free = tuple(n for n in free if n not in LAW_FIELDS)
    model = fit_options.get("model", "full")
    if model in FIT_MODELS:  # (an unknown model is fit's to refuse)
        for law in laws:
            check_model(model, law)
    obs = np.asarray(theta_obs, float)
    if obs.ndim != 1:
        raise ValueError(
            f"compare_laws takes one record: theta_obs of shape (N,), got {obs.shape}."
        )
    tops = [top_guess.replace(friction=law) for law in laws]
    frees = [free + identifiable(law) for law in laws]
    for law, f in zip(laws, frees):
        check_law(law, f)
    w = (
        np.ones_like(obs)
        if weights is None
        else np.broadcast_to(np.asarray(weights, float), obs.shape)
    )
    used = np.isfinite(obs) & (w > 0)
    ts_np = np.asarray(ts, float)

    def judge(res, i):
        return _consistent(res, len(frees[i]), used, w, ts_np, sigma, level)

    def rss_of(res):
        return _rss(res, used, w)

    fits, searched = _fit_laws(
        tops, frees, y0_guess, ts, obs, sigma, weights, fit_options, search, judge, rss_of
    )
    residuals = [np.asarray(res.residuals, float) for res in fits]
    n = int(used.sum())
    k = np.array([len(f) for f in frees])
    rss = np.array([_rss(res, used, w) for res in fits])
    if sigma is None:
        s = math.sqrt(float(np.min(rss / (n - k))))
        deviance = n * np.log(rss / n)
    else:
        s = float(sigma)
        deviance = rss / s**2
    chi2 = rss / s**2
    dof = n - k
    p = np.array([diagnostics.chi2_sf(float(c), float(d)) for c, d in zip(chi2, dof)])
    white = np.array(
        [diagnostics.describes(np.where(used, r, np.nan), ts_np, None)["passes"] for r in residuals]
    )
    aic, bic = deviance + 2 * k, deviance + k * math.log(n)
    ruled_out = (p < level) | ~white
    score = bic if criterion == "bic" else aic
    candidates = np.flatnonzero(~ruled_out)
    preferred = int(candidates[np.argmin(score[candidates])]) if candidates.size else -1
    return LawComparison(
        names=tuple(law_name(law) for law in laws),
        fits=fits,
        searched=searched,
        num_params=k,
        num_samples=n,
        rss=rss,
        sigma=s,
        sigma_given=sigma is not None,
        chi2=chi2,
        dof=dof,
        p_value=p,
        white=white,
        deviance=deviance,
        aic=aic,
        bic=bic,
        likelihood_ratio=deviance - np.min(deviance),
        ruled_out=ruled_out,
        preferred_index=preferred,
        level=float(level),
        criterion=criterion,
    )


def _rss(res: FitResult, used: np.ndarray, w: np.ndarray) -> float:
    """The weighted residual sum of squares of a fit over the samples used; a sample the fit
    could not simulate counts as a residual of pi."""
    r = np.asarray(res.residuals, float)
    return float(np.sum(np.where(used & np.isfinite(r), w * r**2, 0.0))) + float(
        np.sum(used & ~np.isfinite(r))
    ) * (np.pi**2)


def _consistent(res: FitResult, k: int, used, w, ts_np, sigma, level) -> bool:
    """Whether the record would not rule out the law of this fit (`compare_laws`'s rule):
    white residuals and, with a known `sigma`, a chi-square p-value at least `level`."""
    r = np.asarray(res.residuals, float)
    if not diagnostics.describes(np.where(used, r, np.nan), ts_np, None)["passes"]:
        return False
    if sigma is None:
        return True
    return diagnostics.chi2_sf(_rss(res, used, w) / sigma**2, float(used.sum() - k)) >= level


def _fit_laws(tops, frees, y0_guess, ts, obs, sigma, weights, fit_options, search, judge, rss):
    """The fit of each law, and whether it ran the whole strategy (`compare_laws`'s
    `search`); `judge(res, i)` is the rule (whether law i's fit is consistent with the
    record), `rss(res)` a fit's residual sum of squares."""
    n = len(tops)
    cheap = {k: v for k, v in fit_options.items() if k != "strategy"}
    cheap["strategy"] = "windows"

    def one(i, top, y0, options):
        return fit(top, y0, ts, obs, free=frees[i], sigma=sigma, weights=weights, **options)

    if search == "every":
        return tuple(one(i, tops[i], y0_guess, fit_options) for i in range(n)), np.ones(n, bool)
    fits = [one(i, tops[i], y0_guess, cheap) for i in range(n)]
    searched = np.zeros(n, bool)
    passed = [i for i in range(n) if judge(fits[i], i)]
    while not passed and not searched.all():
        i = min(np.flatnonzero(~searched), key=lambda j: rss(fits[j]))
        searched[i] = True
        res = one(i, tops[i], y0_guess, fit_options)
        if judge(res, i) or rss(res) < rss(fits[i]):
            fits[i] = res
        passed = [i] if judge(fits[i], i) else []
    if passed:
        best = fits[min(passed, key=lambda j: rss(fits[j]))]
        launch = dict(t0=float(np.asarray(best.t0))) if "t0" in best.free else {}
        for i in range(n):
            if searched[i] or judge(fits[i], i):
                continue
            top = best.top.replace(friction=tops[i].friction)
            res = one(i, top, best.y0, dict(cheap, **launch))
            if judge(res, i) or rss(res) < rss(fits[i]):
                fits[i] = res
    return tuple(fits), searched
