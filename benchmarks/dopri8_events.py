"""Tsit5 against Dopri8 with events: time ratio, steps, theta error and event times, one run.

Standard top, theta0 = 0.1, t1 = 8 s, 801 save points; spin 100 (inverts; theta error against a
Dopri8 rtol 1e-12 reference) and spin 200 (loses contact near 5.19 s). Then simulate_batch over
a 2 x 16 grid. Medians of 5 runs (3 for the batch) after a compiling call; ratios only.

    python benchmarks/dopri8_events.py
"""

import statistics
import time

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import tippejax as tj


def timed(f, n=5):
    f()
    times = []
    for _ in range(n):
        start = time.perf_counter()
        f()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main():
    top = tj.default_top()
    ts = jnp.linspace(0.0, 8.0, 801)
    ref = tj.simulate(top, tj.initial_state(top, 0.1, 100.0), 8.0, saveat=ts, rtol=1e-12,
                      atol=1e-14, solver=diffrax.Dopri8())
    print("| spin | rtol | Dopri8/Tsit5 time | steps Tsit5, Dopri8 | max dtheta Tsit5, Dopri8 | "
          "t_contact_loss Tsit5, Dopri8 | t_invert Tsit5, Dopri8 |")
    print("|---|---|---|---|---|---|---|")
    for spin in (100.0, 200.0):
        y0 = tj.initial_state(top, 0.1, spin)
        for rtol in (1e-6, 1e-8, 1e-10):
            row = []
            for solver in (diffrax.Tsit5(), diffrax.Dopri8()):
                def run(solver=solver):
                    return tj.simulate(top, y0, 8.0, saveat=ts, rtol=rtol, atol=rtol * 1e-2,
                                       solver=solver, throw=False)

                sol = run()
                err = np.nanmax(np.abs(np.asarray(sol.theta) - np.asarray(ref.theta)))
                row.append((timed(lambda: jax.block_until_ready(run().theta)), int(sol.num_steps),
                            err if spin == 100.0 else np.nan, float(sol.t_contact_loss),
                            float(sol.t_invert)))
            (t_a, s_a, e_a, l_a, i_a), (t_b, s_b, e_b, l_b, i_b) = row
            print(f"| {spin:g} | {rtol:.0e} | {t_b / t_a:.2f} | {s_a}, {s_b} | {e_a:.1e}, {e_b:.1e} | "
                  f"{l_a:.6f}, {l_b:.6f} | {i_a:.6f}, {i_b:.6f} |")
    times = {}
    for solver in (diffrax.Tsit5(), diffrax.Dopri8()):
        times[type(solver).__name__] = timed(lambda solver=solver: jax.block_until_ready(
            tj.simulate_batch(top, [0.1, 0.2], np.linspace(60.0, 150.0, 16), 4.0, solver=solver,
                              saveat=jnp.linspace(0.0, 4.0, 201)).theta), 3)
    print(f"\nsimulate_batch, 32 launches, 4 s: Dopri8/Tsit5 time = "
          f"{times['Dopri8'] / times['Tsit5']:.2f}")


if __name__ == "__main__":
    main()
