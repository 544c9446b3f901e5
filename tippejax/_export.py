"""Results as numpy arrays, CSV, `.npz` and xarray (for `Solution.to_*`)."""

from __future__ import annotations

import csv

import numpy as np

SERIES = (
    "theta",
    "phi",
    "psi",
    "theta_dot",
    "phi_dot",
    "psi_dot",
    "spin",
    "jellet",
    "energy",
    "normal_force",
    "slip_speed",
)
VECTORS = ("position", "velocity")
PER_RUN = (
    "t_invert",
    "t_contact_loss",
    "t_chart_switch",
    "t_final",
    "num_steps",
    "num_rejected_steps",
)
OPTIONAL_PER_RUN = ("t_stem", "t_ball_return", "t_hand_over")
"""Event times some results carry (exported when present)."""


def solution_dict(sol, messages, outcome_names) -> dict[str, np.ndarray]:
    """`sol`'s arrays by name (see `Solution.to_dict`)."""
    out = {"ts": np.asarray(sol.ts)}
    for name in (*SERIES, *VECTORS):
        out[name] = np.asarray(getattr(sol, name))
    for name in (*PER_RUN, *OPTIONAL_PER_RUN):
        value = getattr(sol, name, None)
        if value is not None:
            out[name] = np.asarray(value)
    out["result"] = np.asarray(sol.result._value)
    out["message"] = np.asarray(messages)
    if sol.outcome is not None:
        codes = np.asarray(sol.outcome)
        out["outcome"] = codes
        out["outcome_name"] = np.asarray(outcome_names)[codes]
        out["settled"] = np.asarray(sol.settled)
    if sol.inputs is not None:
        for name, value in sol.inputs.items():
            out[f"inputs.{name}"] = np.asarray(value)
    return out


def _last_saved(series: np.ndarray, batch_ndim: int, trailing: int = 0) -> np.ndarray:
    """The value at the last save time (the series' axis after the batch's; `trailing` axes
    of components after it)."""
    if series.ndim == batch_ndim + trailing:  # summary mode of a batch: the final value
        return series
    return np.take(series, -1, axis=batch_ndim)


def write_csv(arrays: dict, path, *, batch_ndim: int) -> None:
    """One row per member: inputs, per-run values and each series' last saved value."""
    shape = np.shape(arrays["t_final"])
    columns: dict[str, np.ndarray] = {}
    for name, value in arrays.items():
        if name.startswith("inputs."):
            columns[name[len("inputs.") :]] = value
    for name in (*PER_RUN, *OPTIONAL_PER_RUN, "outcome_name", "settled", "message"):
        if name in arrays:
            columns["outcome" if name == "outcome_name" else name] = arrays[name]
    for name in SERIES:
        columns[f"{name}_end"] = _last_saved(arrays[name], batch_ndim)
    for name in VECTORS:
        last = _last_saved(arrays[name], batch_ndim, trailing=1)
        columns[f"{name}_x_end"], columns[f"{name}_y_end"] = last[..., 0], last[..., 1]
    flat = {k: np.broadcast_to(v, shape).ravel() for k, v in columns.items()}
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(list(flat))
        for row in zip(*flat.values()):
            writer.writerow([_cell(x) for x in row])


def _cell(x):
    if isinstance(x, (bool, np.bool_)):
        return str(bool(x))
    if isinstance(x, (float, np.floating)):
        return repr(float(x))
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    return str(x)


def write_npz(arrays: dict, path, *, grid, model: str) -> None:
    extra = {
        "grid": np.asarray(grid if grid is not None else (), dtype=str),
        "model": np.asarray(model),
    }
    np.savez_compressed(path, **arrays, **extra)


def to_xarray(arrays: dict, *, batch_shape, grid, model: str):
    try:
        import xarray as xr
    except ImportError:  # pragma: no cover - depends on the environment
        raise ImportError(
            "Solution.to_xarray needs xarray, an optional dependency: pip install xarray "
            "(or pip install 'tippejax[xarray]')."
        ) from None
    ndim = len(batch_shape)
    if grid is not None and len(grid) == ndim:
        dims = tuple("top" if g == "top" else (g if g == "theta0" else f"{g}0") for g in grid)
    else:
        dims = tuple(f"member_{k}" for k in range(ndim))
    ts = arrays["ts"]
    summary = arrays["theta"].ndim == ndim
    if not summary:
        times = ts.reshape(-1, ts.shape[-1])
        same = np.all(np.isclose(times, times[:1], equal_nan=True))
    data = {}
    for name in SERIES:
        if summary:
            data[name] = (dims, arrays[name])
        else:
            data[name] = ((*dims, "time"), arrays[name])
    for name in VECTORS:
        data[name] = ((*dims, "xy") if summary else (*dims, "time", "xy"), arrays[name])
    for name in (
        *PER_RUN,
        *OPTIONAL_PER_RUN,
        "result",
        "message",
        "outcome",
        "outcome_name",
        "settled",
    ):
        if name in arrays:
            data[name] = (dims, arrays[name])
    coords = {}
    if not summary:
        if same:
            coords["time"] = times[0]
        else:
            data["ts"] = ((*dims, "time"), ts)
    inputs = {k[len("inputs.") :]: v for k, v in arrays.items() if k.startswith("inputs.")}
    for axis, dim in enumerate(dims):
        if dim in inputs:  # the grid axis's values as its index coordinate
            values = inputs.pop(dim)
            index = tuple(slice(None) if i == axis else 0 for i in range(ndim))
            coords[dim] = values[index]
        elif dim == "top":
            coords[dim] = np.arange(batch_shape[axis])
    for name, value in inputs.items():
        coords[name] = (dims, np.asarray(value))
    attrs = {"model": model, "grid": list(grid) if grid is not None else []}
    return xr.Dataset(data, coords=coords, attrs=attrs)
