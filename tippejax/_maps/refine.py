"""Adaptive refinement of a map: simulate a coarse grid, then only the cells that need it."""

from __future__ import annotations

import math
from collections.abc import Callable

import equinox as eqx
import numpy as np

from .._outcome import CONTACT_LOST, INTERMEDIATE, INVERTED, UPRIGHT

NEAR_ZERO = 1.0
r"""A cell whose corners agree is split where an indicator that vanishes at a change of
outcome (the contact margin, the decision margin) comes within this many times its spread
over the corners of zero: $\min v < $ `NEAR_ZERO` $(\max v - \min v)$. For a smooth
indicator that is a band about one cell wide along its zero, which shrinks with the cells."""

TILT_JUMP = 0.5
"""A cell of upright corners is split where the largest tilt the runs reached (`theta_max`)
spreads over more than this (rad) across its corners: a launch nearby may turn over."""

TIME_JUMP = 0.25
"""A cell of inverted (contact-lost) corners is split where their inversion (contact-loss)
times spread over more than this fraction of `t1`."""

MIN_BOXES = 16
"""Boundary cells of one size a base cell must hold before its boundary's dimension is
judged (`DIMENSION_STOP`)."""

DIMENSION_STOP = 1.6
r"""A base cell stops refining where the number $N$ of its cells with disagreeing corners
grows faster than $N \propto s^{-D}$ with $D$ = `DIMENSION_STOP` over the last two halvings
of the cell size $s$ (a curve gives $D = 1$, a region filled with boundary $D = 2$): its
boundary does not become simpler under refinement."""


def base_indices(n: int, step: int) -> np.ndarray:
    """Every `step`-th index of an axis of `n` points, and the last."""
    return np.unique(np.r_[np.arange(0, n, step), n - 1])


class _Known:
    """The points simulated so far, per outcome, as sorted linear indices in row-major and
    column-major order: the outcomes on a cell's edges are counted by binary search."""

    def __init__(self, shape):
        self.shape = shape
        self.rows: dict[int, np.ndarray] = {}
        self.cols: dict[int, np.ndarray] = {}

    def add(self, i, j, outcome):
        n1, n2 = self.shape
        for code in (int(c) for c in np.unique(outcome)):
            sel = outcome == code
            r = np.concatenate(
                [self.rows.get(code, np.zeros(0, np.int64)), i[sel].astype(np.int64) * n2 + j[sel]]
            )
            c = np.concatenate(
                [self.cols.get(code, np.zeros(0, np.int64)), j[sel].astype(np.int64) * n1 + i[sel]]
            )
            self.rows[code], self.cols[code] = np.sort(r), np.sort(c)

    def outcomes_on_edges(self, i0, i1, j0, j1) -> np.ndarray:
        """How many distinct outcomes the simulated points on each cell's four edges hold
        (its corners included)."""
        n1, n2 = self.shape
        distinct = np.zeros(i0.size, int)
        for code in self.rows:
            r, c = self.rows[code], self.cols[code]
            found = np.zeros(i0.size, bool)
            for row in (i0, i1):
                lo, hi = row * n2 + j0, row * n2 + j1
                found |= np.searchsorted(r, hi, "right") > np.searchsorted(r, lo, "left")
            for col in (j0, j1):
                lo, hi = col * n1 + i0, col * n1 + i1
                found |= np.searchsorted(c, hi, "right") > np.searchsorted(c, lo, "left")
            distinct += found
        return distinct


def _intervals(base):
    return (base[:-1], base[1:]) if base.size > 1 else (base, base)


def _corners(field, i0, i1, j0, j1):
    return np.stack([field[i0, j0], field[i0, j1], field[i1, j0], field[i1, j1]], axis=1)


def _near_zero(v):
    lo, hi = np.min(v, axis=1), np.max(v, axis=1)
    return lo < NEAR_ZERO * (hi - lo)


def _spread(v):
    """max - min of each row over its finite values (0 where fewer than two)."""
    finite = np.isfinite(v)
    hi = np.max(np.where(finite, v, -np.inf), axis=1)
    lo = np.min(np.where(finite, v, np.inf), axis=1)
    return np.where(np.sum(finite, axis=1) >= 2, hi - lo, 0.0)


def indicator_split(fields, t1, i0, i1, j0, j1) -> np.ndarray:
    """Which cells (whose corners share an outcome) an indicator says to split (see
    `NEAR_ZERO`, `TILT_JUMP`, `TIME_JUMP`)."""
    outcome = _corners(fields["outcome"], i0, i1, j0, j1)[:, 0]
    ended = outcome <= INTERMEDIATE
    split = np.zeros(i0.size, bool)
    margin = _corners(fields["contact_margin"], i0, i1, j0, j1)
    split |= ended & _near_zero(margin)
    decision = _corners(fields["decision_margin"], i0, i1, j0, j1)
    split |= ended & _near_zero(decision)
    tilt = _corners(fields["theta_max"], i0, i1, j0, j1)
    split |= (outcome == UPRIGHT) & (_spread(tilt) > TILT_JUMP)
    with np.errstate(invalid="ignore"):
        inverted = _corners(fields["t_invert"], i0, i1, j0, j1)
        split |= (outcome == INVERTED) & (_spread(inverted) > TIME_JUMP * t1)
        lost = _corners(fields["t_contact_loss"], i0, i1, j0, j1)
        split |= (outcome == CONTACT_LOST) & (_spread(lost) > TIME_JUMP * t1)
    return split


def _children(i0, i1, j0, j1):
    """The four children of each cell; two where it is one cell wide along an axis (it keeps
    its whole extent along that axis)."""
    wide_i, wide_j = i1 - i0 > 1, j1 - j0 > 1
    im, jm = (i0 + i1) // 2, (j0 + j1) // 2
    first_i, second_i = (i0, np.where(wide_i, im, i1)), (im, i1)
    first_j, second_j = (j0, np.where(wide_j, jm, j1)), (jm, j1)
    parts = [
        (first_i, first_j, np.ones_like(wide_i)),
        (first_i, second_j, wide_j),
        (second_i, first_j, wide_i),
        (second_i, second_j, wide_i & wide_j),
    ]
    return tuple(
        np.concatenate([(a[0], a[1], b[0], b[1])[k][keep] for a, b, keep in parts])
        for k in range(4)
    )


def size_level(levels: int, i0, i1, j0, j1) -> np.ndarray:
    """The refinement level of cells: 0 for a base cell (side up to `2**levels`), `levels - 1`
    for the last cells split (side 2)."""
    side = np.maximum(np.maximum(i1 - i0, j1 - j0), 1)
    return np.clip(levels - np.ceil(np.log2(side)).astype(int), 0, levels)


def box_dimension(counts: np.ndarray) -> float:
    r"""The box-counting dimension from the number of boundary cells at successive levels
    (cell side halving each level): the slope of $\log_2 N$ against the level, over the
    levels with at least one cell (nan with fewer than two)."""
    level = np.flatnonzero(counts > 0)
    if level.size < 2:
        return math.nan
    return float(np.polyfit(level, np.log2(counts[level]), 1)[0])


class Refinement(eqx.Module):
    """What `refine` returns.

    **Fields:** `fields` (every field `evaluate` returns, on the whole grid: nan, or 0, where
    not simulated, but `outcome`, `settled` and `result`, which every launch has),
    `simulated` and `resolved` (bool grids), `history` (`(launches, cells split)` per
    batched call) and `stopped` (`(i0, i1, j0, j1, dimension)` of each base cell that
    stopped refining)."""

    fields: dict[str, np.ndarray]
    simulated: np.ndarray
    resolved: np.ndarray
    history: tuple[tuple[int, int], ...] = eqx.field(static=True)
    stopped: tuple[tuple[int, int, int, int, float], ...] = eqx.field(static=True)


class _Store:
    """The refinement's working state on the host: the fields of the launches simulated so
    far (whole-grid arrays, written in place), which were, and the log."""

    def __init__(self, shape):
        self.shape = shape
        self.simulated = np.zeros(shape, bool)
        self.resolved = np.ones(shape, bool)
        self.fields: dict[str, np.ndarray] = {}
        self.history: list[tuple[int, int]] = []
        self.stopped: list[tuple[int, int, int, int, float]] = []

    def store(self, i, j, out):
        if not self.fields:
            for k, v in out.items():
                fill = np.nan if np.issubdtype(v.dtype, np.floating) else 0
                self.fields[k] = np.full(self.shape, fill, v.dtype)
        for k, v in out.items():
            self.fields[k][i, j] = v
        self.simulated[i, j] = True

    def result(self) -> Refinement:
        return Refinement(
            fields=self.fields,
            simulated=self.simulated,
            resolved=self.resolved,
            history=tuple(self.history),
            stopped=tuple(self.stopped),
        )


def refine(
    shape: tuple[int, int],
    levels: int,
    evaluate: Callable,
    *,
    t1: float,
    progress: Callable | None = None,
) -> Refinement:
    """Refine a map of `shape` points from the base grid of every `2**levels`-th point.

    `evaluate(i, j, hint)` simulates the points `(i, j)` (index arrays) in one batched call,
    `hint` an estimate of each one's cost (None: unknown), and returns per-point arrays with
    at least `outcome`, `num_steps` and the indicators of `indicator_split`. The cells of the
    base grid whose corners disagree, or that an indicator marks, are split into four (their
    edge midpoints and centre simulated), and so on down to cells of one point; a cell kept
    whole is reopened where a later, finer neighbour finds another outcome on its edge. The
    points inside a cell kept whole take its corners' outcome. `progress(points, split)` is
    called after each batched call. See `outcome_map(refine=...)`."""
    n1, n2 = shape
    out = _Store(shape)
    step = 2**levels
    ib, jb = base_indices(n1, step), base_indices(n2, step)
    known = _Known(shape)

    def run(i, j, hint, split):
        res = evaluate(i, j, hint)
        out.store(i, j, res)
        known.add(i, j, res["outcome"])
        out.history.append((int(i.size), int(split)))
        if progress is not None:
            progress(int(i.size), int(split))

    gi, gj = np.meshgrid(ib, jb, indexing="ij")
    run(gi.ravel(), gj.ravel(), None, 0)
    # the base cells (an axis of one point: cells of no width along it)
    (a0, a1), (b0, b1) = _intervals(ib), _intervals(jb)
    ci, cj = np.meshgrid(np.arange(a0.size), np.arange(b0.size), indexing="ij")
    ci, cj = ci.ravel(), cj.ravel()
    frontier = (a0[ci], a1[ci], b0[cj], b1[cj])
    n_patch_j = max(jb.size - 1, 1)

    def patch_of(i0, j0):
        return (np.searchsorted(ib, i0, "right") - 1) * n_patch_j + (
            np.searchsorted(jb, j0, "right") - 1
        )

    n_patches = max(ib.size - 1, 1) * n_patch_j
    counts = np.zeros((n_patches, levels + 1), int)
    stopped = np.zeros(n_patches, bool)
    leaves = tuple(np.zeros(0, np.int64) for _ in range(4))
    unresolved = tuple(np.zeros(0, np.int64) for _ in range(4))
    pending = None  # centres of the last split, waiting for their edge midpoints
    while frontier[0].size:
        i0, i1, j0, j1 = frontier
        patch = patch_of(i0, j0)
        smallest = (i1 - i0 <= 1) & (j1 - j0 <= 1)
        disagree = known.outcomes_on_edges(i0, i1, j0, j1) > 1
        np.add.at(
            counts,
            (patch[disagree & ~smallest], size_level(levels, i0, i1, j0, j1)[disagree & ~smallest]),
            1,
        )
        _stop_patches(counts, stopped, out, ib, jb, n_patch_j)
        split = (
            ~smallest
            & ~stopped[patch]
            & (disagree | indicator_split(out.fields, t1, i0, i1, j0, j1))
        )
        hold = stopped[patch] & ~smallest
        unresolved = tuple(np.concatenate([u, f[hold]]) for u, f in zip(unresolved, frontier))
        leaves = tuple(np.concatenate([lv, f[~split & ~hold]]) for lv, f in zip(leaves, frontier))
        parents = tuple(f[split] for f in frontier)
        children = _children(*parents)
        # the new points of the parents: their edge midpoints and centres; the cells two
        # launches wide (the last split) only where an edge's ends disagree (`_last_split`)
        last = (parents[1] - parents[0] <= 2) & (parents[3] - parents[2] <= 2)
        pi, pj, cost = _new_points(out, tuple(p[~last] for p in parents))
        ei, ej, ecost, centres = _last_split(out, tuple(p[last] for p in parents))
        ci_, cj_, ccost = _centres(out, pending)
        pending = centres
        pi, pj, cost = (
            np.concatenate(x) for x in ((pi, ei, ci_), (pj, ej, cj_), (cost, ecost, ccost))
        )
        flat, first = np.unique(pi.astype(np.int64) * n2 + pj, return_index=True)
        pi, pj, cost = flat // n2, flat % n2, cost[first]
        new = ~out.simulated[pi, pj]
        if np.any(new):
            run(pi[new], pj[new], cost[new], int(split.sum()))
        _infer_edges(out, tuple(p[last] for p in parents))
        # reopen the cells kept whole whose edges now hold another outcome
        li0, li1, lj0, lj1 = leaves
        reopen = (
            (known.outcomes_on_edges(li0, li1, lj0, lj1) > 1)
            & ~stopped[patch_of(li0, lj0)]
            & ((li1 - li0 > 1) | (lj1 - lj0 > 1))
        )
        frontier = tuple(np.concatenate([c, lv[reopen]]) for c, lv in zip(children, leaves))
        leaves = tuple(lv[~reopen] for lv in leaves)
    ci_, cj_, ccost = _centres(out, pending)
    if ci_.size:
        run(ci_, cj_, ccost, 0)
    _centres(out, pending)  # (the centres left: inferred)
    _fill(out, leaves, unresolved)
    return out.result()


def _cost(out, cells):
    """The mean solver steps of each cell's corners: an estimate of a new point's cost."""
    return np.mean(_corners(out.fields["num_steps"].astype(float), *cells), axis=1)


def _new_points(out, parents):
    """The edge midpoints and centres of `parents`, each with its parent's cost."""
    i0, i1, j0, j1 = parents
    im, jm = (i0 + i1) // 2, (j0 + j1) // 2
    return (
        np.concatenate([i0, i1, im, im, im]),
        np.concatenate([jm, jm, j0, j1, jm]),
        np.tile(_cost(out, parents), 5),
    )


def _edges(parents):
    """The edge midpoints of cells two launches wide: `(i, j, (end_i, end_j), (end_i,
    end_j), valid)` for the top, bottom, left and right edges."""
    i0, i1, j0, j1 = parents
    im, jm = (i0 + i1) // 2, (j0 + j1) // 2
    wide_i, wide_j = i1 - i0 == 2, j1 - j0 == 2
    return [
        (i0, jm, (i0, j0), (i0, j1), wide_j),
        (i1, jm, (i1, j0), (i1, j1), wide_j),
        (im, j0, (i0, j0), (i1, j0), wide_i),
        (im, j1, (i0, j1), (i1, j1), wide_i),
    ]


def _last_split(out, parents):
    r"""The last split of cells two launches wide: an edge midpoint is simulated where the
    edge's ends disagree, else it takes their outcome (`_infer_edges`, after the batched
    call); the centre waits for its four neighbours (`_centres`). A launch taken so differs
    from its run only where a boundary crosses the edge twice within two launches, one
    launch from it. **Returns:** `(i, j, cost, centres)`."""
    outcome = out.fields["outcome"]
    cost = _cost(out, parents)
    pi, pj, pc = [], [], []
    for i, j, a, b, valid in _edges(parents):
        ends_differ = valid & (outcome[a] != outcome[b])
        pi.append(i[ends_differ])
        pj.append(j[ends_differ])
        pc.append(cost[ends_differ])
    i0, i1, j0, j1 = parents
    both = (i1 - i0 == 2) & (j1 - j0 == 2)
    centres = tuple(x[both] for x in (i0, i1, j0, j1)) + (cost[both],)
    return np.concatenate(pi), np.concatenate(pj), np.concatenate(pc), centres


def _infer(out, i, j, from_i, from_j):
    """The launches `(i, j)` not simulated take the outcome of `(from_i, from_j)`."""
    todo = ~out.simulated[i, j]
    for name in ("outcome", "settled", "result"):
        field = out.fields[name]
        field[i[todo], j[todo]] = field[from_i[todo], from_j[todo]]


def _infer_edges(out, parents):
    for i, j, a, _, valid in _edges(parents):
        _infer(out, i[valid], j[valid], a[0][valid], a[1][valid])


def _centres(out, pending):
    """The centres of the cells of `_last_split`, once their edge midpoints are known: to be
    simulated where those disagree (returned, `(i, j, cost)`), else given their outcome."""
    empty = np.zeros(0, np.int64)
    if pending is None or not pending[0].size:
        return empty, empty, np.zeros(0)
    i0, i1, j0, j1, cost = pending
    im, jm = (i0 + i1) // 2, (j0 + j1) // 2
    outcome = out.fields["outcome"]
    around = np.stack([outcome[i0, jm], outcome[i1, jm], outcome[im, j0], outcome[im, j1]])
    differ = np.any(around != around[0], axis=0) & ~out.simulated[im, jm]
    agree = ~differ
    _infer(out, im[agree], jm[agree], i0[agree], jm[agree])
    return im[differ], jm[differ], cost[differ]


def _stop_patches(counts, stopped, out, ib, jb, n_patch_j):
    """Stop the base cells whose boundary does not become simpler (`DIMENSION_STOP`)."""
    for patch in np.flatnonzero(~stopped & (counts.max(axis=1) >= MIN_BOXES)):
        row = counts[patch]
        last = np.flatnonzero(row)[-1]
        if last < 2 or row[last] < MIN_BOXES or row[last - 2] == 0:
            continue
        if math.log2(row[last] / row[last - 2]) / 2 >= DIMENSION_STOP:
            stopped[patch] = True
            a, b = divmod(int(patch), n_patch_j)
            out.stopped.append(
                (int(ib[a]), int(ib[a + 1]), int(jb[b]), int(jb[b + 1]), box_dimension(row))
            )


def _fill(out: _Store, leaves, unresolved):
    """The points not simulated: inside a cell kept whole, its corners' outcome; inside a
    cell of a base cell that stopped refining, the nearest corner's (`resolved` False)."""
    f = out.fields
    outcome, settled, result = f["outcome"], f["settled"], f["result"]
    for i0, i1, j0, j1 in zip(*leaves):
        if i1 - i0 <= 1 and j1 - j0 <= 1:
            continue
        block = (slice(i0, i1 + 1), slice(j0, j1 + 1))
        todo = ~out.simulated[block]
        outcome[block][todo] = outcome[i0, j0]
        result[block][todo] = result[i0, j0]
        settled[block][todo] = settled[i0, j0] & settled[i0, j1] & settled[i1, j0] & settled[i1, j1]
    for i0, i1, j0, j1 in zip(*unresolved):
        block = (slice(i0, i1 + 1), slice(j0, j1 + 1))
        todo = ~out.simulated[block]
        ii, jj = np.meshgrid(np.arange(i0, i1 + 1), np.arange(j0, j1 + 1), indexing="ij")
        near_i = np.where(ii - i0 <= i1 - ii, i0, i1)
        near_j = np.where(jj - j0 <= j1 - jj, j0, j1)
        for name in ("outcome", "result", "settled"):
            f[name][block][todo] = f[name][near_i, near_j][todo]
        out.resolved[block][todo] = False
