"""The batch target of issue 18 alone, measured with more rounds than `peers.py` affords.

A batch of 1000 (the scene of `peers.py`: standard top, SO(3) equations, theta0 0.1, spins
140-160 rad/s, 20 s, summary mode, rtol 1e-8 for both, where their errors are equal) on one JAX
device: the plain diffrax script, `tj.simulate(model="so3")` and `tj.simulate(model="full")` in
`jax.vmap`, timed in interleaved rounds after a compiling call. Prints the per-round ratios
tippejax so3 / plain and their median (a paired ratio: both runs of a round see the same load),
and the median full / so3.

    python benchmarks/peers_batch.py [ROUNDS]     # default 15
"""

import statistics
import sys
import time

ROUNDS = int(sys.argv[1]) if len(sys.argv) > 1 else 15
sys.argv = sys.argv[:1]  # peers reads its own flags from sys.argv

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import peers  # noqa: E402  (one host device, float64, the scene)


def main():
    spins = jnp.asarray(np.linspace(140.0, 160.0, 1000))
    r = 1e-8
    fns = {
        "plain": lambda: peers.plain_batch(spins, r, r * 1e-2, None),
        "so3": lambda: peers.tj_batch(spins, jnp.asarray(r), jnp.asarray(r * 1e-2), None, "so3"),
        "full": lambda: peers.tj_batch(spins, jnp.asarray(r), jnp.asarray(r * 1e-2), None,
                                       "full"),
    }
    for f in fns.values():
        jax.block_until_ready(f())
    times = {k: [] for k in fns}
    for _ in range(ROUNDS):
        for k, f in fns.items():
            start = time.perf_counter()
            jax.block_until_ready(f())
            times[k].append(time.perf_counter() - start)
    ratios = [s / p for s, p in zip(times["so3"], times["plain"])]
    print("devices:", jax.devices())
    print("per-round so3 / plain:", " ".join(f"{x:.3f}" for x in ratios))
    print(f"median so3 / plain: {statistics.median(ratios):.3f} "
          f"(quartiles {np.percentile(ratios, 25):.3f}-{np.percentile(ratios, 75):.3f}, "
          f"{ROUNDS} rounds)")
    print(f"median full / so3: "
          f"{statistics.median(f / s for f, s in zip(times['full'], times['so3'])):.3f}")


if __name__ == "__main__":
    main()
