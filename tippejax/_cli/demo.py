"""`tippejax demo`: the default top launched near upright, analysed, simulated and plotted."""

from __future__ import annotations

import math
import os
import time

import jax
import numpy as np

from .._analysis.groups import thresholds
from .._analysis.steady_states import steady_states
from .._invariants import jellet
from .._simulate import simulate
from .._solution import RESULTS
from .._state import initial_state
from .._top import default_top
from .common import default_spin, fmt, print_top, save, use_agg


def demo_analysis(top, theta0: float, spin: float):
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
    print_top(top)
    y0 = initial_state(top, theta=theta0, spin=spin)
    J = jellet(top, y0)
    th = jax.jit(thresholds)(top)
    print(f"launch: theta0 = {theta0:.4g} rad, spin n0 = {spin:.6g} rad/s")
    print(f"Jellet J = {float(J):.6g} kg m^2/s  (J1 = {fmt(th.J1)}, J2 = {fmt(th.J2)})")
    states = steady_states(top, J)
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


def _result_text(sol) -> str:
    return "success" if bool(sol.result == RESULTS.successful) else RESULTS[sol.result]


def demo_simulation(top, theta0: float, spin: float, out: str, *, t1: float = 12.0) -> str:
    """Simulate the demo launch (full model) from `theta0`, `spin`; print a summary and write
    `out/demo.png`.

    **Returns:** the path of the figure.
    """
    use_agg()
    import matplotlib.pyplot as plt

    y0 = initial_state(top, theta0, spin)
    ts = np.linspace(0.0, t1, 2401)
    start = time.perf_counter()
    sol = simulate(top, y0, t1, model="full", saveat=ts, throw=False)
    theta = np.asarray(sol.theta)
    wall = time.perf_counter() - start
    J = np.asarray(sol.jellet)
    E = np.asarray(sol.energy)
    ok = np.isfinite(theta)
    last = np.flatnonzero(ok)[-1]
    print(f"\nSimulation (full model, default solver, rtol 1e-8): t = 0 .. {t1:g} s")
    print(f"  result:            {_result_text(sol)}")
    t_inv = float(sol.t_invert)
    print(
        "  inversion time:    "
        + (
            f"{t_inv:.4f} s (first upward crossing of theta = pi/2)"
            if np.isfinite(t_inv)
            else "none"
        )
    )
    print(f"  Jellet drift:      {np.nanmax(np.abs(J / J[0] - 1)):.2e} (relative, max over t)")
    print(
        f"  energy lost:       {E[0] - E[last]:.4e} J of {E[0]:.4e} J ({100 * (1 - E[last] / E[0]):.1f} %)"
    )
    print(
        f"  final state:       t = {ts[last]:.2f} s, theta = {theta[last]:.4f} rad "
        f"(pi - theta = {np.pi - theta[last]:.2e}), spin n = {float(sol.spin[last]):.2f} rad/s, "
        f"R_n = {float(sol.normal_force[last]):.4f} N"
    )
    print(f"  solver steps:      {int(sol.num_steps)} ({int(sol.num_rejected_steps)} rejected)")
    print(f"  wall time:         {wall:.1f} s (including compilation)")

    axis = np.asarray(sol.states.axis)
    fig = plt.figure(figsize=(12, 7), constrained_layout=True)
    grid = fig.add_gridspec(2, 3)
    panels = [
        (grid[0, 0], theta, r"$\theta$ (rad)"),
        (grid[0, 1], np.asarray(sol.normal_force), r"$R_n$ (N)"),
        (grid[1, 0], E, "energy $E$ (J)"),
        (grid[1, 1], J / J[0] - 1, r"$J/J_0 - 1$"),
    ]
    for spec, values, label in panels:
        ax = fig.add_subplot(spec)
        ax.plot(ts, values, lw=0.8)
        ax.set_xlabel("t (s)")
        ax.set_ylabel(label)
        if np.isfinite(t_inv):
            ax.axvline(t_inv, color="grey", ls=":", lw=0.8)
    ax = fig.add_subplot(grid[:, 2])
    # Points only: the axis precesses ~0.5 rad between save times, so joining them draws chords.
    sc = ax.scatter(axis[ok, 0], axis[ok, 1], c=ts[ok], s=2, cmap="viridis")
    ax.set_aspect("equal")
    ax.set_xlabel("$a_x$")
    ax.set_ylabel("$a_y$")
    ax.set_title("symmetry axis seen from above")
    fig.colorbar(sc, ax=ax, label="t (s)", shrink=0.6)
    fig.suptitle(
        f"Default top, theta0 = {theta0:g} rad, spin {spin:g} rad/s "
        f"(J = {float(jellet(top, y0)):.3e} kg m^2/s), full model"
    )
    os.makedirs(out, exist_ok=True)
    path = save(fig, os.path.join(out, "demo.png"), dpi=110)
    print(f"  figure:            {path}")
    return path


def run(args) -> int:
    top = default_top()
    spin = args.spin if args.spin is not None else default_spin(top)
    demo_analysis(top, args.theta0, spin)
    demo_simulation(top, args.theta0, spin, args.out)
    return 0
