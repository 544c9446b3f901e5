"""The 2-device batch against the same two shards run in two processes, one core each.

`peers.py`'s batch of 1000 on 2 host devices: before tippejax ran its own stage loop
(`StageLoopERK`), `simulate_batch` missed issue 18's 1.2x of the plain script there (1.22x)
while it beat the script on one device. Both shard the batch the same way (each device runs
its 500 members by itself, `jax.shard_map`), so the question is what one process with 2
XLA:CPU devices costs each program beyond its own work. Here every round runs, for
tippejax (`tj.simulate_batch(model="so3", summary=True)`) and the plain diffrax script
(`jax.vmap`), the batch of 1000 in this process on 2 devices, then the same
two halves of 500 at once in two worker processes with one device each, each pinned to its
own core (`os.sched_setaffinity`). The workers are started once and compiled before the
rounds; they wait on a pipe while this process runs. Same scene, same rtols as `peers.py`
(each peer at its equal-error rtol). Wall time per round, medians, and ratios taken round by
round.

    python benchmarks/two_devices.py [rounds]    # default 7; writes its RESULTS.md section
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

WORKER = "--shard-worker" in sys.argv
os.environ["TIPPEJAX_HOST_DEVICES"] = "1" if WORKER else "2"

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import peers  # noqa: E402
from _common import machine_line, paired_ratios, table, write_section  # noqa: E402

N = 1000
TJ_RTOL = 2.45e-8  # tippejax so3 at the plain script's error at rtol 1e-8 (peers.py's ladder)
PEERS = ("tippejax", "plain")


def spins(half=None):
    s = np.linspace(140.0, 160.0, N)
    return s if half is None else (s[: N // 2] if half == 0 else s[N // 2:])


def runner(name, spins_):
    import jax
    import jax.numpy as jnp

    s = jnp.asarray(spins_)
    if name == "tippejax":
        def run():
            return jax.block_until_ready(peers.tj_simulate_batch(s, TJ_RTOL))
    else:
        def run():
            return jax.block_until_ready(peers.plain_batch(s, 1e-8, 1e-10, None))
    return run


def worker(core, half):
    os.sched_setaffinity(0, {core})
    runs = {name: runner(name, spins(half)) for name in PEERS}
    for run in runs.values():
        run()
    print("ready", flush=True)
    for line in sys.stdin:
        name = line.strip()
        start = time.perf_counter()
        out = runs[name]()
        print(f"{time.perf_counter() - start} {int(np.median(np.asarray(out[1])))}", flush=True)


def main(rounds):
    import jax

    start = time.perf_counter()
    cores = sorted(os.sched_getaffinity(0))
    if len(jax.devices()) != 2 or len(cores) < 2:
        raise SystemExit("two_devices.py needs 2 host devices and 2 cores.")
    here = {name: runner(name, spins()) for name in PEERS}
    for run in here.values():
        run()
    workers = [subprocess.Popen([sys.executable, __file__, "--shard-worker", str(c), str(h)],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
               for h, c in enumerate(cores[:2])]
    for w in workers:
        if w.stdout.readline().strip() != "ready":
            raise SystemExit("a worker failed to start")
    walls = {(name, where): [] for name in PEERS for where in ("one process", "two processes")}
    for _ in range(rounds):
        for name in PEERS:
            t0 = time.perf_counter()
            here[name]()
            walls[(name, "one process")].append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            for w in workers:
                w.stdin.write(name + "\n")
                w.stdin.flush()
            for w in workers:
                w.stdout.readline()
            walls[(name, "two processes")].append(time.perf_counter() - t0)
    for w in workers:
        w.stdin.close()
        w.wait()

    med = {k: float(np.median(v)) for k, v in walls.items()}
    rows = [[name, where, f"{1e3 * med[(name, where)] / N:.3f}"]
            for name in PEERS for where in ("one process", "two processes")]

    def ratio(a, b):
        r = paired_ratios(walls[a], walls[b])
        return f"{np.median(r):.3f}", f"{np.quantile(r, 0.25):.3f}-{np.quantile(r, 0.75):.3f}"

    ratios = [
        ["tippejax, one process / two processes", *ratio(("tippejax", "one process"),
                                                         ("tippejax", "two processes"))],
        ["plain, one process / two processes", *ratio(("plain", "one process"),
                                                      ("plain", "two processes"))],
        ["tippejax / plain, one process (issue 18's 2-device target <= 1.2)",
         *ratio(("tippejax", "one process"), ("plain", "one process"))],
        ["tippejax / plain, two processes", *ratio(("tippejax", "two processes"),
                                                  ("plain", "two processes"))],
    ]
    elapsed = time.perf_counter() - start
    body = "\n".join([
        f"`python benchmarks/two_devices.py {rounds}` ({elapsed:.0f} s). {machine_line()}",
        "",
        f"peers.py's batch of {N} (SO(3) level, summary, tippejax at rtol "
        f"{TJ_RTOL:g}, the plain script at 1e-8: equal error), {rounds} rounds. "
        "'one process': this process with 2 host devices, each running its shard of 500 by "
        "itself (`simulate_batch`; the plain script's `jax.shard_map` of its `jax.vmap`). "
        "'two processes': the same two shards in two worker processes with one device each, "
        "pinned to one core each, run at once. Median wall time per top:",
        "",
        table(["peer", "where", "ms per top"], rows),
        "",
        "Ratios of wall time, round by round (median, quartiles):",
        "",
        table(["ratio", "median", "quartiles"], ratios),
    ])
    print(body)
    write_section("two_devices.py", body)


if __name__ == "__main__":
    if WORKER:
        i = sys.argv.index("--shard-worker")
        worker(int(sys.argv[i + 1]), int(sys.argv[i + 2]))
    else:
        args = [a for a in sys.argv[1:] if not a.startswith("-")]
        main(int(args[0]) if args else 7)
