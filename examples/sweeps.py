"""Sweeps of a top's parameters with `tj.simulate_batch`: friction mu, the inertia ratio A/C, spin.

Prints, for the default top launched at theta0 = 0.1 rad with 100 rad/s, the first crossing of
pi/2 (`t_invert`) and where each run ended (`sol.outcome`, `sol.settled`) after 20 s; the README
quotes this output.

    python examples/sweeps.py
"""

import numpy as np

import tippejax as tj

top = tj.default_top()
print(top)

# Friction: one batch of tops, every field but mu shared (grid=(): everything broadcasts).
mus = np.array([0.05, 0.1, 0.3, 1.0, 3.0])
sol = tj.simulate_batch(top.replace(mu=mus), 0.1, 100.0, 20.0, grid=(), summary=True)
print("\nmu (s/m)  t_invert (s)  outcome       settled  message")
for mu, t, o, s, msg in zip(
    mus, np.asarray(sol.t_invert), np.asarray(sol.outcome), np.asarray(sol.settled), sol.message()
):
    print(f"{mu:8.2f}  {t:12.2f}  {tj.OUTCOMES[o]:12s}  {s!s:7s}  {msg}")

# Inertia ratio A/C at two spins: the tops on one grid axis, the spins on the other.
ratios = np.array([0.8, 0.9, 1.1, 1.25, 1.5])
tops = top.replace(A_over_C=ratios)
sol = tj.simulate_batch(tops, 0.1, [60.0, 150.0], 20.0, grid=("top", "spin"), summary=True)
print("\nA/C   group  spin  t_invert (s)  outcome       theta(20 s)")
for i, ratio in enumerate(ratios):
    group = tj.classify(top.replace(A_over_C=ratio))
    for j, spin in enumerate([60.0, 150.0]):
        print(
            f"{ratio:4.2f}  {group:5s}  {spin:4.0f}  {float(sol.t_invert[i, j]):12.2f}  "
            f"{tj.OUTCOMES[int(sol.outcome[i, j])]:12s}  {float(sol.theta[i, j]):.3f}"
        )

# Spin: the default top at theta0 = 0.1 loses contact (R_n = 0) from about 157 rad/s.
spins = np.array([99.0, 150.0, 155.0, 157.0, 160.0, 200.0])
sol = tj.simulate_batch(top, 0.1, spins, 12.0, summary=True)
print("\nspin  t_invert (s)  t_contact_loss (s)  outcome")
for j, spin in enumerate(spins):
    print(
        f"{spin:4.0f}  {float(sol.t_invert[0, j]):12.2f}  {float(sol.t_contact_loss[0, j]):18.2f}  "
        f"{tj.OUTCOMES[int(sol.outcome[0, j])]}"
    )
