"""One top against the plain diffrax script, at equal error, timed in interleaved rounds.

`peers.py` times its single-top ladder one peer after another (three calls each per rtol), so
on a shared machine a peer that happens to run while other work holds a core pays for it. Here
the single-top rows of issue 18 are timed side by side: the same scene as `peers.py` (the
standard top, SO(3) equations, theta0 0.1, spin 150 rad/s, 20 s, `summary=True` for
tippejax), each peer at the rtol that gives the plain script's error at rtol 1e-8
(interpolated on its own rtol ladder, 1e-6 to 1e-10), then 21 rounds calling every peer
once, medians of wall and process CPU time, and the ratio to the plain script also taken
round by round (each pair shares its round's load).

    python benchmarks/single_top.py         # writes its section of benchmarks/RESULTS.md
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import peers  # noqa: E402
from _common import interleaved, machine_line, paired_ratios, table, verdict, write_section  # noqa: E402

ROUNDS = 21
LEVELS = ("so3", "full", "routhian")


def main() -> None:
    import jax
    import jax.numpy as jnp

    start = time.perf_counter()
    spin = jnp.asarray(peers.SPIN)

    def plain(controller):
        single = peers.plain_single if controller is None else peers.plain_single_pi
        return lambda rtol: single(spin, jnp.asarray(rtol), jnp.asarray(rtol * 1e-2))

    def level(name):
        return lambda rtol: peers.tj_single(spin, jnp.asarray(rtol), jnp.asarray(rtol * 1e-2),
                                            name)

    runs = {"plain diffrax": plain(None), peers.PLAIN_PI: plain(peers.PI_CONTROLLER)}
    runs.update({f"tippejax {name}": level(name) for name in LEVELS})
    refs = {"plain": np.asarray(jax.block_until_ready(runs["plain diffrax"](1e-13))[0])}
    for name in LEVELS:  # each level against itself, as in peers.py
        refs[name] = np.asarray(jax.block_until_ready(runs[f"tippejax {name}"](1e-12))[0])
    errors = {}
    for peer, run in runs.items():
        ref = refs[peer.split()[-1]] if peer.startswith("tippejax") else refs["plain"]
        errors[peer] = [peers.state_error(run(r)[0], ref) for r in peers.RTOLS]
    target = float(np.interp(np.log(peers.TARGET_RTOL), np.log(peers.RTOLS[::-1]),
                             np.log(errors["plain diffrax"][::-1])))
    at = {}
    for peer, errs in errors.items():
        # log rtol interpolated in log error (errors fall as rtol falls)
        at[peer] = float(np.exp(np.interp(target, np.log(errs[::-1]),
                                          np.log(np.asarray(peers.RTOLS[::-1])))))
    results = interleaved({peer: (lambda run=run, r=at[peer]: run(r)) for peer, run in
                           runs.items()}, repeats=ROUNDS)
    base = results["plain diffrax"][0]
    rows, ratio = [], {}
    for peer, (timing, out) in results.items():
        final, steps = out
        ratio[peer] = float(np.median(paired_ratios(timing.walls, base.walls)))
        cpu_ratio = float(np.median(paired_ratios(timing.cpus, base.cpus)))
        rows.append([peer, f"{at[peer]:.2e}", int(np.asarray(steps)),
                     f"{1e3 * timing.wall:.1f}", f"{ratio[peer]:.2f}", f"{1e3 * timing.cpu:.1f}",
                     f"{cpu_ratio:.2f}"])
        print(rows[-1], flush=True)
    so3, full = ratio["tippejax so3"], ratio["tippejax full"]
    body = "\n".join([
        "## single_top.py: one top against the plain diffrax script, interleaved",
        "",
        f"`python benchmarks/single_top.py` ({time.perf_counter() - start:.0f} s). "
        + machine_line() + ". " + __doc__.split("\n\n")[1].replace("\n", " ")
        + f" Equal error: {np.exp(target):.2e}.",
        "",
        table(["peer", "rtol at equal error", "steps", "ms per top (median)",
               "vs plain (median of round ratios)", "CPU ms", "vs plain (CPU)"], rows),
        "",
        "| target | measured | verdict |",
        "|---|---|---|",
        f"| single top <= 1.2x plain (SO(3) level) | {so3:.2f}x | {verdict(so3 <= 1.2)} |",
        f"| full <= 1.3x so3 (single top) | {full / so3:.2f}x | {verdict(full / so3 <= 1.3)} |",
    ])
    write_section("single_top.py", body)
    print(body)


if __name__ == "__main__":
    main()
