"""`fit`: physical parameters and launch quantities from a measured tilt, and its driver."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import diffrax
import numpy as np
from jaxtyping import ArrayLike

from .._cache import to_device
from .._state import State
from .._top import TippeTop
from . import profile
from .candidates import (
    better,
    candidate,
    flag,
    judge,
    passing,
    refine,
    select,
    start_point,
    widen,
)
from .inputs import build_setup, check_guess, check_model, check_options, check_records
from .launch import launch_time_suspects
from .result import FIT_RESULTS, FitResult
from .stages import Final
from .strategies import IF_NOISE, STRATEGIES
from .trim import trim_records


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
    r"""Fit free parameters of the top, its friction law and its launch to a measured tilt
    $\theta(t_k)$.

    **The launch time.** `y0_guess` is the state at the launch, at `t0` in the record's clock:
    `t0 = 0` by default, as in `simulate`, so a record whose first frame comes a sample after
    the launch is fitted from the launch, not a sample late. Pass `t0=` when the record's clock
    does not start at the launch (`t0=ts[0]` if the guess is the state at the first frame), or
    free `"t0"` when the launch time is not known.

    **Arguments:**

    - `top_guess`: a `TippeTop`; its fields and its friction law (`top_guess.friction`, any
      law) give the fixed parameters and the starting guess. The fit keeps the law.
    - `y0_guess`: the `State` at the launch time `t0` (see `initial_state`); gives the launch
      quantities.
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
    - `free`: a sequence of names of the parameters to fit: top fields `m, R, eps, A, C, g`;
      the friction law's fields: `mu` for every law (s/m for `Viscous`, dimensionless for the
      Coulomb laws), `patch_radius` (m) for `CoulombContensou`, `slip_scale` (m/s) for
      `Coulomb` (not for `CoulombContensou`, whose motion converges as the slip scale
      goes to 0, so that a record does not determine it); launch quantities `theta0, spin,
      theta_dot, phi_dot, vx, vy`; and the launch time `t0` (s; before it the model top is
      held at its launch state). The spin keeps the sign of its guess (theta alone cannot tell
      its direction). Nothing else is fitted: a launch tilt that is not free is held at the
      guess's exactly, so free `theta0` unless it is known.
    - `phi_obs`: optional precession angle (rad; differences are wrapped), weighted by
      $\sin\theta^{obs}$, NaN masked.
    - `model`: level of model to fit with, `"full"`, `"so3"` or `"routhian"`; one that takes
      the top's law (`"full"` or `"so3"` for laws other than the viscous one; the Coulomb
      laws' creep needs `"full"`, `docs/friction.md`).
    - `method`: `"levenberg_marquardt"` (default) or `"gauss_newton"` (the steps of
      `optimistix.LevenbergMarquardt` and `optimistix.GaussNewton`, taken on the host around
      one compiled evaluation, `tippejax/_fit/optimise.py`), or `"adam"` (`optax.adam` at
      `learning_rate`).
    - `strategy`: `"global"` (default: growing windows from the guess, then, if their fit's
      residuals are not noise, a global search for starts, the spin from the early nutation,
      the other parameters from the slow observables, the phase on growing windows and the
      whole record; see below), `"search"` (the search alone), `"levels"` (the same
      from the guess alone), `"windows"` (growing windows from the guess) or `"plain"` (the
      whole record at once).
    - `t0`: the launch time, the time of `y0_guess` in seconds (default 0, as in `simulate`;
      must be `<= ts[0]`). With the default, a record that starts longer after 0 than it
      lasts is refused with a message (its clock does not start at the launch). With `"t0"`
      free, the guess of the launch time.
    - `weights`: optional non-negative weight per sample (e.g. `1/sigma_k^2`).
    - `sigma`: the noise of `theta_obs` (rad), if known: the diagnostics then also test the
      residuals' level against it.
    - `max_steps`: optimiser steps per optimisation. `tol`: the optimiser's relative and
      absolute tolerance in the final stage.
    - `rtol`, `atol`, `solver`, `sim_max_steps`: passed to `simulate` in the final stage and
      for the statistics (the intermediate stages simulate at `rtol` 1e-7 unless `rtol` is
      looser, the global search at 1e-6). Keep the default 1e-10: the integration error must
      stay well below noise/sqrt(N), which a looser rtol often misses (see the performance
      page).
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

    **The problem.** A weighted nonlinear least-squares problem,

    $$\min_p \tfrac12 \sum_k w_k\,\big(\theta(t_k; p) - \theta^{obs}_k\big)^2
            \;[+\; \tfrac12 \sum_k w^\varphi_k \sin^2\theta^{obs}_k\,
            \mathrm{wrap}\big(\varphi(t_k; p) - \varphi^{obs}_k\big)^2],$$

    where $\theta(t; p)$ comes from `simulate` at the chosen level of model, with the free
    parameters mapped to unconstrained coordinates (`tippejax/_fit/params.py`). Jacobians are
    taken in forward mode through the ODE solve, one pass per optimiser step for the residuals
    and all columns.

    The loss is multimodal: the nutation's phase slips by a cycle for about 1/N of relative
    error in the spin (N nutation cycles in the record), and each slip is a valley. The slow
    loss (the smoothed tilt's envelope and level-crossing times, blind to the phase) has a
    valley of its own (spin traded against mu and eps), plateaus (trial tops that do not turn
    over) and several minima along the curve of matching inversion times. The default strategy
    (`"global"`, `tippejax/_fit/strategies.py`) therefore

    0. if the residuals at the guess itself pass the diagnostics (step 7), only polishes it
       (the whole record, step 6); otherwise it
    1. fits the raw tilt on windows that double from 1/64 of the record, from the guess, with
       each simulation stopped at its window's end (a few simulations of the record); if the
       residuals pass the diagnostics, that is the fit. Otherwise it
    2. ranks 128 starting points in a box of a factor 2 around the guess by the slow loss,
       simulated in one batch (`stages/global_search.py`);
    3. from the best, finds the spin from the early nutation: the raw tilt on a window of ~10
       nutation cycles, scanned along the spin on a grid finer than one cycle, the window then
       growing by 3 with the scan narrowed each time (`stages/phase_scan.py`);
    4. with the spin held, ranks 128 points of the other parameters by the slow loss and
       refines the best 8 (20 steps each); keeps the lowest;
    5. scans the phase along the slow loss's valley on windows that grow to the whole record,
       and refines its 4 best cycles on the whole record (30 steps each);
    6. fits the whole record at the stage tolerance, then at the fit's own (the loss the
       covariance is about), all coordinates inside a trust region of a factor 5 around the
       guess;
    7. tests the residuals (`diagnostics.py`: runs test, Ljung-Box and windowed chi-square); if
       they are not noise, the same start is refined the other way (`stages/valley_scan.py`:
       onto the slow loss's valley with every parameter free, then the phase scanned along the
       valley on growing windows, so that the spin is never traded against the others' error
       in the slow rise; then step 6), then the next start; if none passes, the fit with the
       lowest loss is flagged `local_minimum` rather than returned with confident error bars;
    8. profiles the loss along the slow valley through the fit, +-20 nutation cycles
       (`profile.py`): a lower cycle is refitted (steps 6-7) and kept if it ends lower; where
       cycles beyond 3 standard errors fit within a chi-square of 9, the covariance is widened
       along the valley and the fit is flagged `phase_ambiguous`.
    """
    free = check_options(free, model, method, strategy, max_steps, tol, sigma, STRATEGIES)
    records = check_records(ts, theta_obs, phi_obs, weights, t0, free)
    fields, launch = check_guess(top_guess, y0_guess, free, records.batch)
    check_model(model, top_guess.friction)
    if not isinstance(trim, bool):
        raise ValueError(f"trim must be True or False, got {trim!r}.")

    setup = build_setup(
        top_guess,
        y0_guess,
        records,
        fields,
        launch,
        free=free,
        model=model,
        method=method,
        max_steps=max_steps,
        tol=tol,
        rtol=rtol,
        atol=atol,
        solver=solver,
        sim_max_steps=sim_max_steps,
        learning_rate=learning_rate,
    )
    obs2, batch = records.theta, records.batch
    attempts = STRATEGIES[strategy]
    if "spin" in free or strategy == "search":  # the phase check or the search will need it
        setup.compile_losses_ahead()
    out = _fit_starts(setup, attempts, obs2, sigma)
    if "spin" in free:
        out = _check_phase(setup, out, obs2, sigma)
    ends = np.full(setup.bsize, records.ts[-1])
    if trim:
        out, ends = trim_records(setup, out, obs2, sigma)
    return _result(out, setup, obs2, ends, batch, free, model, method, strategy, sigma)


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
        todo = np.ones(setup.bsize, bool) if best is None else ~passing(best)
        if search == IF_NOISE:
            # (the loss of the first polishing stage: its first evaluation is this one)
            guess = setup.finish(start_point(setup), FIT_RESULTS.successful, setup.data())
            todo &= np.array([v["passes"] for v in judge(guess, setup, obs2, sigma)[1]])
        if not todo.any():
            continue
        idx = np.flatnonzero(todo)
        sub = setup if idx.size == setup.bsize else setup.subset(idx)
        u0 = start_point(sub)
        starts = (
            np.asarray(u0)[None]
            if search is None or search == IF_NOISE
            else np.asarray(search.starts(u0, sub))
        )
        chains = stages if isinstance(stages[0], tuple) else (stages,)
        for s in range(starts.shape[0]):
            for chain in chains:  # alternative chains from the same start, in turn
                tried[idx] += 1
                cand, steps = candidate(
                    sub, refine(to_device(starts[s]), sub, chain), obs2[idx], sigma
                )
                total_steps[idx] += steps
                if sub is not setup:
                    cand = widen(cand, idx, setup.bsize, sub.batched)
                cand["starts"] = tried.copy()
                best = cand if best is None else better(best, cand, setup.bsize)
                if passing(best).all():  # the lowest minimum is noise
                    best["num_steps"] = total_steps
                    best["describes"] = np.array([v["describes_until"] for v in best["verdicts"]])
                    return best
                if sub is not setup and passing(best)[idx].all():
                    break  # (this attempt's records pass; the others wait for the next)
            else:
                continue
            break
    best["num_steps"] = total_steps
    best["describes"] = np.array([v["describes_until"] for v in best["verdicts"]])
    return best


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
        refined = refine(start, setup, (Final(final=False), Final()))
        cand, steps = candidate(setup, refined, obs2, sigma)
        cand["num_steps"] = best["num_steps"] + np.where(lower, steps, 0)
        cand["describes"] = np.array([v["describes_until"] for v in cand["verdicts"]])
        take = lower & (cand["loss"] < best["loss"])
        if take.any():
            starts = best["starts"]
            # (`select` is per record of a batch; a single record takes `cand` whole)
            best = cand if take.all() else select(best, cand, take, bsize)
            best["starts"] = starts
            best["num_steps"] = cand["num_steps"]
            prof = profile.phase_profile(best["u"], setup, spin)
    out = best["out"]
    spin_values = np.asarray(out["values"]).reshape(bsize, -1)[:, spin]
    se_rel = np.asarray(out["std_errors"]).reshape(bsize, -1)[:, spin] / np.abs(spin_values)
    flat, reach = profile.ambiguity(prof, se_rel)
    flat &= passing(best)  # (a fit that fails its diagnostics is flagged already)
    if not flat.any():
        return best
    one = (lambda x: x) if setup.batched else (lambda x: x[0])  # noqa: E731
    cov = profile.widen(
        out["covariance"],
        best["u"],
        setup.template.base,
        setup.cfg.free,
        one(prof.direction),
        one(np.where(flat, reach, 0.0)),
    )
    dtype = out["covariance"].dtype
    std = np.sqrt(np.maximum(np.diagonal(cov, axis1=-2, axis2=-1), 0.0))

    code = flag(out["result"], one(flat), FIT_RESULTS.phase_ambiguous)
    best = dict(best)
    best["out"] = dict(
        out,
        covariance=to_device(cov, dtype),
        std_errors=to_device(std, dtype),
        correlation=to_device(cov / (std[..., :, None] * std[..., None, :]), dtype),
        result=code,
    )
    return best


def _result(best, setup, obs2, ends, batch, free, model, method, strategy, sigma) -> FitResult:
    out = best["out"]
    bsize, n = obs2.shape
    verdicts = best["verdicts"]
    residuals = best["residuals"]
    passes = np.array([v["passes"] for v in verdicts])
    code = out["result"]

    # a converged fit whose residuals are not noise: a launch time that is off, if freeing it
    # would explain them, else a local minimum. A fit that ran out of optimiser steps with
    # residuals that are not noise is flagged so too: "may still be usable" would not hold.
    one = (lambda x: x) if batch is not None else (lambda x: x[0])  # noqa: E731
    code = flag(code, one(launch_time_suspects(setup, best, sigma)), FIT_RESULTS.launch_time)
    code = flag(
        code,
        one(~passes),
        FIT_RESULTS.local_minimum,
        over=(FIT_RESULTS.successful, FIT_RESULTS.max_steps_reached),
    )
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
    arrays = dict(
        residuals=whole,
        theta_obs=np.where(mask, obs2, np.nan),
        ts=ts_out,
        loss_history=best["history"],
    )
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
        top=out["top"],
        y0=out["y0"],
        t0=out["t0"],
        values=out["values"],
        std_errors=out["std_errors"],
        covariance=out["covariance"],
        correlation=out["correlation"],
        loss_history=to_device(arrays["loss_history"], dtype),
        ts=to_device(arrays["ts"], dtype),
        theta_obs=to_device(arrays["theta_obs"], dtype),
        theta_fit=out["theta_fit"],
        residuals=to_device(arrays["residuals"], dtype),
        rms=to_device(per["rms"], dtype),
        rms_fitted=to_device(per["rms_fitted"], dtype),
        noise=to_device(per["noise"], dtype),
        runs_z=to_device(per["runs_z"], dtype),
        ljung_box=to_device(per["ljung_box"], dtype),
        describes_until=to_device(per["describes_until"], dtype),
        fitted_until=to_device(per["fitted_until"], dtype),
        phi_fit=out["phi_fit"],
        phi_residuals=phi_res,
        converged=to_device(np.asarray(code._value) == np.asarray(FIT_RESULTS.successful._value)),
        result=code,
        num_steps=to_device(per["num_steps"]),
        starts=to_device(per["starts"]),
        free=free,
        model=model,
        method=method,
        strategy=strategy,
    )
