"""A batch in the user's own `jax.vmap` of `tj.simulate`: eager, in the user's `jax.jit`, and
in that `jit` with `tj.compiler_options()`, against `tj.simulate_batch` and the plain script.

Scene of `peers.py` (standard top, SO(3) equations for `so3`, the full model for `full`,
theta0 0.1, spins 140-160 rad/s, 20 s, summary mode), a batch of 1000 on one JAX device, each
level at its equal-error rtol (`peers_batch.EQUAL_ERROR`). Routes:

- `eager vmap`: `jax.vmap(one)(spins)`, no `jit`. JAX batches `simulate`'s solve and runs it
  as a top-level program, which tippejax compiles with its CPU options (since 2026-11-29,
  `tippejax._cache.calling_context`);
- `eager vmap, before`: the route an eager `jax.vmap` took before that change (`as_before`):
  the batched solve at XLA's defaults and the outcome classified in a batched program of its
  own;
- `jit(vmap)`: `jax.jit(jax.vmap(one))`, the user's own program, XLA's defaults;
- `jit(vmap), options`: the same with `compiler_options=tj.compiler_options()`;
- `simulate_batch` (tippejax's own batch program), and the plain diffrax script in
  `jax.vmap`.

A first call of each (trace, compile and run: with `TIPPEJAX_COMPILATION_CACHE=0` no program
comes from an earlier process), then ROUNDS interleaved rounds (`_common.interleaved`); ratios are taken round by
round and their medians quoted. Writes its section of benchmarks/RESULTS.md.

    TIPPEJAX_COMPILATION_CACHE=0 python benchmarks/user_vmap.py [ROUNDS]   # default 5
"""

import os
import statistics
import subprocess
import sys

ROUNDS = int(sys.argv[1]) if len(sys.argv) > 1 else 5
sys.argv = sys.argv[:1]  # peers reads its own flags from sys.argv
os.environ.setdefault("TIPPEJAX_HOST_DEVICES", "1")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import peers  # noqa: E402  (float64, the scene)
from _common import interleaved, machine_line, paired_ratios, table, write_section  # noqa: E402
from peers_batch import EQUAL_ERROR  # noqa: E402

import tippejax as tj  # noqa: E402
import tippejax._simulate as simulate_module  # noqa: E402

LEVELS = ("so3", "full")


def one_top(level):
    rtol = EQUAL_ERROR[level]

    def one(spin):
        y0 = tj.initial_state(peers.TOP, peers.THETA0, spin)
        sol = tj.simulate(peers.TOP, y0, peers.T1, model=level, rtol=rtol, atol=rtol * 1e-2,
                          throw=False, summary=True)
        return sol.states.axis[-1], sol.t_contact_loss

    return one


def as_before(fn):
    """`fn` with `simulate` taking its route for an eager `jax.vmap` from before 2026-11-29:
    the batched solve compiled with XLA's defaults, and the outcome classified in a batched
    program of its own (`tippejax._simulate.calling_context` patched so that the eager
    `vmap` is not recognised)."""
    def call(*args):
        own = simulate_module.calling_context
        simulate_module.calling_context = lambda: "eager"
        try:
            return fn(*args)
        finally:
            simulate_module.calling_context = own
    return call


FIRST_CALL = r"""
import sys, time
sys.path.insert(0, {here!r})
level, route = sys.argv[1], sys.argv[2]
sys.argv = sys.argv[:1]
import jax, jax.numpy as jnp, numpy as np
import user_vmap
f = jax.vmap(user_vmap.one_top(level))
if route == "before":
    f = user_vmap.as_before(f)
spins = jnp.asarray(np.linspace(140.0, 160.0, 1000))
t = time.perf_counter(); jax.block_until_ready(f(spins)); first = time.perf_counter() - t
t = time.perf_counter(); jax.block_until_ready(f(spins)); second = time.perf_counter() - t
print(first - second)
"""


def first_calls(rounds=2):
    """First call less the second of an eager `jax.vmap`, each in a new process with the
    cache off, the two routes alternated: {(level, route): [seconds]}."""
    env = dict(os.environ, TIPPEJAX_COMPILATION_CACHE="0", TIPPEJAX_HOST_DEVICES="1")
    code = FIRST_CALL.format(here=os.path.dirname(os.path.abspath(__file__)))
    out = {}
    for _ in range(rounds):
        for level in LEVELS:
            for route in ("before", "now"):
                run = subprocess.run([sys.executable, "-c", code, level, route], env=env,
                                     capture_output=True, text=True, check=True)
                out.setdefault((level, route), []).append(
                    float(run.stdout.strip().splitlines()[-1]))
    return out


def main():
    spins = jnp.asarray(np.linspace(140.0, 160.0, 1000))
    r = EQUAL_ERROR["plain"]
    fns = {"plain": lambda: peers.plain_batch(spins, r, r * 1e-2, None)}
    for level in LEVELS:
        one = one_top(level)
        eager = jax.vmap(one)
        eager_default = as_before(jax.vmap(one))
        user_jit = jax.jit(jax.vmap(one))
        user_jit_options = jax.jit(jax.vmap(one), compiler_options=tj.compiler_options())
        # (the old route first: the first call of a level also pays what the routes share)
        fns[f"{level} eager vmap, before"] = lambda f=eager_default: f(spins)
        fns[f"{level} eager vmap"] = lambda f=eager: f(spins)
        fns[f"{level} jit(vmap)"] = lambda f=user_jit: f(spins)
        fns[f"{level} jit(vmap), options"] = lambda f=user_jit_options: f(spins)
        fns[f"{level} simulate_batch"] = lambda lv=level: peers.tj_simulate_batch(
            spins, EQUAL_ERROR[lv], level=lv)
    results = interleaved(fns, ROUNDS)
    first = {k: timing.first_wall for k, (timing, _) in results.items()}
    finals = {k: out for k, (_, out) in results.items()}
    times = {k: timing.walls for k, (timing, _) in results.items()}
    for k in fns:
        print(f"{k:40s} first call {first[k]:.2f} s", flush=True)
    # the routes of one level compute the same batch. Compiled differently, they round
    # differently: the members that run to t1 end at the same axis to well within the
    # solve's own error (4.4e-8 at these rtols); those that lose contact (the full level,
    # spins above 156.7 rad/s) stop at the same located time (one root find's tolerance
    # apart), where the axis moves fast enough that their end states differ more
    gaps, loss_gaps = [], [0.0]
    for level in LEVELS:
        ref_axis, ref_loss = (np.asarray(x) for x in finals[f"{level} jit(vmap)"])
        ran = ~np.isfinite(ref_loss)
        for route in ("eager vmap", "eager vmap, before", "jit(vmap), options"):
            axis, loss = (np.asarray(x) for x in finals[f"{level} {route}"])
            assert np.array_equal(np.isfinite(loss), ~ran), (level, route)
            gaps.append(float(np.max(np.abs(axis[ran] - ref_axis[ran]))))
            if not ran.all():
                loss_gaps.append(float(np.max(np.abs(loss[~ran] - ref_loss[~ran]))))
    print(f"largest gap between the routes' final axes: {max(gaps):.1e}; "
          f"between their contact-loss times: {max(loss_gaps):.1e} s")
    assert max(gaps) < 1e-7 and max(loss_gaps) < 1e-6
    def med(a, b):
        ratios = paired_ratios(times[a], times[b])
        q = np.quantile(ratios, [0.25, 0.75])
        return statistics.median(ratios), q

    rows = []
    for level in LEVELS:
        for route in ("eager vmap", "eager vmap, before", "jit(vmap)",
                      "jit(vmap), options", "simulate_batch"):
            k = f"{level} {route}"
            m, q = med(k, "plain")
            base = f"{level} eager vmap, before"
            mb, qb = med(k, base)
            rows.append([level, route, f"{1e3 * statistics.median(times[k]) / 1000:.3f}",
                         f"{m:.3f} ({q[0]:.3f}-{q[1]:.3f})", f"{mb:.3f}", f"{first[k]:.1f}"])
            print(rows[-1], flush=True)
    full_so3 = {route: med(f"full {route}", f"so3 {route}")[0]
                for route in ("eager vmap", "eager vmap, before", "jit(vmap)",
                              "jit(vmap), options", "simulate_batch")}
    print("full / so3:", {k: round(v, 3) for k, v in full_so3.items()})
    compiles = first_calls()
    compile_text = "; ".join(
        f"{level}: " + ", ".join(f"{x:.2f}" for x in compiles[(level, "now")]) + " s against "
        + ", ".join(f"{x:.2f}" for x in compiles[(level, "before")]) + " s before"
        for level in LEVELS)
    print("eager vmap, first call less the second, new processes:", compile_text)
    body = "\n".join([
        "## user_vmap.py: a batch in the user's own `jax.vmap` of `tj.simulate`",
        "",
        f"`python benchmarks/user_vmap.py {ROUNDS}`"
        + (" (`TIPPEJAX_COMPILATION_CACHE=0`)"
           if os.environ.get("TIPPEJAX_COMPILATION_CACHE") == "0" else "")
        + f". {machine_line()}. "
        "Batch of 1000 (peers.py's scene: standard top, theta0 0.1, spins 140-160 rad/s, 20 s, "
        "summary mode) on one JAX device, each level at its equal-error rtol. Routes: an eager "
        "`jax.vmap` of `simulate` (its batched solve a top-level program, compiled with "
        "tippejax's CPU options, the outcome classified inside it), the route it took before "
        "2026-11-29 (XLA's defaults, the outcome classified in a program of its own), the user's `jax.jit(jax.vmap(...))` (XLA's defaults), the same with "
        "`compiler_options=tj.compiler_options()`, and `tj.simulate_batch`. "
        f"{ROUNDS} interleaved rounds after a first call; ratios taken round by round, median "
        "(quartiles). The 'first call' column is in this process, in the table's order within "
        "a level, so the first route of a level also pays what the routes share; the eager "
        "routes' first calls in new processes (cache off) are below the table. The routes of a level end at the same states: members that run to t1 at "
        f"the same axis (largest gap {max(gaps):.1e}; the solve's own error is 4.4e-8), "
        "members that lose contact (full level, spins above 156.7 rad/s) at the same time "
        f"(largest gap {max(loss_gaps):.1e} s).",
        "",
        table(["level", "route", "ms per top (median)", "vs plain script", "vs eager vmap, before", "first call s"], rows),
        "",
        "full / so3 per route: " + ", ".join(f"{k} {v:.3f}" for k, v in full_so3.items())
        + " (issue 18: the full model at most 1.3x the SO(3) level).",
        "",
        "An eager `jax.vmap`'s first call less its second, each in a new process with the "
        "cache off, the routes alternated: " + compile_text + ".",
    ])
    write_section("user_vmap.py", body)


if __name__ == "__main__":
    main()
