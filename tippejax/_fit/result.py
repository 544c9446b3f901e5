"""What a fit returns: `FitResult` and the `FIT_RESULTS` codes."""

from __future__ import annotations

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._state import State
from .._top import TippeTop
from .params import units


class FIT_RESULTS(eqxi.Enumeration):
    """Outcome of a fit. `successful` is the empty message."""

    successful = ""
    max_steps_reached = (
        "The optimiser used max_steps without meeting its tolerance. The fit may still be "
        "usable (look at loss_history); raise max_steps or try another strategy."
    )
    optimiser_failed = "The optimiser stopped on a non-finite loss or a singular linear system."
    simulation_failed = (
        "At the fitted parameters the simulation fails before the end of the record (contact "
        "lost, the R_n singularity or max steps): those save times carry the failure residual."
    )
    outside_trust_region = (
        "The fit ended at the edge of its trust region, a factor 5 from the guess in some "
        "free parameter (|u| = 1.6 in the coordinates of tippejax/_fit/params.py): the "
        "guess is too far off for the search, or the data do not determine that parameter. "
        "Start from a better guess, or hold the parameter fixed."
    )
    local_minimum = (
        "The residuals are not noise (they run in long stretches of one sign, or part of the "
        "record is fitted much worse than the rest): the fit sits in a local minimum, or the "
        "model does not describe the record. The standard errors do not apply. Try another "
        "guess, more starts (strategy), or trim=True for a record whose end the model does "
        "not describe."
    )
    launch_time = (
        "The residuals are not noise, and a shift of the launch time would explain most of "
        "them: the record's clock probably does not start at the launch. y0_guess is the "
        "state at the launch time t0 (0 by default, as in simulate). Pass t0= the launch's "
        "time in the record's clock, or free 't0'. The standard errors do not apply."
    )
    phase_ambiguous = (
        "The nutation's phase does not pin the spin: along the valley of the slow motion, "
        "spins one or more nutation cycles away fit the record as well (chi-square within 9 "
        "of this fit), so the fit may sit on a neighbouring cycle. The standard errors are "
        "widened along that valley to cover them (a lower bound when the flat stretch "
        "reaches the end of the scan, 20 cycles or 10% of the spin). A longer or less noisy "
        "record, phi_obs, or a known spin narrows it."
    )


class FitResult(eqx.Module):
    r"""The result of `fit`. Batched fits (several recordings) carry a leading batch axis.

    **Fields:**

    - `top`, `y0`: the fitted `TippeTop` (its friction law included) and initial `State`
      (free quantities replaced).
    - `t0`: the launch time (s): the time of `y0` in the record's clock (fitted if `"t0"` was
      free; else the given `t0`, by default 0). `simulate(res.top, res.y0, t1, t0=res.t0)`
      runs the fitted motion.
    - `free`: the names of the free parameters, in the order of `values`.
    - `values`: fitted values of the free parameters.
    - `std_errors`: their standard errors, $\sqrt{\mathrm{diag}\,\Sigma}$.
    - `covariance`: $\Sigma = s^2 (J^\top J)^{-1}$, the Gauss-Newton covariance in the physical
      parameters, with $J$ the Jacobian of the weighted residuals at the fit and $s^2 =
      \mathrm{RSS}/(N - p)$ the residual variance ($N$ used points, $p$ free parameters). It
      assumes independent errors of equal variance and a model that describes the data (the
      diagnostics below test both); it is linear, so it understates the uncertainty of badly
      determined parameters. When the phase check (`profile.py`) finds nutation cycles beyond
      these error bars that fit as well (`phase_ambiguous`), it is widened along the slow
      valley to cover them: $\Sigma + a^2 (Gv)(Gv)^\top$, $G = \partial p/\partial u$.
    - `correlation`: $\Sigma_{ij}/\sqrt{\Sigma_{ii}\Sigma_{jj}}$.
    - `loss_history`: $\tfrac12\sum r_k^2$ after each optimiser step, all stages one after the
      other, of the start that was kept (nan-padded to a fixed length).
    - `ts`, `theta_obs`: the data (nan where masked); `ts` carries the batch axis too, so
      `jax.tree_util.tree_map(lambda x: x[b], result)` picks recording `b`.
    - `theta_fit`: the fitted model's tilt at `ts` over the whole record (nan past a failure).
    - `residuals`: `theta_fit - theta_obs` over the whole record (nan where masked or failed).
    - `rms`: root mean square of the residuals over the whole record (rad).
    - `rms_fitted`: the same over the part of the record the fit used (`fitted_until`).
    - `noise`: the noise level the residuals are judged against: `sigma` if given, else the
      median of the mean-square residual of windows of the fitted record (a robust estimate
      of the noise when at least half the record is described).
    - `runs_z`: the z-score of the Wald-Wolfowitz runs test on the signs of the fitted
      residuals; white noise gives $|z| \lesssim 3$, a fit in the wrong valley (a slipped
      nutation phase, a wrong envelope) gives long runs of one sign and a large $-z$.
    - `ljung_box`: the Ljung-Box statistic of the fitted residuals' autocorrelations at lags
      1-20, divided by its rejection threshold (chi-square at a false-alarm rate of 1e-3):
      above 1, the residuals are serially correlated (left-over nutation, even when sampled
      below its frequency).
    - `describes_until`: the end of the initial part of the record the model describes: the
      end of the last window before the first one whose mean-square residual is too large for
      noise of level `noise` (a chi-square test at a false-alarm rate of 1e-3 over all
      windows; when the residuals fail the tests but no window stands out against the median,
      against the quietest window instead). For data the model made, the whole record.
    - `fitted_until`: the end of the part of the record the fit used (`trim`; else the end).
    - `phi_fit`, `phi_residuals`: the fitted precession angle and its wrapped residual (nan
      unless `phi_obs` was given).
    - `converged`: the optimiser met its tolerance, the residuals pass the diagnostics
      (runs test, Ljung-Box, windows; and their level against `sigma` when it is given) and
      the phase check found no other nutation cycle that fits as well.
    - `result`: a `FIT_RESULTS` code; `message` gives its text.
    - `num_steps`: optimiser steps, all stages and starts.
    - `starts`: how many starting points were refined before one passed the diagnostics.
    - `model`, `method`, `strategy`: the level of model, optimiser and strategy used.
    """

    top: TippeTop
    y0: State
    t0: Float[Array, "*batch"]
    values: Float[Array, "*batch p"]
    std_errors: Float[Array, "*batch p"]
    covariance: Float[Array, "*batch p p"]
    correlation: Float[Array, "*batch p p"]
    loss_history: Float[Array, "*batch steps"]
    ts: Float[Array, "*batch N"]
    theta_obs: Float[Array, "*batch N"]
    theta_fit: Float[Array, "*batch N"]
    residuals: Float[Array, "*batch N"]
    rms: Float[Array, "*batch"]
    rms_fitted: Float[Array, "*batch"]
    noise: Float[Array, "*batch"]
    runs_z: Float[Array, "*batch"]
    ljung_box: Float[Array, "*batch"]
    describes_until: Float[Array, "*batch"]
    fitted_until: Float[Array, "*batch"]
    phi_fit: Float[Array, "*batch N"]
    phi_residuals: Float[Array, "*batch N"]
    converged: Bool[Array, "*batch"]
    result: FIT_RESULTS
    num_steps: Int[Array, "*batch"]
    starts: Int[Array, "*batch"]
    free: tuple[str, ...] = eqx.field(static=True)
    model: str = eqx.field(static=True)
    method: str = eqx.field(static=True)
    strategy: str = eqx.field(static=True)

    @property
    def params(self) -> dict[str, Array]:
        """The fitted free parameters by name."""
        return {name: self.values[..., i] for i, name in enumerate(self.free)}

    def message(self) -> str | np.ndarray:
        """Why the fit stopped ("converged" when it did): a str, or an array of str for a
        batched fit (elementwise)."""
        codes = np.asarray(self.result._value)
        texts = np.array(
            [FIT_RESULTS[_item(self.result, i)] or "converged" for i in range(codes.size)],
            dtype=object,
        )
        return str(texts[0]) if codes.ndim == 0 else texts.reshape(codes.shape)

    def table(self) -> str:
        """The fitted values with standard errors, one line per free parameter."""
        values, errors = np.asarray(self.values), np.asarray(self.std_errors)
        lines = []
        message = self.message()
        law = self.top.friction
        if values.ndim == 1:
            lines.append(f"friction law: {law!r}")
            lines.append(f"{'parameter':>12}  {'value':>13}  {'std error':>11}  {'rel':>8}  units")
            for name, v, e in zip(self.free, values, errors):
                rel = abs(e / v) if v != 0 else np.inf
                lines.append(f"{name:>12}  {v:13.6g}  {e:11.3g}  {rel:8.2%}  {units(name, law)}")
            lines.append(
                f"rms residual {float(self.rms):.4g} rad over the record, "
                f"{float(self.rms_fitted):.4g} rad over the fitted part (noise level "
                f"{float(self.noise):.3g}); runs test z = {float(self.runs_z):.2g}, Ljung-Box "
                f"{float(self.ljung_box):.2g} of its threshold; describes "
                f"the record until t = {float(self.describes_until):.4g} s of "
                f"{float(self.ts[-1]):.4g} s; {int(self.num_steps)} optimiser steps from "
                f"{int(self.starts)} start(s); {message}"
            )
        else:
            for b in range(values.shape[0]):
                row = ", ".join(
                    f"{n} = {v:.6g} +- {e:.2g}" for n, v, e in zip(self.free, values[b], errors[b])
                )
                lines.append(
                    f"[{b}] {row}; rms {float(self.rms[b]):.3g}; runs z "
                    f"{float(self.runs_z[b]):.2g}; {int(self.num_steps[b])} steps; {message[b]}"
                )
        return "\n".join(lines)


def _item(result, i):
    return jax.tree_util.tree_map(lambda x: jnp.ravel(x)[i], result)
