"""Speed baseline: the simplest alternative a user has, scipy's DOP853 on the paper's Euler-angle ODE.

The equations are those of `tests/euler_reference.py` (plain numpy, one 6x6 linear solve per
right-hand-side call for the accelerations and R_n together), integrated with
`scipy.integrate.solve_ivp(method="DOP853")`.

Limitation: the ZXZ Euler chart is singular at theta = 0 and pi, so this baseline cannot follow a
launch near a pole (a real tippe top starts near theta = 0 and ends near pi): `euler_reference.solve`
raises once theta comes within 0.05 rad of a pole. Benchmark it only on launches that stay away
from the poles over the timed interval; tippejax's vector form has no such restriction. The
`__main__` launch (standard top, theta0 = 0.6, spin 150 rad/s) stays above theta = 0.16 in the full
model, but the SO(3) model damps its nutation down to theta ~ 0.01 by t ~ 1 s, so only "full" is
timed there. atol is rtol * 1e-2 (tippejax's default ratio, 1e-8 / 1e-10).

    python benchmarks/scipy_baseline.py
"""

import pathlib
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent / "tests"))
import euler_reference  # noqa: E402


def run(params, theta0, spin, t1, ts, *, variant, rtol, atol):
    """theta at `ts` (ts[-1] must be t1), wall-clock seconds of the integration, nfev."""
    ts = np.asarray(ts, float)
    if not np.isclose(ts[-1], t1):
        raise ValueError("ts must end at t1")
    start = time.perf_counter()
    out = euler_reference.solve(params, theta0, spin, ts, variant=variant, rtol=rtol, atol=atol)
    wall = time.perf_counter() - start
    return out["theta"], wall, out["nfev"]


def standard_params():
    """The standard top: A/C = 0.9, eps/R = 0.3, m = 0.02 kg, R = 0.025 m, mu = 0.3 s/m."""
    m, R = 0.02, 0.025
    C = 0.4 * m * R**2
    return dict(m=m, R=R, eps=0.3 * R, A=0.9 * C, C=C, g=9.81, mu=0.3)


if __name__ == "__main__":
    params = standard_params()
    theta0, spin, t1 = 0.6, 150.0, 2.0
    ts = np.linspace(0.0, t1, 201)
    ref, _, _ = run(params, theta0, spin, t1, ts, variant="full", rtol=1e-13, atol=1e-15)
    print(f"standard top, theta0={theta0}, spin={spin} rad/s, t1={t1} s, DOP853 (scipy)")
    print(f"{'variant':8s} {'rtol':>7s} {'wall s':>8s} {'nfev':>8s} {'us/call':>8s} {'max|dtheta|':>12s}")
    for variant in ("full", "so3"):
        try:
            ref_v = ref if variant == "full" else run(
                params, theta0, spin, t1, ts, variant=variant, rtol=1e-13, atol=1e-15)[0]
        except RuntimeError as error:  # the SO(3) model damps this launch to theta ~ 0.01
            print(f"{variant:8s} not measurable: {error}")
            continue
        for rtol in (1e-6, 1e-8, 1e-10):
            theta, wall, nfev = run(params, theta0, spin, t1, ts, variant=variant, rtol=rtol,
                                    atol=rtol * 1e-2)
            err = np.max(np.abs(theta - ref_v))
            print(f"{variant:8s} {rtol:7.0e} {wall:8.3f} {nfev:8d} {1e6 * wall / nfev:8.1f} {err:12.2e}")
