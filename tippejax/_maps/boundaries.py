"""Boundaries of a map: polylines between outcomes, the linear theory's curves, their distance
and the boxes a boundary fills."""

from __future__ import annotations

import math

import contourpy
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._analysis.potential import effective_potential_d2_closed_form
from .._bucket import bucket
from .._invariants import jellet
from .._outcome import INTERMEDIATE, INVERTED, OUTCOMES, UPRIGHT
from .._state import initial_state
from .axes import MapAxes, base_top

THEORY_POINTS = 512
"""Most points along each axis at which the linear theory is evaluated (every k-th point of
the map): its curves are smooth, and are interpolated in between."""


class MapBoundary(eqx.Module):
    r"""The boundary between two outcomes of a map (`OutcomeMap.boundaries()`).

    **Fields:**

    - `outcomes`: the two outcomes' names, in the order of `OUTCOMES`.
    - `lines`: polylines, each an array `(k, 2)` of points in the map's coordinates (first
      axis, second axis), midway between neighbouring points of the two outcomes.
    - `cells`: the number of cells of the map (2 x 2 neighbouring points) that hold both.
    - `dimension`: its box-counting dimension, the slope of $\log N$ against $\log(1/s)$ for
      the number $N$ of boxes of side $s$ cells (1, 2, 4, ...) it passes through: 1 for a
      curve, more for a boundary that does not become simpler on finer grids (nan where it
      is too short to tell).
    - `theory`: the linear theory's curve it is compared with: `"J1"` ($W''(0; J) = 0$, the
      upright state's loss of stability, for a boundary of `"upright"`), `"J2"`
      ($W''(\pi; J) = 0$, for one of `"inverted"`), or None.
    - `distance`, `distance_max`: the median and the largest distance (in cells) of the
      polylines' points from that curve (nan without one).
    """

    outcomes: tuple[str, str] = eqx.field(static=True)
    lines: tuple[np.ndarray, ...]
    cells: int = eqx.field(static=True)
    dimension: float = eqx.field(static=True)
    theory: str | None = eqx.field(static=True)
    distance: float = eqx.field(static=True)
    distance_max: float = eqx.field(static=True)


def _index_lines(z, level=0.0) -> list[np.ndarray]:
    """Contour lines of `z` (masked where invalid) at `level`, in index coordinates
    `(i, j)` of its two axes."""
    n1, n2 = z.shape
    if n1 < 2 or n2 < 2:
        return []
    gen = contourpy.contour_generator(
        x=np.arange(n2, dtype=float),
        y=np.arange(n1, dtype=float),
        z=z,
        line_type=contourpy.LineType.Separate,
    )
    return [line[:, ::-1].copy() for line in gen.lines(level) if len(line) >= 2]


def to_values(line: np.ndarray, values) -> np.ndarray:
    """Index coordinates `(i, j)` to the map's coordinates (linear between grid values)."""
    out = np.empty_like(line, dtype=float)
    for k in (0, 1):
        v = np.asarray(values[k], float)
        out[:, k] = np.interp(line[:, k], np.arange(v.size), v)
    return out


def pair_cells(outcome: np.ndarray, a: int, b: int) -> np.ndarray:
    """Which cells (2 x 2 neighbouring points, shape `(n1 - 1, n2 - 1)`) hold both `a` and
    `b`."""

    def any_in_cell(mask):
        return mask[:-1, :-1] | mask[1:, :-1] | mask[:-1, 1:] | mask[1:, 1:]

    return any_in_cell(outcome == a) & any_in_cell(outcome == b)


def box_counting_dimension(cells: np.ndarray) -> float:
    """The box-counting dimension of the set of `cells` (bool grid): the slope of log N(s)
    against log(1/s), boxes of side s = 1, 2, 4, ... cells up to an eighth of the map, over
    the sides where the set fills at least 4 boxes (nan with fewer than three such sides)."""
    sides, counts = [], []
    side = 1
    while side <= max(1, min(cells.shape) // 8):
        n1, n2 = -(-cells.shape[0] // side), -(-cells.shape[1] // side)
        padded = np.zeros((n1 * side, n2 * side), bool)
        padded[: cells.shape[0], : cells.shape[1]] = cells
        count = int(padded.reshape(n1, side, n2, side).any(axis=(1, 3)).sum())
        if count >= 4:
            sides.append(side)
            counts.append(count)
        side *= 2
    if len(sides) < 3:
        return math.nan
    return float(-np.polyfit(np.log(sides), np.log(counts), 1)[0])


@eqx.filter_jit
def _pole_curvatures(tops, launches):
    def one(top, launch):
        theta0, spin, theta_dot, phi_dot, phi, psi, vx, vy = launch
        y0 = initial_state(
            top, theta0, spin, theta_dot=theta_dot, phi_dot=phi_dot, phi=phi, psi=psi, vx=vx, vy=vy
        )
        J = jellet(top, y0)
        return (
            effective_potential_d2_closed_form(top, 0.0, J),
            effective_potential_d2_closed_form(top, jnp.pi, J),
        )

    axes = jax.tree_util.tree_map(lambda x: 0 if jnp.ndim(x) == 1 else None, tops)
    return jax.vmap(one, in_axes=(axes, 0))(tops, launches)


def map_axes_of(om) -> MapAxes:
    """The `MapAxes` of a finished map."""
    return MapAxes(
        names=om.axes,
        values=tuple(np.asarray(v, float) for v in om.axis_values),
        fixed=dict(om.fixed),
    )


def theory_fields(om) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    r"""$W''(0; J)$ and $W''(\pi; J)$ of every launch's $J$ on every k-th point of the map
    (at most `THEORY_POINTS` per axis, and the last), with the grid indices they are at."""
    n1, n2 = np.shape(om.outcome)
    picks = []
    for n in (n1, n2):
        step = max(1, -(-n // THEORY_POINTS))
        picks.append(np.unique(np.r_[np.arange(0, n, step), n - 1]))
    axes = map_axes_of(om)
    gi, gj = np.meshgrid(*picks, indexing="ij")
    i, j = gi.ravel(), gj.ravel()
    dtype = jnp.result_type(om.top.m)
    tops = axes.tops(base_top(om.top, axes), i, j)
    up, down = _pole_curvatures(tops, jnp.asarray(axes.launches(i, j), dtype))
    shape = gi.shape
    return (
        np.asarray(up, float).reshape(shape),
        np.asarray(down, float).reshape(shape),
        picks[0],
        picks[1],
    )


def theory_lines(om) -> dict[str, list[np.ndarray]]:
    r"""The linear theory's curves in index coordinates: `"J1"` where $W''(0; J) = 0$ and
    `"J2"` where $W''(\pi; J) = 0$ for the launches' $J$."""
    up, down, pi, pj = theory_fields(om)
    out = {}
    for name, field in (("J1", up), ("J2", down)):
        lines = _index_lines(np.ma.masked_invalid(field))
        out[name] = [
            np.stack(
                [
                    np.interp(line[:, 0], np.arange(pi.size), pi),
                    np.interp(line[:, 1], np.arange(pj.size), pj),
                ],
                axis=1,
            )
            for line in lines
        ]
    return out


def _distances(om, axes: MapAxes, points: np.ndarray, which: int) -> np.ndarray:
    r"""The distance (cells) of `points` (index coordinates) from the zero set of the linear
    theory's field `which` (0: $W''(0; J)$, 1: $W''(\pi; J)$), to first order: $|f| /
    |\nabla f|$, with $f$ at each point and its gradient by central differences over half
    a cell along each axis."""
    dtype = jnp.result_type(om.top.m)
    base = base_top(om.top, axes)
    n = [v.size for v in axes.values]
    offsets = ((0.0, 0.0), (0.5, 0.0), (-0.5, 0.0), (0.0, 0.5), (0.0, -0.5))
    values = []
    for di, dj in offsets:
        at = [
            np.interp(points[:, k] + d, np.arange(n[k]), axes.values[k])
            for k, d in ((0, di), (1, dj))
        ]
        # (padded to a bucket of lengths: one compilation for boundaries of similar sizes)
        pad = bucket(len(points)) - len(points)
        at = [np.concatenate([a, np.repeat(a[-1:], pad)]) for a in at]
        f = _pole_curvatures(axes.tops_at(base, *at), jnp.asarray(axes.launches_at(*at), dtype))[
            which
        ]
        values.append(np.asarray(f, float)[: len(points)])
    f, up_i, down_i, up_j, down_j = values
    # (one-sided at the ends of an axis, where the half cell beyond is clipped)
    span_i = np.clip(points[:, 0] + 0.5, 0, n[0] - 1) - np.clip(points[:, 0] - 0.5, 0, n[0] - 1)
    span_j = np.clip(points[:, 1] + 0.5, 0, n[1] - 1) - np.clip(points[:, 1] - 0.5, 0, n[1] - 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        gradient = np.hypot((up_i - down_i) / span_i, (up_j - down_j) / span_j)
        return np.abs(f) / gradient


def boundaries(om) -> tuple[MapBoundary, ...]:
    """The boundaries between every pair of outcomes of `om` that touch (see
    `OutcomeMap.boundaries`)."""
    outcome = np.asarray(om.outcome)
    present = [int(k) for k in np.unique(outcome)]
    axes = map_axes_of(om)
    out = []
    for x, a in enumerate(present):
        for b in present[x + 1 :]:
            cells = pair_cells(outcome, a, b)
            if not cells.any():
                continue
            z = np.where(outcome == a, 1.0, np.where(outcome == b, -1.0, np.nan))
            lines = _index_lines(np.ma.masked_invalid(z))
            curve, distance, distance_max = None, math.nan, math.nan
            kinds = {a, b}
            if lines and kinds & {UPRIGHT, INVERTED} and kinds <= {UPRIGHT, INVERTED, INTERMEDIATE}:
                points = np.concatenate(lines)
                candidates = ([("J1", 0)] if UPRIGHT in kinds else []) + (
                    [("J2", 1)] if INVERTED in kinds else []
                )
                best = None
                for name, which in candidates:
                    d = _distances(om, axes, points, which)
                    if np.any(np.isfinite(d)) and (
                        best is None or np.nanmedian(d) < np.nanmedian(best[1])
                    ):
                        best = (name, d)
                if best is not None:
                    curve, d = best
                    distance, distance_max = float(np.nanmedian(d)), float(np.nanmax(d))
            out.append(
                MapBoundary(
                    outcomes=(OUTCOMES[a], OUTCOMES[b]),
                    lines=tuple(to_values(line, om.axis_values) for line in lines),
                    cells=int(cells.sum()),
                    dimension=box_counting_dimension(cells),
                    theory=curve,
                    distance=distance,
                    distance_max=distance_max,
                )
            )
    return tuple(out)
