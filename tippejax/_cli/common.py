"""What the commands share: the output folder, a top of each group, the printed top, figures."""

from __future__ import annotations

import math
import os

import jax
import numpy as np

from .._analysis.groups import GROUPS, classify, group_index, thresholds
from .._plot import group_map
from .._top import TippeTop, default_top

DEFAULT_OUT = "tippejax-out"

# One representative (A/C, eps/R) per group, well inside it (distance to the nearest other group
# in the (A/C, eps/R) plane in brackets; Groups Ia and IIc are thin). Checked with `classify`.
REPRESENTATIVES: dict[str, tuple[float, float]] = {
    "Ia": (0.91, 0.035),  # (0.035)
    "Ib": (0.65, 0.15),  # (0.15)
    "IIa": (0.69, 0.38),  # (0.05)
    "IIb": (0.95, 0.45),  # (0.2)
    "IIc": (0.976, 0.04),  # (0.012)
    "III": (1.6, 0.2),  # (0.4)
}

_THRESHOLD_UNITS = (
    ("n1", "rad/s"),
    ("n2", "rad/s"),
    ("J1", "kg m^2/s"),
    ("J2", "kg m^2/s"),
    ("theta_c", "rad"),
    ("x_b", ""),
    ("theta_b", "rad"),
)


def fmt(value: float, spec: str = ".6g") -> str:
    """A number, or "-" for nan."""
    value = float(value)
    return "-" if math.isnan(value) else format(value, spec)


def mu_text(top, spec: str = ".4g") -> str:
    """`mu = ...` with the units of the top's friction law (s/m for the viscous law,
    dimensionless for the Coulomb laws)."""
    units = top.friction.mu_units
    return f"mu = {float(top.mu):{spec}} " + ("(dimensionless)" if units == "1" else units)


def print_top(top) -> str:
    """Print a top's parameters, group and thresholds; returns its group."""
    th = jax.jit(thresholds)(top)  # one compilation instead of one per elementwise op
    group = GROUPS[int(jax.jit(group_index)(top))]
    print(
        f"top: m = {float(top.m):.4g} kg, R = {float(top.R):.4g} m, eps = {float(top.eps):.4g} m, "
        f"A = {float(top.A):.4g} kg m^2, C = {float(top.C):.4g} kg m^2, {mu_text(top)}"
    )
    print(f"A/C = {float(top.A / top.C):.4g}, eps/R = {float(top.eps / top.R):.4g}: Group {group}")
    print("thresholds (- = undefined for this group):")
    for name, unit in _THRESHOLD_UNITS:
        print(f"  {name:8s} = {fmt(getattr(th, name)):>12s} {unit}")
    return group


def use_agg():
    """Draw without a display (matplotlib's Agg backend), before pyplot is imported."""
    import matplotlib

    matplotlib.use("Agg")


def save(fig, path: str, dpi: float = 130) -> str:
    """Write `fig` to `path` and close it; returns the path."""
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def write_group_map(out: str, points=None) -> str:
    """Write `group_map.png` to the folder `out`; returns its path."""
    use_agg()
    ax = group_map(points=points)
    return save(ax.figure, os.path.join(out, "group_map.png"))


def representative_tops() -> dict:
    """`{group: TippeTop}` for `REPRESENTATIVES`, each checked to be in its group."""
    tops = {}
    for name, (a, e) in REPRESENTATIVES.items():
        top = TippeTop.from_ratios(a, e)
        got = classify(top)
        if got != name:  # pragma: no cover - guards the table above
            raise RuntimeError(f"Representative of Group {name} (A/C={a}, eps/R={e}) is in {got}.")
        tops[name] = top
    return tops


def default_spin(top) -> float:
    r"""A launch spin above the inversion threshold: $1.5\max(n_1, n_2(R+\epsilon)/(R-\epsilon))$,
    rounded up to a whole rad/s (ignoring undefined thresholds; 100 rad/s if both are)."""
    th = thresholds(top)
    lever = float((top.R + top.eps) / (top.R - top.eps))
    candidates = [v for v in (float(th.n1), float(th.n2) * lever) if not math.isnan(v)]
    if not candidates:
        return 100.0
    return float(np.ceil(1.5 * max(candidates)))


def top_from_options(args) -> TippeTop:
    """The top of a command's options: `default_top()` with the given fields replaced.

    `--m`, `--R`, `--eps`, `--mu` replace those fields. `--A-over-C` and/or `--eps-over-R`
    rebuild the top with `TippeTop.from_ratios` (keeping m, R, mu; the ratio not given is kept
    from the top so far; C = 0.4 m R^2, a homogeneous sphere).
    """
    if args.eps is not None and args.eps_over_R is not None:
        raise ValueError("give the eccentricity once: --eps (m) or --eps-over-R, not both.")
    top = default_top()
    fields = {f: float(getattr(top, f)) for f in ("m", "R", "eps", "A", "C", "g", "mu")}
    for name in ("m", "R", "eps", "mu"):
        value = getattr(args, name)
        if value is not None:
            fields[name] = float(value)
    if args.A_over_C is not None or args.eps_over_R is not None:
        a_over_c = args.A_over_C if args.A_over_C is not None else fields["A"] / fields["C"]
        eps_over_r = args.eps_over_R if args.eps_over_R is not None else fields["eps"] / fields["R"]
        return TippeTop.from_ratios(
            a_over_c, eps_over_r, m=fields["m"], R=fields["R"], mu=fields["mu"], g=fields["g"]
        )
    return TippeTop(**fields)
