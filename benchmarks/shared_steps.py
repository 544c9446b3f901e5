"""Shared steps against per-member steps: `simulate_batch(..., steps="shared")` and the default
`steps="per_member"` on the same batch, in one process.

The batch: the standard top, theta0 = 0.1, 1000 spins from 140 to 160 rad/s, t1 = 20 s, rtol
1e-8 (the default), summary mode, for the models "so3" and "full". Each path is run once to
compile, then 3 times; the median is reported per top, with the largest step count, and the
largest difference between the paths of t_invert and of the final tilt.

Run it with one host device and with the default (every core a device), e.g.

    TIPPEJAX_HOST_DEVICES=1 python benchmarks/shared_steps.py
    python benchmarks/shared_steps.py

Prints only (does not write RESULTS.md). `BENCH_N` sets the batch size.
"""

from __future__ import annotations

import os
import time

import jax
import numpy as np

import tippejax as tj


def main():
    n = int(os.environ.get("BENCH_N", "1000"))
    top = tj.default_top()
    spins = np.linspace(140.0, 160.0, n)
    print(f"{jax.device_count()} device(s), {n} tops")
    for model in ("so3", "full"):
        sols = {}
        for steps in ("per_member", "shared"):
            def run():
                return tj.simulate_batch(top, theta0=0.1, spin=spins, t1=20.0, model=model,
                                         summary=True, grid=("spin",), steps=steps)

            start = time.perf_counter()
            jax.block_until_ready(run().theta)
            first = time.perf_counter() - start
            times = []
            for _ in range(3):
                start = time.perf_counter()
                sol = run()
                jax.block_until_ready(sol.theta)
                times.append(time.perf_counter() - start)
            sols[steps] = sol
            print(f"{model:4s} {steps:10s} first call {first:5.1f} s, median "
                  f"{np.median(times) / n * 1e3:.3f} ms per top, steps (max) "
                  f"{int(np.max(np.asarray(sol.num_steps)))}")
        a, b = sols["per_member"], sols["shared"]
        d_invert = np.nanmax(np.abs(np.asarray(a.t_invert) - np.asarray(b.t_invert)))
        d_theta = np.nanmax(np.abs(np.asarray(a.theta[..., -1]) - np.asarray(b.theta[..., -1])))
        print(f"{model:4s} max |t_invert difference| {d_invert:.2e} s, max |final theta "
              f"difference| {d_theta:.2e} rad")


if __name__ == "__main__":
    main()
