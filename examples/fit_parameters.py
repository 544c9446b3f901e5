"""Fit mu, eps and the launch spin of a tippe top to a noisy record of its tilt theta(t).

Makes synthetic data from the standard top (`tj.default_top()`: A/C 0.9, eps/R 0.3, m 20 g,
R 25 mm, mu 0.3 s/m) launched at theta0 = 0.1 rad with spin 100 rad/s: theta(t) sampled at
100 Hz for 8 s (it turns over at t = 5.70 s) plus Gaussian noise of 0.01 rad. Then fits mu, eps
and the spin with `tj.fit` from guesses 25-30% off, and prints true against fitted values with
standard errors and the wall time. Writes

- `examples/figures/fit_parameters.png` (`fit_figure`: data, fit and residuals);
- `examples/data/synthetic_top.csv` (columns t, theta: the format `tippejax fit` reads), and
  prints the equivalent command line.

    python examples/fit_parameters.py
"""

import pathlib
import time

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import tippejax as tj  # noqa: E402
from tippejax._plot import fit_figure  # noqa: E402

NOISE = 0.01  # rad
RATE = 100.0  # Hz
DURATION = 8.0  # s
THETA0, SPIN = 0.1, 100.0  # launch: rad, rad/s
FREE = ("mu", "eps", "spin")


def main():
    here = pathlib.Path(__file__).parent
    (here / "figures").mkdir(exist_ok=True)
    (here / "data").mkdir(exist_ok=True)

    top = tj.default_top()
    y0 = tj.initial_state(top, THETA0, SPIN)
    ts = np.linspace(0.0, DURATION, int(RATE * DURATION) + 1)
    sol = tj.simulate(top, y0, DURATION, saveat=ts)
    theta_obs = np.asarray(sol.theta) + NOISE * np.random.default_rng(0).standard_normal(ts.shape)
    print(
        f"synthetic data: {ts.size} samples, {RATE:g} Hz, noise {NOISE} rad; "
        f"the true top inverts at t = {float(sol.t_invert):.2f} s"
    )

    # Guesses 25-30% off (mu too large, eps too small, spin too fast); theta0 is known.
    guess = tj.TippeTop(m=top.m, R=top.R, eps=0.75 * top.eps, A=top.A, C=top.C, mu=1.3 * top.mu)
    spin_guess = 1.27 * SPIN
    start = time.perf_counter()
    result = tj.fit(guess, tj.initial_state(guess, THETA0, spin_guess), ts, theta_obs, free=FREE)
    wall = time.perf_counter() - start

    truth = {"mu": float(top.mu), "eps": float(top.eps), "spin": SPIN}
    start_values = {"mu": float(guess.mu), "eps": float(guess.eps), "spin": spin_guess}
    print(
        f"\n{'':6s} {'true':>11s} {'guess':>11s} {'fitted':>11s} {'std error':>10s} "
        f"{'rel error':>10s} {'(fit-true)/se':>14s}"
    )
    for name, value, error in zip(
        result.free, np.asarray(result.values), np.asarray(result.std_errors)
    ):
        true = truth[name]
        print(
            f"{name:6s} {true:11.6g} {start_values[name]:11.6g} {value:11.6g} {error:10.2g} "
            f"{(value - true) / true:10.2e} {(value - true) / error:14.2f}"
        )
    print(
        f"\nrms residual {float(result.rms):.4g} rad (noise {NOISE}); "
        f"describes until {float(result.describes_until):.3g} s of {DURATION:g} s; "
        f"{int(result.num_steps)} optimiser steps; {result.message()}"
    )
    print(f"wall time of the fit: {wall:.1f} s (including compilation)")

    fig = fit_figure(
        result,
        title="Standard top, synthetic data (noise 0.01 rad): fit of "
        "mu, eps, spin from guesses 25-30% off",
    )
    path = here / "figures" / "fit_parameters.png"
    fig.savefig(path, dpi=130)
    plt.close(fig)
    print(f"wrote {path}")

    csv_path = here / "data" / "synthetic_top.csv"
    np.savetxt(
        csv_path,
        np.column_stack([ts, theta_obs]),
        delimiter=",",
        header="t,theta",
        comments="",
        fmt="%.10g",
    )
    print(f"wrote {csv_path}")
    print(
        "the same fit from the command line:\n"
        f"  tippejax fit {csv_path.relative_to(here.parent)} --free {','.join(FREE)} "
        f"--mu {float(guess.mu):g} --eps {float(guess.eps):g} --spin {spin_guess:g} "
        f"--theta0 {THETA0:g}"
    )


if __name__ == "__main__":
    main()
