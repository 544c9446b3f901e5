"""What the engine costs per step beyond the plain script, under tippejax's CPU options.

peers.py's scene (standard top, SO(3) equations, theta0 0.1, spins 140-160 rad/s, 20 s,
summary), a batch of 1000 on one JAX device, every run in `simulate_batch`'s CPU layout
(blocks of 125 members, `jax.lax.map` over `jax.vmap`, compiled with
`tippejax._engine.cpu.CPU_COMPILER_OPTIONS`):

- the plain diffrax script (Dopri8, I controller, rtol 1e-8: the equal-error reference);
- tippejax's SO(3) field (one flat vector) in a plain diffrax loop with tippejax's PI
  controller and error norm, no events;
- the same with the engine's event watch (`WatchedSolver`: the quintic of each condition over
  a step, its Bernstein coefficients; no event location, no records read);
- `tj.simulate_batch(model="so3", summary=True)`: the whole engine (event records and their
  location, the summary's outputs, the checks in Python).

tippejax's runs at rtol 2.45e-8 (the plain script's error at 1e-8, peers.py's ladder).
Each run also with Dopri8's stages written out (`tippejax._engine.unrolled.UnrolledERK`,
tippejax's default on accelerators), and the plain script written out with XLA:CPU's
fusion emitters on (its fastest form found). The field rows run diffrax's stage loop;
`simulate_batch` runs tippejax's CPU default, `StageLoopERK` (the same loop without the
transposed copy of the stage buffer at every stage), so the step from the watch row to the
whole engine is that change less the rest of the engine.
Interleaved rounds; ratios paired per round against the plain script.

    python benchmarks/engine_tax.py [ROUNDS]     # default 7; writes its RESULTS.md section
"""

import dataclasses
import os
import statistics
import sys

ROUNDS = int(sys.argv[1]) if len(sys.argv) > 1 else 7
sys.argv = sys.argv[:1]  # peers reads its own flags from sys.argv

import diffrax  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import peers  # noqa: E402  (one host device, float64, the scene)
from _common import interleaved, machine_line, paired_ratios, table, write_section  # noqa: E402

import tippejax as tj  # noqa: E402
from tippejax._engine.cpu import CPU_COMPILER_OPTIONS  # noqa: E402
from tippejax._engine.segment import STEP_CONTROL, FlatField, Watch, ravel_state  # noqa: E402
from tippejax._engine.unrolled import UnrolledERK  # noqa: E402
from tippejax._engine.watch import WatchedSolver  # noqa: E402
from tippejax._models.levels import LEVELS  # noqa: E402

BATCH, BLOCK = 1000, 125
RTOL = 2.45e-8


WRITTEN_OUT = ", stages written out"
FUSION_OPTIONS = {"xla_backend_optimization_level": 1}  # XLA:CPU's fusion emitters left on


def _blocks(one, options):
    def blocks(spins):
        out = jax.lax.map(jax.vmap(one), spins.reshape(BATCH // BLOCK, BLOCK))
        return jax.tree_util.tree_map(lambda x: x.reshape(BATCH, *x.shape[2:]), out)

    return jax.jit(blocks, compiler_options=options)


def plain_blocks(solver, options=CPU_COMPILER_OPTIONS):
    """peers.py's plain script in the same blocks, with `solver`."""
    return _blocks(lambda s: peers.plain_solve(s, 1e-8, 1e-10, solver=solver), options)


def engine_loop(watched: bool, unrolled: bool = False):
    """The SO(3) field in a plain diffrax loop (with the watch where `watched`), in blocks."""
    level = dataclasses.replace(LEVELS["so3"], body=False)

    def one(spin):
        y = level.from_state(peers.TOP, tj.initial_state(peers.TOP, peers.THETA0, spin))
        flat, unravel = ravel_state(y, 64)
        field = FlatField(level, unravel, 64)
        solver = UnrolledERK(diffrax.Dopri8()) if unrolled else diffrax.Dopri8()
        if watched:
            watch = Watch(level, unravel, ("singular", "contact", "upright"))
            solver = WatchedSolver(solver, watch, (2,), pieces=1, terminating=(0, 1))
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(field), solver, 0.0, peers.T1, None, flat, peers.TOP,
            saveat=diffrax.SaveAt(t1=True), max_steps=100_000,
            stepsize_controller=diffrax.PIDController(rtol=RTOL, atol=RTOL * 1e-2,
                                                      norm=field.error_norm, **STEP_CONTROL))
        return sol.ys[0][-1], sol.stats["num_steps"]

    return _blocks(one, CPU_COMPILER_OPTIONS)


def tj_simulate_batch(spins, solver=None):
    """`peers.tj_simulate_batch` at `RTOL`, with `solver` (tippejax's default where None)."""
    sol = tj.simulate_batch(peers.TOP, peers.THETA0, np.asarray(spins), peers.T1, grid=(),
                            model="so3", rtol=RTOL, atol=RTOL * 1e-2, summary=True,
                            solver=solver)
    return sol.states.omega, sol.num_steps


def main():
    spins = jnp.asarray(np.linspace(140.0, 160.0, BATCH))
    written = UnrolledERK(diffrax.Dopri8())
    fns = {}
    for suffix, unrolled in (("", False), (WRITTEN_OUT, True)):
        plain = plain_blocks(written if unrolled else diffrax.Dopri8())
        bare, watched = engine_loop(False, unrolled), engine_loop(True, unrolled)
        kw = dict(solver=written) if unrolled else {}
        fns.update({
            "plain diffrax script" + suffix: lambda plain=plain: plain(spins),
            "tippejax field, plain loop, no events" + suffix: lambda bare=bare: bare(spins),
            "the same with the event watch" + suffix: lambda watched=watched: watched(spins),
            "tj.simulate_batch (the whole engine)" + suffix:
                lambda kw=kw: tj_simulate_batch(spins, **kw),
        })
    fused = plain_blocks(written, FUSION_OPTIONS)
    fns["plain diffrax script" + WRITTEN_OUT + ", fusion emitters on"] = lambda: fused(spins)
    load = os.getloadavg()[0]
    timed = interleaved(fns, repeats=ROUNDS)
    steps = {k: float(np.median(np.asarray(out[1]))) for k, (_, out) in timed.items()}
    wall = {k: t.walls for k, (t, _) in timed.items()}
    base = "plain diffrax script"
    rows = []
    for k in fns:
        ratios = paired_ratios(wall[k], wall[base])
        per_step = statistics.median(wall[k]) / (BATCH * steps[k]) * 1e6
        rows.append([k, f"{steps[k]:.0f}", f"{statistics.median(wall[k]) / BATCH * 1e3:.3f}",
                     f"{per_step:.3f}", f"{statistics.median(ratios):.3f}"])
        print(rows[-1])
    body = "\n".join([
        "## engine_tax.py: the engine's cost per step beyond the plain script (CPU options)",
        "",
        f"`python benchmarks/engine_tax.py {ROUNDS}` (1-minute load average {load:.1f} at the "
        f"start). {machine_line()}.",
        "",
        f"peers.py's scene, batch of {BATCH} on one JAX device, every run in blocks of {BLOCK} "
        "compiled with tippejax's CPU options (LLVM level 1, XLA:CPU's element-wise loop "
        f"emitter); tippejax's runs at rtol {RTOL:g} (equal error with the plain script at "
        f"1e-8); {ROUNDS} interleaved rounds, medians:",
        "",
        table(["run", "steps (median)", "ms per top", "us per member-step",
               "x plain script (paired)"], rows),
        "",
        "Read down the last column: what the field costs against the plain script's, then what "
        "the event watch adds, then the whole engine (event records and location, the "
        "summary's outputs, the checks in Python), which on a CPU runs its stages in "
        "tippejax's own loop (`StageLoopERK`) where the rows above run diffrax's; then the same "
        "with the stages written out.",
    ])
    write_section("engine_tax.py", body)


if __name__ == "__main__":
    main()
