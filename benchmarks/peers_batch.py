"""The batch target of issue 18 alone, measured with more rounds than `peers.py` affords.

A batch of 1000 (the scene of `peers.py`: standard top, SO(3) equations, theta0 0.1, spins
140-160 rad/s, 20 s, summary mode) at equal error on one JAX device (the rtols `EQUAL_ERROR`
at which peers.py's ladder gives each the plain script's error at rtol 1e-8): the plain diffrax script (in `jax.vmap`, and in `simulate_batch`'s CPU layout: blocks
with tippejax's CPU options), `tj.simulate(model="so3")` and `tj.simulate(model="full")` in `jax.vmap`,
and `tj.simulate_batch` at both levels, timed in interleaved rounds after a compiling call.
Prints the per-round ratios to the plain script and their medians (paired ratios: the runs
of a round see the same load), and the medians of full / so3, and writes its section of
benchmarks/RESULTS.md with the verdicts of the two batch targets it measures.

    python benchmarks/peers_batch.py [ROUNDS]     # default 15
    TIPPEJAX_HOST_DEVICES=2 python benchmarks/peers_batch.py [ROUNDS]   # 2 host devices

With more than one device (`TIPPEJAX_HOST_DEVICES`) every batch runs each device's shard as
its own loop (`jax.shard_map`; peers.py's runners), and the section is written as
`peers_batch.py@N` beside the one-device one.
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
from _common import machine_line, paired_ratios, table, verdict, write_section  # noqa: E402

EQUAL_ERROR = dict(plain=1e-8, so3=2.50e-8, full=2.57e-8)
"""rtol of each at the plain script's error at rtol 1e-8 (4.42e-8), from `peers.py --big`
(benchmarks/RESULTS.md, 2026-11-29; 2.45e-8 and 2.70e-8 on 2026-11-27): tippejax's PI
controller ends with a 2-3x smaller error than the plain script's I controller at the same
rtol."""


def main():
    spins = jnp.asarray(np.linspace(140.0, 160.0, 1000))
    r, r3, rf = EQUAL_ERROR["plain"], EQUAL_ERROR["so3"], EQUAL_ERROR["full"]
    fns = {
        "plain": lambda: peers.plain_batch(spins, r, r * 1e-2, None),
        "plain in blocks": lambda: peers.plain_blocks(spins, r, r * 1e-2),
        "so3 vmap": lambda: peers.tj_batch(spins, jnp.asarray(r3), jnp.asarray(r3 * 1e-2), None,
                                           "so3"),
        "full vmap": lambda: peers.tj_batch(spins, jnp.asarray(rf), jnp.asarray(rf * 1e-2), None,
                                            "full"),
        "so3 simulate_batch": lambda: peers.tj_simulate_batch(spins, r3),
        "full simulate_batch": lambda: peers.tj_simulate_batch(spins, rf, level="full"),
    }
    for f in fns.values():
        jax.block_until_ready(f())
    times = {k: [] for k in fns}
    for _ in range(ROUNDS):
        for k, f in fns.items():
            start = time.perf_counter()
            jax.block_until_ready(f())
            times[k].append(time.perf_counter() - start)
    print("devices:", jax.devices())

    def paired(a, b):
        ratios = paired_ratios(times[a], times[b])
        return (statistics.median(ratios), np.percentile(ratios, 25),
                np.percentile(ratios, 75))

    per_round = " ".join(
        f"{x / y:.3f}" for x, y in zip(times["so3 simulate_batch"], times["plain"]))
    print("per-round so3 simulate_batch / plain:", per_round)
    pairs = {
        ("so3 simulate_batch", "plain"): "issue 18: <= 1.2x",
        ("full simulate_batch", "plain"): "",
        ("full simulate_batch", "so3 simulate_batch"): "issue 18: <= 1.3x",
        ("so3 simulate_batch", "plain in blocks"): "the strongest JAX script we know",
        ("plain in blocks", "plain"): "",
        ("so3 vmap", "plain"): "`tj.simulate` in the user's own `jax.vmap`",
        ("full vmap", "so3 vmap"): "",
    }
    bounds = {("so3 simulate_batch", "plain"): 1.2, ("full simulate_batch", "so3 simulate_batch"): 1.3}
    rows = []
    for (a, b), what in pairs.items():
        med, lo, hi = paired(a, b)
        print(f"{a} / {b}: median {med:.3f} (quartiles {lo:.3f}-{hi:.3f})")
        bound = bounds.get((a, b))
        rows.append([f"{a} / {b}", f"{med:.3f}", f"{lo:.3f}-{hi:.3f}",
                     f"{what}: {verdict(med <= bound)}" if bound else what])
    print(f"{ROUNDS} rounds")
    n_dev = len(jax.devices())
    name = "peers_batch.py" if n_dev == 1 else f"peers_batch.py@{n_dev}"
    write_section(name, "\n".join([
        f"## {name}: the batch target with more rounds",
        "",
        f"`python benchmarks/peers_batch.py {ROUNDS}` ({time.strftime('%Y-%m-%d')}). "
        f"{machine_line()}. Batch of 1000 (peers.py's scene: standard top, SO(3) equations, "
        "theta0 0.1, spins 140-160 rad/s, 20 s, summary mode), "
        f"{'one JAX device' if n_dev == 1 else f'{n_dev} JAX devices'}, "
        f"{ROUNDS} interleaved rounds after a compiling call, each at its equal-error rtol "
        f"(plain {EQUAL_ERROR['plain']:g}, so3 {EQUAL_ERROR['so3']:g}, full "
        f"{EQUAL_ERROR['full']:g}: the plain script's error at rtol 1e-8, from peers.py). "
        "'plain in blocks' is the plain script in `simulate_batch`'s CPU layout (blocks of "
        "at most 128 under `lax.map`, tippejax's CPU compile options). Ratios are taken round "
        "by round (each pair shares its round's load), then their median and quartiles.",
        "",
        f"Per round, so3 `simulate_batch` / plain script: {per_round}.",
        "",
        table(["ratio", "median", "quartiles", "note"], rows),
    ]))


if __name__ == "__main__":
    main()
