"""The model ladder: error of each cheaper level against the full model, and its cost.

For a set of scenes, runs the full, SO(3) and Routhian levels from the same initial state and
reports max |theta_level(t) - theta_full(t)| (rad), the difference in inversion time, and the
median wall time (after compilation) relative to the full model. Writes benchmarks/LEVELS.md.

    python benchmarks/levels.py
"""

from __future__ import annotations

import pathlib
import platform
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

import tippejax as tj

HERE = pathlib.Path(__file__).parent
LEVELS = ("so3", "routhian")
N_SAVE = 2001
REPEATS = 3


def scenes():
    standard = tj.default_top()
    iib = tj.TippeTop.from_ratios(0.9, 0.3, mu=1.0)
    th = tj.thresholds(iib)
    # Spin at theta0 = 0.1 whose Jellet lies midway between J1 and J2.
    target_j = 0.5 * (float(th.J1) + float(th.J2))
    y_probe = tj.initial_state(iib, 0.1, 1.0)
    spin_mid = target_j / float(tj.jellet(iib, y_probe))
    stiff = tj.TippeTop.from_ratios(0.9, 0.3, mu=300.0)
    return [
        ("inverting (n0=100, theta0=0.1)", standard, tj.initial_state(standard, 0.1, 100.0), 10.0),
        ("non-inverting (n0=20 < n1)", standard, tj.initial_state(standard, 0.1, 20.0), 5.0),
        (
            f"to intermediate state (IIb, mu=1, n0={spin_mid:.1f})",
            iib,
            tj.initial_state(iib, 0.1, spin_mid),
            10.0,
        ),
        ("near the pole (theta0=0.02, n0=60)", standard, tj.initial_state(standard, 0.02, 60.0), 5.0),
        ("stiff (mu=300, n0=100)", stiff, tj.initial_state(stiff, 0.1, 100.0), 2.0),
        (
            "generic, CM velocity (theta0=0.5, thd=2, v=(0.2,-0.1))",
            standard,
            tj.initial_state(standard, 0.5, 80.0, theta_dot=2.0, vx=0.2, vy=-0.1),
            5.0,
        ),
    ]


def timed(top, y0, t1, model, ts):
    sol = tj.simulate(top, y0, t1, model=model, saveat=ts, throw=False)
    jax.block_until_ready(sol.theta)
    times = []
    for _ in range(REPEATS):
        start = time.perf_counter()
        sol = tj.simulate(top, y0, t1, model=model, saveat=ts, throw=False)
        jax.block_until_ready(sol.theta)
        times.append(time.perf_counter() - start)
    return sol, statistics.median(times)


def main():
    rows = []
    for name, top, y0, t1 in scenes():
        ts = jnp.linspace(0.0, t1, N_SAVE)
        ref, t_ref = timed(top, y0, t1, "full", ts)
        row = dict(scene=name, t_invert_full=float(ref.t_invert), steps_full=int(ref.num_steps))
        for level in LEVELS:
            sol, t_level = timed(top, y0, t1, level, ts)
            both = np.isfinite(np.asarray(sol.theta)) & np.isfinite(np.asarray(ref.theta))
            err = float(np.max(np.abs(np.asarray(sol.theta)[both] - np.asarray(ref.theta)[both])))
            row[level] = dict(
                theta_err=err,
                t_invert_err=abs(float(sol.t_invert) - float(ref.t_invert)),
                cost=t_level / t_ref,
                model=sol.model,
                result=str(sol.result),
            )
        rows.append(row)
        print(name, {k: v for k, v in row.items() if k != "scene"}, flush=True)
    lines = [
        "# The model ladder: error of each level against the full model",
        "",
        "Made by `python benchmarks/levels.py` (float64, rtol 1e-8, atol 1e-10, default solver, "
        f"{N_SAVE} save points). Machine: {platform.processor() or platform.machine()}, "
        f"{jax.devices()[0].platform}. Error: max over the save times of |theta_level - theta_full| "
        "(rad); inversion: |t_invert_level - t_invert_full| (s, nan when neither inverts); cost: "
        f"median wall time of {REPEATS} runs after compilation, relative to the full model in the "
        "same run (a ratio; absolute times on this shared machine mean little).",
        "",
        "| scene | t_invert full (s) | so3 theta err | so3 t_invert err | so3 cost | routhian theta err | routhian t_invert err | routhian cost | routhian used |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        s, r = row["so3"], row["routhian"]
        lines.append(
            f"| {row['scene']} | {row['t_invert_full']:.4f} | {s['theta_err']:.2e} | "
            f"{s['t_invert_err']:.2e} | {s['cost']:.2f} | {r['theta_err']:.2e} | "
            f"{r['t_invert_err']:.2e} | {r['cost']:.2f} | {r['model']} |"
        )
    worst = {lv: max(row[lv]["theta_err"] for row in rows) for lv in LEVELS}
    worst_no_v = {
        lv: max(row[lv]["theta_err"] for row in rows if "CM velocity" not in row["scene"])
        for lv in LEVELS
    }
    lines += [
        "",
        f"Worst theta error over all scenes: so3 {worst['so3']:.3g} rad, routhian "
        f"{worst['routhian']:.3g} rad; without the scene with initial centre-of-mass velocity: "
        f"so3 {worst_no_v['so3']:.3g} rad, routhian {worst_no_v['routhian']:.3g} rad.",
        "",
        "`model=\"auto\"` (tippejax/_levels.py) uses these worst-case numbers: it picks the cheapest "
        "level whose worst error here is below the caller's `tolerance`, counting a level as "
        "cheaper only if its median cost is below 0.9 (`COST_MARGIN`: these ratios move by "
        "~0.1-0.2 between runs on a shared machine).",
    ]
    (HERE / "LEVELS.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
