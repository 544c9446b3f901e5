"""Issue 18's goal alone: `simulate_batch` against the compiled numba loop, per core and on
every core, in interleaved rounds of one process.

peers.py's scene (standard top, SO(3) equations, theta0 0.1, spins 140-160 rad/s, 20 s,
summary), a batch of 1000 (`BATCH`), each at its equal-error rtol from peers.py's ladder
(numba 1.73e-8, tippejax so3 2.45e-8: the plain script's error at rtol 1e-8). The process has
2 host devices; `tj.simulate_batch(..., shard=False)` runs on one device, the default on both;
numba's `prange` loop runs with `numba.set_num_threads(1)` and `(2)` (set before each call, so
that neither inherits the other's threads: `peers.NUMBA_THREADS`). `simulate_batch` runs with
each member's own steps (the default) and with `steps="shared"` (the batch as one solve, in
buckets by spin), at the same rtol. Every run's error is measured here, not assumed: the
largest over the members of `peers.state_error` of its final state against the plain script at
rtol 1e-12 (`REFERENCE_RTOL`). Reports wall and process CPU time per top, and the medians of the
paired ratios (the runs of a round see the same load).

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
REFERENCE_RTOL = 1e-12
PER_MEMBER_1, PER_MEMBER_2 = "simulate_batch, 1 device", "simulate_batch, 2 devices"
SHARED_1, SHARED_2 = "simulate_batch shared steps, 1 device", "simulate_batch shared steps, 2 devices"
NUMBA_1, NUMBA_2 = "numba, 1 thread", "numba, 2 threads (prange)"


def main():
    nb_run, numba = peers.numba_parts()
    spins = np.linspace(140.0, 160.0, BATCH)

    def batch(shard, steps="per_member"):
        sol = tj.simulate_batch(peers.TOP, peers.THETA0, spins, peers.T1, grid=(), model="so3",
                                rtol=RTOL["so3"], atol=RTOL["so3"] * 1e-2, summary=True,
                                shard=shard, steps=steps)
        return np.concatenate([sol.states.axis[:, -1], sol.states.omega[:, -1]], axis=-1)

    def compiled(threads):
        peers.NUMBA_THREADS = threads  # (peers' runner sets numba's threads before each call)
        return nb_run(spins, RTOL["numba"], RTOL["numba"] * 1e-2)[0]

    fns = {NUMBA_1: lambda: compiled(1), PER_MEMBER_1: lambda: batch(False),
           SHARED_1: lambda: batch(False, "shared"), NUMBA_2: lambda: compiled(2),
           PER_MEMBER_2: lambda: batch(True), SHARED_2: lambda: batch(True, "shared")}
    start = time.perf_counter()
    load = os.getloadavg()[0]
    ref = peers.plain_reference(spins, REFERENCE_RTOL)
    errors = {k: max(peers.state_error(f, r) for f, r in zip(np.asarray(fn()), ref))
              for k, fn in fns.items()}
    print({k: f"{e:.2e}" for k, e in errors.items()})
    timed = interleaved(fns, repeats=ROUNDS)
    wall = {k: [x / BATCH * 1e3 for x in t.walls] for k, (t, _) in timed.items()}
    cpu = {k: [x / BATCH * 1e3 for x in t.cpus] for k, (t, _) in timed.items()}
    rows = [[k, f"{statistics.median(wall[k]):.3f}", f"{statistics.median(cpu[k]):.3f}",
             f"{errors[k]:.1e}"] for k in fns]
    pairs = []
    for a, b, what in ((PER_MEMBER_1, NUMBA_1, "one core"), (SHARED_1, NUMBA_1, "one core"),
                       (PER_MEMBER_2, NUMBA_2, "2 cores"), (SHARED_2, NUMBA_2, "2 cores")):
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
        f"{RTOL['numba']:g}, tippejax so3 {RTOL['so3']:g}, both step modes); {ROUNDS} interleaved "
        "rounds in one process with 2 host devices. Medians per top; error: the largest over the "
        "members of the final state's error against the plain script at rtol "
        f"{REFERENCE_RTOL:g} (the goal is per top at equal error: a run with the smaller error "
        "is the more accurate for its time):",
        "",
        table(["run", "wall ms per top", "CPU ms per top", "error"], rows),
        "",
        "Paired ratios of wall time (issue 18's goal: at or below the compiled loop):",
        "",
        table(["ratio", "median", "quartiles", "goal"], pairs),
    ])
    write_section("numba_goal.py", body)


if __name__ == "__main__":
    main()
