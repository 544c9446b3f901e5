"""Work-precision of the gyroscopic level against the full model: t_invert error vs wall time.

Default top, theta0 = 0.1, n0 = 100 rad/s, 10 s, summary mode. The reference is the full model
at rtol 1e-12; theta(t) of the gyroscopic level differs from it by the nutation it drops, so the
error is |t_invert - t_invert_ref| (s). Both levels at rtol 1e-4 ... 1e-10 (atol = rtol/100),
median wall time of REPEATS interleaved runs after compilation (one jitted function per level,
rtol traced). The gyroscopic curve flattens at its model error (the slow flow's own plus the
projection of a launch with omega = n a), which no tolerance removes.

    python benchmarks/gyroscopic_wp.py      # writes benchmarks/gyroscopic_work_precision.png
"""

from __future__ import annotations

import pathlib
import statistics
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import tippejax as tj  # noqa: E402

HERE = pathlib.Path(__file__).parent
RTOLS = (1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10)
REPEATS = 5
T1 = 10.0


def main():
    top = tj.default_top()
    y0 = tj.initial_state(top, 0.1, 100.0)
    t1 = jnp.asarray(T1)

    def make(model):
        @eqx.filter_jit
        def run(rtol):
            sol = tj.simulate(top, y0, t1, model=model, summary=True, rtol=rtol,
                              atol=rtol / 100, throw=False)
            return sol.t_invert, sol.num_steps
        return run

    ref = float(make("full")(jnp.asarray(1e-12))[0])
    fns = {"full": make("full"), "gyroscopic": make("gyroscopic")}
    rows = {m: [] for m in fns}
    for rtol in RTOLS:
        r = jnp.asarray(rtol)
        out = {m: jax.block_until_ready(f(r)) for m, f in fns.items()}
        times = {m: [] for m in fns}
        for _ in range(REPEATS):
            for m, f in fns.items():
                start = time.perf_counter()
                jax.block_until_ready(f(r))
                times[m].append(time.perf_counter() - start)
        for m in fns:
            err = abs(float(out[m][0]) - ref)
            rows[m].append((rtol, statistics.median(times[m]), err, int(out[m][1])))
            print(f"{m:10s} rtol {rtol:.0e}: {statistics.median(times[m]) * 1e3:8.3f} ms, "
                  f"|dt_inv| {err:.2e} s, {int(out[m][1])} steps", flush=True)
    fig, ax = plt.subplots(figsize=(6, 4.5))
    for m, style in (("full", "o-"), ("gyroscopic", "s-")):
        xs = [t for _, t, _, _ in rows[m]]
        ys = [max(e, 1e-16) for _, _, e, _ in rows[m]]
        ax.loglog(xs, ys, style, label=m)
        for rtol, t, e, _ in rows[m]:
            ax.annotate(f"{rtol:.0e}", (t, max(e, 1e-16)), fontsize=7, xytext=(3, 3),
                        textcoords="offset points")
    ax.set_xlabel("wall time per run (s, median, after compilation)")
    ax.set_ylabel("|t_invert - t_invert(full, rtol 1e-12)| (s)")
    ax.set_title(f"default top, theta0 0.1, n0 100 rad/s, {T1:.0f} s (labels: rtol)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(HERE / "gyroscopic_work_precision.png", dpi=110)
    print("wrote", HERE / "gyroscopic_work_precision.png")


if __name__ == "__main__":
    main()
