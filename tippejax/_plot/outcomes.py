"""The figure of an outcome map: where each launch ends, beside the linear theory's prediction."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._analysis.groups import classify
from .._analysis.potential import effective_potential_d2_closed_form
from .._invariants import jellet
from .._outcome import OUTCOMES, stable_states
from .._state import initial_state
from .._top import TippeTop
from .bifurcation import bifurcation_diagram, jellet_scale
from .groups import group_map

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
