"""Fit the tippejax model to a tippe top simulated by another engine (MuJoCo, Coulomb friction).

`examples/data/mujoco_tippe_top.csv` (made by `examples/mujoco_tippe_top.py`) is the standard
top (A/C 0.9, eps/R 0.3, m 20 g, R 25 mm) launched at theta0 = 0.1 rad with spin 100 rad/s on a
table with Coulomb friction 0.3 and MuJoCo's soft contact. tippejax's model has viscous friction
(F = -mu R_n v_Q), so no mu makes the two agree exactly. This script fits mu, eps and the spin

1. to the whole record (8 s), without and with `trim` (refit on the part the model describes),
2. to the rise only (t <= 1.4 s: the part a viscous law might describe),
3. mu alone, eps and the spin held at MuJoCo's true values, on the rise,

and prints for each the fitted values, the rms residual against the noise level and up to when
the model describes the record. Writes `examples/figures/fit_mujoco.png`.

Run from the repository root: `python examples/fit_mujoco.py`.
"""

from __future__ import annotations

import pathlib
import time

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt

import tippejax as tj

HERE = pathlib.Path(__file__).resolve().parent
DATA = HERE / "data" / "mujoco_tippe_top.csv"


def main():
    table = np.genfromtxt(DATA, delimiter=",", names=True)
    ts_all, theta_all = table["t"], table["theta"]
    true = tj.default_top()
    guess = tj.TippeTop(m=true.m, R=true.R, eps=true.eps, A=true.A, C=true.C, mu=3.0)
    y0 = tj.initial_state(guess, float(theta_all[0]), 100.0)
    runs = {
        "whole record, trim=False": (ts_all, theta_all, ("mu", "eps", "spin"), False),
        "whole record": (ts_all, theta_all, ("mu", "eps", "spin"), True),
        "rise (t <= 1.4 s)": (
            ts_all[ts_all <= 1.4],
            theta_all[ts_all <= 1.4],
            ("mu", "eps", "spin"),
            True,
        ),
        "rise, mu only": (ts_all[ts_all <= 1.4], theta_all[ts_all <= 1.4], ("mu",), True),
    }
    fig, axes = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    axes[0].plot(ts_all, theta_all, "k.", ms=2, label="MuJoCo (Coulomb friction 0.3)")
    for name, (ts, theta, free, trim) in runs.items():
        t = time.perf_counter()
        res = tj.fit(guess, y0, ts, theta, free=free, trim=trim)
        wall = time.perf_counter() - t
        print(f"\n== {name}: {ts.size} samples, {wall:.1f} s")
        print(res.table())
        print(f"fitted on t <= {float(res.fitted_until):.3f} s")
        print(
            f"t_invert of the fitted model: "
            f"{float(tj.simulate(res.top, res.y0, float(ts[-1]) + 10.0, summary=True, throw=False).t_invert):.3f} s "
            "(MuJoCo: 1.066 s)"
        )
        axes[0].plot(ts, np.asarray(res.theta_fit), lw=1.2, label=f"fit: {name}")
        axes[1].plot(ts, np.asarray(res.residuals), lw=0.8, label=name)
    axes[0].set(ylabel=r"$\theta$ (rad)", title="tippejax (viscous friction) fitted to MuJoCo data")
    axes[0].legend(fontsize=8)
    axes[1].set(xlabel="$t$ (s)", ylabel="residual (rad)")
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    out = HERE / "figures" / "fit_mujoco.png"
    fig.savefig(out, dpi=120)
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
