r"""What the analysis takes from the friction law: its slope at zero slip, and its drilling torque."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._friction.viscous import Viscous
from .._top import TippeTop


def slip_coefficient(top: TippeTop, drilling_rate) -> Float[Array, "*batch"]:
    r"""The law's viscous coefficient at zero slip, $k = -\partial f_X/\partial v_X$ at
    $v = 0$ and the drilling rate $\omega_n$ (s/m), by forward-mode autodiff of the law.

    $\mu$ for the viscous law, $\mu/\delta$ for the regularised Coulomb law (whatever
    $\omega_n$), $\mu\varphi_F'(0)/\sqrt{\rho^2\omega_n^2 + \delta^2}$ for a Contensou law. At a
    steady state the slip vanishes, so a law without drilling torque linearises there to the
    viscous law of coefficient $k$ (its force is $-k R_n v$ to first order in $v$)."""
    law = top.friction
    rate = jnp.asarray(drilling_rate, jnp.result_type(top.m))
    zero = jnp.zeros_like(rate)

    def force_x(vx):
        return law.components(vx, zero, rate)[0]

    return -jax.jvp(force_x, (zero,), (jnp.ones_like(rate),))[1]


def drilling_torque_at_rest(top: TippeTop, drilling_rate) -> Float[Array, "*batch"]:
    r"""The law's drilling torque per unit normal force at zero slip, $m(0, \omega_n)$ (m):
    zero for a law without drilling friction, $-\tfrac{3\pi}{16}\mu\rho\,\mathrm{sign}
    \,\omega_n$ for the exact Contensou law while $\rho|\omega_n| \gg \delta$."""
    rate = jnp.asarray(drilling_rate, jnp.result_type(top.m))
    zero = jnp.zeros_like(rate)
    return top.friction.components(zero, zero, rate)[2]


def drifting_message(top: TippeTop, what: str) -> str:
    """Why `what` is not defined for a top whose law has a drilling torque."""
    law = type(top.friction).__name__
    return (
        f"{what} is not defined for a top with the {law} law: its drilling torque does not "
        "vanish at a spinning relative equilibrium (the contact drills at omega_n != 0 with "
        "zero slip), so the Jellet integral drifts there, dJ/dt = M (R - eps cos theta), and "
        "the relative equilibria are quasi-steady states that move with J, not fixed points "
        "with eigenvalues. Their positions, their J-thresholds and their stability at frozen J "
        "(W'' > 0) do not depend on the law: tj.steady_states reports them, with the drift "
        "rate (jellet_rate), and nan for the eigenvalues. Linear stability margins are derived "
        "for laws without drilling torque (the viscous and Coulomb laws)."
    )


def linearised_top(top: TippeTop, drilling_rate) -> TippeTop:
    r"""The top with the viscous law that has the same linearisation at a steady state:
    coefficient `slip_coefficient(top, drilling_rate)` (the top itself for the viscous law, up
    to its object). A law with a drilling torque has no such linearisation (`drifting_message`):
    `ValueError`."""
    if top.friction.has_drilling_torque:
        raise ValueError(drifting_message(top, "A linearisation at a steady state"))
    return top.replace(friction=Viscous(slip_coefficient(top, drilling_rate)))
