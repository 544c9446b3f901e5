"""Work-precision of the gyroscopic level against SO(3) and the full model, one top per group.

One top per group (the tops of `python benchmarks/levels.py --groups`:
`TippeTop.from_ratios(A/C, eps/R, mu=0.3)`), launched with omega = n a at theta0 = 0.1 and
n0 = 3 n1 (3 n2 in group I, where n1 is undefined), run for `T1` s in summary mode. The
quantity: t_invert where the full model's reference inverts (groups II and III), else theta at
`T1` (groups I, where the top stays near upright). Reference: the full model at rtol 1e-12.
Each level at rtol 1e-4 ... 1e-10 (atol = rtol/100), median wall time of `REPEATS` interleaved
runs after compilation (one jitted function per level, the top, launch and rtol traced, so one
compilation serves every group). The gyroscopic curve flattens at its model error (the slow
flow's own, the averaged launch projection's, and the full model's difference from the SO(3)
model the slow flow averages), which no tolerance removes; the SO(3) curve shows that last
part alone.

    python benchmarks/gyroscopic_wp.py      # writes benchmarks/gyroscopic_work_precision.png
"""

from __future__ import annotations

import pathlib
import platform
import statistics
import time

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import tippejax as tj  # noqa: E402

jax.config.update("jax_enable_x64", True)

HERE = pathlib.Path(__file__).parent
RTOLS = (1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10)
REPEATS = 5
T1 = 15.0
TOPS = {"Ia": (0.96, 0.02), "Ib": (0.7, 0.2), "IIa": (0.8, 0.3), "IIb": (0.9, 0.3),
        "IIc": (0.99, 0.02), "III": (1.5, 0.2)}
WP_MARK = "## Work-precision per group: the gyroscopic level against SO(3) and the full model"
SOLVERS = {"full": diffrax.Dopri8(), "so3": diffrax.Dopri8(), "gyroscopic": diffrax.Dopri5()}


def make(model):
    @eqx.filter_jit
    def run(top, y0, rtol):
        sol = tj.simulate(top, y0, T1, model=model, summary=True, rtol=rtol, atol=rtol / 100,
                          solver=SOLVERS[model], throw=False)
        return sol.t_invert, sol.theta[-1], sol.num_steps, sol.result._value
    return run


def reference_spin(top):
    th = tj.thresholds(top)
    n1 = float(th.n1)
    return 3.0 * (n1 if np.isfinite(n1) else float(th.n2))


def main():
    fns = {m: make(m) for m in SOLVERS}
    results = {}
    for group, (a_c, e_r) in TOPS.items():
        top = tj.TippeTop.from_ratios(a_c, e_r, mu=0.3)
        assert str(tj.classify(top)) == group, (group, tj.classify(top))
        spin = reference_spin(top)
        y0 = tj.initial_state(top, 0.1, spin)
        ref = fns["full"](top, y0, jnp.asarray(1e-12))
        inverts = bool(np.isfinite(float(ref[0])))
        quantity = (lambda out: float(out[0])) if inverts else (lambda out: float(out[1]))
        ref_q = quantity(ref)
        rows = {m: [] for m in fns}
        for rtol in RTOLS:
            r = jnp.asarray(rtol)
            out = {m: jax.block_until_ready(f(top, y0, r)) for m, f in fns.items()}
            times = {m: [] for m in fns}
            for _ in range(REPEATS):
                for m, f in fns.items():
                    start = time.perf_counter()
                    jax.block_until_ready(f(top, y0, r))
                    times[m].append(time.perf_counter() - start)
            for m in fns:
                ok = int(out[m][3]) == 0
                err = abs(quantity(out[m]) - ref_q) if ok else float("nan")
                rows[m].append((rtol, statistics.median(times[m]), err, int(out[m][2])))
        results[group] = dict(spin=spin, inverts=inverts, ref=ref_q, rows=rows)
        for m in fns:
            print(group, m, [(f"{r:.0e}", f"{t * 1e3:.2f}ms", f"{e:.1e}", s)
                             for r, t, e, s in rows[m]], flush=True)
    fig, axes = plt.subplots(2, 3, figsize=(13, 8))
    for ax, (group, res) in zip(axes.ravel(), results.items()):
        for m, style in (("full", "o-"), ("so3", "^-"), ("gyroscopic", "s-")):
            xs = [t for _, t, _, _ in res["rows"][m]]
            ys = [max(e, 1e-16) for _, _, e, _ in res["rows"][m]]
            ax.loglog(xs, ys, style, label=m, ms=4)
        what = "|t_invert error| (s)" if res["inverts"] else "|theta(T1) error| (rad)"
        a_c, e_r = TOPS[group]
        ax.set_title(f"{group}: A/C {a_c}, eps/R {e_r}, n0 {res['spin']:.0f} rad/s", fontsize=9)
        ax.set_ylabel(what, fontsize=8)
        ax.set_xlabel("wall time per run (s, median)", fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
    axes.ravel()[0].legend(fontsize=8)
    fig.suptitle(f"theta0 0.1, omega = n a, mu 0.3, {T1:.0f} s; reference: full model at rtol "
                 "1e-12; points: rtol 1e-4 ... 1e-10", fontsize=10)
    fig.tight_layout()
    fig.savefig(HERE / "gyroscopic_work_precision.png", dpi=100)
    print("wrote", HERE / "gyroscopic_work_precision.png")
    # the table for LEVELS.md
    lines = ["| group | n0 (rad/s) | quantity | level | error at rtol 1e-6 / 1e-8 / 1e-10 | "
             "median time relative to full at rtol 1e-8 |", "|---|---|---|---|---|---|"]
    for group, res in results.items():
        t_full = res["rows"]["full"][RTOLS.index(1e-8)][1]
        for m in fns:
            errs = " / ".join(f"{res['rows'][m][RTOLS.index(r)][2]:.1e}" for r in (1e-6, 1e-8, 1e-10))
            rel = res["rows"][m][RTOLS.index(1e-8)][1] / t_full
            lines.append(f"| {group} | {res['spin']:.0f} | "
                         f"{'t_invert' if res['inverts'] else 'theta(T1)'} | {m} | {errs} | "
                         f"{rel:.2f} |")
    print("\n".join(lines))
    from levels import write_section

    write_section(WP_MARK, [
        WP_MARK, "",
        "Made by `python benchmarks/gyroscopic_wp.py` (chart `gyroscopic_work_precision.png`), "
        f"{platform.machine()}, jax {jax.__version__}. One top per group (those of the section "
        "above, mu = 0.3), theta0 = 0.1, omega = n a at n0 = 3 n1 (3 n2 in group I), "
        f"{T1:g} s, summary mode, default launch projection (averaged). Error of t_invert "
        "where the full model inverts, else of theta at t1, against the full model at rtol "
        "1e-12; each level at rtol 1e-4 ... 1e-10 (atol = rtol/100), wall time the median of "
        f"{REPEATS} interleaved runs after compilation. The SO(3) and gyroscopic curves flatten "
        "at their model error; where the two flatten at the same value the slow flow's error "
        "is the full model's difference from the SO(3) model it averages, not its own.", "",
        *lines, "",
    ])


if __name__ == "__main__":
    main()
