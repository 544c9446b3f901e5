"""The slow observables of the data, in numpy: the kernel smoother and the ladder of levels."""

from __future__ import annotations

import numpy as np

from .problem import NUM_LEVELS
from .setup import bucket

MAX_BINS = 512  # the smoother's time bins (fewer for a record with fewer samples)


def smoother(ts: np.ndarray, nutation_period: float):
    r"""A Gaussian kernel smoother from the data times onto a uniform grid, through time bins.

    The samples are first summed into `B` uniform time bins (each bin stands at the mean time of
    its samples), and the bin sums are then smoothed onto the grid by a Gaussian kernel of
    width $w$ cut at $4w$:
    $$\bar y(g) = \frac{\sum_j K(g - c_j)\,\sum_{k \in j} m_k y_k}
                      {\sum_j K(g - c_j)\,\sum_{k \in j} m_k}.$$
    Returns `((bins, kernel), grid)`: the bin of each sample, shape `(n,)`, the kernel from
    the bins to the grid, shape `(G, B)`, and the grid.

    The width is wider than 2.5 nutation periods (so that it averages the nutation out), than
    4 sample spacings and than 1/80 of the record (and at most 1/8 of it). It follows the
    guess's spin, but no shape does: `G` is set by the narrowest width the record allows and
    `B` by its number of samples, so a guess with another spin runs the programs already
    compiled. With `B` = min(512, n) bins, a bin is at most 1/6 of the narrowest width."""
    span = ts[-1] - ts[0]
    floor = min(max(span / 80.0, 4.0 * float(np.median(np.diff(ts)))), span / 8.0)
    width = min(max(floor, 2.5 * nutation_period), span / 8.0)
    # grid sizes in buckets too: fewer compilations
    num = bucket(int(min(max(np.ceil(4 * span / floor) + 1, 50), 1500)))
    grid = np.linspace(ts[0], ts[-1], num)
    count = min(MAX_BINS, bucket(ts.size))
    bins = np.clip(np.floor((ts - ts[0]) / span * count).astype(int), 0, count - 1)
    filled = np.bincount(bins, minlength=count)
    centres = np.where(
        filled > 0,
        np.bincount(bins, weights=ts, minlength=count) / np.maximum(filled, 1),
        ts[0] + (np.arange(count) + 0.5) * span / count,
    )
    offset = (grid[:, None] - centres[None, :]) / width
    kernel = np.where(np.abs(offset) <= 4.0, np.exp(-0.5 * offset**2), 0.0)
    return (bins, kernel), grid


def smooth_numpy(theta: np.ndarray, mask: np.ndarray, band) -> np.ndarray:
    """`problem.smoothed` in numpy (for the data)."""
    bins, kernel = band
    count = kernel.shape[-1]
    y = mask * np.nan_to_num(theta)
    sums = np.bincount(bins, weights=y[: bins.size], minlength=count)
    weights = np.bincount(bins, weights=mask[: bins.size], minlength=count)
    return (kernel @ sums) / np.maximum(kernel @ weights, 1e-300)


def ladder(smooth: np.ndarray, grid: np.ndarray):
    """Levels between the smoothed start and maximum, and the data's first crossing times.

    Returns the levels, their times and whether the record rises enough (0.3 rad) to use them.
    """
    start, top = smooth[0], smooth.max()
    rises = top - start > 0.3
    lo, hi = start + 0.1 * (top - start), top - 0.1 * (top - start)
    levels = np.linspace(lo, hi, NUM_LEVELS) if rises else np.zeros(NUM_LEVELS)
    times = first_crossings_numpy(smooth, grid, levels)
    return levels, times, rises


def first_crossings_numpy(smooth: np.ndarray, grid: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """`problem.first_crossings` in numpy (for the data: no small programs to compile in a new
    process)."""
    smooth, grid = np.asarray(smooth, float), np.asarray(grid, float)
    out = np.empty(len(levels))
    for i, level in enumerate(np.asarray(levels, float)):
        above = smooth >= level
        k = max(int(np.argmax(above)), 1)
        lo, hi = smooth[k - 1], smooth[k]
        frac = np.clip((level - lo) / (hi - lo if hi > lo else 1.0), 0.0, 1.0)
        t_hit = grid[k - 1] + frac * (grid[k] - grid[k - 1])
        t_miss = grid[-1] + (level - smooth.max()) * (grid[-1] - grid[0]) / np.pi
        out[i] = t_hit if above.any() else t_miss
    return out
