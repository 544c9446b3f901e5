"""The two axes of a map: names, values, checks, and the launches and tops of its points."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import numpy as np

from .._batch import LAUNCH
from .._state import check_theta0
from .._top import _BODY_FIELDS, TippeTop

RATIOS = ("A_over_C", "eps_over_R")
TOP_FIELDS = (*_BODY_FIELDS, "mu", *RATIOS)
"""The fields of the top a map can sweep (`TippeTop.replace`'s names); besides them, the
friction law's own parameters (`law_fields`)."""

_SAME_FIELD = (("A", "A_over_C"), ("eps", "eps_over_R"))


def law_fields(top: TippeTop) -> tuple[str, ...]:
    """The array fields of the top's friction law other than `mu` (e.g. `slip_scale`,
    `patch_radius`): map axes too."""
    return tuple(
        f.name
        for f in dataclasses.fields(top.friction)
        if not f.metadata.get("static") and f.name != "mu"
    )


def quantity_names(top: TippeTop) -> tuple[str, ...]:
    """Every name a map of `top` takes, in the order the default axes follow: the launch
    quantities (`simulate_batch`'s), the top's fields, its friction law's parameters."""
    return (*LAUNCH, *TOP_FIELDS, *law_fields(top))


class MapAxes(eqx.Module):
    """The axes of a map and the values of every other quantity it fixes."""

    names: tuple[str, str] = eqx.field(static=True)
    values: tuple[np.ndarray, np.ndarray]  # each 1-d, strictly monotone
    fixed: dict[str, float]  # the other quantities given (launch quantities and top fields)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.values[0].size, self.values[1].size)

    @property
    def top_varies(self) -> bool:
        """Whether an axis is a field of the top (then every point has a top of its own)."""
        return any(name not in LAUNCH for name in self.names)

    def launches(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """The launch quantities of the points `(i, j)` (grid indices): shape `(N, 8)`, rows
        in the order of `LAUNCH`."""
        return self.launches_at(self.values[0][i], self.values[1][j])

    def tops(self, top: TippeTop, i: np.ndarray, j: np.ndarray) -> TippeTop:
        """The tops of the points `(i, j)`: `top` with its fields on the axes set (a batch,
        checked as `TippeTop` checks one), or `top` itself if no axis is a top field."""
        return self.tops_at(top, self.values[0][i], self.values[1][j])

    def launches_at(self, first: np.ndarray, second: np.ndarray) -> np.ndarray:
        """`launches` at any values `first`, `second` of the two axes."""
        first, second = np.broadcast_arrays(np.asarray(first, float), np.asarray(second, float))
        out = np.zeros((first.size, len(LAUNCH)))
        for k, name in enumerate(LAUNCH):
            if name == self.names[0]:
                out[:, k] = first.ravel()
            elif name == self.names[1]:
                out[:, k] = second.ravel()
            else:
                out[:, k] = self.fixed.get(name, 0.0)
        return out

    def tops_at(self, top: TippeTop, first: np.ndarray, second: np.ndarray) -> TippeTop:
        """`tops` at any values `first`, `second` of the two axes."""
        first, second = np.broadcast_arrays(np.asarray(first, float), np.asarray(second, float))
        changes = {
            name: v.ravel() for name, v in zip(self.names, (first, second)) if name not in LAUNCH
        }
        return with_fields(top, changes) if changes else top


def with_fields(top: TippeTop, changes: dict) -> TippeTop:
    """`top` with the fields and law parameters `changes` set (arrays make a batch)."""
    law = {k: v for k, v in changes.items() if k == "mu" or k in law_fields(top)}
    body = {k: v for k, v in changes.items() if k not in law}
    if law:
        body["friction"] = top.friction.replace(**law)
    return top.replace(**body)


def _as_values(where: str, name: str, value) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(
            f"{where}: {name} must be a number or a 1-d list of numbers, got "
            f"{type(value).__name__}."
        ) from None
    if array.ndim > 1:
        raise ValueError(
            f"{where}: {name} must be a number or a 1-d list (an axis), got shape {array.shape}."
        )
    if array.size == 0:
        raise ValueError(f"{where}: {name} is empty.")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{where}: {name} must be finite (got NaN or inf).")
    return array


def _check_monotone(where: str, name: str, values: np.ndarray) -> None:
    if values.size < 2:
        return
    step = np.diff(values)
    if not (np.all(step > 0) or np.all(step < 0)):
        k = int(np.argmax(step <= 0) if step[0] > 0 else np.argmax(step >= 0))
        raise ValueError(
            f"{where}: the {name} axis must be strictly increasing or strictly decreasing "
            f"(its cells and boundaries follow the order of its values); it goes "
            f"{values[k]:g}, {values[k + 1]:g} at index {k}. Sort it (np.sort) and drop "
            "repeated values (np.unique)."
        )


def map_axes(where: str, top: TippeTop, given: dict, axes=None) -> MapAxes:
    """The axes of a map from the quantities `given` ({name: number or 1-d list}) and the
    optional `axes` (two names), checked.

    Without `axes`, the axes are the quantities given as 1-d lists, in the order of
    `quantity_names`; where fewer than two are, `theta0` and then `spin` (given as numbers)
    fill in, as axes of length 1. Every other quantity must be a number."""
    names = quantity_names(top)
    unknown = [k for k in given if k not in names]
    if unknown:
        raise ValueError(
            f"{where}: unknown quantity {unknown[0]!r}. A map's axes and fixed values are "
            f"launch quantities {LAUNCH}, fields of the top {TOP_FIELDS}"
            + (f" or parameters of its friction law {law_fields(top)}" if law_fields(top) else "")
            + "."
        )
    given = {k: v for k, v in given.items() if v is not None}
    for a, b in _SAME_FIELD:
        if a in given and b in given:
            raise ValueError(f"{where}: give {a} or {b}, not both (both set the top's {a}).")
    for name in ("theta0", "spin"):
        if name not in given:
            raise ValueError(
                f"{where}: give {name} (a number, or a 1-d list for an axis): every launch "
                "needs its tilt theta0 (rad) and spin (rad/s)."
            )
    values = {k: _as_values(where, k, v) for k, v in given.items()}
    if axes is None:
        chosen = [k for k in names if k in values and values[k].ndim == 1]
        if len(chosen) > 2:
            raise ValueError(
                f"{where}: a map has two axes, but {len(chosen)} quantities are 1-d lists "
                f"({', '.join(chosen)}); give the others as numbers, or name the two axes "
                "with axes=(..., ...)."
            )
        for name in ("theta0", "spin"):
            if len(chosen) < 2 and name not in chosen:
                chosen.append(name)
        chosen.sort(key=names.index)
    else:
        if isinstance(axes, str) or len(tuple(axes)) != 2:
            raise ValueError(f"{where}: axes must name two quantities, got {axes!r}.")
        chosen = list(axes)
        if chosen[0] == chosen[1]:
            raise ValueError(f"{where}: axes names {chosen[0]!r} twice; a map has two axes.")
        for name in chosen:
            if name not in names:
                raise ValueError(f"{where}: axes names {name!r}, which is not one of {names}.")
            if name not in values:
                raise ValueError(f"{where}: axes names {name!r}; give its values ({name}=[...]).")
        others = [k for k in values if k not in chosen and values[k].ndim == 1]
        if others:
            raise ValueError(
                f"{where}: {', '.join(others)} given as 1-d lists, but the axes are "
                f"{tuple(chosen)}; give the other quantities as numbers."
            )
    for a, b in _SAME_FIELD:
        if a in chosen and b in chosen:
            raise ValueError(f"{where}: the axes {a} and {b} both set the top's {a}.")
    axis_values = []
    for name in chosen:
        v = np.atleast_1d(values[name])
        _check_monotone(where, name, v)
        axis_values.append(v)
    if "theta0" in values:
        check_theta0(f"{where}: theta0", values["theta0"])
    fixed = {k: float(v) for k, v in values.items() if k not in chosen}
    # The top's fields on an axis, and the fixed ones, checked as a TippeTop checks them.
    try:
        base = with_fields(top, {k: v for k, v in fixed.items() if k not in LAUNCH})
        for name, v in zip(chosen, axis_values):
            if name not in LAUNCH:
                with_fields(base, {name: v})
    except ValueError as err:
        raise ValueError(f"{where}: {err}") from None
    return MapAxes(names=tuple(chosen), values=tuple(axis_values), fixed=fixed)


def base_top(top: TippeTop, axes: MapAxes) -> TippeTop:
    """`top` with the fixed top fields of the map set."""
    changes = {k: v for k, v in axes.fixed.items() if k not in LAUNCH}
    return with_fields(top, changes) if changes else top
