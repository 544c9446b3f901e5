"""The result of a map: where each launch ended, on a grid of any two quantities."""

from __future__ import annotations

import equinox as eqx
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._outcome import INTERMEDIATE, OUTCOMES
from .._solution import RESULTS
from .._top import TippeTop
from .boundaries import MapBoundary, boundaries, theory_lines, to_values


class OutcomeMap(eqx.Module):
    r"""Where each launch of a map ended (returned by `outcome_map` and `outcome_map_tops`).

    The map's two axes are named in `axes` (e.g. `("theta0", "spin")`, `("mu", "spin")`,
    `("A_over_C", "eps_over_R")` for `outcome_map_tops`) and their values are `axis_values`.
    Every per-launch field has the grid's shape `(len(first axis), len(second axis))`. In an
    adaptive map (`refine`) the fields of a launch that was not simulated (`simulated`
    False) are nan (0 for `num_steps`), except `outcome`, `settled` and `result`, which it
    takes from the cell around it.

    **Fields:**

    - `top`: the top (for a map over fields of the top: the top whose fields are varied).
    - `axes`, `axis_values`: the axes' names and values (1-d each).
    - `fixed`: the other quantities given to the map and their values, `((name, value),
      ...)`.
    - `theta0`, `spin`, `A_over_C`, `eps_over_R`: the axis values (1-d) where they are an
      axis, else the launch's or the top's value (0-d).
    - `outcome`: index into `OUTCOMES` (int8).
    - `settled`: the final tilt is within `settle_tol` of the state it is classified into.
    - `theta_final`: $\theta$ where the run ended (at `t1`, or where it stopped).
    - `theta_expected`: the tilt of the stable state it is classified into (nan if none).
    - `t_invert`: first upward crossing of $\pi/2$ (nan if none).
    - `t_contact_loss`, `t_final`: time $R_n$ reached 0 (nan if never), time the run ended.
    - `jellet`: $J$ of the launch.
    - `contact_margin`: the closest approach to contact loss, $\min_t (g + \ddot h_0)/g$
      over the run ($R_n D / g$ with $D$ the denominator of eq. reactie: 1 for a top at
      rest, 0 where $R_n$ reaches 0; at the end of each accepted step).
    - `theta_max`: the largest tilt the run reached (at the end of each accepted step).
    - `result`: the `RESULTS` code of each run (int8); `om.message()` gives the messages
      (`tj.RESULTS.message(om.result)`, elementwise).
    - `num_steps`: solver steps of each run.
    - `model_index`: index into `models`, the level each launch was simulated with; for the
      staged maps of `model="auto"` the route, e.g. `"full->gyroscopic"` (the levels in the
      order they ran; a `"full"` after `"gyroscopic"` is the full model run again from where
      the run last left it, see `tippejax/_maps/stages.py`).
    - `simulated`: whether each launch was simulated (all of them in a dense map).
    - `resolved`: False where an adaptive map stopped refining because the boundary did not
      become simpler (see `unresolved`); those launches take the nearest simulated one's
      outcome.
    - `refine`: the levels of refinement (0: a dense map).
    - `levels`: `((launches simulated, cells split), ...)`, one entry per batched call of
      an adaptive map, the base grid first.
    - `unresolved`: the regions where refinement stopped, `((first-axis low, high,
      second-axis low, high, box-counting dimension), ...)`.
    - `t1`, `rtol`, `atol`, `settle_tol`: the settings.
    """

    top: TippeTop
    axes: tuple[str, str] = eqx.field(static=True)
    axis_values: tuple[Float[Array, " n1"], Float[Array, " n2"]]
    fixed: tuple[tuple[str, float], ...] = eqx.field(static=True)
    theta0: Float[Array, "..."]
    spin: Float[Array, "..."]
    A_over_C: Float[Array, "..."]
    eps_over_R: Float[Array, "..."]
    outcome: Int[Array, "n1 n2"]
    settled: Bool[Array, "n1 n2"]
    theta_final: Float[Array, "n1 n2"]
    theta_expected: Float[Array, "n1 n2"]
    t_invert: Float[Array, "n1 n2"]
    t_contact_loss: Float[Array, "n1 n2"]
    t_final: Float[Array, "n1 n2"]
    jellet: Float[Array, "n1 n2"]
    contact_margin: Float[Array, "n1 n2"]
    theta_max: Float[Array, "n1 n2"]
    result: Int[Array, "n1 n2"]
    num_steps: Int[Array, "n1 n2"]
    model_index: Int[Array, "n1 n2"]
    simulated: Bool[Array, "n1 n2"]
    resolved: Bool[Array, "n1 n2"]
    models: tuple[str, ...] = eqx.field(static=True)
    t1: float = eqx.field(static=True)
    rtol: float = eqx.field(static=True)
    atol: float = eqx.field(static=True)
    settle_tol: float = eqx.field(static=True)
    refine: int = eqx.field(static=True, default=0)
    levels: tuple[tuple[int, int], ...] = eqx.field(static=True, default=())
    unresolved: tuple[tuple[float, float, float, float, float], ...] = eqx.field(
        static=True, default=()
    )

    @property
    def share_simulated(self) -> float:
        """The fraction of the map's launches that were simulated (1 for a dense map)."""
        return float(np.mean(np.asarray(self.simulated)))

    def message(self) -> np.ndarray:
        """The message of each run's `result`, a numpy array of `str` with the grid's shape
        (`"successful"` where the run succeeded). Same as `tj.RESULTS.message(om.result)`."""
        return RESULTS.message(self.result)

    def counts(self) -> dict[str, int]:
        """Number of launches per outcome, and of unsettled ones (key `"unsettled"`)."""
        outcome = np.asarray(self.outcome)
        out = {name: int(np.sum(outcome == k)) for k, name in enumerate(OUTCOMES)}
        ended = outcome <= INTERMEDIATE
        out["unsettled"] = int(np.sum(ended & ~np.asarray(self.settled)))
        return out

    def boundaries(self) -> tuple[MapBoundary, ...]:
        r"""The boundaries between outcomes, one `MapBoundary` per pair of outcomes that
        touch: polylines in the map's coordinates midway between neighbouring launches of the
        two outcomes (`contourpy`), their box-counting dimension, and where the linear theory
        applies (a boundary of `"upright"` or `"inverted"` with either or `"intermediate"`)
        their distance in cells from its curve: $J = J_1$ ($W''(0; J) = 0$) or $J = J_2$
        ($W''(\pi; J) = 0$) for each launch's $J$ (for a launch with $\omega = n\,a$,
        $J = C n (R\cos\theta_0 - \epsilon)$, eq. jello). The linear theory says where
        the vertical states lose stability; the launches' boundaries lie near its curves
        where the motion settles, and away from them where it does not (slow settling near
        the thresholds at `t1`, nutation, contact loss)."""
        return boundaries(self)

    def theory_curves(self) -> dict[str, list[np.ndarray]]:
        r"""The linear theory's curves in the map's coordinates: `"J1"`, the polylines
        where $W''(0; J) = 0$ for the launches' $J$, and `"J2"`, where $W''(\pi; J) = 0$
        (empty where the map does not cross them)."""
        return {
            name: [to_values(line, self.axis_values) for line in lines]
            for name, lines in theory_lines(self).items()
        }

    def summary(self) -> str:
        """A few lines: the grid, the levels used, the simulated share, and the counts."""
        n = int(np.asarray(self.outcome).size)
        counts = self.counts()
        lines = [
            f"outcome map over {self.axes[0]} x {self.axes[1]}: {np.shape(self.outcome)} = {n} "
            f"launches, t1 = {self.t1:g} s, rtol = {self.rtol:g}",
            "levels: "
            + ", ".join(
                f"{name} ({int(np.sum(np.asarray(self.model_index) == k))})"
                for k, name in enumerate(self.models)
            ),
        ]
        if self.refine:
            lines.append(
                f"adaptive, refine = {self.refine}: {int(np.sum(np.asarray(self.simulated)))} "
                f"launches simulated ({100 * self.share_simulated:.2f}%) in "
                f"{len(self.levels)} batched calls"
                + (
                    f"; refinement stopped in {len(self.unresolved)} region(s)"
                    if self.unresolved
                    else ""
                )
            )
        lines += [
            f"  {name:>13}: {counts[name]:7d} ({100 * counts[name] / n:5.1f}%)"
            for name in (*OUTCOMES, "unsettled")
        ]
        return "\n".join(lines)
