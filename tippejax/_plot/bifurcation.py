r"""Bifurcation diagrams: $J^2$ against $\theta$, the steady states of one top or one per group."""

from __future__ import annotations

import math
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from .._analysis.branch import branch_jellet, stability_function
from .._analysis.groups import GROUPS, classify, thresholds
from .._top import TippeTop
from .groups import _group_index_on_grid

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
