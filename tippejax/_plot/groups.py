r"""The map of the six groups over $A/C$ and $\epsilon/R$."""

from __future__ import annotations

from collections.abc import Mapping

import jax
import numpy as np

from .._analysis.groups import GROUPS, group_index
from .._top import TippeTop

# One colour per group, in the order of `GROUPS`: blues for I (never inverts), greens/orange for
# II (inverts), purple for III (rises only to theta_c).
GROUP_COLOURS = ("#9ecae1", "#3182bd", "#a1d99b", "#31a354", "#fd8d3c", "#9e9ac8")


@jax.jit
def _group_index_on_grid(a_over_c, eps_over_r):
    return group_index(TippeTop.from_ratios(a_over_c, eps_over_r))


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
