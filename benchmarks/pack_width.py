"""The state layout of `simulate_batch`'s CPU programs: vectors of at most 6 components
(`PACK_WIDTH`, the layout now) against the whole state in one vector (the layout until
2026-11-29).

peers.py's scene (standard top, theta0 0.1, spins 140-160 rad/s, 20 s, rtol 1e-8), a batch
of 1000 through `tj.simulate_batch` (its CPU options, blocks of at most 128), at the SO(3)
and full levels, in summary mode (no body vector: SO(3) 6 components, the same layout
either way; full 4 + 6 against 10) and with 6 saves (the body vector as a frame and an
angle: SO(3) 6 + 4 against 10, full 4 + 6 + 4 against 14). Each layout is its own compiled
program (the batch program with its own jit cache, traced with `PACK_WIDTH` set to the
width); all of them run in interleaved rounds after a compiling call, on every CPU device,
then the same in a subprocess on one device (`TIPPEJAX_HOST_DEVICES=1`). Prints and writes
the per-round ratio of the two layouts' wall and CPU times (medians and quartiles) to
benchmarks/RESULTS.md.

    python benchmarks/pack_width.py [ROUNDS]     # default 7; about 10 minutes on 2 cores
"""

import json
import os
import statistics
import subprocess
import sys
import time

WORKER = "--worker" in sys.argv
ROUNDS = int(next((a for a in sys.argv[1:] if a.isdigit()), 7))
sys.argv = sys.argv[:1]  # peers reads its own flags from sys.argv
if not WORKER:
    os.environ["TIPPEJAX_HOST_DEVICES"] = str(os.cpu_count())  # every core a device

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import peers  # noqa: E402  (float64, the scene; sets one device only if unset)
from _common import machine_line, paired_ratios, table, write_section  # noqa: E402

import tippejax._batch as batch_module  # noqa: E402
import tippejax._engine.segment as segment  # noqa: E402
from tippejax._engine.cpu import CpuProgram  # noqa: E402

ONE_VECTOR = 64
"""A width no level state reaches: the whole state in one vector."""

RTOL = 1e-8
SAVES = np.linspace(0.0, peers.T1, 6)


class TracedWith:
    """`simulate_batch`'s CPU program with a jit cache of its own, traced with the batch
    layout `PACK_WIDTH = width`."""

    def __init__(self, width):
        self.width = width
        self.program = CpuProgram(lambda *a, **k: batch_module._batch_run_impl(*a, **k))

    def __call__(self, *args, **kwargs):
        saved = segment.PACK_WIDTH
        segment.PACK_WIDTH = self.width
        try:
            return self.program(*args, **kwargs)
        finally:
            segment.PACK_WIDTH = saved


def measure():
    spins = jnp.asarray(np.linspace(140.0, 160.0, 1000))
    programs = {w: TracedWith(w) for w in (segment.PACK_WIDTH, ONE_VECTOR)}
    cases = [(level, mode) for level in ("so3", "full") for mode in ("summary", "saves")]

    def runner(width, level, mode):
        def run():
            batch_module._batch_run_cpu = programs[width]
            return peers.tj_simulate_batch(spins, RTOL, SAVES if mode == "saves" else None,
                                           level=level)
        return run

    fns = {(w, c): runner(w, *c) for c in cases for w in programs}
    finals = {}
    for key, fn in fns.items():
        final, steps = jax.block_until_ready(fn())
        finals[key] = (np.asarray(final), np.asarray(steps))
    for c in cases:  # the layout changes the speed only
        (a, sa), (b, sb) = finals[(segment.PACK_WIDTH, c)], finals[(ONE_VECTOR, c)]
        # (a member that stopped, at a loss of contact, has no state at the last save: nan)
        assert np.allclose(a, b, rtol=1e-6, atol=1e-6, equal_nan=True), c
        assert abs(np.median(sa) / np.median(sb) - 1) < 0.01, c
    walls = {k: [] for k in fns}
    cpus = {k: [] for k in fns}
    for _ in range(ROUNDS):
        for key, fn in fns.items():
            w0, c0 = time.perf_counter(), time.process_time()
            jax.block_until_ready(fn())
            walls[key].append(time.perf_counter() - w0)
            cpus[key].append(time.process_time() - c0)
    out = {}
    for c in cases:
        new, old = (segment.PACK_WIDTH, c), (ONE_VECTOR, c)
        wall = paired_ratios(walls[new], walls[old])
        cpu = paired_ratios(cpus[new], cpus[old])
        out["/".join(c)] = dict(
            wall=[statistics.median(wall), np.percentile(wall, 25), np.percentile(wall, 75)],
            cpu=statistics.median(cpu), steps=float(np.median(finals[new][1])))
    return dict(devices=len(jax.devices()), cases=out)


def main():
    if WORKER:
        print("RESULT " + json.dumps(measure()))
        return
    runs = [measure()]
    # (tippejax's import put this process's device count in XLA_FLAGS, which it keeps)
    env = dict(os.environ, TIPPEJAX_HOST_DEVICES="1",
               XLA_FLAGS="--xla_force_host_platform_device_count=1")
    proc = subprocess.run([sys.executable, __file__, str(ROUNDS), "--worker"], env=env,
                          capture_output=True, text=True, check=True)
    runs.append(json.loads(proc.stdout.split("RESULT ", 1)[1]))
    rows = []
    for run in runs:
        for case, r in run["cases"].items():
            med, lo, hi = r["wall"]
            rows.append([case, str(run["devices"]), f"{r['steps']:.0f}", f"{med:.3f}",
                         f"{lo:.3f}-{hi:.3f}", f"{r['cpu']:.3f}"])
            print(f"{case:14s} {run['devices']} device(s): width {segment.PACK_WIDTH} / one "
                  f"vector: wall {med:.3f} ({lo:.3f}-{hi:.3f}), CPU {r['cpu']:.3f}")
    write_section("pack_width.py", "\n".join([
        "## pack_width.py: the state layout of simulate_batch's CPU programs",
        "",
        f"`python benchmarks/pack_width.py {ROUNDS}` ({time.strftime('%Y-%m-%d')}). "
        f"{machine_line()}. peers.py's scene, a batch of 1000 through `tj.simulate_batch` "
        f"(rtol {RTOL:g}; summary mode without the body vector, or 6 saves with it), each "
        f"layout its own compiled program, {ROUNDS} interleaved rounds after a compiling call, "
        "on every CPU device and (a subprocess) on one. The ratio of the layout now (vectors "
        f"of at most {segment.PACK_WIDTH} components: SO(3) summary 6, saves 6 + 4; full "
        "summary 4 + 6, saves 4 + 6 + 4) to the whole state in one vector (the layout until "
        "2026-11-29), round by round: below 1 the layout now is faster. Both end at the same "
        "states (checked).",
        "",
        table(["level / outputs", "devices", "steps (median)", "wall ratio", "quartiles",
               "CPU-time ratio"], rows),
    ]))


if __name__ == "__main__":
    main()
