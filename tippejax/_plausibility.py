"""Warnings for values that are valid but far outside any real tippe top (a unit mistake)."""

from __future__ import annotations

import warnings

import numpy as np

DENSEST = 2.3e4
"""kg/m^3: about the density of osmium, the densest element; a top is no denser on average."""
LIGHTEST = 10.0
"""kg/m^3: a mean density below this (ten times air) is no solid top."""
SPIN_ENERGY_RATIO = 2.0e3
r"""The largest plausible ratio of the spin energy $\tfrac12 C n^2$ to $m g R$. A tippe top
spun by hand has a few tens to a few hundred; far above, the value was most likely given in rpm
(or degrees per second)."""


def _max_abs(x) -> float:
    x = np.abs(np.asarray(x, dtype=float))
    return float(np.nanmax(x)) if x.size else 0.0


def warn_if_implausible_top(m, R, eps, A, C, g) -> None:
    """Warn (without refusing) when a top's values look like a unit mistake.

    Checks the mean density $m / (\\tfrac43\\pi R^3)$ of the ball (a mass in grams or a radius
    in millimetres shows as a density far outside solids), the axial inertia against the
    largest a body inside the ball can have ($C \\le m R^2$) and the gravitational
    acceleration (m/s^2). Concrete numpy values only; for a batch, the worst member is named.
    """
    m, R, A, C, g = (np.asarray(v, dtype=float) for v in (m, R, A, C, g))
    density = np.asarray(m / (4.0 / 3.0 * np.pi * R**3))
    if np.any(density > DENSEST) or np.any(density < LIGHTEST):
        i = np.unravel_index(np.argmax(np.abs(np.log(density / 1e3))), density.shape)
        m_i = float(np.broadcast_to(m, density.shape)[i])
        R_i = float(np.broadcast_to(R, density.shape)[i])
        warnings.warn(
            f"TippeTop: m = {m_i:.4g} kg in a ball of radius R = {R_i:.4g} m is a mean density "
            f"of {float(density[i]):.3g} kg/m^3, outside any solid top ({LIGHTEST:g} to "
            f"{DENSEST:g} kg/m^3). Masses are in kg and lengths in m (a 25 mm ball is "
            "R = 0.025).",
            UserWarning,
            stacklevel=4,
        )
    if np.any(C > m * R**2 * (1 + 1e-9)):
        warnings.warn(
            "TippeTop: the axial moment of inertia C exceeds m R^2, more than any body inside "
            "its ball can have (a ring of mass m at the rim has m R^2). Inertias are in kg m^2.",
            UserWarning,
            stacklevel=4,
        )
    if np.any(g < 0.5) or np.any(g > 50.0):
        warnings.warn(
            f"TippeTop: g = {_max_abs(g):.4g} m/s^2 is far from any planet's surface gravity "
            "(Earth: 9.81 m/s^2). Was it given in other units?",
            UserWarning,
            stacklevel=4,
        )


def warn_if_implausible_spin(m, R, C, g, spin) -> None:
    r"""Warn (without refusing) when a launch spin is far beyond any real tippe top.

    The test is the spin energy $\tfrac12 C n^2$ against $m g R$ (`SPIN_ENERGY_RATIO`); such a
    spin is most likely in rpm (rad/s = rpm $\cdot 2\pi/60$). Concrete values only.
    """
    spin = np.asarray(spin, dtype=float)
    if spin.size == 0:
        return
    scale = np.asarray(m * g * R / C, dtype=float)
    ratio = 0.5 * spin**2 / scale
    if np.any(ratio > SPIN_ENERGY_RATIO):
        i = np.unravel_index(np.argmax(ratio), ratio.shape)
        n = float(np.broadcast_to(spin, ratio.shape)[i])
        limit = float(np.sqrt(2.0 * SPIN_ENERGY_RATIO * np.broadcast_to(scale, ratio.shape)[i]))
        warnings.warn(
            f"initial_state: a spin of {n:.6g} rad/s is far beyond any tippe top (its spin "
            f"energy is {float(ratio[i]):.3g} times m g R; this warning starts at about "
            f"{limit:.3g} rad/s for this top). Spins are in rad/s: if this is "
            f"rpm, pass {n:g} * 2 * pi / 60 = {n * 2 * np.pi / 60:.6g} rad/s.",
            UserWarning,
            stacklevel=4,
        )
