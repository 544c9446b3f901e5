r"""Plots: bifurcation diagrams $J^2$ vs $\theta$, the map of the six groups, and a fit.

The first two are the pictures of the paper's Fig. 1 (blank in our copy) and of its Sec. 5, drawn
from the closed forms of the package (`branch_jellet`, `stability_function`, `thresholds`,
`group_index`). `fit_figure` draws the data, the fitted tilt and the residuals of a `FitResult`.
matplotlib is imported lazily, inside the functions; the caller chooses the backend (the CLI and the
examples use the non-interactive "Agg").

Line conventions (as in the paper's Fig. 1): solid = linearly stable, dashed = unstable. Every line
that represents steady states carries a `gid` saying what it is, so tests can check it:
`"branch-stable"`, `"branch-unstable"`, `"vertical-0-stable"`, `"vertical-0-unstable"`,
`"vertical-pi-stable"`, `"vertical-pi-unstable"`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from ._analysis.groups import GROUPS, classify, group_index, thresholds
from ._analysis.potential import effective_potential_d2_closed_form
from ._analysis.steady_states import branch_jellet, stability_function
from ._invariants import jellet
from ._outcome import OUTCOMES, stable_states
from ._state import initial_state
from ._top import TippeTop

# One colour per group, in the order of `GROUPS`: blues for I (never inverts), greens/orange for
# II (inverts), purple for III (rises only to theta_c).
GROUP_COLOURS = ("#9ecae1", "#3182bd", "#a1d99b", "#31a354", "#fd8d3c", "#9e9ac8")

_STABLE = dict(linestyle="-", linewidth=2.0, color="black")
_UNSTABLE = dict(linestyle="--", linewidth=1.6, color="black")
_POLE_TICKS = (0.0, math.pi / 4, math.pi / 2, 3 * math.pi / 4, math.pi)
_POLE_LABELS = ("0", r"$\pi/4$", r"$\pi/2$", r"$3\pi/4$", r"$\pi$")


# Jitted once per shape: eager evaluation would compile every elementwise op separately.
_thresholds = jax.jit(thresholds)
_THETA_POINTS = 2001  # points of the theta grid of the branch (+ theta_b, theta_c)


@jax.jit
def _branch_on_grid(top: TippeTop, theta):
    return branch_jellet(top, theta), stability_function(top, jnp.cos(theta))


@jax.jit
def _group_index_on_grid(a_over_c, eps_over_r):
    return group_index(TippeTop.from_ratios(a_over_c, eps_over_r))


def jellet_scale(top: TippeTop) -> float:
    r"""The natural scale of $J^2$: $m g \epsilon R^2 C$ (kg$^2$ m$^4$ s$^{-2}$).

    On the intermediate branch $J^2/(m g\epsilon R^2 C) = P(x)^2/\tilde B(x)$ depends only on
    $A/C$, $\epsilon/R$ and $x = \cos\theta$ (eq. define_intstates).
    """
    return float(top.m * top.g * top.eps * top.R**2 * top.C)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs [i, j) of True in a 1-d boolean array."""
    runs, start = [], None
    for i, value in enumerate(mask):
        if value and start is None:
            start = i
        elif not value and start is not None:
            runs.append((start, i))
            start = None
    if start is not None:
        runs.append((start, len(mask)))
    return runs


def _branch_segments(top: TippeTop):
    r"""The intermediate branch as pieces of constant stability.

    **Returns:** a list of `(theta, J2, stable)`, numpy arrays of $\theta$ and $J^2$ (SI) and a
    bool. Neighbouring pieces share their end point (the fold at $\theta_b$), so the curve is
    drawn without a gap.
    """
    th = _thresholds(top)
    # Add theta_b and theta_c to the grid (0 where undefined: a repeated point, harmless), so
    # that the fold is exact and the grid has a fixed length (one compilation).
    extra = [float(t) if np.isfinite(float(t)) else 0.0 for t in (th.theta_b, th.theta_c)]
    theta = np.sort(np.concatenate([np.linspace(0.0, math.pi, _THETA_POINTS), extra]))
    jellet, g = (np.asarray(v) for v in _branch_on_grid(top, theta))
    exists = np.isfinite(jellet)
    segments = []
    for stable in (True, False):
        for i, j in _runs(exists & ((g > 0) == stable)):
            # Extend by one point into a neighbouring piece of the branch, so that the stable
            # and unstable pieces meet at the fold.
            j_ext = j + 1 if j < len(theta) and exists[j] else j
            segments.append((theta[i:j_ext], jellet[i:j_ext] ** 2, stable))
    segments.sort(key=lambda s: s[0][0])
    return segments


def _finite(x) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


def bifurcation_diagram(top: TippeTop, *, ax=None, scaled: bool = True, legend: bool = True):
    r"""The bifurcation diagram of the steady states of one top: $J^2$ against $\theta$.

    Draws, as in the paper's Fig. 1 (Sec. 3-5):

    - the branch of intermediate states $J^2(\theta) = m g C R^2\epsilon\,P^2/\tilde B$
      (`branch_jellet`), solid where $g(\cos\theta) > 0$ (stable, eq. eq:defg) and dashed where not;
    - the vertical states $\theta = 0$ and $\theta = \pi$ as vertical lines. $\theta = 0$ is stable
      for $J^2 < J_1^2$ (Groups II, III; always in I), $\theta = \pi$ for $J^2 > J_2^2$ (Groups I,
      II; never in III), with $J_1 = C(R-\epsilon)n_1$, $J_2 = C(R+\epsilon)n_2$ (eqs. n1, n2);
    - dotted markers at $\theta_c$ (end of the branch, where $J^2\to\infty$) and at the fold
      $\theta_b$ (eq. eqbif).

    **Arguments:**

    - `top`: a single `TippeTop`.
    - `ax`: a matplotlib `Axes` to draw in (default: a new figure).
    - `scaled`: plot $J^2/(m g\epsilon R^2 C)$ (default), else $J^2$ in SI units.
    - `legend`: draw a legend (stable/unstable) in the axes.

    **Returns:** the `Axes`.
    """
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    if ax is None:
        _, ax = plt.subplots(figsize=(5.0, 3.8))
    scale = jellet_scale(top) if scaled else 1.0
    th = _thresholds(top)
    j1_sq = _finite(th.J1**2)
    j2_sq = _finite(th.J2**2)
    theta_c, theta_b = _finite(th.theta_c), _finite(th.theta_b)

    segments = _branch_segments(top)
    # y range: 3 x the larger threshold, and high enough to show the branch rise towards
    # theta_c (where J^2 -> infinity) over 85% of its length.
    levels = [v for v in (j1_sq, j2_sq) if v is not None]
    levels += [float(np.min(s[1])) for s in segments]
    if theta_c is not None:
        a_minus_1 = float(top.A / top.C) - 1.0
        near_c = 0.85 * theta_c if a_minus_1 > 0 else theta_c + 0.15 * (math.pi - theta_c)
        theta_near = np.full(_THETA_POINTS + 2, near_c)  # the shape compiled above
        levels.append(1.2 / 3.0 * float(_branch_on_grid(top, theta_near)[0][0]) ** 2)
    ymax = 3.0 * max(levels) / scale
    ymax = ymax if np.isfinite(ymax) and ymax > 0 else 1.0

    for theta, j2, stable in segments:
        y = np.minimum(j2 / scale, 10 * ymax)  # the branch goes to infinity at theta_c
        (line,) = ax.plot(theta, y, **(_STABLE if stable else _UNSTABLE))
        line.set_gid("branch-stable" if stable else "branch-unstable")

    def vertical(x, y0, y1, stable, name):
        (line,) = ax.plot([x, x], [y0, y1], **(_STABLE if stable else _UNSTABLE))
        line.set_gid(f"vertical-{name}-{'stable' if stable else 'unstable'}")

    # theta = 0: stable below J1^2 (always if J1 is undefined, Group I).
    if j1_sq is None:
        vertical(0.0, 0.0, ymax, True, "0")
    else:
        vertical(0.0, 0.0, j1_sq / scale, True, "0")
        vertical(0.0, j1_sq / scale, ymax, False, "0")
    # theta = pi: stable above J2^2 (never if J2 is undefined, Group III).
    if j2_sq is None:
        vertical(math.pi, 0.0, ymax, False, "pi")
    else:
        vertical(math.pi, 0.0, j2_sq / scale, False, "pi")
        vertical(math.pi, j2_sq / scale, ymax, True, "pi")

    for value, x, label in ((j1_sq, 0.0, r"$J_1^2$"), (j2_sq, math.pi, r"$J_2^2$")):
        if value is not None and value / scale < ymax:
            ax.plot([x], [value / scale], "o", color="black", markersize=4)
            offset = 0.05 if x == 0.0 else -0.05
            ax.annotate(
                label,
                (x + offset, value / scale),
                ha="left" if x == 0.0 else "right",
                va="bottom",
                fontsize=9,
            )
    for value, label, colour in (
        (theta_c, r"$\theta_c$", "tab:red"),
        (theta_b, r"$\theta_b$", "tab:blue"),
    ):
        if value is not None:
            ax.axvline(value, color=colour, linestyle=":", linewidth=1.2)
            ax.annotate(
                label,
                (value, 0.97 * ymax),
                xytext=(3, 0),
                textcoords="offset points",
                ha="left",
                va="top",
                color=colour,
                fontsize=10,
            )

    # A margin either side, so that the vertical states are not hidden by the frame.
    ax.set_xlim(-0.06 * math.pi, 1.06 * math.pi)
    for side in ("left", "right"):
        ax.spines[side].set_color("0.6")
    ax.set_ylim(0.0, ymax)
    ax.set_xticks(_POLE_TICKS, _POLE_LABELS)
    ax.set_xlabel(r"$\theta$ (rad)")
    ax.set_ylabel(r"$J^2 / (m g \epsilon R^2 C)$" if scaled else r"$J^2$ (kg$^2$ m$^4$ s$^{-2}$)")
    a, e = float(top.A / top.C), float(top.eps / top.R)
    group = GROUPS[int(_group_index_on_grid(top.A / top.C, top.eps / top.R))]
    ax.set_title(f"Group {group}   ($A/C$ = {a:.3g}, $\\epsilon/R$ = {e:.3g})", fontsize=10)
    if legend:
        handles = [
            Line2D([], [], **_STABLE, label="stable"),
            Line2D([], [], **_UNSTABLE, label="unstable"),
        ]
        ax.legend(handles=handles, loc="upper center", fontsize=8, framealpha=0.9)
    return ax


def bifurcation_diagrams(tops_by_group: Mapping[str, TippeTop], *, scaled: bool = True):
    r"""The six bifurcation diagrams of the paper's Fig. 1 in a 3x2 figure.

    **Arguments:**

    - `tops_by_group`: one `TippeTop` per group name of `GROUPS` ("Ia", ..., "III"); the panels
      are in that order. Each top must belong to its group (checked with `classify`).
    - `scaled`: as in `bifurcation_diagram`.

    **Returns:** the matplotlib `Figure`.
    """
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    missing = [name for name in GROUPS if name not in tops_by_group]
    if missing:
        raise ValueError(f"bifurcation_diagrams needs one top per group; missing {missing}.")
    for name in GROUPS:
        got = classify(tops_by_group[name])
        if got != name:
            raise ValueError(f"The top given for Group {name} belongs to Group {got}.")
    fig, axes = plt.subplots(3, 2, figsize=(10.0, 11.0), layout="constrained")
    for name, ax in zip(GROUPS, axes.ravel()):
        bifurcation_diagram(tops_by_group[name], ax=ax, scaled=scaled, legend=False)
    handles = [
        Line2D([], [], **_STABLE, label="stable steady states"),
        Line2D([], [], **_UNSTABLE, label="unstable steady states"),
        Line2D([], [], color="tab:red", linestyle=":", label=r"$\theta_c$: end of the branch"),
        Line2D(
            [], [], color="tab:blue", linestyle=":", label=r"$\theta_b$: fold (change of stability)"
        ),
    ]
    fig.legend(handles=handles, loc="outside lower center", ncols=4, fontsize=9)
    fig.suptitle(
        r"Steady states of the tippe top: $J^2$ vs $\theta$ (vertical states at $\theta = 0, \pi$)"
    )
    return fig


def _group_grid(a_range, e_range, n):
    a = np.linspace(*a_range, n)
    e = np.linspace(*e_range, n + 2)[1:-1]
    a_grid, e_grid = np.meshgrid(a, e)
    # A batch of tops as array fields: group_index is elementwise, no vmap needed.
    return a, e, np.asarray(_group_index_on_grid(a_grid, e_grid))


def group_map(
    *,
    n: int = 400,
    ax=None,
    points: Mapping[str, tuple[float, float]] | None = None,
    inset: bool = True,
):
    r"""The six groups in the plane of $(A/C, \epsilon/R)$ (Sec. 5).

    Colours each point of $A/C \in [1/2, 2]$, $\epsilon/R \in (0, 1)$ by `group_index`, evaluated on
    an `n` x `n` grid of tops at once. Draws the boundaries $A/C - 1 = \pm\epsilon/R$ (Groups I, II,
    III, eq. Exist) and $1 - A/C = (\epsilon/R)^2$ (where the fold $x_b$ of eq. eqbif exists);
    the remaining boundaries, $x_b = \pm 1$, show as the edges of the colours. Groups Ia and IIc
    are thin, so an inset (`inset=True`) magnifies the corner near $A/C = 1$, $\epsilon/R = 0$.

    **Arguments:**

    - `n`: grid points per axis.
    - `ax`: a matplotlib `Axes` (default: a new figure).
    - `points`: optional `{label: (A/C, eps/R)}` to mark (e.g. the tops of the diagrams).
    - `inset`: draw the magnified inset.

    **Returns:** the `Axes`.
    """
    import matplotlib.pyplot as plt
    from matplotlib.colors import BoundaryNorm, ListedColormap
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    if ax is None:
        _, ax = plt.subplots(figsize=(7.5, 5.5), layout="constrained")
    cmap = ListedColormap(GROUP_COLOURS)
    norm = BoundaryNorm(np.arange(-0.5, len(GROUPS) + 0.5), cmap.N)

    def draw(axes, a_range, e_range, grid_n, with_labels):
        a, e, index = _group_grid(a_range, e_range, grid_n)
        da, de = a[1] - a[0], e[1] - e[0]
        axes.imshow(
            index,
            cmap=cmap,
            norm=norm,
            origin="lower",
            aspect="auto",
            interpolation="nearest",
            extent=(a[0] - da / 2, a[-1] + da / 2, e[0] - de / 2, e[-1] + de / 2),
        )
        ee = np.linspace(0.0, 1.0, 400)
        kw = dict(color="black", linewidth=1.0)
        axes.plot(1.0 + ee, ee, **kw)
        axes.plot(1.0 - ee, ee, **kw)
        axes.plot(1.0 - ee**2, ee, color="black", linewidth=1.0, linestyle="--")
        if points:
            for label, (pa, pe) in points.items():
                if a_range[0] <= pa <= a_range[1] and e_range[0] <= pe <= e_range[1]:
                    axes.plot([pa], [pe], "k*", markersize=9 if with_labels else 7)
                    if with_labels:
                        axes.annotate(
                            label, (pa, pe), xytext=(5, 3), textcoords="offset points", fontsize=9
                        )
        axes.set_xlim(*a_range)
        axes.set_ylim(*e_range)

    draw(ax, (0.5, 2.0), (0.0, 1.0), n, True)
    ax.set_xlabel(r"$A/C$")
    ax.set_ylabel(r"$\epsilon/R$")
    ax.set_title("Groups of tippe tops (Ciocci & Langerock, Sec. 5)")
    handles = [Patch(color=c, label=f"Group {g}") for g, c in zip(GROUPS, GROUP_COLOURS)]
    handles += [
        Line2D([], [], color="black", label=r"$A/C - 1 = \pm\epsilon/R$"),
        Line2D([], [], color="black", linestyle="--", label=r"$1 - A/C = (\epsilon/R)^2$"),
    ]
    ax.legend(handles=handles, loc="upper right", fontsize=9, framealpha=0.95)
    if inset:
        a_range, e_range = (0.84, 1.04), (0.0, 0.12)
        sub = ax.inset_axes([0.60, 0.06, 0.37, 0.34])
        draw(sub, a_range, e_range, n, False)  # same n: no new compilation
        sub.tick_params(labelsize=7)
        sub.set_title("zoom: Ia and IIc", fontsize=8)
        ax.indicate_inset_zoom(sub, edgecolor="black")
    return ax


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


# ---------------------------------------------------------------------------------------------
# Outcome maps

OUTCOME_COLOURS = ("#6baed6", "#31a354", "#fd8d3c", "#252525", "#e7298a", "#756bb1")
"""One colour per entry of `OUTCOMES`: upright, inverted, intermediate, contact lost, failed,
on the stem."""


@jax.jit
def _pole_curvatures(top: TippeTop, theta0, spin):

    J = jellet(top, initial_state(top, theta0, spin))
    n_stable = jax.vmap(lambda j: jnp.sum(stable_states(top, j)[1]))(J.ravel()).reshape(J.shape)
    return (
        n_stable,
        effective_potential_d2_closed_form(top, 0.0, J),
        effective_potential_d2_closed_form(top, jnp.pi, J),
    )


def _cell_edges(values: np.ndarray) -> np.ndarray:
    values = np.asarray(values, float)
    if values.size == 1:
        return np.array([values[0] - 0.5, values[0] + 0.5])
    mid = 0.5 * (values[1:] + values[:-1])
    return np.concatenate([[2 * values[0] - mid[0]], mid, [2 * values[-1] - mid[-1]]])


def _draw_outcomes(ax, x, y, outcome, settled):
    """Categorical image of `outcome[y, x]`; unsettled cells hatched."""
    from matplotlib.colors import BoundaryNorm, ListedColormap

    cmap = ListedColormap(OUTCOME_COLOURS)
    norm = BoundaryNorm(np.arange(-0.5, len(OUTCOMES) + 0.5), cmap.N)
    xe, ye = _cell_edges(x), _cell_edges(y)
    ax.pcolormesh(xe, ye, outcome, cmap=cmap, norm=norm, shading="flat")
    unsettled = (~settled) & (outcome <= 2)
    if np.any(unsettled):
        ax.contourf(
            x,
            y,
            unsettled.astype(float),
            levels=[0.5, 1.5],
            colors="none",
            hatches=["///"],
        )
    ax.set_xlim(xe[0], xe[-1])
    ax.set_ylim(ye[0], ye[-1])


def _outcome_handles(outcome, settled, extra=()):
    from matplotlib.patches import Patch

    present = set(np.unique(outcome).tolist())
    handles = [
        Patch(color=c, label=name.replace("_", " "))
        for k, (name, c) in enumerate(zip(OUTCOMES, OUTCOME_COLOURS))
        if k in present
    ]
    if np.any((~settled) & (outcome <= 2)):
        handles.append(
            Patch(facecolor="white", edgecolor="black", hatch="///", label="unsettled at t1")
        )
    return handles + list(extra)


def outcome_map_figure(om, *, title: str | None = None):
    r"""Plot an `OutcomeMap`, with the linear theory drawn on it.

    **Launch map** (`outcome_map`: axes theta0 x spin), two panels:

    - left: the outcome of every launch over (spin, theta0), unsettled cells hatched, with the
      linear-theory boundaries: the curves where $W''(0; J) = 0$ and $W''(\pi; J) = 0$ for the
      launch's Jellet $J$, i.e. $J = J_1$ and $J = J_2$ (at $\theta_0 = 0$ they meet the
      spin axis at $n_1$ and $n_2 (R+\epsilon)/(R-\epsilon)$, eqs. n1, n2: $n_2$ is a spin at
      $\theta = \pi$). Where the analysis level has two stable states for the launch's $J$
      (groups Ib, IIa: both poles, or a pole and the intermediate branch past its fold), the
      region is dotted and the colours there are the basins of the two states.
    - right: the final tilt of every launch against $J^2$ on the top's bifurcation diagram
      (`bifurcation_diagram`: the intermediate branch, solid where stable), coloured by
      outcome: settled launches sit on the stable states of the diagram.

    **Top map** (`outcome_map_tops`: axes A/C x eps/R): the outcomes over the plane of
    $(A/C, \epsilon/R)$, beside the group map of the analysis level (`group_map`) over the same
    range, with the group boundaries drawn on both.

    **Returns:** the matplotlib `Figure`.
    """
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    outcome = np.asarray(om.outcome)
    settled = np.asarray(om.settled)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(12.5, 5.8), layout="constrained")
    if om.axes == ("theta0", "spin"):
        theta0, spin = np.asarray(om.theta0), np.asarray(om.spin)
        top = om.top
        _draw_outcomes(ax, spin, theta0, outcome, settled)
        th_f = np.linspace(theta0.min(), theta0.max(), 150)
        sp_f = np.linspace(spin.min(), spin.max(), 200)
        TH, SP = np.meshgrid(th_f, sp_f, indexing="ij")
        n_stable, up, down = (np.asarray(v) for v in _pole_curvatures(top, TH, SP))
        ax.contour(SP, TH, up, levels=[0.0], colors="white", linewidths=2.2)
        ax.contour(SP, TH, up, levels=[0.0], colors="black", linewidths=1.2)
        ax.contour(SP, TH, down, levels=[0.0], colors="white", linewidths=2.2)
        ax.contour(SP, TH, down, levels=[0.0], colors="black", linewidths=1.2, linestyles="--")
        both = n_stable >= 2
        if np.any(both):
            ax.contourf(
                SP, TH, both.astype(float), levels=[0.5, 1.5], colors="none", hatches=["..."]
            )
            ax.contour(
                SP,
                TH,
                both.astype(float),
                levels=[0.5],
                colors="0.3",
                linewidths=0.8,
                linestyles=":",
            )
        extra = [
            Line2D(
                [],
                [],
                color="black",
                label=r"$W''(0;J)=0$: $J = J_1$ ($n = n_1$ at $\theta_0 = 0$); upright stable left",
            ),
            Line2D(
                [],
                [],
                color="black",
                linestyle="--",
                label=r"$W''(\pi;J)=0$: $J = J_2$ ($n = n_2\frac{R+\epsilon}{R-\epsilon}$ at "
                r"$\theta_0 = 0$); inverted stable right",
            ),
        ]
        if np.any(both):
            extra.append(
                Patch(
                    facecolor="none",
                    edgecolor="0.3",
                    hatch="...",
                    label="two stable states for this J: colours are basins",
                )
            )
        ax.legend(
            handles=_outcome_handles(outcome, settled, extra),
            fontsize=8,
            ncol=2,
            loc="upper center",
            bbox_to_anchor=(0.5, -0.13),
            framealpha=0.9,
        )
        ax.set_xlabel("launch spin $n$ (rad/s)")
        ax.set_ylabel(r"launch tilt $\theta_0$ (rad)")
        group = classify(top)
        ax.set_title(
            f"Outcome at t1 = {om.t1:g} s, Group {group} ($A/C$ = {float(top.A_over_C):.3g}, "
            f"$\\epsilon/R$ = {float(top.eps_over_R):.3g}, $\\mu$ = {float(top.mu):.3g}"
            f"{'' if top.friction.mu_units == '1' else ' ' + top.friction.mu_units})",
            fontsize=10,
        )
        # Right: the end states on the bifurcation diagram.
        bifurcation_diagram(top, ax=ax2, legend=False)
        scale = jellet_scale(top)
        j2 = np.asarray(om.jellet) ** 2 / scale
        th_final = np.asarray(om.theta_final)
        for k, colour in enumerate(OUTCOME_COLOURS[:3]):
            sel = outcome == k
            ax2.scatter(
                th_final[sel],
                j2[sel],
                s=10,
                color=colour,
                edgecolors="black",
                linewidths=0.3,
                zorder=5,
            )
        ax2.set_title("end states on the bifurcation diagram (solid: stable)", fontsize=10)
        ymax = ax2.get_ylim()[1]
        ended = outcome <= 2
        if np.any(ended):
            ax2.set_ylim(0, max(ymax, 1.05 * float(np.max(j2[ended]))))
    else:
        a, e = np.asarray(om.A_over_C), np.asarray(om.eps_over_R)
        _draw_outcomes(ax, a, e, outcome.T, settled.T)
        ee = np.linspace(0.0, 1.0, 400)
        for other in (ax, ax2):
            other.plot(1.0 + ee, ee, color="black", linewidth=1.0)
            other.plot(1.0 - ee, ee, color="black", linewidth=1.0)
            other.plot(1.0 - ee**2, ee, color="black", linewidth=1.0, linestyle="--")
        ax.set_xlim(_cell_edges(a)[[0, -1]])
        ax.set_ylim(_cell_edges(e)[[0, -1]])
        ax.legend(
            handles=_outcome_handles(outcome, settled),
            fontsize=8,
            ncol=3,
            loc="upper center",
            bbox_to_anchor=(0.5, -0.13),
            framealpha=0.9,
        )
        ax.set_xlabel(r"$A/C$")
        ax.set_ylabel(r"$\epsilon/R$")
        ax.set_title(
            f"Outcome at t1 = {om.t1:g} s of the launch theta0 = {float(om.theta0):.3g} rad, "
            f"n = {float(om.spin):.4g} rad/s",
            fontsize=10,
        )
        group_map(ax=ax2, inset=False)
        ax2.set_xlim(ax.get_xlim())
        ax2.set_ylim(ax.get_ylim())
        ax2.set_title("Groups of the analysis level (linear theory)", fontsize=10)
    if title:
        fig.suptitle(title)
    return fig
