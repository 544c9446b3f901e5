"""`simulate`'s checks of its arguments, and the save grid and tolerances they give."""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np

from .._bucket import bucket
from .._engine.solver_choice import is_traced
from .._errors import error_if
from .._state import State
from .._top import TippeTop


def concrete(*xs) -> bool:
    """Whether no leaf of `xs` is traced (under `jit`, `vmap` or `grad`)."""
    return not any(is_traced(x) for x in jax.tree_util.tree_leaves(xs))


def as_dtype(x, dtype):
    """`x` as an array of `dtype`: a jax array or tracer of that dtype as it is, else
    converted by `jnp.asarray`; a host value stays on the host as a numpy array of `dtype`
    (no program, no transfer of its own: the call's inputs go to the device together)."""
    if isinstance(x, jax.Array) or is_traced(x):
        return x if jnp.result_type(x) == dtype else jnp.asarray(x, dtype)
    return np.asarray(x, dtype)


def check_top_and_state(top: TippeTop, y0: State):
    if not isinstance(top, TippeTop):
        raise TypeError(f"top must be a tippejax.TippeTop, got {type(top).__name__}.")
    if not isinstance(y0, State):
        raise TypeError(
            f"y0 must be a tippejax.State (see tj.initial_state), got {type(y0).__name__}."
        )
    shapes = {jnp.shape(x) for x in jax.tree_util.tree_leaves(top)}
    if shapes != {()}:
        raise ValueError(
            f"simulate takes one top, but this TippeTop has fields of shape {sorted(shapes)}. "
            "For a sweep of tops or launches use tj.simulate_batch(tops, theta0, spin, t1, "
            "grid=...), or jax.vmap(lambda top: tj.simulate(top, ...))(tops)."
        )
    if y0.axis.shape != (3,):
        raise ValueError(
            f"simulate takes one state, but y0.axis has shape {y0.axis.shape}. Use jax.vmap over "
            "states (or tj.simulate_batch) for a batch."
        )


def check_stem(model: str, top: TippeTop, y0: State) -> None:
    """A top with a stem runs at the full level only, from a launch whose stem is clear of the
    table (concrete values); else a `ValueError` saying what is allowed."""
    if top.stem is None:
        return
    if jnp.result_type(top.m) != jnp.float64:
        raise ValueError(
            "A top with a stem (tj.Stem) runs in float64 only: the stem level's compliant "
            "contacts are pressed in by about (m g/k)^(2/3) (1e-7 m for a hard top), which a "
            "float32 height and axis resolve to a part in a few hundred at a top's size, and "
            "the noisy contact forces stall the steps. Pass a float64 top (the default)."
        )
    if model != "full":
        raise ValueError(
            f"model={model!r}: a top with a stem (tj.Stem) runs at the full level only, which "
            "hands over to the stem level (two compliant contacts) before the stem touches. "
            "Use model='full' (or 'auto'), or take the stem off: top.replace(stem=None)."
        )
    if concrete(top, y0.axis):
        theta0 = float(np.arccos(np.clip(np.asarray(y0.axis)[2], -1.0, 1.0)))
        theta_s = float(top.stem_angle)
        if theta0 >= theta_s:
            raise ValueError(
                f"The launch tilt theta0 = {theta0:.6g} rad puts the stem on or below the table "
                f"(with the ball on it the stem touches at theta_s = {theta_s:.6g} rad, "
                "top.stem_angle). Launch a top with a stem at theta0 < theta_s."
            )


def warn_of_friction(top: TippeTop) -> None:
    """A `UserWarning` for a law whose inversion time is not a property of the top
    (`AbstractFriction.inversion_time_caveat`; concrete tops)."""
    if not concrete(top):
        return
    caveat = top.friction.inversion_time_caveat()
    if caveat is not None:
        warnings.warn(caveat, UserWarning, stacklevel=3)  # (at the caller of simulate)


_STATE_TOL = 1e-6
_STATE_MESSAGE = (
    "y0 is not a valid state: its axis and body vectors must be unit vectors, perpendicular to "
    f"each other (within {_STATE_TOL:g}), and every field finite. Build states with "
    "tj.initial_state or tj.state_from_euler."
)


def _state_defect(y0: State, xp=jnp):
    """How far `y0`'s axis and body vectors are from unit vectors perpendicular to each other
    (inf if a field is not finite); `xp=np` for a concrete state (no device programs)."""
    a, b = y0.axis, y0.body
    defect = xp.maximum(xp.abs(xp.sum(a * a) - 1), xp.abs(xp.sum(b * b) - 1))
    defect = xp.maximum(defect, xp.abs(xp.sum(a * b)))
    finite = xp.all(xp.stack([xp.all(xp.isfinite(x)) for x in jax.tree_util.tree_leaves(y0)]))
    return xp.where(finite, defect, xp.inf)


def _check_tolerances(rtol, atol):
    for name, value, lowest in (("rtol", rtol, "> 0"), ("atol", atol, ">= 0")):
        if concrete(value):
            v = float(value)
            bad = not np.isfinite(v) or (v <= 0 if name == "rtol" else v < 0)
            if bad:
                raise ValueError(f"{name} must be finite and {lowest}, got {value}.")


def _check_saveat(saveat, t0, t1, dtype):
    """`saveat` checked, as a numpy array where it and the times are concrete (no device
    program), else as a traced array that raises at run time if it is out of order."""
    on_host = concrete(saveat, t0, t1)
    ts = np.asarray(saveat, dtype=dtype) if on_host else jnp.asarray(saveat, dtype=dtype)
    if ts.ndim != 1 or ts.shape[0] < 1:
        raise ValueError(f"saveat must be a 1-d array of save times, got shape {ts.shape}.")
    if on_host:
        arr = np.asarray(ts, dtype=float)
        if not np.all(np.isfinite(arr)):
            raise ValueError("saveat must hold finite times.")
        if np.any(np.diff(arr) < 0):
            raise ValueError("saveat must be non-decreasing.")
        # The same rounding as the save times themselves (float32 tops round t1 too).
        lo, hi = float(np.asarray(t0, dtype)), float(np.asarray(t1, dtype))
        if arr[0] < lo or arr[-1] > hi:
            raise ValueError(
                f"saveat must lie within [t0, t1] = [{t0}, {t1}], got times from {arr[0]} to "
                f"{arr[-1]}. Pass a larger t1 or drop the later save times."
            )
    else:
        bad = (ts[0] < t0) | (ts[-1] > t1) | jnp.any(jnp.diff(ts) < 0)
        ts = error_if(ts, bad, "saveat must be non-decreasing and lie within [t0, t1].")
    return ts


def check_run_options(max_steps, event_pieces, t0, t1, rtol, atol, summary, saveat, body):
    """`simulate`'s checks of its options past the model, the top and the state."""
    if not (isinstance(max_steps, (int, np.integer)) and max_steps > 0):
        raise ValueError(f"max_steps must be a positive integer, got {max_steps!r}.")
    if not (isinstance(event_pieces, (int, np.integer)) and event_pieces >= 1):
        raise ValueError(f"event_pieces must be a positive integer, got {event_pieces!r}.")
    if concrete(t0, t1) and not float(t1) > float(t0):
        raise ValueError(f"t1 must be greater than t0, got t0={t0}, t1={t1}.")
    _check_tolerances(rtol, atol)
    if summary and saveat is not None:
        raise ValueError("Pass either saveat or summary=True, not both.")
    if body is not None and not isinstance(body, (bool, np.bool_)):
        raise ValueError(f"body must be True, False or None (the default), got {body!r}.")


def tolerances_for(dtype, rtol, atol):
    """`rtol`, `atol` raised to at least 1e-5 and 1e-7 for a float32 top."""
    if dtype != jnp.float64:
        if concrete(rtol, atol):
            rtol, atol = max(float(rtol), 1e-5), max(float(atol), 1e-7)
        else:
            rtol, atol = jnp.maximum(rtol, 1e-5), jnp.maximum(atol, 1e-7)
    return rtol, atol


def save_times(summary, saveat, t0, t1, dtype):
    """The save grid a run uses (None in summary mode), padded to its bucket, and the number
    of save times asked for (None in summary mode)."""
    if summary:
        ts = None
    elif saveat is None:
        if concrete(t0, t1):  # (numpy: no device program for a default grid)
            ts = np.linspace(np.asarray(t0, dtype), np.asarray(t1, dtype), 1001, dtype=dtype)
        else:
            ts = jnp.linspace(t0, t1, 1001, dtype=dtype)
    else:
        ts = _check_saveat(saveat, t0, t1, dtype)
    # Save grids are padded to a bucket length (the next power of two, at least 16) with
    # copies of the last time, and the outputs cut back: a new length of `saveat` reuses the
    # compiled program of its bucket instead of compiling anew.
    n_save = None if ts is None else int(ts.shape[0])
    if ts is not None:
        size = bucket(n_save)
        xp = np if isinstance(ts, np.ndarray) else jnp
        if size > n_save:
            ts = xp.concatenate([ts, xp.broadcast_to(ts[-1:], (size - n_save,))])
    return ts, n_save


def checked_state(y0: State) -> State:
    """`y0`, checked to be a valid state (`_state_defect`): a `ValueError` for a concrete
    state, a runtime check (`tippejax._errors`) for a traced one."""
    if concrete(y0):  # (checked in numpy: no device program)
        defect = _state_defect(jax.tree_util.tree_map(np.asarray, jax.device_get(y0)), xp=np)
        if not float(defect) < _STATE_TOL:
            raise ValueError(_STATE_MESSAGE)
        return y0
    defect = _state_defect(y0)
    return error_if(y0, ~(defect < _STATE_TOL), _STATE_MESSAGE)
