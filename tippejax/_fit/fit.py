r"""`fit`: physical parameters and launch quantities from a measured tilt $\theta(t_k)$.

The fit is a weighted nonlinear least-squares problem,

$$\min_p \tfrac12 \sum_k w_k\,\big(\theta(t_k; p) - \theta^{obs}_k\big)^2
        \;[+\; \tfrac12 \sum_k w^\varphi_k \sin^2\theta^{obs}_k\,
        \mathrm{wrap}\big(\varphi(t_k; p) - \varphi^{obs}_k\big)^2],$$

where $\theta(t; p)$ comes from `simulate` at the chosen level of model, with free parameters
mapped to unconstrained coordinates (`params.py`). Jacobians are taken in forward mode through
the ODE solve, one pass per optimiser step for the residuals and all columns.

The loss is multimodal: the nutation's phase slips by a cycle for about 1/N of relative error
in the spin (N nutation cycles in the record), and each slip is a valley. The slow loss (the
smoothed tilt's envelope and level-crossing times, blind to the phase) has a valley of its own
(spin traded against mu and eps), plateaus (trial tops that do not turn over) and several
minima along the curve of matching inversion times. The default strategy (`"global"`,
`strategies.py`) therefore

0. if the residuals at the guess itself pass the diagnostics (step 7), only polishes it (the
   whole record, step 6); otherwise it
1. fits the raw tilt on windows that double from 1/64 of the record, from the guess, with
   each simulation stopped at its window's end (a few simulations of the record); if the
   residuals pass the diagnostics, that is the fit. Otherwise it
2. ranks 128 starting points in a box of a factor 2 around the guess by the slow loss,
   simulated in one batch (`stages/global_search.py`);
3. from the best, finds the spin from the early nutation: the raw tilt on a window of ~10
   nutation cycles, scanned along the spin on a grid finer than one cycle, the window then
   growing by 3 with the scan narrowed each time (`stages/phase_scan.py`);
4. with the spin held, ranks 128 points of the other parameters by the slow loss and refines
   the best 8 (20 steps each); keeps the lowest;
5. scans the phase along the slow loss's valley on windows that grow to the whole record, and
   refines its 4 best cycles on the whole record (30 steps each);
6. fits the whole record at the stage tolerance, then at the fit's own (the loss the
   covariance is about), all coordinates inside a trust region of a factor 5 around the guess;
7. tests the residuals (`diagnostics.py`: runs test, Ljung-Box and windowed chi-square); if
   they are not noise, the same start is refined the other way (`stages/valley_scan.py`:
   onto the slow loss's valley with every parameter free, then the phase scanned along the
   valley on growing windows, so that the spin is never traded against the others' error in
   the slow rise; then step 6), then the next start; if none passes, the fit with the lowest
   loss is flagged `local_minimum` rather than returned with confident error bars;
8. profiles the loss along the slow valley through the fit, +-20 nutation cycles
   (`profile.py`): a lower cycle is refitted (steps 6-7) and kept if it ends lower; where
   cycles beyond 3 standard errors fit within a chi-square of 9, the covariance is widened
   along the valley and the fit is flagged `phase_ambiguous`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from .._cache import to_device
from .._simulate import MODELS
from .._state import State
from .._top import TippeTop, _checks
from . import diagnostics, profile
from .params import FREE_NAMES, LAUNCH_FIELDS, TOP_FIELDS, Base, launch_of
from .problem import Config, Data, ladder, smooth_numpy, smoother
from .result import FIT_RESULTS, FitResult
from .setup import Setup, bucket
from .stages import Final
from .stages.windows import window_ends
from .strategies import IF_NOISE, STRATEGIES

METHODS = ("levenberg_marquardt", "gauss_newton", "adam")
FIT_MODELS = ("full", "so3", "routhian")
MAX_RECORD_SPAN = 600.0  # s: a longer record is taken for times in the wrong unit


# ---------------------------------------------------------------------------------------------
# Input checks: every one raises before anything is compiled.


def _check_options(free, model, method, strategy, max_steps, tol, sigma):
    if isinstance(free, str):
        raise ValueError(
            f"free must be a sequence of names, e.g. free=({free!r},) or ('mu', 'eps', 'spin'), "
            f"not the string {free!r} (which would be read letter by letter)."
        )
    free = tuple(free)
    unknown = [n for n in free if n not in FREE_NAMES]
    if unknown:
        raise ValueError(f"Unknown names in free: {unknown}; choose from {FREE_NAMES}.")
    if not free:
        raise ValueError(f"free is empty; name at least one of {FREE_NAMES}.")
    if len(set(free)) != len(free):
        raise ValueError(f"free names a parameter twice: {free}.")
    if model not in FIT_MODELS:
        allowed = tuple(m for m in MODELS if m in FIT_MODELS)
        raise ValueError(f"fit supports model in {allowed}, got {model!r}.")
    if method not in METHODS:
        raise ValueError(f"Unknown method {method!r}; choose one of {METHODS}.")
    if strategy not in STRATEGIES:
        raise ValueError(f"Unknown strategy {strategy!r}; choose one of {tuple(STRATEGIES)}.")
    if not (isinstance(max_steps, (int, np.integer)) and max_steps > 0):
        raise ValueError(f"max_steps must be a positive integer, got {max_steps!r}.")
    if not tol > 0:
        raise ValueError(f"tol must be positive, got {tol}.")
    if sigma is not None and not (np.isfinite(sigma) and sigma > 0):
        raise ValueError(f"sigma must be a positive noise level (rad), got {sigma}.")
    return free


def _as_1d_times(ts) -> np.ndarray:
    arr = np.asarray(ts, dtype=float)
    if arr.ndim != 1 or arr.size < 2:
        raise ValueError(f"ts must be a 1-d array of at least 2 times, got shape {arr.shape}.")
    if not np.all(np.isfinite(arr)):
        raise ValueError("ts must hold finite times (NaN or inf found); mark missing data with "
                         "NaN in theta_obs instead.")
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


def _observations(name, obs, n) -> np.ndarray:
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


def _check_guess(top_guess, y0_guess, free, batch):
    if not isinstance(top_guess, TippeTop):
        raise TypeError(f"top_guess must be a tippejax.TippeTop, got {type(top_guess).__name__}.")
    if not isinstance(y0_guess, State):
        raise TypeError(
            f"y0_guess must be a tippejax.State (see initial_state), got {type(y0_guess).__name__}."
        )
    fields = {f: np.asarray(getattr(top_guess, f), dtype=float) for f in TOP_FIELDS}
    for f, v in fields.items():
        if not np.all(np.isfinite(v)):
            raise ValueError(f"top_guess.{f} is not finite.")
        if v.ndim > 1 or (v.ndim == 1 and (batch is None or v.shape[0] != batch)):
            raise ValueError(
                f"top_guess.{f} has shape {v.shape}: a guess is one top, or one per recording "
                f"when theta_obs has shape (batch, N)."
            )
    for failed, message in _checks(*(fields[f] for f in ("m", "R", "eps", "A", "C", "g", "mu"))):
        if np.any(failed):
            raise ValueError(f"top_guess is not a valid top: {message}")
    for name in ("m", "R", "g", "mu"):
        if name in free and np.any(fields[name] == 0):
            raise ValueError(f"{name!r} is free but its guess is 0; give a positive guess.")
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
        raise ValueError("'spin' is free but the guess has zero spin: give a non-zero guess "
                         "(its sign is kept; theta alone cannot tell the spin's direction).")
    if "A" in free and np.any(fields["A"] / fields["C"] <= 0.5):
        raise ValueError("'A' is free but the guess has A/C = 1/2: give A/C > 1/2.")
    if "C" in free and "A" not in free and np.any(fields["C"] >= 2 * fields["A"]):
        raise ValueError("'C' is free but the guess has C >= 2A, which no rigid body has.")
    return fields, launch


def _nutation_period(fields, launch) -> float:
    """The fast nutation's period of the guess, 2 pi A / (C |n|) (the fast-top limit)."""
    period = 2 * np.pi * np.asarray(fields["A"]) / (
        np.asarray(fields["C"]) * np.maximum(np.abs(np.asarray(launch["spin"])), 1e-6)
    )
    return float(np.max(period))


# ---------------------------------------------------------------------------------------------


def fit(
    top_guess: TippeTop,
    y0_guess: State,
    ts: ArrayLike,
    theta_obs: ArrayLike,
    *,
    free: Sequence[str] = ("mu", "eps", "spin"),
    phi_obs: ArrayLike | None = None,
    model: Literal["full", "so3", "routhian"] = "full",
    method: Literal["levenberg_marquardt", "gauss_newton", "adam"] = "levenberg_marquardt",
    strategy: Literal["global", "search", "levels", "windows", "plain"] = "global",
    t0: float | None = None,
    weights: ArrayLike | None = None,
    sigma: float | None = None,
    max_steps: int = 100,
    tol: float = 1e-6,
    rtol: float = 1e-10,
    atol: float = 1e-12,
    solver: diffrax.AbstractSolver | None = None,
    sim_max_steps: int = 100_000,
    learning_rate: float = 0.02,
    trim: bool = False,
) -> FitResult:
    r"""Fit free parameters of the top and its launch to a measured tilt $\theta(t_k)$.

    **Arguments:**

    - `top_guess`: a `TippeTop`; its fields give the fixed parameters and the starting guess.
    - `y0_guess`: the `State` at time `t0` (see `initial_state`); gives the launch quantities.
      Any valid state, including one at a pole (an upright top with a tilt rate: free
      `theta_dot` then, not `theta0`). When no launch quantity is free it is simulated as
      given.
    - `ts`: the observation times in seconds (strictly increasing, finite), shape `(N,)`.
    - `theta_obs`: the measured tilt in radians, shape `(N,)`, or `(batch, N)` to fit several
      recordings at once (one vmapped program evaluates the batch, split over the most JAX
      devices that divide it; each recording has its own optimiser state and stopping test,
      and gets the fit it would get alone: a stage that some recordings need, the search
      from a guess that does not describe them, runs on those alone). **NaN marks a missing
      sample**, which is left out of the loss.
    - `free`: a sequence of names of the parameters to fit: top fields `m, R, eps, A, C, g,
      mu` and launch quantities `theta0, spin, theta_dot, phi_dot, vx, vy`. The spin keeps
      the sign of its guess (theta alone cannot tell its direction). Nothing else is fitted:
      a launch tilt that is not free is held at the guess's exactly, so free `theta0` unless
      it is known.
    - `phi_obs`: optional precession angle (rad; differences are wrapped), weighted by
      $\sin\theta^{obs}$, NaN masked.
    - `model`: level of model to fit with, `"full"`, `"so3"` or `"routhian"`.
    - `method`: `"levenberg_marquardt"` (default) or `"gauss_newton"` (the steps of
      `optimistix.LevenbergMarquardt` and `optimistix.GaussNewton`, taken on the host around
      one compiled evaluation, `tippejax/_fit/optimise.py`), or `"adam"` (`optax.adam` at
      `learning_rate`).
    - `strategy`: `"global"` (default: growing windows from the guess, then, if their fit's
      residuals are not noise, a global search for starts, the spin from the early nutation,
      the other parameters from the slow observables, the phase on growing windows and the
      whole record; see the module docstring), `"search"` (the search alone), `"levels"` (the same
      from the guess alone), `"windows"` (growing windows from the guess) or `"plain"` (the
      whole record at once).
    - `t0`: time of `y0_guess` (default `ts[0]`; must be `<= ts[0]`).
    - `weights`: optional non-negative weight per sample (e.g. `1/sigma_k^2`).
    - `sigma`: the noise of `theta_obs` (rad), if known: the diagnostics then also test the
      residuals' level against it.
    - `max_steps`: optimiser steps per optimisation. `tol`: the optimiser's relative and
      absolute tolerance in the final stage.
    - `rtol`, `atol`, `solver`, `sim_max_steps`: passed to `simulate` in the final stage and
      for the statistics (the intermediate stages simulate at `rtol` 1e-7 unless `rtol` is
      looser, the global search at 1e-6). The default 1e-10 keeps the integration error below
      a tenth of noise/sqrt(N) for the records of `benchmarks/fitting.py`, where 1e-8 did not
      for a quarter of them.
    - `trim`: for a record whose end the model does not describe (a real top whose stem
      lands). When the fit of the whole record fails the diagnostics, windows growing from the
      record's start (doubling, as in the window stage) are fitted while their residuals pass;
      the last one that passes predicts the rest of the record, a windowed chi-square test at a
      false-alarm rate of 1e-3 says how far that prediction holds (`describes_until`), and the
      record is fitted again up to there (`fitted_until`). Off by default: a record the model
      describes is never trimmed (its whole-record fit passes), and without trim a record it
      does not describe is flagged (`local_minimum`).

    **Returns:** a `FitResult`, with standard errors from the Gauss-Newton covariance
    $s^2 (J^\top J)^{-1}$, $s^2 = \mathrm{RSS}/(N - p)$, and diagnostics of the residuals
    (`runs_z`, `describes_until`); `converged` is True only when the residuals pass them.
    """
    free = _check_options(free, model, method, strategy, max_steps, tol, sigma)
    ts_np = _as_1d_times(ts)
    n = ts_np.size
    obs = _observations("theta_obs", theta_obs, n)
    batch = obs.shape[0] if obs.ndim == 2 else None
    obs2 = obs.reshape(-1, n)
    phi2 = None
    if phi_obs is not None:
        phi_arr = _observations("phi_obs", phi_obs, n)
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
    t0 = float(ts_np[0]) if t0 is None else float(t0)
    if not t0 <= ts_np[0]:
        raise ValueError(f"t0 = {t0} must not be later than the first observation ts[0] = {ts_np[0]}.")
    fields, launch = _check_guess(top_guess, y0_guess, free, batch)
    if not isinstance(trim, bool):
        raise ValueError(f"trim must be True or False, got {trim!r}.")

    setup = _setup(top_guess, y0_guess, ts_np, obs2, mask2, w2, phi2, fields, launch, t0,
                   free=free, model=model, method=method, max_steps=max_steps, tol=tol,
                   rtol=rtol, atol=atol, solver=solver, sim_max_steps=sim_max_steps,
                   learning_rate=learning_rate, batched=batch is not None)
    attempts = STRATEGIES[strategy]
    if "spin" in free or strategy == "search":  # the phase check or the search will need it
        setup.compile_losses_ahead()
    out = _fit_starts(setup, attempts, obs2, sigma)
    if "spin" in free:
        out = _check_phase(setup, out, obs2, sigma)
    ends = np.full(setup.bsize, ts_np[-1])
    if trim:
        out, ends = _trim(setup, out, obs2, sigma)
    return _result(out, setup, obs2, ends, batch, free, model, method, strategy)


def _setup(top_guess, y0_guess, ts_np, obs2, mask2, w2, phi2, fields, launch, t0, *, free,
           model, method, max_steps, tol, rtol, atol, solver, sim_max_steps, learning_rate,
           batched) -> Setup:
    dtype = jnp.result_type(top_guess.m)
    bsize, n = obs2.shape
    band, grid = smoother(ts_np, _nutation_period(fields, launch))
    smooth_obs = np.stack([smooth_numpy(obs2[b], mask2[b].astype(float), band) for b in range(bsize)])
    ladders = [ladder(smooth_obs[b], grid) for b in range(bsize)]
    rises = np.array([lad[2] for lad in ladders])

    def per_rec(x):  # a field of the guess: scalar or (batch,)
        x = np.asarray(x, dtype=float)
        return to_device(np.broadcast_to(x, (bsize,)), dtype)

    state = jax.tree_util.tree_map(
        lambda x: to_device(np.broadcast_to(np.asarray(x), (bsize,) + np.shape(x)[-1:]), dtype),
        y0_guess,
    ) if batched else jax.tree_util.tree_map(lambda x: to_device(np.asarray(x, dtype)[None]), y0_guess)
    base = Base(
        top={f: per_rec(v) for f, v in fields.items()},
        launch={k: per_rec(v) for k, v in launch.items()},
        state=state,
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
        tol=per_rec(tol),
        pinned=to_device(np.zeros((bsize, len(free))), dtype),
        steps=per_rec(float(max_steps)),
    )
    if not batched:
        # (indexed in numpy: a jax index is a small program to compile in each new process)
        template = jax.tree_util.tree_map(lambda x: to_device(np.asarray(x)[0], x.dtype), template)
    cfg = Config(
        free=free, model=model, method=method, max_steps=int(max_steps),
        sim_max_steps=int(sim_max_steps), has_phi=phi2 is not None, solver=solver,
        learning_rate=float(learning_rate),
    )
    return Setup(ts=ts_np, mask=mask2, weights=w2, phi=phi2, rises=rises, template=template,
                 cfg=cfg, batched=batched, tol=float(tol), rtol=float(rtol))


def _refine(u, setup, stages):
    histories, counts, code = [], [], None
    for stage in stages:
        run = stage.run(u, setup)
        u, code = run.u, run.code
        histories += run.histories
        counts += run.counts
    return u, histories, counts, code


def _judge(out, setup, obs2, sigma):
    """Diagnostics of each record's residuals over the samples the fit used."""
    theta_fit = np.asarray(out["theta_fit"]).reshape(obs2.shape[0], -1)[:, : obs2.shape[1]]
    residuals = theta_fit - obs2
    verdicts = []
    for b in range(setup.bsize):
        used = setup.mask[b] & setup.fitted[b]
        r = np.where(used, residuals[b], np.nan)
        verdicts.append(diagnostics.describes(r, setup.ts, sigma))
    return residuals, verdicts


def _candidate(setup, refined, obs2, sigma):
    """A refined start (`_refine`'s output) finished and judged: the dict `_better` and
    `_select` compare, and the steps it took per record."""
    u, histories, counts, code = refined
    out = setup.finish(u, code, setup.data(tol=setup.tol, final=True))
    residuals, verdicts = _judge(out, setup, obs2, sigma)
    steps = np.asarray(sum(np.asarray(c) for c in counts)).reshape(-1)
    cand = dict(out=out, residuals=residuals, verdicts=verdicts, u=u,
                history=_pack(histories, counts, setup.bsize, setup.cfg.max_steps),
                loss=np.asarray(out["loss"]).reshape(-1))
    return cand, steps


def _start(setup):
    """The guess's coordinates (all 0: each coordinate is relative to the guess)."""
    p = len(setup.cfg.free)
    return to_device(np.zeros((setup.bsize, p) if setup.batched else (p,)), jnp.result_type(float))


def _fit_starts(setup, attempts, obs2, sigma):
    """Refine the starts of each attempt in turn until every record has a fit whose residuals
    pass; keep the lowest loss per record.

    In a batch, each attempt runs on the records that have no passing fit yet (and the
    polish on those whose guess passes), as a batch of its own: vmapped, every record would
    pay for the slowest record's search."""
    best = None
    total_steps = np.zeros(setup.bsize, int)
    tried = np.zeros(setup.bsize, int)  # starts tried per record
    for search, stages in attempts:
        todo = np.ones(setup.bsize, bool) if best is None else ~_passing(best)
        if search == IF_NOISE:
            # (the loss of the first polishing stage: its first evaluation is this one)
            guess = setup.finish(_start(setup), FIT_RESULTS.successful, setup.data())
            todo &= np.array([v["passes"] for v in _judge(guess, setup, obs2, sigma)[1]])
        if not todo.any():
            continue
        idx = np.flatnonzero(todo)
        sub = setup if idx.size == setup.bsize else setup.subset(idx)
        u0 = _start(sub)
        starts = (np.asarray(u0)[None] if search is None or search == IF_NOISE
                  else np.asarray(search.starts(u0, sub)))
        chains = stages if isinstance(stages[0], tuple) else (stages,)
        for s in range(starts.shape[0]):
            for chain in chains:  # alternative chains from the same start, in turn
                tried[idx] += 1
                cand, steps = _candidate(sub, _refine(to_device(starts[s]), sub, chain),
                                         obs2[idx], sigma)
                total_steps[idx] += steps
                if sub is not setup:
                    cand = _widen(cand, idx, setup.bsize, sub.batched)
                cand["starts"] = tried.copy()
                best = cand if best is None else _better(best, cand, setup.bsize)
                if _passing(best).all():  # the lowest minimum is noise
                    best["num_steps"] = total_steps
                    best["describes"] = np.array([v["describes_until"] for v in best["verdicts"]])
                    return best
                if sub is not setup and _passing(best)[idx].all():
                    break  # (this attempt's records pass; the others wait for the next)
            else:
                continue
            break
    best["num_steps"] = total_steps
    best["describes"] = np.array([v["describes_until"] for v in best["verdicts"]])
    return best


def _passing(cand) -> np.ndarray:
    """Per record, whether the candidate's residuals pass the diagnostics."""
    return np.array([v["passes"] for v in cand["verdicts"]])


def _widen(cand, idx, bsize, batched):
    """A candidate of the records `idx` of a batch (`_candidate`'s dict of a `subset`) as one of
    the whole batch: the other records hold placeholders (loss inf, failing verdicts) that
    `_better` never picks over a fit and any later fit replaces."""
    pos = np.zeros(bsize, int)
    pos[idx] = np.arange(idx.size)
    inside = np.zeros(bsize, bool)
    inside[idx] = True

    def rows(x):
        x = np.asarray(x)
        return (x if batched else x[None])[pos]

    def device_rows(x):
        return to_device(rows(x), x.dtype)

    failing = dict(cand["verdicts"][0], passes=False)
    return dict(
        out=jax.tree_util.tree_map(device_rows, cand["out"]),
        residuals=np.asarray(cand["residuals"])[pos],
        verdicts=[cand["verdicts"][pos[b]] if inside[b] else failing for b in range(bsize)],
        u=device_rows(cand["u"]),
        history=np.asarray(cand["history"])[pos],
        loss=np.where(inside, np.asarray(cand["loss"])[pos], np.inf),
    )


def _check_phase(setup, best, obs2, sigma):
    """The phase check of `profile.py`: refine a lower point of each record's profile along
    the valley if there is one (once; kept if its end is lower), then, for the fits whose
    residuals pass, widen the covariance and flag `phase_ambiguous` where cycles beyond the
    error bars fit as well."""
    bsize = setup.bsize
    spin = setup.cfg.free.index("spin")

    prof = profile.phase_profile(best["u"], setup, spin)
    lower, points = profile.lower_points(prof)
    if lower.any():
        u_old = np.asarray(best["u"]).reshape(bsize, -1)
        start = np.where(lower[:, None], points, u_old)
        start = to_device(start if setup.batched else start[0], best["u"].dtype)
        refined = _refine(start, setup, (Final(final=False), Final()))
        cand, steps = _candidate(setup, refined, obs2, sigma)
        cand["num_steps"] = best["num_steps"] + np.where(lower, steps, 0)
        cand["describes"] = np.array([v["describes_until"] for v in cand["verdicts"]])
        take = lower & (cand["loss"] < best["loss"])
        if take.any():
            starts = best["starts"]
            # (`_select` is per record of a batch; a single record takes `cand` whole)
            best = cand if take.all() else _select(best, cand, take, bsize)
            best["starts"] = starts
            best["num_steps"] = cand["num_steps"]
            prof = profile.phase_profile(best["u"], setup, spin)
    out = best["out"]
    spin_values = np.asarray(out["values"]).reshape(bsize, -1)[:, spin]
    se_rel = np.asarray(out["std_errors"]).reshape(bsize, -1)[:, spin] / np.abs(spin_values)
    flat, reach = profile.ambiguity(prof, se_rel)
    flat &= _passing(best)  # (a fit that fails its diagnostics is flagged already)
    if not flat.any():
        return best
    one = (lambda x: x) if setup.batched else (lambda x: x[0])  # noqa: E731
    cov = profile.widen(out["covariance"], best["u"], setup.template.base, setup.cfg.free,
                        one(prof.direction), one(np.where(flat, reach, 0.0)))
    dtype = out["covariance"].dtype
    std = np.sqrt(np.maximum(np.diagonal(cov, axis1=-2, axis2=-1), 0.0))

    code = _flag(out["result"], one(flat), FIT_RESULTS.phase_ambiguous)
    best = dict(best)
    best["out"] = dict(out, covariance=to_device(cov, dtype), std_errors=to_device(std, dtype),
                       correlation=to_device(cov / (std[..., :, None] * std[..., None, :]), dtype),
                       result=code)
    return best


def _flag(code, where, new):
    """`code` (a `FIT_RESULTS` item, one per record) set to `new` where `where` holds and the
    code is `successful`; in numpy (no small programs to compile in a new process)."""
    value = np.asarray(code._value)
    hit = np.asarray(where, bool) & (value == np.asarray(FIT_RESULTS.successful._value))
    flagged = np.where(hit, np.asarray(new._value), value).astype(value.dtype)
    return eqx.tree_at(lambda c: c._value, code, to_device(flagged))


def _trim(setup, out, obs2, sigma):
    r"""Refit each record whose whole-record fit fails on the part of it the model describes.

    A fit of the whole record is distorted everywhere by a stretch the model cannot describe
    (a stem landing), so its own residuals do not say where the description ends. Instead the
    windows of `Windows` grow from the guess, each fitted from the last, while the residuals
    of the window pass the diagnostics; the last window that passes is trusted. Its parameters
    predict the rest of the record, and the windowed chi-square test of that prediction
    (`describes_until`) says how far the description reaches; the record is fitted again up to
    there, and kept if it passes (else the last window that passed is kept). Records whose
    whole-record fit passes are left as they are.
    """
    ts = setup.ts
    bsize = setup.bsize
    passed = np.array([v["passes"] for v in out["verdicts"]])
    ends = np.full(bsize, ts[-1])
    if passed.all():
        return out, ends

    def per_record(mask_b, a, b):  # a where mask_b, else b (u has shape (*batch, p))
        if not setup.batched:
            return a if bool(mask_b[0]) else b
        return jnp.where(jnp.asarray(mask_b)[:, None], a, b)

    def fit_to(u, fit_ends, stages):
        setup.fitted = ts[None, :] <= fit_ends[:, None] + 1e-12
        u, histories, counts, code = _refine(u, setup, stages)
        cand = setup.finish(u, code, setup.data(tol=setup.tol, final=True))
        residuals, verdicts = _judge(cand, setup, obs2, sigma)
        return u, cand, residuals, verdicts, histories, counts

    u = per_record(passed, out["u"], jnp.zeros_like(out["u"]))
    growing = ~passed
    u_ok, end_ok = u, np.where(passed, ts[-1], np.nan)
    histories, counts = [], []
    for end in window_ends(ts)[:-1]:
        if not growing.any():
            break
        fit_ends = np.where(growing, end, end_ok)
        fit_ends = np.where(np.isfinite(fit_ends), fit_ends, end)
        u, _, _, verdicts, hist, cnt = fit_to(u, fit_ends, (Final(final=False),))
        histories += hist
        counts += cnt
        ok = np.array([v["passes"] for v in verdicts])
        now_ok = growing & ok
        u_ok = per_record(now_ok, u, u_ok)
        end_ok = np.where(now_ok, end, end_ok)
        growing = growing & ok
    trimmed = ~passed & np.isfinite(end_ok)
    if not trimmed.any():
        return out, ends
    # How far does the last trusted window's description reach?
    setup.fitted = np.ones_like(setup.mask)
    reach = setup.finish(u_ok, out["out"]["result"], setup.data(tol=setup.tol, final=True))
    _, verdicts = _judge(reach, setup, obs2, sigma)
    until = np.array([v["describes_until"] for v in verdicts])
    until = np.where(np.isfinite(until), np.maximum(until, end_ok), end_ok)
    fit_ends = np.where(trimmed, until, ts[-1])
    u, cand, residuals, verdicts, hist, cnt = fit_to(u_ok, fit_ends, (Final(final=False), Final()))
    ok = np.array([v["passes"] for v in verdicts])
    if np.any(trimmed & ~ok):  # the reach was too long: the last trusted window alone
        fit_ends = np.where(trimmed & ~ok, end_ok, fit_ends)
        u, cand, residuals, verdicts, hist2, cnt2 = fit_to(
            per_record(trimmed & ~ok, u_ok, u), fit_ends, (Final(),))
        hist += hist2
        cnt += cnt2
    histories += hist
    counts += cnt
    steps = np.asarray(sum(np.asarray(c) for c in counts)).reshape(-1)
    new = dict(
        out=cand, residuals=residuals, verdicts=verdicts, u=u,
        history=_pack(histories, counts, bsize, setup.cfg.max_steps),
        loss=np.asarray(cand["loss"]).reshape(-1), starts=out["starts"],
        num_steps=out["num_steps"] + steps,
        describes=np.array([v["describes_until"] for v in verdicts]),
    )
    if (~trimmed).any():  # records not trimmed keep their whole-record fit
        new = _merge(out, new, ~trimmed, bsize)
    return new, np.where(trimmed, fit_ends, ts[-1])


def _select(a, b, take_b, bsize):
    """Per record of a batch, the fit in `b` where `take_b`, else the one in `a` (dicts of
    `_fit_starts`; keys both have). Loss histories of different lengths are nan-padded."""
    pick = np.asarray(take_b)
    take = lambda x, y: jnp.where(  # noqa: E731
        jnp.asarray(pick).reshape((bsize,) + (1,) * (jnp.ndim(x) - 1)), y, x
    )
    width = max(a["history"].shape[-1], b["history"].shape[-1])

    def wide(h):
        return np.pad(h, ((0, 0), (0, width - h.shape[-1])), constant_values=np.nan)

    out = dict(
        out=jax.tree_util.tree_map(take, a["out"], b["out"]),
        residuals=np.where(pick[:, None], b["residuals"], a["residuals"]),
        verdicts=[b["verdicts"][i] if pick[i] else a["verdicts"][i] for i in range(bsize)],
        history=np.where(pick[:, None], wide(b["history"]), wide(a["history"])),
        u=take(a["u"], b["u"]),
    )
    for key in ("loss", "num_steps", "describes"):
        if key in a and key in b:
            out[key] = np.where(pick, b[key], a[key])
    return out


def _merge(a, b, keep_a, bsize):
    """Per record of a batch, `a` where `keep_a`, else `b`."""
    return dict(_select(a, b, ~np.asarray(keep_a), bsize), starts=a["starts"])


def _better(a, b, bsize):
    """Per record, the fit with the lower loss (the least-squares estimate is the lowest
    minimum found; the diagnostics only say whether to trust it)."""
    # (a loss of inf in `a` is a placeholder of `_widen` or a failed fit: any fit replaces it)
    pick = np.array([b["loss"][i] < a["loss"][i] or a["loss"][i] == np.inf for i in range(bsize)])
    if not pick.any():
        a["starts"] = b["starts"]
        return a
    if pick.all():
        return b
    return dict(_select(a, b, pick, bsize), starts=b["starts"])


def _pack(histories, counts, bsize, max_steps):
    """Each optimisation's losses one after the other, nan-padded to a fixed length."""
    hist = np.concatenate([np.asarray(h) for h in histories], axis=-1).reshape(
        bsize, len(histories), max_steps)
    cnt = np.stack([np.asarray(c) for c in counts], -1).reshape(bsize, -1)
    packed = np.full((bsize, len(histories) * max_steps), np.nan)
    for b in range(bsize):
        row = np.concatenate([hist[b, s, : cnt[b, s]] for s in range(len(histories))])
        packed[b, : row.size] = row
    return packed


def _result(best, setup, obs2, ends, batch, free, model, method, strategy) -> FitResult:
    out = best["out"]
    bsize, n = obs2.shape
    verdicts = best["verdicts"]
    residuals = best["residuals"]
    passes = np.array([v["passes"] for v in verdicts])
    code = out["result"]

    # a converged fit whose residuals are not noise is a local minimum
    code = _flag(code, ~passes if batch is not None else ~passes[0], FIT_RESULTS.local_minimum)
    mask = setup.mask
    whole = np.where(mask, residuals, np.nan)
    rms = np.sqrt(np.nanmean(whole**2, axis=-1))
    ts_out = np.broadcast_to(setup.ts, (bsize, n))
    per = dict(
        rms=rms,
        rms_fitted=np.array([v["rms"] for v in verdicts]),
        noise=np.array([v["noise"] for v in verdicts]),
        runs_z=np.array([v["runs_z"] for v in verdicts]),
        ljung_box=np.array([v["ljung_box"] for v in verdicts]),
        describes_until=best["describes"],
        fitted_until=ends,
        num_steps=best["num_steps"],
        starts=best["starts"],
    )
    arrays = dict(residuals=whole, theta_obs=np.where(mask, obs2, np.nan), ts=ts_out,
                  loss_history=best["history"])
    dtype = out["values"].dtype
    if batch is None:
        per = {k: v[0] for k, v in per.items()}
        arrays = {k: v[0] for k, v in arrays.items()}
    out = dict(out)
    for k in ("theta_fit", "phi_fit"):
        out[k] = to_device(np.asarray(out[k])[..., :n])
    phi_res = to_device(np.full(np.shape(out["phi_fit"]), np.nan), out["phi_fit"].dtype)
    if setup.phi is not None:
        dphi = np.asarray(out["phi_fit"]).reshape(obs2.shape) - setup.phi
        wrapped = np.arctan2(np.sin(dphi), np.cos(dphi))
        phi_res = to_device(wrapped if batch is not None else wrapped[0], dtype)
    return FitResult(
        top=out["top"], y0=out["y0"], values=out["values"], std_errors=out["std_errors"],
        covariance=out["covariance"], correlation=out["correlation"],
        loss_history=to_device(arrays["loss_history"], dtype),
        ts=to_device(arrays["ts"], dtype), theta_obs=to_device(arrays["theta_obs"], dtype),
        theta_fit=out["theta_fit"], residuals=to_device(arrays["residuals"], dtype),
        rms=to_device(per["rms"], dtype), rms_fitted=to_device(per["rms_fitted"], dtype),
        noise=to_device(per["noise"], dtype), runs_z=to_device(per["runs_z"], dtype),
        ljung_box=to_device(per["ljung_box"], dtype),
        describes_until=to_device(per["describes_until"], dtype),
        fitted_until=to_device(per["fitted_until"], dtype),
        phi_fit=out["phi_fit"], phi_residuals=phi_res,
        converged=to_device(np.asarray(code._value) == np.asarray(FIT_RESULTS.successful._value)),
        result=code,
        num_steps=to_device(per["num_steps"]), starts=to_device(per["starts"]),
        free=free, model=model, method=method, strategy=strategy,
    )


__all__ = ["fit", "METHODS", "FIT_MODELS", "LAUNCH_FIELDS", "TOP_FIELDS"]
