"""precision: float32 against float64 on the same runs: error and cost.

Standard top, theta0 0.1, spin 100 rad/s, 8 s (it inverts at about 5.7 s), 201 saves. The top
and state in float32 (`top.astype(jnp.float32)`) and in float64, each solver at each rtol;
reference: float64 Dopri8 at rtol 1e-12. `simulate` raises a float32 rtol to at least 1e-5.

    python benchmarks/precision.py
"""

from __future__ import annotations

import functools

import _harness as h
import diffrax
import equinox as eqx
import jax.numpy as jnp
import numpy as np

import tippejax as tj

T1, N = 8.0, 201
RTOLS = {"float32": (1e-4, 1e-5, 1e-6), "float64": (1e-4, 1e-5, 1e-6, 1e-8)}
SOLVERS = {"Dopri8": diffrax.Dopri8(), "Tsit5": diffrax.Tsit5()}


def precision(args):
    top = tj.default_top()
    ref = tj.simulate(
        top,
        tj.initial_state(top, 0.1, 100.0),
        T1,
        saveat=jnp.linspace(0.0, T1, N),
        rtol=1e-12,
        atol=1e-14,
    )
    theta_ref, t_ref = np.asarray(ref.theta), float(ref.t_invert)
    fns, solvers = {}, {"Dopri8": SOLVERS["Dopri8"]} if args.smoke else SOLVERS
    for dname, dtype in (("float32", jnp.float32), ("float64", jnp.float64)):
        top_d = tj.default_top().astype(dtype)
        y0, ts = tj.initial_state(top_d, 0.1, 100.0), jnp.linspace(0.0, T1, N, dtype=dtype)
        for sname, solver in solvers.items():
            run = eqx.filter_jit(
                lambda r, top_d=top_d, y0=y0, ts=ts, solver=solver: tj.simulate(
                    top_d, y0, T1, saveat=ts, rtol=r, atol=r * 1e-2, solver=solver, throw=False
                )
            )
            for rtol in RTOLS[dname][: 2 if args.smoke else None]:
                fns[(sname, dname, rtol)] = functools.partial(run, jnp.asarray(rtol, dtype))
    rows, curves = [], {}
    for (sname, dname, rtol), (t, sol) in h.interleaved(fns, 1 if args.smoke else 5).items():
        err = float(np.nanmax(np.abs(np.asarray(sol.theta, float) - theta_ref)))
        t_err, ok = abs(float(sol.t_invert) - t_ref), bool(sol.result == tj.RESULTS.successful)
        curves.setdefault((sname, dname), []).append((t.wall, err, t_err))
        rows.append(
            f"{sname} | {dname} | {rtol:.0e} | {t.wall:.4f} | {int(sol.num_steps)} | {err:.2e} | {t_err:.2e} | {ok}"
        )
    best = min(e for (_, d), c in curves.items() if d == "float32" for _, e, _ in c)
    h.write(
        "precision.py",
        "float32 against float64",
        f"""
Standard top, theta0 0.1, spin 100 rad/s, {T1:g} s, {N} saves; reference float64 Dopri8 at rtol 1e-12 (t_invert {t_ref:.9f} s). Medians of {1 if args.smoke else 5} interleaved runs. Chart: `float32.png`.

{h.table("solver | dtype | rtol | median wall s | steps | max d theta (rad) | d t_invert (s) | ok", rows)}

float32's floor on this scene: {best:.1e} rad in theta over {T1:g} s.
""",
        args,
    )
    plt = h.pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), constrained_layout=True)
    for (sname, dname), pts in curves.items():
        for ax, k in zip(axes, (1, 2)):
            style, colour = "--" if dname == "float32" else "-", "C1" if sname == "Dopri8" else "C0"
            ax.loglog(
                [x[0] for x in pts],
                [max(x[k], 1e-16) for x in pts],
                style,
                marker="o",
                color=colour,
                label=f"{sname} {dname}",
            )
    for ax, label in zip(axes, ("max |theta - theta_ref| (rad)", "|t_invert - t_invert_ref| (s)")):
        ax.set(xlabel="median wall time per run (s)", ylabel=label)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"float32 against float64, standard top, spin 100, {T1:g} s", fontsize=9)
    fig.savefig(h.figure_path("float32.png", args), dpi=110)


MODES = {"precision": (precision, "float32 against float64; float32.png")}

if __name__ == "__main__":
    h.run(MODES, h.parse(__doc__, MODES))
