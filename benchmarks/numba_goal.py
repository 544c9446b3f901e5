"""Issue 18's goal alone: `simulate_batch` against the compiled numba loop, per core and on
every core, in interleaved rounds of one process.

peers.py's scene (standard top, SO(3) equations, theta0 0.1, spins 140-160 rad/s, 20 s,
summary), a batch of 1000 (`BATCH`), each at its equal-error rtol from peers.py's ladder
(numba 1.73e-8, tippejax so3 2.45e-8: the plain script's error at rtol 1e-8). The process has
2 host devices; `tj.simulate_batch(..., shard=False)` runs on one device, the default on both;
numba's `prange` loop runs with `numba.set_num_threads(1)` and `(2)` (set before each call, so
that neither inherits the other's threads: `peers.NUMBA_THREADS`). Reports wall and process CPU time per top, and the
medians of the paired ratios (the runs of a round see the same load).

    python benchmarks/numba_goal.py [ROUNDS]     # default 9; writes its RESULTS.md section
"""

import os
import statistics
import sys
import time

ROUNDS = int(sys.argv[1]) if len(sys.argv) > 1 else 9
sys.argv = sys.argv[:1]  # peers reads its own flags from sys.argv
os.environ["TIPPEJAX_HOST_DEVICES"] = "2"

import numpy as np  # noqa: E402
import peers  # noqa: E402
from _common import interleaved, machine_line, paired_ratios, table, verdict, write_section  # noqa: E402

import tippejax as tj  # noqa: E402

BATCH = 1000
RTOL = {"numba": 1.73e-8, "so3": 2.45e-8}


def main():
    nb_run, numba = peers.numba_parts()
    spins = np.linspace(140.0, 160.0, BATCH)

    def batch(shard):
        sol = tj.simulate_batch(peers.TOP, peers.THETA0, spins, peers.T1, grid=(), model="so3",
                                rtol=RTOL["so3"], atol=RTOL["so3"] * 1e-2, summary=True,
                                shard=shard)
        return sol.theta

    def compiled(threads):
        peers.NUMBA_THREADS = threads  # (peers' runner sets numba's threads before each call)
        return nb_run(spins, RTOL["numba"], RTOL["numba"] * 1e-2)

    fns = {"numba, 1 thread": lambda: compiled(1), "simulate_batch, 1 device": lambda: batch(False),
           "numba, 2 threads (prange)": lambda: compiled(2),
           "simulate_batch, 2 devices": lambda: batch(True)}
    start = time.perf_counter()
    load = os.getloadavg()[0]
    timed = interleaved(fns, repeats=ROUNDS)
    wall = {k: [x / BATCH * 1e3 for x in t.walls] for k, (t, _) in timed.items()}
    cpu = {k: [x / BATCH * 1e3 for x in t.cpus] for k, (t, _) in timed.items()}
    rows = [[k, f"{statistics.median(wall[k]):.3f}", f"{statistics.median(cpu[k]):.3f}"]
            for k in fns]
    pairs = []
    for a, b, what in (("simulate_batch, 1 device", "numba, 1 thread", "one core"),
                       ("simulate_batch, 2 devices", "numba, 2 threads (prange)", "2 cores")):
        ratios = paired_ratios(wall[a], wall[b])
        med = statistics.median(ratios)
        pairs.append([f"{a} / {b} ({what})", f"{med:.3f}",
                      f"{np.percentile(ratios, 25):.3f}-{np.percentile(ratios, 75):.3f}",
                      verdict(med <= 1.0)])
        print(pairs[-1])
    body = "\n".join([
        "## numba_goal.py: `simulate_batch` against compiled numba, per core and on 2 cores",
        "",
        f"`python benchmarks/numba_goal.py {ROUNDS}` ({time.perf_counter() - start:.0f} s, "
        f"first calls included; 1-minute load average {load:.1f} at the start). {machine_line()}.",
        "",
        f"peers.py's scene, batch of {BATCH}, summary, each at its equal-error rtol (numba "
        f"{RTOL['numba']:g}, tippejax so3 {RTOL['so3']:g}); {ROUNDS} interleaved rounds in one "
        "process with 2 host devices. Medians per top:",
        "",
        table(["run", "wall ms per top", "CPU ms per top"], rows),
        "",
        "Paired ratios of wall time (issue 18's goal: at or below the compiled loop):",
        "",
        table(["ratio", "median", "quartiles", "goal"], pairs),
    ])
    write_section("numba_goal.py", body)


if __name__ == "__main__":
    main()
