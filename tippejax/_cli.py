"""Command line: `tippejax classify | diagram | demo`.

- `classify`: the group and thresholds of a top, and a map of the groups.
- `diagram`: the six bifurcation diagrams (the paper's Fig. 1) and the map of the groups.
- `demo`: the analysis of the default top launched near upright (and, later, its simulation).

Run as `tippejax ...` (console script) or `python -m tippejax._cli ...`.
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Sequence

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


def _fmt(value: float, spec: str = ".6g") -> str:
    """A number, or "-" for nan."""
    value = float(value)
    return "-" if math.isnan(value) else format(value, spec)


def _print_top(top) -> str:
    import jax

    import tippejax as tj
    from tippejax._analysis.groups import group_index

    th = jax.jit(tj.thresholds)(top)  # one compilation instead of one per elementwise op
    group = tj.GROUPS[int(jax.jit(group_index)(top))]
    print(
        f"top: m = {float(top.m):.4g} kg, R = {float(top.R):.4g} m, eps = {float(top.eps):.4g} m, "
        f"A = {float(top.A):.4g} kg m^2, C = {float(top.C):.4g} kg m^2, mu = {float(top.mu):.4g} s/m"
    )
    print(f"A/C = {float(top.A / top.C):.4g}, eps/R = {float(top.eps / top.R):.4g}: Group {group}")
    print("thresholds (- = undefined for this group):")
    for name, unit in _THRESHOLD_UNITS:
        print(f"  {name:8s} = {_fmt(getattr(th, name)):>12s} {unit}")
    return group


def _save(fig, path: str) -> str:
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=130)
    plt.close(fig)
    return path


def _agg():
    import matplotlib

    matplotlib.use("Agg")


def write_group_map(out: str, points=None) -> str:
    """Write `group_map.png` to the folder `out`; returns its path."""
    _agg()
    from ._plot import group_map

    ax = group_map(points=points)
    return _save(ax.figure, os.path.join(out, "group_map.png"))


def representative_tops() -> dict:
    """`{group: TippeTop}` for `REPRESENTATIVES`, each checked to be in its group."""
    import tippejax as tj

    tops = {}
    for name, (a, e) in REPRESENTATIVES.items():
        top = tj.TippeTop.from_ratios(a, e)
        got = tj.classify(top)
        if got != name:  # pragma: no cover - guards the table above
            raise RuntimeError(f"Representative of Group {name} (A/C={a}, eps/R={e}) is in {got}.")
        tops[name] = top
    return tops


def write_diagrams(out: str) -> list[str]:
    """Write `bifurcation_diagrams.png` and `group_map.png` to the folder `out`."""
    _agg()
    from ._plot import bifurcation_diagrams

    fig = bifurcation_diagrams(representative_tops())
    paths = [_save(fig, os.path.join(out, "bifurcation_diagrams.png"))]
    paths.append(write_group_map(out, points=REPRESENTATIVES))
    return paths


def default_spin(top) -> float:
    r"""A launch spin above the inversion threshold: $1.5\max(n_1, n_2(R+\epsilon)/(R-\epsilon))$,
    rounded up to a whole rad/s (ignoring undefined thresholds; 100 rad/s if both are)."""
    import numpy as np

    import tippejax as tj

    th = tj.thresholds(top)
    lever = float((top.R + top.eps) / (top.R - top.eps))
    candidates = [v for v in (float(th.n1), float(th.n2) * lever) if not math.isnan(v)]
    if not candidates:
        return 100.0
    return float(np.ceil(1.5 * max(candidates)))


def _demo_analysis(top, theta0: float, spin: float):
    r"""Print the analysis of a launch: group, thresholds, Jellet and steady states at that Jellet.

    $J = C n_0(R\cos\theta_0 - \epsilon)$ for a launch without precession (eq. Jellet); the steady
    states are those of `tj.steady_states` (vertical: $W'' > 0$ at the pole; intermediate:
    $g(\cos\theta_0) > 0$).

    **Arguments:**

    - `top`: the `TippeTop`.
    - `theta0`: launch tilt (rad).
    - `spin`: launch spin $n_0$ (rad/s).

    **Returns:** the Jellet $J$ (a JAX scalar, kg m^2/s).
    """
    import jax
    import numpy as np

    import tippejax as tj

    _print_top(top)
    y0 = tj.initial_state(top, theta=theta0, spin=spin)
    J = tj.jellet(top, y0)
    th = jax.jit(tj.thresholds)(top)
    print(f"launch: theta0 = {theta0:.4g} rad, spin n0 = {spin:.6g} rad/s")
    print(f"Jellet J = {float(J):.6g} kg m^2/s  (J1 = {_fmt(th.J1)}, J2 = {_fmt(th.J2)})")
    states = tj.steady_states(top, J)
    print("steady states at this J:")
    for theta, spin_v, stable in zip(
        np.asarray(states.vertical_theta),
        np.asarray(states.vertical_spin),
        np.asarray(states.vertical_stable),
    ):
        name = "theta = 0 " if theta == 0 else "theta = pi"
        print(
            f"  vertical     {name}      spin n = {spin_v:9.4g} rad/s  "
            f"{'stable' if stable else 'unstable'}"
        )
    valid = np.asarray(states.intermediate_valid)
    if not valid.any():
        print("  intermediate none")
    for theta, g, stable, ok in zip(
        np.asarray(states.intermediate_theta),
        np.asarray(states.intermediate_g),
        np.asarray(states.intermediate_stable),
        valid,
    ):
        if ok:
            print(
                f"  intermediate theta = {theta:.6g} rad ({math.degrees(theta):.2f} deg)  "
                f"g = {g:.4g}  {'stable' if stable else 'unstable'}"
            )
    return J


def _demo_simulation(top, theta0: float, spin: float, out: str):
    """Simulate the demo launch (full model), print a summary and write `out/demo.png`.

    **Returns:** the path of the figure.
    """
    from ._demo import run_demo_simulation

    return run_demo_simulation(top, theta0, spin, out)


def _cmd_classify(args) -> int:
    import tippejax as tj

    if (args.A_over_C is None) != (args.eps_over_R is None):
        raise SystemExit("classify: give both --A-over-C and --eps-over-R, or neither.")
    if args.A_over_C is None:
        top = tj.default_top()
    else:
        top = tj.TippeTop.from_ratios(args.A_over_C, args.eps_over_R)
    group = _print_top(top)
    os.makedirs(args.out, exist_ok=True)
    point = {f"this top ({group})": (float(top.A / top.C), float(top.eps / top.R))}
    print(f"wrote {write_group_map(args.out, points=point)}")
    return 0


def _cmd_diagram(args) -> int:
    os.makedirs(args.out, exist_ok=True)
    for name, (a, e) in REPRESENTATIVES.items():
        print(f"Group {name:3s}: A/C = {a:g}, eps/R = {e:g}")
    for path in write_diagrams(args.out):
        print(f"wrote {path}")
    return 0


def _cmd_demo(args) -> int:
    import tippejax as tj

    top = tj.default_top()
    spin = args.spin if args.spin is not None else default_spin(top)
    _demo_analysis(top, args.theta0, spin)
    # Simulation of the same launch.
    _demo_simulation(top, args.theta0, spin, args.out)
    return 0


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tippejax", description="Steady states and groups of the tippe top (tippejax)."
    )
    sub = parser.add_subparsers(dest="command", required=True)

    def out_option(p):
        p.add_argument("--out", default=DEFAULT_OUT, help=f"output folder (default ./{DEFAULT_OUT})")

    p = sub.add_parser("classify", help="group and thresholds of a top; writes group_map.png")
    p.add_argument("--A-over-C", dest="A_over_C", type=float, default=None, help="A/C (>= 0.5)")
    p.add_argument("--eps-over-R", dest="eps_over_R", type=float, default=None, help="eps/R in (0, 1)")
    out_option(p)
    p.set_defaults(func=_cmd_classify)

    p = sub.add_parser("diagram", help="writes bifurcation_diagrams.png and group_map.png")
    out_option(p)
    p.set_defaults(func=_cmd_diagram)

    p = sub.add_parser("demo", help="steady states of the default top launched near upright")
    out_option(p)
    p.add_argument(
        "--spin", type=float, default=None,
        help="launch spin n0 (rad/s); default 1.5 x the inversion threshold, rounded up",
    )
    p.add_argument("--theta0", type=float, default=0.1, help="launch tilt (rad), default 0.1")
    p.set_defaults(func=_cmd_demo)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `tippejax` console script. **Returns:** the exit status (0)."""
    args = _parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    raise SystemExit(main())
