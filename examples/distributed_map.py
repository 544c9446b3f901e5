"""An outcome map over several processes (or hosts) with `jax.distributed`: the same code as on
one machine.

`tj.outcome_map` shards its launches over `jax.devices()`. After `jax.distributed.initialize`
that list holds the devices of every process, so each process simulates the launches that land
on its own devices and every process receives the whole map. Nothing else changes: there is no
scheduler here.

Two CPU processes on one machine (what `tests/test_maps.py` runs):

    python examples/distributed_map.py --coordinator localhost:12355 --num-processes 2 --process-id 0 &
    python examples/distributed_map.py --coordinator localhost:12355 --num-processes 2 --process-id 1

On a cluster, start one process per host (or per GPU) with the same arguments and its own
`--process-id`, `--coordinator` naming the host of process 0 and a free port. Under SLURM or
Open MPI, or on Cloud TPU, `jax.distributed.initialize()` reads all three from the environment:

    srun --nodes 4 --ntasks-per-node 1 python examples/distributed_map.py --auto-cluster

With `--refine k` the map is adaptive (`outcome_map(refine=k)`): every level of refinement is
one batched call spread over every process in the same way.

Process 0 writes the map to `--out` (an `.npz` file) and prints launches per second.
"""

from __future__ import annotations

import argparse
import time


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--coordinator", help="host:port of process 0")
    p.add_argument("--num-processes", type=int)
    p.add_argument("--process-id", type=int)
    p.add_argument(
        "--auto-cluster",
        action="store_true",
        help="let jax.distributed.initialize() read the cluster from the environment",
    )
    p.add_argument("--n-theta", type=int, default=8)
    p.add_argument("--n-spin", type=int, default=16)
    p.add_argument("--t1", type=float, default=12.0)
    p.add_argument("--chunk-size", type=int, default=4096)
    p.add_argument(
        "--refine",
        type=int,
        default=None,
        help="an adaptive map: levels of refinement (each level spread over every process)",
    )
    p.add_argument("--out", default="distributed_map.npz")
    args = p.parse_args(argv)

    import jax

    if jax.config.jax_platforms in (None, "", "cpu") and not args.auto_cluster:
        # CPU processes exchange the results through gloo collectives.
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    if args.auto_cluster:
        jax.distributed.initialize()
    else:
        jax.distributed.initialize(
            coordinator_address=args.coordinator,
            num_processes=args.num_processes,
            process_id=args.process_id,
        )
    import numpy as np

    import tippejax as tj

    top = tj.default_top()
    theta0 = np.linspace(0.05, 1.5, args.n_theta)
    spin = np.linspace(15.0, 200.0, args.n_spin)
    start = time.perf_counter()
    om = tj.outcome_map(
        top, theta0, spin, t1=args.t1, model="full", chunk_size=args.chunk_size, refine=args.refine
    )
    elapsed = time.perf_counter() - start
    n = theta0.size * spin.size
    if jax.process_index() == 0:
        np.savez(
            args.out,
            theta0=theta0,
            spin=spin,
            outcome=np.asarray(om.outcome),
            theta_final=np.asarray(om.theta_final),
            t_invert=np.asarray(om.t_invert),
            jellet=np.asarray(om.jellet),
            num_steps=np.asarray(om.num_steps),
            simulated=np.asarray(om.simulated),
            levels=np.array(om.levels, dtype=int),
            process_count=jax.process_count(),
            device_count=jax.device_count(),
        )
        print(
            f"{jax.process_count()} processes, {jax.device_count()} devices: {n} launches in "
            f"{elapsed:.2f} s (with compilation), {n / elapsed:.1f} launches/s"
        )
        print(om.summary())
    jax.distributed.shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
