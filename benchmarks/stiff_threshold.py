"""Where does an implicit solver pay off? Tsit5, Dopri8 and Kvaerno5 as friction grows.

Standard top (A/C 0.9, eps/R 0.3), theta0 = 0.1, spin 100 rad/s, t1 = 0.5 s, rtol 1e-8, full model;
error: max |theta - theta_ref| against Kvaerno5 at rtol 1e-11. One timed run after a compiling
run. Prints a table; its numbers back `tippejax.default_solver`.

    python benchmarks/stiff_threshold.py
"""

import time

import diffrax
import jax
import numpy as np

import tippejax as tj

for mu in [300.0, 3000.0, 30000.0]:
    top = tj.TippeTop.from_ratios(0.9, 0.3, mu=mu)
    y0 = tj.initial_state(top, 0.1, 100.0)
    ts = np.linspace(0, 0.5, 51)
    kw = dict(saveat=ts, throw=False, max_steps=2_000_000)
    ref = tj.simulate(top, y0, 0.5, rtol=1e-11, atol=1e-13, solver=diffrax.Kvaerno5(), **kw)
    for name, solver in [("Tsit5", diffrax.Tsit5()), ("Dopri8", diffrax.Dopri8()), ("Kvaerno5", diffrax.Kvaerno5())]:
        tj.simulate(top, y0, 0.5, solver=solver, **kw)
        start = time.perf_counter()
        sol = tj.simulate(top, y0, 0.5, solver=solver, **kw)
        jax.block_until_ready(sol.theta)
        wall = time.perf_counter() - start
        err = np.nanmax(np.abs(np.asarray(sol.theta) - np.asarray(ref.theta)))
        ok = bool(sol.result == tj.RESULTS.successful)
        print(f"mu={mu:g} rate={float(tj.friction_rate(top)):.3g}/s {name}: {wall:.3f} s, "
              f"{int(sol.num_steps)} steps, err {err:.1e}, {'ok' if ok else 'FAILED'}", flush=True)
