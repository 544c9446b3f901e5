"""The fibre projection of a launch onto the gyroscopic level's slow manifold: its two solves."""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from .._models.gyroscopic import (
    SETTLE_AMPLITUDE,
    SETTLE_TIME_MAX,
    AbstractProjection,
    GyroscopicLevel,
    GyroscopicLevelState,
    linear_state,
    settle_time,
)
from .._models.so3 import SO3Level
from .._state import State
from .._top import TippeTop
from .packing import overflow_safe

SETTLE_RTOL, SETTLE_ATOL = 1e-7, 1e-10
"""Tolerances of the two short solves of the fibre projection."""

SETTLE_MAX_STEPS = 4096
"""Step budget of each of the two short solves (a failed solve falls back to the linear
projection)."""


def short_solve(vector_field, y0, t0, t1, norm, *, rtol, atol):
    """One short Tsit5 solve of `vector_field(t, y)` from `t0` to `t1` (either direction):
    the state at `t1` and whether the solve succeeded (it never raises)."""
    controller = diffrax.PIDController(rtol=rtol, atol=atol, norm=overflow_safe(norm))
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(lambda t, y, args: vector_field(t, y)),
        diffrax.Tsit5(),
        t0,
        t1,
        None,
        y0,
        stepsize_controller=controller,
        saveat=diffrax.SaveAt(t1=True),
        max_steps=SETTLE_MAX_STEPS,
        throw=False,
    )
    ok = sol.result == diffrax.RESULTS.successful
    return jax.tree_util.tree_map(lambda x: x[-1], sol.ys), ok


def settle_launch(
    top: TippeTop,
    state: State,
    *,
    amplitude: float = SETTLE_AMPLITUDE,
    time_max: float = SETTLE_TIME_MAX,
    rtol: float = SETTLE_RTOL,
    atol: float = SETTLE_ATOL,
) -> GyroscopicLevelState:
    """The fibre projection of a (single) state (see `FibreProjection`)."""
    linear = linear_state(top, state)
    T = settle_time(top, state, amplitude=amplitude, time_max=time_max)
    short = T <= 0
    t_end = jnp.where(short, 1e-6, T).astype(T.dtype)
    so3 = SO3Level()
    forward, ok_forward = short_solve(
        lambda t, y: so3.vector_field(t, y, top),
        so3.from_state(top, state),
        jnp.zeros_like(t_end),
        t_end,
        so3.error_norm,
        rtol=rtol,
        atol=atol,
    )
    settled = linear_state(top, so3.to_state(top, forward))
    # J is exact in the SO(3) model: keep the launch's, not the solve's rounding of it
    settled = eqx.tree_at(lambda y: y.jellet, settled, linear.jellet)
    level = GyroscopicLevel()
    back, ok_back = short_solve(
        lambda t, y: level.vector_field(t, y, top),
        settled,
        t_end,
        jnp.zeros_like(t_end),
        level.error_norm,
        rtol=rtol,
        atol=atol,
    )
    finite = jnp.all(jnp.stack([jnp.isfinite(x) for x in jax.tree_util.tree_leaves(back)]))
    use = ~short & ok_forward & ok_back & finite
    return jax.tree_util.tree_map(lambda a, b: jnp.where(use, a, b), back, linear)


class FibreProjection(AbstractProjection):
    r"""The fibre projection (Fenichel's fast fibres of the slow manifold, numerically): the
    launch is followed in the SO(3) model for the time $T$ (`settle_time`) its nutation takes to
    decay to `amplitude`, where the linear projection is accurate (its error is quadratic in
    the remaining amplitude), projected linearly there, and the slow flow (G3) is integrated
    back from $T$ to the launch time. Falls back to the linear projection where either solve
    fails or $T = 0$ (a launch with less nutation than `amplitude`). Derivation:
    `docs/derivations/launch-projection.md`.

    More exact than `AveragedProjection` for launches tilted far or mixing both modes; it costs
    two short solves per launch where the averaged projection costs a few evaluations of the
    slow flow (see the performance page).

    **Static options:** `amplitude` (default `SETTLE_AMPLITUDE`, rad), `time_max` (default
    `SETTLE_TIME_MAX`, s), and the tolerances `rtol`, `atol` of the two solves (defaults
    `SETTLE_RTOL`, `SETTLE_ATOL`).
    """

    name = "fibre"
    amplitude: float = eqx.field(static=True, default=SETTLE_AMPLITUDE)
    time_max: float = eqx.field(static=True, default=SETTLE_TIME_MAX)
    rtol: float = eqx.field(static=True, default=SETTLE_RTOL)
    atol: float = eqx.field(static=True, default=SETTLE_ATOL)

    def __check_init__(self):
        for name in ("amplitude", "time_max", "rtol", "atol"):
            if not getattr(self, name) > 0:
                raise ValueError(
                    f"FibreProjection: {name} must be positive, got {getattr(self, name)!r}."
                )

    def project(self, top, state):
        return settle_launch(
            top,
            state,
            amplitude=self.amplitude,
            time_max=self.time_max,
            rtol=self.rtol,
            atol=self.atol,
        )
