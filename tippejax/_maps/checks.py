"""The checks of `outcome_map`'s and `outcome_map_tops`' arguments."""

from __future__ import annotations

import math

import jax
import numpy as np

from .._simulate import MODELS
from .._top import TippeTop

MAX_REFINE = 16
"""The most levels of refinement `outcome_map(refine=...)` takes (a base grid 65536 times
coarser than the map)."""


def _check_common(where, model, t1, rtol, atol, settle_tol, chunk_size):
    if model not in MODELS:
        raise ValueError(f"{where}: unknown model {model!r}; choose one of {MODELS}.")
    if not (isinstance(t1, (int, float, np.number)) and math.isfinite(t1) and t1 > 0):
        raise ValueError(f"{where}: t1 must be a positive finite time (s), got {t1!r}.")
    for name, value in (("rtol", rtol), ("atol", atol), ("settle_tol", settle_tol)):
        if not (isinstance(value, (int, float, np.number)) and value > 0):
            raise ValueError(f"{where}: {name} must be a positive number, got {value!r}.")
    if (
        isinstance(chunk_size, bool)
        or not isinstance(chunk_size, (int, np.integer))
        or chunk_size < 1
    ):
        raise ValueError(f"{where}: chunk_size must be a positive integer, got {chunk_size!r}.")


def _check_refine(where, refine) -> int:
    if refine is None:
        return 0
    if (
        isinstance(refine, bool)
        or not isinstance(refine, (int, np.integer))
        or not (0 <= refine <= MAX_REFINE)
    ):
        raise ValueError(
            f"{where}: refine must be None (a dense map) or an integer from 0 to {MAX_REFINE} "
            f"(levels of refinement: the base grid is every 2**refine-th value of each axis), "
            f"got {refine!r}."
        )
    return int(refine)


def _check_one_top(where: str, top) -> None:
    if not isinstance(top, TippeTop):
        raise ValueError(f"{where}: top must be a tippejax.TippeTop, got {type(top).__name__}.")
    shapes = {np.shape(x) for x in jax.tree_util.tree_leaves(top)}
    if shapes != {()}:
        raise ValueError(
            f"{where} maps one top, but this TippeTop is a batch (field shapes "
            f"{sorted(shapes)}). Give the field as an axis of the map instead "
            "(tj.outcome_map(top, mu=[...], spin=[...], theta0=...)), use tj.outcome_map_tops "
            "for a grid of A/C x eps/R, or tj.simulate_batch(tops, ...) with sol.outcome for "
            "a sweep of tops."
        )


def _ratio_axis(name, values, *, low, high, what):
    values = np.atleast_1d(np.asarray(values, dtype=float))
    if values.ndim != 1 or values.size == 0:
        raise ValueError(
            f"outcome_map_tops: {name} must be a non-empty 1-d list, got shape {values.shape}."
        )
    if not np.all(np.isfinite(values)):
        raise ValueError(f"outcome_map_tops: {name} must be finite (got NaN or inf).")
    if np.any(values < low) or np.any(values > high):
        raise ValueError(
            f"outcome_map_tops: {name} must lie in [{low}, {high}]{what}; got "
            f"{values.min():g} to {values.max():g}."
        )
    return values
