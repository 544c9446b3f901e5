"""Batches with shared steps against per-member steps, a plain diffrax script and numba.

`peers.py`'s scene: the standard top, theta0 0.1, 1000 spins from 140 to 160 rad/s, 20 s,
summary mode, rtol 1e-8 (atol 1e-10) for every run. The runs:

- numba: CyRK's compiled DOP853 in a `prange` loop over the tops, on every core (`peers.py`);
- plain diffrax, vmap: the 25-line SO(3) script under `jax.vmap` (each member its own steps;
  on several devices each device runs its shard's loop, `jax.shard_map`: 1.20 ms per top on
  2 devices against 1.40 ms with `jax.jit` on sharded inputs, where the loop condition is
  reduced across the devices at every step);
- plain diffrax, shared steps: ONE `diffeqsolve` whose state is the whole batch (N, 6), the
  vector field vmapped over the members and the step-size controller's norm the largest
  member's RMS norm, so that every member's error is controlled and all take the same steps;
  on several devices each runs its shard as one such solve (`jax.shard_map`);
- `tj.simulate_batch(..., steps="per_member")` (the default) and `steps="shared"`, SO(3) and
  full levels, events on.

Each run is timed in interleaved rounds after a compiling call; the ratios are paired (to numba
and to the plain vmap script in the same round). Errors: largest over the members of
`peers.state_error` of the final state against the plain script at rtol 1e-12 (the full
model's: against tippejax's full model at rtol 1e-12, per member; shared steps are
set by the member that needs the smallest, so the others come out more accurate than asked);
the agreement of the two tippejax paths in t_invert and the final tilt. The script runs itself
once with one JAX device and once with every core a device (two subprocesses), and writes its
section of `benchmarks/RESULTS.md`.

    python benchmarks/shared_steps.py [ROUNDS]     # default 5
    python benchmarks/shared_steps.py --random K   # agreement on K seeded random tops

`--random K`: the two paths on tops nobody tuned on, drawn as `maps.py --auto-random` draws
them (seed 0: A/C in [0.6, 1.7], eps/R in [0.03, 0.4], mu log-uniform in [0.05, 1] s/m), each
with 48 random launches (theta0 in [0.02, 1.5], spin in [0.5, 8] x its n1, n2 in group I),
10 s, the full and SO(3) levels, contact loss stopping a member (the default), 4 buckets by
spin for both paths: the result codes, the outcomes, t_invert, t_contact_loss and the final
tilt of every member compared. Writes its own section of RESULTS.md.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
BATCH = 1000
RTOL = 1e-8
NUMBA = "numba DOP853, prange"
PLAIN = "plain diffrax, vmap"


def worker(rounds: int) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    sys.argv = sys.argv[:1]
    import peers  # the scene (keeps TIPPEJAX_HOST_DEVICES as set by the parent)

    import tippejax as tj

    devices = jax.devices()
    mesh = Mesh(np.array(devices), ("batch",))
    spec = PartitionSpec("batch")

    def plain_shared_solve(spins, rtol, atol):
        return peers.plain_shared_solve(spins, rtol, atol)[0]

    if len(devices) == 1:
        plain_shared = jax.jit(plain_shared_solve)
    else:
        plain_shared = jax.jit(jax.shard_map(
            plain_shared_solve, mesh=mesh, in_specs=(spec, PartitionSpec(), PartitionSpec()),
            out_specs=spec, check_vma=False))
    def plain_vmap(spins, rtol, atol):  # peers.py's: on several devices, each its shard's loop
        return peers.plain_batch(spins, rtol, atol)[0]

    def put(x):
        x = jnp.asarray(x)
        return x if len(devices) == 1 else jax.device_put(x, NamedSharding(mesh, spec))

    spins = np.linspace(140.0, 160.0, BATCH)
    spins_dev = put(spins)
    nb_run, numba = peers.numba_parts()
    r, a = jnp.asarray(RTOL), jnp.asarray(RTOL * 1e-2)
    top = tj.default_top()
    sols = {}

    def tj_run(model, steps):
        def run():
            sol = tj.simulate_batch(top, theta0=peers.THETA0, spin=spins, t1=peers.T1,
                                    model=model, summary=True, rtol=RTOL, atol=RTOL * 1e-2,
                                    grid=("spin",), steps=steps)
            sols[(model, steps)] = sol
            return jnp.concatenate([sol.states.axis[:, -1], sol.states.omega[:, -1]], axis=1)
        return run

    runs = {
        NUMBA: lambda: nb_run(spins, RTOL, RTOL * 1e-2)[0],
        PLAIN: lambda: plain_vmap(spins_dev, r, a),
        "plain diffrax, shared steps": lambda: plain_shared(spins_dev, r, a),
    }
    for model in ("so3", "full"):
        for steps in ("per_member", "shared"):
            runs[f"tippejax {model}, {steps.replace('_', ' ')}"] = tj_run(model, steps)
    reference = peers.plain_reference(spins, 1e-12)
    # The full model's own reference: the per-member path at rtol 1e-12.
    ref_full = tj.simulate_batch(top, theta0=peers.THETA0, spin=spins, t1=peers.T1,
                                 model="full", summary=True, rtol=1e-12, atol=1e-14,
                                 grid=("spin",))
    reference_full = np.concatenate([np.asarray(ref_full.states.axis[:, -1]),
                                     np.asarray(ref_full.states.omega[:, -1])], axis=1)
    errors, firsts, mismatched = {}, {}, {}
    for name, fn in runs.items():
        start = time.perf_counter()
        out = np.asarray(jax.block_until_ready(fn()))
        firsts[name] = time.perf_counter() - start
        ref = reference_full if "full" in name else reference
        members = range(BATCH)
        if name.startswith("tippejax full"):
            # 16% of these launches lose contact in the full model, some by a grazing dip of
            # R_n that one tolerance finds and another not: compare the members whose run
            # ended as the reference's did, and count the others.
            model, steps = "full", name.split(", ")[1].replace(" ", "_")
            same = (np.asarray(sols[(model, steps)].result._value)
                    == np.asarray(ref_full.result._value))
            members = np.flatnonzero(same)
            mismatched[name] = int(BATCH - same.sum())
        errors[name] = max(peers.state_error(out[i], ref[i]) for i in members)
    times = {name: [] for name in runs}
    for _ in range(rounds):
        for name, fn in runs.items():
            start = time.perf_counter()
            jax.block_until_ready(fn())
            times[name].append(time.perf_counter() - start)
    agreement = {}
    for model in ("so3", "full"):
        a_, b_ = sols[(model, "per_member")], sols[(model, "shared")]
        agreement[model] = dict(
            t_invert=float(np.nanmax(np.abs(np.asarray(a_.t_invert) - np.asarray(b_.t_invert)))),
            theta=float(np.nanmax(np.abs(np.asarray(a_.theta[..., -1])
                                         - np.asarray(b_.theta[..., -1])))),
            steps=(int(np.max(np.asarray(a_.num_steps))), int(np.max(np.asarray(b_.num_steps)))),
            same_results=bool(np.all(np.asarray(a_.result._value) == np.asarray(b_.result._value))),
        )
    rows = []
    for name, ts in times.items():
        rows.append(dict(
            name=name, per_top_ms=1e3 * statistics.median(ts) / BATCH,
            to_numba=statistics.median(t / b for t, b in zip(ts, times[NUMBA])),
            to_plain=statistics.median(t / p for t, p in zip(ts, times[PLAIN])),
            error=errors[name], first=firsts[name]))
    return dict(devices=len(devices), threads=numba.get_num_threads(), rows=rows,
                agreement=agreement, mismatched=mismatched)


def main():
    rounds = int(sys.argv[1]) if len(sys.argv) > 1 else 5
    sys.path.insert(0, HERE)
    from _common import machine_line, table, verdict, write_section

    start = time.perf_counter()
    print(machine_line(), flush=True)
    results = []
    for devices in (1, os.cpu_count()):
        env = dict(os.environ, TIPPEJAX_HOST_DEVICES=str(devices))
        out = subprocess.run([sys.executable, __file__, "--worker", str(rounds)], env=env,
                             capture_output=True, text=True, check=True, cwd=HERE)
        res = json.loads(out.stdout.strip().splitlines()[-1])
        results.append(res)
        print(f"{res['devices']} device(s), numba {res['threads']} threads:")
        for row in res["rows"]:
            print(f"  {row['name']:32s} {row['per_top_ms']:7.3f} ms/top, {row['to_numba']:5.2f}x"
                  f" numba, {row['to_plain']:5.2f}x plain vmap, error {row['error']:.1e}",
                  flush=True)
        for model, ag in res["agreement"].items():
            print(f"  {model}: shared - per member: t_invert {ag['t_invert']:.1e} s, final theta"
                  f" {ag['theta']:.1e} rad, steps {ag['steps'][1]} / {ag['steps'][0]}, "
                  f"same results {ag['same_results']}")
    elapsed = time.perf_counter() - start
    best = {r["devices"]: {row["name"]: row for row in r["rows"]} for r in results}
    many = max(best)
    so3_shared = best[many]["tippejax so3, shared"]
    lines = [
        "## shared_steps.py: a batch with shared steps, against numba",
        "",
        f"`python benchmarks/shared_steps.py` ({elapsed:.0f} s). peers.py's scene: standard top, "
        f"theta0 0.1, {BATCH} spins 140-160 rad/s, 20 s, summary mode, rtol 1e-8 for every "
        f"run; {rounds} interleaved rounds after a compiling call, ratios paired per round. "
        "Error: largest over the members of the final state's error against the plain script "
        "at rtol 1e-12 (the full model's rows: against tippejax's full model at rtol 1e-12, "
        "over the members whose run ended as the reference's did; 16% of these launches lose "
        "contact in the full model, some by a grazing dip of R_n that one tolerance finds and "
        "another not: "
        + ", ".join(f"{k} {v}" for k, v in results[-1]["mismatched"].items())
        + " members ended otherwise). numba runs its `prange` loop on every core in both rows (its thread "
        "count is printed); the JAX runs on 1 device, then on every core as a device.",
        "",
        "| target | measured | verdict |",
        "|---|---|---|",
        f"| goal: batch of 1000 at or below numba `prange` on the same cores | tippejax so3 with "
        f"`steps=\"shared\"` on {many} devices {so3_shared['to_numba']:.2f}x numba "
        f"({results[-1]['threads']} threads), error {so3_shared['error']:.1e} against numba's "
        f"{best[many][NUMBA]['error']:.1e}; full {best[many]['tippejax full, shared']['to_numba']:.2f}x"
        f" | {verdict(so3_shared['to_numba'] <= 1.0)} |",
        "",
    ]
    for res in results:
        lines += [f"### {res['devices']} JAX device(s), numba {res['threads']} threads", ""]
        lines.append(table(
            ["run", "ms per top (median)", "x numba", "x plain vmap", "max error",
             "first call s"],
            [[row["name"], f"{row['per_top_ms']:.3f}", f"{row['to_numba']:.2f}",
              f"{row['to_plain']:.2f}", f"{row['error']:.1e}", f"{row['first']:.1f}"]
             for row in res["rows"]]))
        lines += [""]
        lines.append(table(
            ["level", "max |t_invert shared - per member| s", "max |final theta diff| rad",
             "steps shared / per member (max)", "same result codes"],
            [[model, f"{ag['t_invert']:.1e}", f"{ag['theta']:.1e}",
              f"{ag['steps'][1]} / {ag['steps'][0]}", str(ag["same_results"])]
             for model, ag in res["agreement"].items()]))
        lines += [""]
    write_section("shared_steps.py", "\n".join(lines))
    print(f"done in {elapsed:.0f} s")


def random_check(n_tops: int, seed: int = 0, t1: float = 10.0, launches: int = 48):
    os.environ.setdefault("TIPPEJAX_HOST_DEVICES", str(os.cpu_count()))
    import jax
    import numpy as np

    import tippejax as tj

    sys.path.insert(0, HERE)
    from _common import machine_line, random_top, table, write_section

    start = time.perf_counter()
    print(machine_line(), flush=True)
    rng = np.random.default_rng(seed)
    rows = []
    for _ in range(n_tops):
        top, a_c, e_r, mu, n_ref = random_top(rng)
        theta0 = rng.uniform(0.02, 1.5, launches)
        spin = rng.uniform(0.5, 8.0, launches) * n_ref
        for model in ("full", "so3"):
            sols, secs = {}, {}
            for steps in ("per_member", "shared"):
                def run():
                    return tj.simulate_batch(top, theta0=theta0, spin=spin, t1=t1, model=model,
                                             summary=True, grid=(), buckets=4, steps=steps)
                jax.block_until_ready(run().theta)
                begin = time.perf_counter()
                sols[steps] = run()
                jax.block_until_ready(sols[steps].theta)
                secs[steps] = time.perf_counter() - begin
            a, b = sols["per_member"], sols["shared"]
            code_a, code_b = np.asarray(a.result._value), np.asarray(b.result._value)
            same = code_a == code_b

            def diff(name, a=a, b=b, same=same):
                x, y = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))
                if x.ndim > 1:
                    x, y = x[..., -1], y[..., -1]
                both = same & np.isfinite(x) & np.isfinite(y)
                nan_mismatch = int(np.sum(same & (np.isfinite(x) != np.isfinite(y))))
                return float(np.max(np.abs(x - y)[both], initial=0.0)), nan_mismatch

            row = dict(group=str(tj.classify(top)), A_over_C=a_c, eps_over_R=e_r, mu=mu,
                       model=model, spins=(float(spin.min()), float(spin.max())),
                       same=int(same.sum()), n=launches,
                       outcome=int(np.sum(np.asarray(a.outcome) == np.asarray(b.outcome))),
                       lost=int(np.sum(code_a == int(tj.RESULTS.contact_lost._value))),
                       t_invert=diff("t_invert"), t_contact_loss=diff("t_contact_loss"),
                       theta=diff("theta"), speed=secs["per_member"] / secs["shared"])
            rows.append(row)
            print("random", row, flush=True)
    n = sum(r["n"] for r in rows)
    same = sum(r["same"] for r in rows)
    outcome = sum(r["outcome"] for r in rows)
    table_rows = [[r["group"], r["model"], f"{r['A_over_C']:.2f}", f"{r['eps_over_R']:.2f}",
                   f"{r['mu']:.2f}", f"{r['spins'][0]:.0f}-{r['spins'][1]:.0f}",
                   f"{r['same']}/{r['n']}", f"{r['outcome']}/{r['n']}", str(r["lost"]),
                   f"{r['t_invert'][0]:.1e}", f"{r['t_contact_loss'][0]:.1e}",
                   f"{r['theta'][0]:.1e}",
                   str(r["t_invert"][1] + r["t_contact_loss"][1]), f"{r['speed']:.2f}x"]
                  for r in rows]
    elapsed = time.perf_counter() - start
    body = "\n".join([
        "## shared_steps.py --random: shared against per-member steps on random tops",
        "",
        f"`python benchmarks/shared_steps.py --random {n_tops}` ({elapsed:.0f} s, seed {seed},"
        f" {len(jax.devices())} devices). Seeded random tops (A/C in [0.6, 1.7], eps/R in "
        "[0.03, 0.4], mu log-uniform in [0.05, 1] s/m), each with "
        f"{launches} random launches (theta0 in [0.02, 1.5], spin in [0.5, 8] x n1, n2 in "
        f"group I), t1 = {t1:g} s, summary mode, contact loss stopping a member, `buckets=4` "
        "for both paths. Differences are the largest over the members whose result code is "
        "the same on both paths; 'event nan mismatches': members with the same result code "
        "where one path found an inversion or contact loss and the other did not. Speed: "
        "per-member time / shared time, one call each after a compiling call (rough).",
        "",
        f"Over all {n} member runs: {100 * same / n:.2f}% the same result code, "
        f"{100 * outcome / n:.2f}% the same outcome.",
        "",
        table(["group", "level", "A/C", "eps/R", "mu", "spins (rad/s)", "same result",
               "same outcome", "contact lost (per member)", "max d t_invert s",
               "max d t_contact_loss s", "max d final theta rad", "event nan mismatches",
               "speed"], table_rows),
        "",
    ])
    write_section("shared_steps.py --random", body)
    print(f"done in {elapsed:.0f} s: {same}/{n} same result codes, {outcome}/{n} same outcomes")


if __name__ == "__main__":
    if "--random" in sys.argv:
        random_check(int(sys.argv[sys.argv.index("--random") + 1]))
    elif "--worker" in sys.argv:
        rounds = int(sys.argv[sys.argv.index("--worker") + 1])
        print(json.dumps(worker(rounds)))
    else:
        main()
