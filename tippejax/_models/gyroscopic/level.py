"""The gyroscopic level: the slow flow for the tilt alone, with the nutation averaged out."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ..._state import state_from_euler
from ..base import AbstractLevel, Conditions
from ..full import FullLevel
from .averaged import AveragedProjection
from .base import AbstractProjection, projection_of
from .chart import HAND_OVER_MARGIN, chart_condition
from .coordinate import POLE, cos_sin
from .linear import linear_state
from .manifold import slow_manifold_at
from .nutation import nutation_at
from .state import GyroscopicLevelState


class GyroscopicLevel(AbstractLevel):
    r"""The slow flow (G3) for $\theta$ with $J$ fixed: the SO(3) model (Sec. 2.2) on its slow
    manifold, the gyroscopic balance

    $$\sin\theta\,\big(A\Omega^2\cos\theta - C n\Omega - m g\epsilon\big) = 0, \tag{G1}$$

    where the nutation has decayed and $\dot\theta$ is of the order of the friction. With $n$
    from the Jellet (eq. jello), (G1) is a quadratic for the precession rate $\Omega$ (G2,
    `balance_discriminant`); on its root of larger $|\Omega|$ the friction torque gives
    $\dot\theta$ (G3, `slow_manifold`). The level integrates $u = \ln\tan(\theta/2)$, regular at
    the poles, and carries the log of the amplitude of the nutation it drops, which grows at
    the rate $\sigma$ (`nutation_damping`). Derivation and the limits of the level:
    `docs/derivations/gyroscopic-averaging.md`.

    `to_state` gives the state on the slow manifold: $\theta$, $\dot\theta$ of (G3) (the slow
    drift, no nutation), $\dot\varphi = \Omega$, spin $n$ from (G1), horizontal position and
    velocity zero. `from_state` projects a state onto it (`projection`). The step size is
    controlled on $u$ alone. Where (G2) has no real root or the slow manifold repels, the run
    continues in the full model (`fallback`; `sol.model == "gyroscopic->full"`).

    **Static options:**

    - `projection`: how a launch is put onto the slow manifold, an `AbstractProjection`:
      `AveragedProjection()` (the default: first-order averaging over the nutation, in closed
      form), `FibreProjection()` (`tippejax/_engine/fibre.py`: more exact for launches tilted
      far or mixing both modes, at the cost of a short SO(3) solve and a short slow solve per
      launch) or `LinearProjection()`. The names `"averaged"`, `"fibre"` and `"linear"` are
      accepted too. See `docs/derivations/launch-projection.md`.
    - `hand_over` (default True): where the chart ends, continue in the full model; False: the
      slow flow alone, stopping where the nutation it drops has grown past `NUTATION_MAX`
      (with `RESULTS.no_gyroscopic_balance`).
    - `stop_at_hand_over` (default False): with `hand_over`, stop where the run would hand
      over instead of continuing (with `RESULTS.no_gyroscopic_balance`, at the state on the
      slow manifold there), for a caller that continues the run itself: `outcome_map` does,
      in a batch of its own.
    - `hand_over_margin` (default `HAND_OVER_MARGIN`): with `hand_over`, hand over where
      $-\sigma/\nu$ falls below this.
    - `contact_margin` (default None): with `hand_over`, also hand over where the nutation
      the level carries, of amplitude $a$ and frequency $\nu$, would take the fraction
      `contact_margin` of $g$ off the normal force: where $\epsilon\sin\theta\,a\nu^2$ (the
      amplitude of the vertical acceleration of the centre of mass) reaches `contact_margin`
      $g$. The full model's contact loss comes where it reaches about $g$; the slow flow
      ($R_n = mg$) cannot see it.
    """

    name = "gyroscopic"
    unmodelled = ("psi", "normal_force", "slip_speed", "position", "velocity")
    friction_model = "so3"
    has_chart = True
    chart_end_result = "no_gyroscopic_balance"
    slow_flow = True
    projection: AbstractProjection = eqx.field(
        static=True, default=AveragedProjection(), converter=projection_of
    )
    hand_over: bool = eqx.field(static=True, default=True)
    stop_at_hand_over: bool = eqx.field(static=True, default=False)
    hand_over_margin: float = eqx.field(static=True, default=HAND_OVER_MARGIN)
    contact_margin: float | None = eqx.field(static=True, default=None)

    def from_state(self, top, state):
        return self.projection.project(top, state)

    def to_state(self, top, y):
        x, s = cos_sin(y.log_tan_half_theta)
        sm = slow_manifold_at(top, x, s, y.jellet)
        psi_dot = sm.spin - sm.precession * x
        theta = jnp.arctan2(s, x)
        return state_from_euler(theta, y.phi, y.psi, sm.theta_dot, sm.precession, psi_dot)

    def vector_field(self, t, y, top):
        u = y.log_tan_half_theta
        x, s = cos_sin(u)
        sm = slow_manifold_at(top, x, s, y.jellet)
        nutation = nutation_at(top, x, s, y.jellet, sm)
        return GyroscopicLevelState(
            log_tan_half_theta=jnp.where(jnp.abs(u) < POLE, sm.rate, 0.0),
            phi=sm.precession,
            psi=sm.spin - sm.precession * x,
            nutation=nutation.damping if y.nutation_rate is None else y.nutation_rate,
            jellet=jnp.zeros_like(y.jellet),
            nutation_rate=None if y.nutation_rate is None else jnp.zeros_like(y.nutation_rate),
        )

    def conditions(self, top, y):
        x, s = cos_sin(y.log_tan_half_theta)
        sm = slow_manifold_at(top, x, s, y.jellet)
        # R'_n of eq. reactie (as `routhian_normal_force`) on the slow manifold
        eps_s = top.eps * s
        h = top.R - top.eps * x
        numerator = (
            top.g
            + sm.theta_dot**2 * top.eps * x
            + eps_s * s * sm.precession * (sm.precession * x - top.C * sm.spin / top.A)
        )
        denominator = 1.0 / top.m + eps_s * (eps_s + top.mu * h**2 * sm.theta_dot) / top.A
        nutation = nutation_at(top, x, s, y.jellet, sm)
        return Conditions(
            contact=numerator,  # R_n D
            singular=denominator,
            upright=x,
            chart=chart_condition(
                top,
                x,
                y.jellet,
                y.nutation,
                nutation,
                hand_over=self.hand_over,
                margin=self.hand_over_margin,
                sin_theta=s,
                contact_margin=self.contact_margin,
            ),
        )

    def in_chart(self, top, state):
        # the linear projection's amplitude and balance decide (cheap, and what the chart reads)
        return self.conditions(top, linear_state(top, state)).chart > 0

    def fallback(self):
        if self.hand_over and not self.stop_at_hand_over:
            return FullLevel(body=self.body)
        return None

    def error_norm(self, scaled_error):
        return jnp.abs(scaled_error.log_tan_half_theta)
