"""How long the fibre projection follows a launch before it projects it (its solves: the engine)."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array

from ..._state import State
from ..._top import TippeTop
from .linear import linear_projection
from .modes import mode_ratio

SETTLE_AMPLITUDE = 0.01
r"""The fibre projection follows a launch's nutation in the SO(3) model until its linear
projection's amplitude is about this (rad)."""

SETTLE_TIME_MAX = 1.0
r"""The longest the fibre projection follows a launch in the SO(3) model (s)."""


def settle_time(
    top: TippeTop,
    state: State,
    *,
    amplitude: float = SETTLE_AMPLITUDE,
    time_max: float = SETTLE_TIME_MAX,
) -> Array:
    r"""How long the fibre projection follows a launch in the SO(3) model: the time its nutation
    (the other root's mode, amplitude $a_0$ of the linear projection, decaying at the rate
    $-\mathrm{Im}\,r_-$ of that mode at the nearer pole) takes to fall to `amplitude`; 0 for a
    launch with less, at most `time_max`."""
    _, _, _, log_amplitude, J = linear_projection(top, state)
    north = state.axis[2] >= 0
    pole = jnp.where(north, 0.0, jnp.pi).astype(log_amplitude.dtype)
    _, decay = mode_ratio(top, pole, J, -1)
    decaying = decay < 0
    rate = jnp.where(decaying, -decay, 1.0)
    time = (log_amplitude - jnp.log(amplitude)) / rate
    return jnp.where(decaying, jnp.clip(time, 0.0, time_max), 0.0)
