"""Fit four recordings of four different tops at once (one vmapped fit), against a Python loop.

Four tops like the standard one (A/C 0.9, eps/R 0.3, m 20 g, R 25 mm) with friction coefficients
mu = 0.25, 0.3, 0.35, 0.4 s/m, launched at theta0 = 0.1 rad with spins 90-110 rad/s; theta(t)
sampled at 100 Hz for 8 s with Gaussian noise of 0.01 rad. mu, eps and the spin of each are
fitted from guesses about 20% off, first all at once (`theta_obs` of shape (4, N), a `TippeTop`
whose fields have shape (4,), `initial_state` with an array of spins: one compilation, one
vmapped solve per optimiser step), then one at a time in a loop (one compilation, four fits).
Prints true against fitted values for each recording and both wall times (each includes its
compilation). Writes `examples/figures/fit_batch.png` (recording 0, `fit_figure`).

    python examples/fit_batch.py
"""

import pathlib
import time

import matplotlib

matplotlib.use("Agg")

import jax.numpy as jnp  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import tippejax as tj  # noqa: E402
from tippejax._plot import fit_figure  # noqa: E402

NOISE = 0.01  # rad
TS = np.linspace(0.0, 8.0, 801)  # 100 Hz
THETA0 = 0.1  # rad, known
MUS = np.array([0.25, 0.3, 0.35, 0.4])  # s/m
SPINS = np.array([90.0, 97.0, 104.0, 110.0])  # rad/s
FREE = ("mu", "eps", "spin")
# Guess factors per recording: about 20% off, in both directions.
MU_FACTOR = np.array([1.2, 0.8, 1.2, 0.8])
EPS_FACTOR = np.array([0.8, 1.2, 1.2, 0.8])
SPIN_FACTOR = np.array([1.2, 1.2, 0.8, 0.8])


def main():
    base = tj.default_top()
    m, R, A, C, eps = (float(getattr(base, f)) for f in ("m", "R", "A", "C", "eps"))
    rng = np.random.default_rng(1)
    theta_obs = np.empty((len(MUS), TS.size))
    for b, (mu, spin) in enumerate(zip(MUS, SPINS)):
        top = tj.TippeTop(m=m, R=R, eps=eps, A=A, C=C, mu=mu)
        sol = tj.simulate(top, tj.initial_state(top, THETA0, spin), TS[-1], saveat=TS)
        theta_obs[b] = np.asarray(sol.theta) + NOISE * rng.standard_normal(TS.size)
        print(
            f"recording {b}: mu = {mu:g} s/m, spin = {spin:g} rad/s, "
            f"inverts at t = {float(sol.t_invert):.2f} s"
        )

    mu_guess, eps_guess, spin_guess = MU_FACTOR * MUS, EPS_FACTOR * eps, SPIN_FACTOR * SPINS
    guess = tj.TippeTop(m=m, R=R, eps=jnp.asarray(eps_guess), A=A, C=C, mu=jnp.asarray(mu_guess))
    y0_guess = tj.initial_state(guess, THETA0, jnp.asarray(spin_guess))

    start = time.perf_counter()
    batch = tj.fit(guess, y0_guess, TS, theta_obs, free=FREE)
    wall_batch = time.perf_counter() - start

    start = time.perf_counter()
    singles = []
    for b in range(len(MUS)):
        top_b = tj.TippeTop(m=m, R=R, eps=eps_guess[b], A=A, C=C, mu=mu_guess[b])
        y0_b = tj.initial_state(top_b, THETA0, spin_guess[b])
        singles.append(tj.fit(top_b, y0_b, TS, theta_obs[b], free=FREE))
        if b == 0:
            wall_first = time.perf_counter() - start
    wall_loop = time.perf_counter() - start

    values, errors = np.asarray(batch.values), np.asarray(batch.std_errors)
    print(
        f"\n{'':3s} {'':5s} {'true':>10s} {'guess':>10s} {'batch fit':>10s} {'std error':>10s} "
        f"{'(fit-true)/se':>13s} {'loop fit':>10s}"
    )
    for b in range(len(MUS)):
        truth = {"mu": MUS[b], "eps": eps, "spin": SPINS[b]}
        start_values = {"mu": mu_guess[b], "eps": eps_guess[b], "spin": spin_guess[b]}
        for i, name in enumerate(FREE):
            v, e, t = values[b, i], errors[b, i], truth[name]
            single = float(singles[b].values[i])
            print(
                f"[{b}] {name:5s} {t:10.5g} {start_values[name]:10.5g} {v:10.6g} {e:10.2g} "
                f"{(v - t) / e:13.2f} {single:10.6g}"
            )
        print(
            f"    rms {float(batch.rms[b]):.4g} rad, {int(batch.num_steps[b])} steps, "
            f"{batch.message()[b]} (loop: rms {float(singles[b].rms):.4g}, "
            f"{int(singles[b].num_steps)} steps)"
        )
    print(f"\nwall time, 4 recordings at once (vmapped):  {wall_batch:6.1f} s (incl. compilation)")
    print(
        f"wall time, 4 fits in a loop:                {wall_loop:6.1f} s (incl. compilation; "
        f"first fit {wall_first:.1f} s, the other three {wall_loop - wall_first:.1f} s)"
    )
    print(f"loop / batch: {wall_loop / wall_batch:.2f}")

    fig = fit_figure(batch)
    path = pathlib.Path(__file__).parent / "figures" / "fit_batch.png"
    path.parent.mkdir(exist_ok=True)
    fig.savefig(path, dpi=130)
    plt.close(fig)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
