"""The figure of a fit: the data, the fitted tilt and the residuals."""

from __future__ import annotations

import math

import numpy as np

from .bifurcation import _POLE_LABELS, _POLE_TICKS


def fit_figure(result, *, title: str | None = None):
    r"""The data and the fitted tilt of a `FitResult`, with the residuals below.

    Top axes: the observations $\theta^{obs}_k$ (small dots; missing samples are not drawn) and
    the fitted model's $\theta(t)$ at the same times, with a dashed vertical line at
    `result.describes_until` when it ends before the record (the model stops describing the data
    there). Bottom axes (same $t$): the residuals $\theta - \theta^{obs}$ (rad) and a band of
    $\pm$ their RMS. The title gives the fitted values with their standard errors unless `title`
    is given.

    **Arguments:**

    - `result`: a `FitResult` of `fit`. For a batched fit (several recordings, `theta_obs` of
      shape `(batch, N)`), only recording 0 is drawn.
    - `title`: the figure's title (default: the free parameters' values and errors).

    **Returns:** the matplotlib `Figure`.
    """
    import matplotlib.pyplot as plt

    ts = np.asarray(result.ts)
    theta_obs = np.asarray(result.theta_obs)
    theta_fit = np.asarray(result.theta_fit)
    residuals = np.asarray(result.residuals)
    values, errors = np.asarray(result.values), np.asarray(result.std_errors)
    rms = np.asarray(result.rms)
    describes = np.asarray(result.describes_until)
    fitted_until = np.asarray(getattr(result, "fitted_until", ts[..., -1]))
    rms_fitted = np.asarray(getattr(result, "rms_fitted", rms))
    batched = theta_obs.ndim == 2
    if batched:  # recording 0 only
        theta_obs, theta_fit, residuals = theta_obs[0], theta_fit[0], residuals[0]
        values, errors, rms, describes = values[0], errors[0], rms[0], describes[0]
        fitted_until = fitted_until[0] if fitted_until.ndim else fitted_until
        rms_fitted = rms_fitted[0] if rms_fitted.ndim else rms_fitted
        ts = ts[0] if ts.ndim == 2 else ts
    rms, describes = float(rms), float(describes)
    fitted_until, rms_fitted = float(fitted_until), float(rms_fitted)

    fig, (ax, ax_res) = plt.subplots(
        2,
        1,
        figsize=(8.0, 6.0),
        sharex=True,
        layout="constrained",
        gridspec_kw=dict(height_ratios=(2.2, 1.0)),
    )
    seen = np.isfinite(theta_obs)
    ax.plot(ts[seen], theta_obs[seen], ".", color="0.45", markersize=2.5, label="data")
    ax.plot(ts, theta_fit, "-", color="tab:red", linewidth=1.2, label=f"fit ({result.model} model)")
    if np.isfinite(describes) and describes < ts[-1]:
        for axes in (ax, ax_res):
            axes.axvline(describes, color="black", linestyle="--", linewidth=1.0)
        left = describes - ts[0] > 0.5 * (ts[-1] - ts[0])  # the label on the roomier side
        ax.annotate(
            f"describes until {describes:.3g} s",
            (describes, 1.0),
            xycoords=("data", "axes fraction"),
            xytext=(-4 if left else 4, -4),
            textcoords="offset points",
            ha="right" if left else "left",
            va="top",
            fontsize=9,
        )
    ax.set_ylabel(r"$\theta$ (rad)")
    if np.nanmax(theta_obs) - np.nanmin(theta_obs) > math.pi / 2:  # a record that inverts
        ax.set_yticks(_POLE_TICKS, _POLE_LABELS)
    ax.legend(loc="best", fontsize=9, framealpha=0.9, markerscale=3)

    if fitted_until < ts[-1]:  # trimmed: the part of the record the fit did not use
        for axes in (ax, ax_res):
            axes.axvspan(fitted_until, ts[-1], color="0.85", alpha=0.5, linewidth=0)
    if np.isfinite(rms):
        label = f"$\\pm$ rms = {rms:.3g} rad (whole record)"
        if fitted_until < ts[-1]:
            label += f"; {rms_fitted:.3g} rad fitted (t $\\leq$ {fitted_until:.3g} s)"
        ax_res.axhspan(-rms, rms, color="tab:red", alpha=0.15, linewidth=0, label=label)
    ax_res.axhline(0.0, color="black", linewidth=0.6)
    ax_res.plot(ts, residuals, ".", color="0.3", markersize=2.0)
    ax_res.set_xlabel("$t$ (s)")
    ax_res.set_ylabel(r"$\theta - \theta^{obs}$ (rad)")
    if np.isfinite(rms):
        ax_res.legend(loc="best", fontsize=9, framealpha=0.9)
    ax_res.set_xlim(ts[0], ts[-1])

    if title is None:
        title = ", ".join(
            f"{name} = {v:.4g} $\\pm$ {e:.2g}" for name, v, e in zip(result.free, values, errors)
        )
        if batched:
            title += f"  (recording 0 of {np.asarray(result.theta_obs).shape[0]})"
    fig.suptitle(title, fontsize=10)
    return fig
