"""The inputs of `fit`: every argument checked before anything compiles, and the data set up."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._cache import to_device
from .._models.levels import levels_taking
from .._simulate import MODELS
from .._state import State
from .._top import TippeTop, _checks
from .params import (
    BODY_FIELDS,
    FREE_NAMES,
    LAW_FIELDS,
    NAMES,
    Base,
    identifiable,
    launch_of,
    law_fields,
    law_options,
    units,
)
from .problem import Config, Data
from .setup import Setup, bucket
from .smoothing import ladder, smooth_numpy, smoother

METHODS = ("levenberg_marquardt", "gauss_newton", "adam")
"""The optimisers of `fit(method=...)`."""

FIT_MODELS = ("full", "so3", "routhian")
"""The levels of model `fit(model=...)` fits with."""

LAUNCH_TIME = 0.0
"""The default launch time of `fit` (s): `y0_guess` is the state at t = 0, as in `simulate`."""

MAX_RECORD_SPAN = 600.0  # s: a longer record is taken for times in the wrong unit


def check_options(free, model, method, strategy, max_steps, tol, sigma, strategies):
    """The options of `fit`, checked; returns `free` as a tuple. `strategies` is the table of
    strategies `fit` chooses from."""
    if isinstance(free, str):
        raise ValueError(
            f"free must be a sequence of names, e.g. free=({free!r},) or ('mu', 'eps', 'spin'), "
            f"not the string {free!r} (which would be read letter by letter)."
        )
    free = tuple(free)
    unknown = [n for n in free if n not in NAMES]
    if unknown:
        raise ValueError(
            f"Unknown names in free: {unknown}; choose from {FREE_NAMES} (a top with the "
            f"viscous law), the fields of the top's friction law ({LAW_FIELDS[1:]} where it "
            "has them) and the launch time 't0'."
        )
    if not free:
        raise ValueError(f"free is empty; name at least one of {FREE_NAMES}.")
    if len(set(free)) != len(free):
        raise ValueError(f"free names a parameter twice: {free}.")
    if model not in FIT_MODELS:
        allowed = tuple(m for m in MODELS if m in FIT_MODELS)
        raise ValueError(f"fit supports model in {allowed}, got {model!r}.")
    if method not in METHODS:
        raise ValueError(f"Unknown method {method!r}; choose one of {METHODS}.")
    if strategy not in strategies:
        raise ValueError(f"Unknown strategy {strategy!r}; choose one of {tuple(strategies)}.")
    if not (isinstance(max_steps, (int, np.integer)) and max_steps > 0):
        raise ValueError(f"max_steps must be a positive integer, got {max_steps!r}.")
    if not tol > 0:
        raise ValueError(f"tol must be positive, got {tol}.")
    if sigma is not None and not (np.isfinite(sigma) and sigma > 0):
        raise ValueError(f"sigma must be a positive noise level (rad), got {sigma}.")
    return free


def as_1d_times(ts) -> np.ndarray:
    """`ts` as a 1-d float array of increasing finite times in seconds, checked."""
    arr = np.asarray(ts, dtype=float)
    if arr.ndim != 1 or arr.size < 2:
        raise ValueError(f"ts must be a 1-d array of at least 2 times, got shape {arr.shape}.")
    if not np.all(np.isfinite(arr)):
        raise ValueError(
            "ts must hold finite times (NaN or inf found); mark missing data with "
            "NaN in theta_obs instead."
        )
    if np.any(np.diff(arr) <= 0):
        raise ValueError("ts must be strictly increasing.")
    span = arr[-1] - arr[0]
    if span > MAX_RECORD_SPAN:
        raise ValueError(
            f"ts spans {span:g}, but times are in seconds and a tippe top's record lasts seconds "
            f"to a minute (at most {MAX_RECORD_SPAN:g} s here). Were the times given in "
            "milliseconds? Pass ts / 1000."
        )
    return arr


def observations(name, obs, n) -> np.ndarray:
    """`theta_obs` or `phi_obs` (`name`) as a float array of shape `(N,)` or `(batch, N)`, checked."""
    arr = np.asarray(obs, dtype=float)
    if arr.ndim not in (1, 2) or arr.shape[-1] != n:
        raise ValueError(
            f"{name} must have shape (N,) or (batch, N) with N = len(ts) = {n}, got {arr.shape}."
        )
    if np.any(np.isinf(arr)):
        raise ValueError(f"{name} holds inf; use NaN to mark missing samples (they are masked).")
    if name == "theta_obs":
        finite = arr[np.isfinite(arr)]
        if finite.size and (finite.max() > np.pi + 0.5 or finite.min() < -0.5):
            raise ValueError(
                f"theta_obs holds values from {finite.min():.4g} to {finite.max():.4g}, but the "
                "tilt is in radians, between 0 and pi. Were they given in degrees? Pass "
                "np.deg2rad(theta_obs)."
            )
    return arr


def check_guess(top_guess, y0_guess, free, batch):
    """The guesses checked; returns their top fields and launch quantities in numpy."""
    if not isinstance(top_guess, TippeTop):
        raise TypeError(f"top_guess must be a tippejax.TippeTop, got {type(top_guess).__name__}.")
    if not isinstance(y0_guess, State):
        raise TypeError(
            f"y0_guess must be a tippejax.State (see initial_state), got {type(y0_guess).__name__}."
        )
    law = top_guess.friction
    check_law(law, free)
    fields = {f: np.asarray(getattr(top_guess, f), dtype=float) for f in BODY_FIELDS}
    fields |= {f: np.asarray(getattr(law, f), dtype=float) for f in law_fields(law)}
    for f, v in fields.items():
        where = f if f in BODY_FIELDS else f"friction.{f}"
        if not np.all(np.isfinite(v)):
            raise ValueError(f"top_guess.{where} is not finite.")
        if v.ndim > 1 or (v.ndim == 1 and (batch is None or v.shape[0] != batch)):
            raise ValueError(
                f"top_guess.{where} has shape {v.shape}: a guess is one top, or one per "
                f"recording when theta_obs has shape (batch, N)."
            )
    for failed, message in _checks(*(fields[f] for f in BODY_FIELDS)):
        if np.any(failed):
            raise ValueError(f"top_guess is not a valid top: {message}")
    try:  # the law's own rules, and those that involve the ball
        checked_law = type(law)(**{f: fields[f] for f in law_fields(law)}, **dict(law_options(law)))
    except ValueError as err:
        raise ValueError(f"top_guess is not a valid top: {err}") from None
    for failed, message in checked_law.ball_rules(fields["R"], np):
        if np.any(failed):
            raise ValueError(f"top_guess is not a valid top: {message}")
    for name in ("m", "R", "g", *law_fields(law)):
        if name in free and np.any(fields[name] == 0):
            raise ValueError(
                f"{name!r} is free but its guess is 0 ({units(name, law)}); give a positive guess."
            )
    launch = {k: np.asarray(v, dtype=float) for k, v in launch_of(y0_guess).items()}
    for k, v in launch.items():
        if not np.all(np.isfinite(v)):
            raise ValueError(f"y0_guess gives a non-finite launch quantity {k}.")
    at_pole = np.sin(launch["theta0"]) < 1e-9
    if "theta0" in free and np.any(at_pole):
        raise ValueError(
            "'theta0' is free but the guess is launched at a pole (theta = 0 or pi); free "
            "'theta_dot' instead (the tilt rate that takes the top off the pole), or give a "
            "small non-zero tilt guess."
        )
    if "theta_dot" in free and np.any(at_pole & (launch["theta_dot"] == 0)):
        raise ValueError(
            "'theta_dot' is free and the guess sits at a pole with theta_dot = 0, from which a "
            "model top never leaves; give the guess a non-zero tilt rate."
        )
    if "spin" in free and np.any(launch["spin"] == 0):
        raise ValueError(
            "'spin' is free but the guess has zero spin: give a non-zero guess "
            "(its sign is kept; theta alone cannot tell the spin's direction)."
        )
    if "A" in free and np.any(fields["A"] / fields["C"] <= 0.5):
        raise ValueError("'A' is free but the guess has A/C = 1/2: give A/C > 1/2.")
    if "C" in free and "A" not in free and np.any(fields["C"] >= 2 * fields["A"]):
        raise ValueError("'C' is free but the guess has C >= 2A, which no rigid body has.")
    return fields, launch


def check_law(law, free) -> None:
    """The free names of the friction law's fields, checked against the law `law`."""
    fields, fittable = law_fields(law), identifiable(law)
    name = type(law).__name__
    for n in free:
        if n in LAW_FIELDS and n not in fields:
            raise ValueError(
                f"{n!r} is free, but the top's friction law {name} has no field {n!r} (its "
                f"fields: {', '.join(fields)}). Give the top a law that has it (e.g. "
                "friction=tj.CoulombContensou(...) for 'patch_radius'), or leave it out of free."
            )
        if n in fields and n not in fittable:
            raise ValueError(
                f"{n!r} is free, but a record of the tilt does not determine the {name} law's "
                f"{n} ({units(n, law)}): with a drilling torque the motion converges as "
                "slip_scale -> 0 (docs/friction.md), so a fit would wander along a flat "
                f"valley. Hold it at a small value; the law's fields a fit may free: "
                f"{', '.join(fittable)}."
            )


def check_model(model, law) -> None:
    """The fit's level of model, checked against the top's friction law."""
    taking = tuple(m for m in FIT_MODELS if m in levels_taking(law))
    if model not in taking:
        raise ValueError(
            f"fit model={model!r} is derived for the viscous law only, and this top has a "
            f"{type(law).__name__} law (mu in {law.mu_units}). Fit it with one of the levels "
            f"that take it: {', '.join(repr(m) for m in taking)}."
        )


def nutation_period(fields, launch) -> float:
    """The fast nutation's period of the guess, 2 pi A / (C |n|) (the fast-top limit)."""
    period = (
        2
        * np.pi
        * np.asarray(fields["A"])
        / (np.asarray(fields["C"]) * np.maximum(np.abs(np.asarray(launch["spin"])), 1e-6))
    )
    return float(np.max(period))


class Records(NamedTuple):
    """The checked data of a fit, one row per recording."""

    ts: np.ndarray  # (N,) times
    theta: np.ndarray  # (bsize, N) tilt, NaN where missing
    phi: np.ndarray | None  # (bsize, N) precession angle, or None
    weights: np.ndarray  # (bsize, N)
    mask: np.ndarray  # (bsize, N) bool: a usable sample (finite, weight > 0)
    batch: int | None  # the number of recordings, None for theta_obs of shape (N,)
    t0: float  # the time of the guess


def check_records(ts, theta_obs, phi_obs, weights, t0, free) -> Records:
    """The times, observations and weights of `fit`, checked and shaped as `Records`."""
    ts_np = as_1d_times(ts)
    n = ts_np.size
    obs = observations("theta_obs", theta_obs, n)
    batch = obs.shape[0] if obs.ndim == 2 else None
    obs2 = obs.reshape(-1, n)
    phi2 = None
    if phi_obs is not None:
        phi_arr = observations("phi_obs", phi_obs, n)
        if phi_arr.shape != obs.shape:
            raise ValueError(f"phi_obs has shape {phi_arr.shape}, theta_obs {obs.shape}.")
        phi2 = phi_arr.reshape(-1, n)
    if weights is None:
        w2 = np.ones_like(obs2)
    else:
        w = np.broadcast_to(np.asarray(weights, dtype=float), obs.shape).reshape(-1, n)
        if np.any(~np.isfinite(w)) or np.any(w < 0):
            raise ValueError("weights must be finite and non-negative.")
        w2 = w.copy()
    mask2 = np.isfinite(obs2) & (w2 > 0)
    for b in range(obs2.shape[0]):
        if mask2[b].sum() <= len(free):
            raise ValueError(
                f"Recording {b} has {mask2[b].sum()} usable samples (not NaN) for "
                f"{len(free)} free parameters; a fit needs more samples than parameters."
            )
    given, t0 = t0 is not None, LAUNCH_TIME if t0 is None else float(t0)
    if not np.isfinite(t0):
        raise ValueError(f"t0 (the launch time, s) must be finite, got {t0}.")
    if not t0 <= ts_np[0]:
        raise ValueError(
            f"t0 = {t0:g} s (the launch time{'' if given else ', by default 0 as in simulate'}) "
            f"must not be later than the first observation ts[0] = {ts_np[0]:g} s: y0_guess is "
            "the state at the launch. Pass t0= the launch's time in the record's clock, or "
            "free 't0' (with a guess t0 <= ts[0])."
        )
    span = ts_np[-1] - ts_np[0]
    if not given and ts_np[0] - t0 > span:
        raise ValueError(
            f"The record starts at ts[0] = {ts_np[0]:g} s, longer after the launch at t0 = 0 "
            f"(the default, as in simulate) than it lasts ({span:g} s): y0_guess is the state "
            "at the launch. Pass t0= the launch's time in the record's clock (t0=ts[0] if the "
            "guess is the state at the first frame), or free 't0'."
        )
    return Records(ts=ts_np, theta=obs2, phi=phi2, weights=w2, mask=mask2, batch=batch, t0=t0)


def build_setup(
    top_guess,
    y0_guess,
    records: Records,
    fields,
    launch,
    *,
    free,
    model,
    method,
    max_steps,
    tol,
    rtol,
    atol,
    solver,
    sim_max_steps,
    learning_rate,
) -> Setup:
    """The `Setup` of a fit: the records padded to a bucket length, their smoothed tilt and
    level ladder, and the guess, as the template of every stage's `Data`."""
    ts_np, obs2, mask2, w2, phi2 = (
        records.ts,
        records.theta,
        records.mask,
        records.weights,
        records.phi,
    )
    t0, batched = records.t0, records.batch is not None
    dtype = jnp.result_type(top_guess.m)
    bsize, n = obs2.shape
    band, grid = smoother(ts_np, nutation_period(fields, launch))
    smooth_obs = np.stack(
        [smooth_numpy(obs2[b], mask2[b].astype(float), band) for b in range(bsize)]
    )
    ladders = [ladder(smooth_obs[b], grid) for b in range(bsize)]
    rises = np.array([lad[2] for lad in ladders])

    def per_rec(x):  # a field of the guess: scalar or (batch,)
        x = np.asarray(x, dtype=float)
        return to_device(np.broadcast_to(x, (bsize,)), dtype)

    state = (
        jax.tree_util.tree_map(
            lambda x: to_device(np.broadcast_to(np.asarray(x), (bsize,) + np.shape(x)[-1:]), dtype),
            y0_guess,
        )
        if batched
        else jax.tree_util.tree_map(lambda x: to_device(np.asarray(x, dtype)[None]), y0_guess)
    )
    # the launch time's guess and its scale (params.py): the guess's distance to the first
    # frame, or a quarter of the guess's nutation period (a phase the windows can follow), or
    # one frame
    t0_scale = max(
        ts_np[0] - t0, 0.25 * nutation_period(fields, launch), float(np.median(np.diff(ts_np)))
    )
    law = top_guess.friction
    base = Base(
        top={f: per_rec(v) for f, v in fields.items()},
        launch={k: per_rec(v) for k, v in (launch | dict(t0=t0, t0_scale=t0_scale)).items()},
        state=state,
        law=type(law),
        options=law_options(law),
    )
    # Arrays padded to a bucket length (padding: the last time, weight and mask 0), so that
    # records of similar lengths share one compilation.
    size = bucket(n)
    ts_pad = np.concatenate([ts_np, np.full(size - n, ts_np[-1])])

    def pad(x):
        return np.concatenate([x, np.zeros((bsize, size - n))], -1)

    bins = np.concatenate([band[0], np.zeros(size - n, int)])  # padding: mask 0, any bin
    kernel = band[1]
    zeros = np.zeros((bsize, size))
    template = Data(
        base=base,
        ts=to_device(np.broadcast_to(ts_pad, (bsize, size)), dtype),
        t0=per_rec(t0),
        t_end=per_rec(ts_np[-1]),
        theta_obs=to_device(pad(np.where(mask2, obs2, 0.0)), dtype),
        weights=to_device(zeros, dtype),
        mask=to_device(pad(mask2.astype(float)), dtype),
        phi_obs=to_device(pad(np.nan_to_num(phi2)) if phi2 is not None else zeros, dtype),
        phi_weights=to_device(zeros, dtype),
        smoother_bin=to_device(np.broadcast_to(bins, (bsize,) + bins.shape)),
        smoother_kernel=to_device(np.broadcast_to(kernel, (bsize,) + kernel.shape), dtype),
        grid=to_device(np.broadcast_to(grid, (bsize,) + grid.shape), dtype),
        smooth_obs=to_device(smooth_obs, dtype),
        envelope_weight=per_rec(0.0),
        levels=to_device(np.stack([lad[0] for lad in ladders]), dtype),
        t_levels=to_device(np.stack([lad[1] for lad in ladders]), dtype),
        level_weight=per_rec(0.0),
        rtol=per_rec(rtol),
        atol=per_rec(atol),
        slip_floor=per_rec(0.0),
        tol=per_rec(tol),
        pinned=to_device(np.zeros((bsize, len(free))), dtype),
        steps=per_rec(float(max_steps)),
    )
    if not batched:
        # (indexed in numpy: a jax index is a small program to compile in each new process)
        template = jax.tree_util.tree_map(lambda x: to_device(np.asarray(x)[0], x.dtype), template)
    cfg = Config(
        free=free,
        model=model,
        method=method,
        max_steps=int(max_steps),
        sim_max_steps=int(sim_max_steps),
        has_phi=phi2 is not None,
        solver=solver,
        learning_rate=float(learning_rate),
    )
    return Setup(
        ts=ts_np,
        mask=mask2,
        weights=w2,
        phi=phi2,
        rises=rises,
        template=template,
        cfg=cfg,
        batched=batched,
        tol=float(tol),
        rtol=float(rtol),
    )
