r"""The two modes of a state near a pole, $w = r_\pm\xi$, and the slow component they split off."""

from __future__ import annotations

import jax.numpy as jnp

from ..._state import State, euler_angles
from ..._top import TippeTop
from .coordinate import POLE, safe_log, safe_sqrt
from .manifold import slow_manifold

NUTATION_FLOOR = 1e-12
r"""Nutation amplitude (rad) given to a launch that has none (on the slow manifold)."""


def mode_ratio(top: TippeTop, theta, J, branch):
    r"""(Re, Im) of $r = \dot\psi + i\dot\theta/\sin\theta$ of the mode on one root of (G2):
    every state of that mode has $w = r\xi$, $\xi = a_X + ia_Y$, $w = \omega_X + i\omega_Y$."""
    sm = slow_manifold(top, theta, J, branch=branch)
    return sm.spin - sm.precession * jnp.cos(theta), sm.rate


def split(top: TippeTop, state: State, J, theta_in):
    r"""(Re, Im) of the slow component $\xi_s = (w - r_-\xi)/(r_+ - r_-)$ of a state, $r_-$ of
    the other root at `theta_in`, $r_+$ of the level's root at the state's own tilt (complex
    arithmetic in real components)."""
    theta, _, _ = euler_angles(state)
    a, w = state.axis, state.omega
    in_re, in_im = mode_ratio(top, theta_in, J, -1)
    out_re, out_im = mode_ratio(top, theta, J, 1)
    num_re = w[0] - (in_re * a[0] - in_im * a[1])
    num_im = w[1] - (in_re * a[1] + in_im * a[0])
    den_re, den_im = out_re - in_re, out_im - in_im
    den2 = den_re**2 + den_im**2
    den2 = jnp.where(den2 > 0, den2, 1.0)
    c_re = (num_re * den_re + num_im * den_im) / den2
    c_im = (num_im * den_re - num_re * den_im) / den2
    return c_re, c_im


def slow_state(state: State, north, c_re, c_im, log_gain, turn, spin_turn, side):
    r"""$(u, \varphi_s, \psi_s, \ln a_0)$ of the slow component $\xi_s = c$ of a state: its
    modulus scaled by $e^{\rm log\_gain}$, its phase advanced by `turn`, and the body's angle
    about the vertical ($\varphi + $ `side` $\psi$) turned by `spin_turn` (all 0 and `side` = 1
    for the linear projection)."""
    _, phi, psi = euler_angles(state)
    a = state.axis
    mod2 = c_re**2 + c_im**2
    positive = mod2 > 0
    modulus = jnp.where(positive, jnp.sqrt(jnp.where(positive, mod2, 1.0)), 0.0)
    modulus = jnp.clip(modulus * jnp.exp(log_gain), 0, 1)
    # sin(tilt) = |xi_s|; tan(tilt/2) = sin/(1 + cos), no cancellation
    # (a finite derivative where the modulus is clipped at 1, for a caller that differentiates
    # the projection along a run)
    log_tan = safe_log(modulus / (1 + safe_sqrt(1 - modulus**2)), -POLE)
    u = jnp.clip(jnp.where(north, log_tan, -log_tan), -POLE, POLE)
    # xi_s = -i sin(theta_s) e^{i phi_s}: phi_s = atan2(Re xi_s, -Im xi_s)
    phi_s = jnp.where(positive, jnp.arctan2(c_re, -c_im) + turn, phi)
    psi_s = psi + side * (phi - phi_s + spin_turn)
    # the nutation: what is left of the horizontal axis, xi - xi_s
    rest2 = (a[0] - c_re) ** 2 + (a[1] - c_im) ** 2
    floor2 = jnp.asarray(NUTATION_FLOOR, rest2.dtype) ** 2
    log_amplitude = 0.5 * jnp.log(jnp.maximum(rest2, floor2))
    return u, phi_s, psi_s, log_amplitude
