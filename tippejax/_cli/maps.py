"""`tippejax map`: where a grid of launches ends (dense or adaptive, with its boundaries), and a
map over (A/C, eps/R) beside the groups."""

from __future__ import annotations

import math
import os
import sys
import time

import jax
import numpy as np

from .._analysis.groups import classify, thresholds
from .._maps import OUTCOMES, outcome_map, outcome_map_tops
from .._plot import OUTCOME_COLOURS, outcome_map_figure
from .common import REPRESENTATIVES, mu_text, save, top_from_options, use_agg

MAP_GROUP_TOPS = ("standard", *REPRESENTATIVES)

ADAPTIVE_BASE = 32
"""Cells of the base grid along each axis that `--adaptive` aims at: `refine` is the
nearest integer to log2((resolution - 1) / ADAPTIVE_BASE)."""


def adaptive_refine(resolution: int) -> int:
    """The levels of refinement of `tippejax map --adaptive` at `resolution` points per axis:
    a base grid of about `ADAPTIVE_BASE` cells per axis."""
    return max(0, round(math.log2(max(resolution - 1, 1) / ADAPTIVE_BASE)))


def _map_top(args):
    """The top of `tippejax map`: `--group` (a representative of a group, or the standard top),
    then the fields given on the command line (as `top_from_options`)."""
    if args.group not in (None, "standard"):
        a_over_c, eps_over_r = REPRESENTATIVES[args.group]
        args.A_over_C = a_over_c if args.A_over_C is None else args.A_over_C
        args.eps_over_R = eps_over_r if args.eps_over_R is None else args.eps_over_R
    for name in ("m", "R", "eps"):
        setattr(args, name, getattr(args, name, None))
    top = top_from_options(args)
    return top, classify(top)


def map_arrays(om) -> dict[str, np.ndarray]:
    """An `OutcomeMap` as arrays for `np.savez` (read back with `np.load`, no pickle): its
    axes (`axes`, `axis0`, `axis1`), per-launch fields, flags (`simulated`, `resolved`),
    outcome names, and the boundaries and the linear theory's curves as polylines: the points
    of all lines one after the other (`boundary_points`, shape `(k, 2)`, in the map's
    coordinates), where each line starts (`boundary_starts`) and which pair of outcomes it
    parts (`boundary_pairs`, `"a|b"`); the same with the prefix `theory_` (`"J1"`,
    `"J2"`)."""
    out = dict(
        axes=np.array(om.axes),
        axis0=np.asarray(om.axis_values[0]),
        axis1=np.asarray(om.axis_values[1]),
        outcomes=np.array(OUTCOMES),
        fixed_names=np.array([k for k, _ in om.fixed], dtype=str),
        fixed_values=np.array([v for _, v in om.fixed], dtype=float),
        refine=np.array(om.refine),
    )
    for key in (
        "outcome",
        "settled",
        "simulated",
        "resolved",
        "theta_final",
        "t_invert",
        "t_contact_loss",
        "jellet",
        "contact_margin",
        "theta_max",
        "result",
        "num_steps",
    ):
        out[key] = np.asarray(getattr(om, key))
    if om.axes == ("theta0", "spin"):  # (the keys of earlier versions)
        out["theta0"], out["spin"] = out["axis0"], out["axis1"]

    def lines(prefix, named):
        points = [line for _, line in named]
        out[f"{prefix}_points"] = np.concatenate(points) if points else np.zeros((0, 2))
        out[f"{prefix}_starts"] = np.cumsum([0] + [len(p) for p in points])[:-1].astype(int)
        out[f"{prefix}_pairs"] = np.array([name for name, _ in named], dtype=str)

    lines("boundary", [("|".join(b.outcomes), line) for b in om.boundaries() for line in b.lines])
    lines("theory", [(name, line) for name, ls in om.theory_curves().items() for line in ls])
    return out


def _uniform(values) -> bool:
    step = np.diff(values)
    return step.size == 0 or bool(np.allclose(step, step[0], rtol=1e-6))


def _image(ax, values, first, second, **style):
    """`values[i, j]` over (second axis across, first up): an image on a uniform grid, cells
    between the midpoints elsewhere."""
    if _uniform(first) and _uniform(second):
        ax.imshow(
            values,
            origin="lower",
            extent=(second[0], second[-1], first[0], first[-1]),
            aspect="auto",
            interpolation="nearest",
            **style,
        )
    else:
        ax.pcolormesh(second, first, values, shading="nearest", **style)


def adaptive_map_figure(om, *, title: str | None = None):
    r"""An adaptive (or any) `OutcomeMap` over its two axes with its boundaries and the
    linear theory's curves; right, which launches were simulated.

    Left: the outcome of every launch (second axis across, first axis up), the boundaries
    between outcomes (`om.boundaries()`, white over black) and the curves $J = J_1$
    ($W''(0; J) = 0$, solid) and $J = J_2$ ($W''(\pi; J) = 0$, dashed) for each launch's
    $J$ (`om.theory_curves()`). Right: the launches simulated (dark) and inferred from the
    cell around them (light), and where refinement stopped (red).

    **Returns:** the matplotlib `Figure`."""
    import matplotlib.pyplot as plt
    from matplotlib.colors import BoundaryNorm, ListedColormap
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    outcome = np.asarray(om.outcome)
    first, second = (np.asarray(v, float) for v in om.axis_values)
    extent = (second[0], second[-1], first[0], first[-1])
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(13, 5.8), layout="constrained")
    cmap = ListedColormap(OUTCOME_COLOURS[: len(OUTCOMES)])
    norm = BoundaryNorm(np.arange(-0.5, len(OUTCOMES) + 0.5), cmap.N)
    _image(ax, outcome, first, second, cmap=cmap, norm=norm)
    for b in om.boundaries():
        for line in b.lines:
            ax.plot(line[:, 1], line[:, 0], color="white", linewidth=1.6)
            ax.plot(line[:, 1], line[:, 0], color="black", linewidth=0.6)
    styles = {"J1": "-", "J2": "--"}
    for name, lines in om.theory_curves().items():
        for line in lines:
            ax.plot(line[:, 1], line[:, 0], color="#e7298a", linewidth=1.2, linestyle=styles[name])
    present = [k for k in range(len(OUTCOMES)) if np.any(outcome == k)]
    handles = [
        Patch(color=OUTCOME_COLOURS[k], label=OUTCOMES[k].replace("_", " ")) for k in present
    ]
    handles += [
        Line2D([], [], color="black", label="boundaries (map)"),
        Line2D([], [], color="#e7298a", label=r"$J = J_1$: $W''(0;J)=0$"),
        Line2D([], [], color="#e7298a", linestyle="--", label=r"$J = J_2$: $W''(\pi;J)=0$"),
    ]
    ax.legend(
        handles=handles,
        fontsize=8,
        ncol=3,
        loc="upper center",
        bbox_to_anchor=(0.5, -0.11),
        framealpha=0.9,
    )
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_xlabel(om.axes[1])
    ax.set_ylabel(om.axes[0])
    kind = f"adaptive, refine = {om.refine}" if om.refine else "dense"
    ax.set_title(
        f"Outcome at t1 = {om.t1:g} s, {outcome.shape[0]} x {outcome.shape[1]} launches ({kind})",
        fontsize=10,
    )
    flags = np.where(np.asarray(om.simulated), 1, 0)
    flags = np.where(np.asarray(om.resolved), flags, 2)
    _image(
        ax2,
        flags,
        first,
        second,
        cmap=ListedColormap(["#f0f0f0", "#252525", "#de2d26"]),
        norm=BoundaryNorm([-0.5, 0.5, 1.5, 2.5], 3),
    )
    ax2.set_xlabel(om.axes[1])
    ax2.set_ylabel(om.axes[0])
    ax2.set_title(
        f"simulated: {100 * om.share_simulated:.2f}% of the launches (dark); "
        "refinement stopped: red",
        fontsize=10,
    )
    if title:
        fig.suptitle(title)
    return fig


def run(args) -> int:
    """Outcome maps of one top: launch plane (theta0 x spin), dense or adaptive, and the plane
    of (A/C, eps/R)."""
    use_agg()
    try:
        top, group = _map_top(args)
        n_theta, n_spin = args.n_theta, args.n_spin
        if args.resolution is not None:
            n_theta = n_spin = args.resolution
        if min(n_theta, n_spin) < 2:
            raise ValueError("--n-theta, --n-spin and --resolution must be at least 2.")
        refine = args.refine
        if refine is None and args.adaptive:
            refine = adaptive_refine(max(n_theta, n_spin))
        theta0 = np.linspace(args.theta_min, args.theta_max, n_theta)
        spin_max = args.spin_max if args.spin_max is not None else 6.0 * float(thresholds(top).n1)
        spin = np.linspace(args.spin_min, spin_max, n_spin)
        os.makedirs(args.out, exist_ok=True)
        print(
            f"top: Group {group}, A/C = {float(top.A_over_C):.4g}, "
            f"eps/R = {float(top.eps_over_R):.4g}, {mu_text(top)}"
        )
        start = time.perf_counter()
        om = outcome_map(
            top,
            theta0,
            spin,
            t1=args.t1,
            model=args.model,
            tolerance=args.tolerance,
            refine=refine or None,
            progress=bool(refine),
        )
        elapsed = time.perf_counter() - start
        n = theta0.size * spin.size
        print(om.summary())
        print(
            f"{n} launches in {elapsed:.1f} s ({n / elapsed:.1f} launches/s, compilation "
            f"included) on {len(jax.devices())} device(s)"
        )
        for b in om.boundaries():
            near = f"; {b.distance:.2f} cells (median) from J = {b.theory[1:]}" if b.theory else ""
            print(
                f"boundary {b.outcomes[0]} | {b.outcomes[1]}: {b.cells} cells, box-counting "
                f"dimension {b.dimension:.2f}{near}"
            )
        figure = adaptive_map_figure(om) if refine else outcome_map_figure(om)
        paths = [save(figure, os.path.join(args.out, "outcome_map.png"), dpi=110)]
        np.savez(os.path.join(args.out, "outcome_map.npz"), **map_arrays(om))
        paths.append(os.path.join(args.out, "outcome_map.npz"))
        if args.tops:
            a = np.linspace(0.55, 1.6, args.n_tops)
            e = np.linspace(0.04, 0.7, max(2, (3 * args.n_tops) // 4))
            spin_tops = (
                args.spin_tops if args.spin_tops is not None else float(spin[len(spin) // 2])
            )
            start = time.perf_counter()
            omt = outcome_map_tops(
                top,
                a,
                e,
                theta0=args.theta0_tops,
                spin=spin_tops,
                t1=args.t1,
                model="full" if args.model == "auto" else args.model,
            )
            print(omt.summary())
            print(f"{a.size * e.size} tops in {time.perf_counter() - start:.1f} s")
            paths.append(
                save(
                    outcome_map_figure(omt), os.path.join(args.out, "outcome_map_tops.png"), dpi=110
                )
            )
    except (ValueError, TypeError, OSError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for path in paths:
        print(f"wrote {path}")
    return 0
