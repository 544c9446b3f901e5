"""Which diffrax solver is cheapest at equal error for a regularised Coulomb-Contensou top.

Scene: Leine & Glocker's top (m = 6 g, R = 15 mm, eps = 3 mm, A = 8e-7, C = 7e-7 kg m^2,
no stem) with `tj.CoulombContensou(mu=0.3, patch_radius=5e-4, slip_scale=1e-5)` (Hertz
pressure), launched at theta0 = 0.1 with 180 rad/s about its axis, full level, through the
first crossing of theta = pi/2 (t1 = 1.2 s by default), `--saves` points. Reference: Dopri8 at
rtol 1e-11 (atol 1e-13). For Dopri8, Tsit5 and Kvaerno5 at each rtol (atol = rtol * 1e-2):
max |d theta| over the saves, |d t_invert|, steps, and the median wall time of `--repeats`
calls after a compiling one (the solvers timed side by side, `_common.interleaved`). Writes
its section of benchmarks/RESULTS.md; `default_solver` says which solver the package picks.

    python benchmarks/friction_solvers.py                    # the small run
    python benchmarks/friction_solvers.py --rtols 1e-5 1e-7 1e-9 --repeats 5
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

import diffrax
import numpy as np

import tippejax as tj

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _common import interleaved, machine_line, table, write_section  # noqa: E402

SOLVERS = {"Dopri8": diffrax.Dopri8, "Tsit5": diffrax.Tsit5, "Kvaerno5": diffrax.Kvaerno5}


def scene(pressure: str, slip_scale: float):
    law = tj.CoulombContensou(mu=0.3, patch_radius=5e-4, slip_scale=slip_scale,
                              pressure=pressure)
    top = tj.TippeTop(m=0.006, R=0.015, eps=0.003, A=8e-7, C=7e-7, friction=law)
    return top, tj.initial_state(top, theta=0.1, spin=180.0)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--t1", type=float, default=1.2)
    parser.add_argument("--saves", type=int, default=61)
    parser.add_argument("--rtols", type=float, nargs="+", default=[1e-6, 1e-8])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--slip-scale", type=float, default=1e-5)
    parser.add_argument("--pressure", default="hertz")
    parser.add_argument("--max-steps", type=int, default=400_000)
    args = parser.parse_args()
    start = time.perf_counter()
    top, y0 = scene(args.pressure, args.slip_scale)
    ts = np.linspace(0.0, args.t1, args.saves)

    def run(solver, rtol):
        return tj.simulate(top, y0, t1=args.t1, model="full", saveat=ts, solver=solver,
                           rtol=rtol, atol=rtol * 1e-2, max_steps=args.max_steps, throw=False)

    ref = run(diffrax.Dopri8(), 1e-11)
    theta_ref, t_ref = np.asarray(ref.theta), float(ref.t_invert)
    rows = []
    for rtol in args.rtols:
        fns = {name: (lambda s=cls(), r=rtol: run(s, r)) for name, cls in SOLVERS.items()}
        for name, (timing, sol) in interleaved(fns, repeats=args.repeats).items():
            ok = not tj.RESULTS[sol.result]
            err = float(np.max(np.abs(np.asarray(sol.theta) - theta_ref))) if ok else np.nan
            rows.append(dict(rtol=rtol, solver=name, wall=timing.wall, first=timing.first_wall,
                             steps=int(sol.num_steps), rejected=int(sol.num_rejected_steps),
                             err=err, dt=abs(float(sol.t_invert) - t_ref), ok=ok))
            print(f"rtol {rtol:.0e} {name:8s} {timing.wall:8.3f} s  steps {rows[-1]['steps']:7d}"
                  f"  err {err:.1e}  dt_invert {rows[-1]['dt']:.1e}", flush=True)
    default = type(tj.default_solver(top)).__name__
    body = "\n".join([
        "## friction_solvers.py: solvers for a regularised Coulomb-Contensou top",
        "",
        f"{machine_line()}. Command: `python benchmarks/friction_solvers.py "
        f"--t1 {args.t1:g} --saves {args.saves} --rtols {' '.join(f'{r:g}' for r in args.rtols)}"
        f" --repeats {args.repeats} --slip-scale {args.slip_scale:g} --pressure "
        f"{args.pressure}` ({time.perf_counter() - start:.0f} s).",
        "",
        f"Leine & Glocker's top without the stem, `CoulombContensou(mu=0.3, patch_radius=5e-4, "
        f"slip_scale={args.slip_scale:g}, pressure='{args.pressure}')`, theta0 = 0.1, 180 rad/s "
        f"about the axis, full level, t1 = {args.t1:g} s, {args.saves} saves; reference Dopri8 "
        f"at rtol 1e-11 (t_invert = {t_ref:.9f} s); atol = rtol x 1e-2; wall: median of "
        f"{args.repeats} calls after the compiling one, solvers interleaved. "
        f"`tj.friction_rate(top)` = {float(tj.friction_rate(top)):.3g}/s; "
        f"`tj.default_solver(top)` = {default}.",
        "",
        table(["rtol", "solver", "wall s", "first call s", "steps", "rejected",
               "max d theta", "d t_invert (s)"],
              [[f"{r['rtol']:.0e}", r["solver"], f"{r['wall']:.3f}", f"{r['first']:.1f}",
                r["steps"], r["rejected"], f"{r['err']:.1e}" if r["ok"] else "failed",
                f"{r['dt']:.1e}"] for r in rows]),
    ])
    write_section("friction_solvers.py", body)


if __name__ == "__main__":
    main()
