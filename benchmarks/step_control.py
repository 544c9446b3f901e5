"""The step-size controller: diffrax's default I controller against the PI controller
tippejax uses (`tippejax._engine.segment.STEP_CONTROL`), at equal error, on seeded random
tops nobody tuned on.

Each of K tops is drawn by `_common.random_top` (A/C 0.6-1.7, eps/R 0.03-0.4, mu 0.05-1 s/m,
so every group), launched at theta0 uniform in [0.05, 1.5] rad and a spin of 0.5-8 times its
n1 (n2 in group I), and run 10 s in summary mode at rtol 1e-6 ... 1e-10 (atol = rtol / 100) by
`tj.simulate` at the SO(3), full and Routhian levels, once with each controller (each in its
own process, so that nothing compiled under one is reused by the other). Error: the largest
relative difference of the final axis and omega (and velocity, full level) from the I
controller's run at rtol 1e-12. Work: the step attempts (accepted + rejected; a step's cost
does not depend on the controller). For each top and level, the PI controller's attempts at
the errors the I controller reached (log-log interpolation on PI's curve, inside its range)
divided by the I controller's: below 1 the PI controller does the same accuracy for less.
Members that end early (a contact loss, ...) in either run are left out, with a count.

    python benchmarks/step_control.py [--tops 24] [--seed 11]
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
RTOLS = (1e-6, 1e-7, 1e-8, 1e-9, 1e-10)
REF_RTOL = 1e-12
T1 = 10.0
LEVELS = ("so3", "full", "routhian")
CONTROLLERS = {"I": dict(pcoeff=0.0, icoeff=1.0), "PI": None}  # None: tippejax's own


def _arg(name, default):
    return sys.argv[sys.argv.index(name) + 1] if name in sys.argv else default


def draw(tops, seed):
    sys.path.insert(0, HERE)
    from _common import random_top

    rng = np.random.default_rng(seed)
    out = []
    for _ in range(tops):
        top, a_c, e_r, mu, n_ref = random_top(rng)
        out.append((top, float(rng.uniform(0.05, 1.5)), float(rng.uniform(0.5, 8.0) * n_ref),
                    dict(a_c=a_c, e_r=e_r, mu=mu)))
    return out


def child(controller, tops, seed, path):
    """One controller, every level and rtol: final states, attempts, result codes, time."""
    os.environ.setdefault("TIPPEJAX_HOST_DEVICES", "1")
    import time

    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import tippejax as tj
    from tippejax._engine import segment

    if CONTROLLERS[controller] is not None:
        segment.STEP_CONTROL = CONTROLLERS[controller]
    drawn = draw(tops, seed)
    top = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *[d[0] for d in drawn])
    theta0 = jnp.array([d[1] for d in drawn])
    spin = jnp.array([d[2] for d in drawn])
    out = dict(controller=segment.STEP_CONTROL, groups=[str(tj.classify(d[0])) for d in drawn],
               draws=[d[3] | dict(theta0=d[1], spin=d[2]) for d in drawn])
    for level in LEVELS:
        @eqx.filter_jit
        def run(top, theta0, spin, rtol, level=level):
            def one(top, theta0, spin):
                sol = tj.simulate(top, tj.initial_state(top, theta0, spin), T1, model=level,
                                  summary=True, rtol=rtol, atol=rtol * 1e-2, throw=False)
                s = sol.states
                final = jnp.concatenate([s.axis[-1], s.omega[-1], s.velocity[-1]])
                return final, sol.num_steps + sol.num_rejected_steps, sol.result._value
            return jax.vmap(one)(top, theta0, spin)

        for rtol in (REF_RTOL, *RTOLS):
            args = (top, theta0, spin, jnp.asarray(rtol))
            jax.block_until_ready(run(*args))
            begin = time.perf_counter()
            final, attempts, result = jax.block_until_ready(run(*args))
            out[f"{level} {rtol:g}"] = dict(
                final=np.asarray(final).tolist(), attempts=np.asarray(attempts).tolist(),
                result=np.asarray(result).tolist(), seconds=time.perf_counter() - begin)
    with open(path, "w") as f:
        json.dump(out, f)


def compare(runs):
    """Per level: the PI/I attempts ratios at equal error, over tops and rtols."""
    sys.path.insert(0, HERE)
    from _common import interp_loglog

    rows, ratios_all = [], {}
    for level in LEVELS:
        ref = np.array(runs["I"][f"{level} {REF_RTOL:g}"]["final"])
        ratios, left_out, time_ratio = [], 0, []
        for k in range(ref.shape[0]):
            curves = {}
            for name, run in runs.items():
                cells = [run[f"{level} {r:g}"] for r in RTOLS]
                err = [float(np.max(np.abs(np.array(c["final"][k]) - ref[k])
                                    / np.maximum(1.0, np.abs(ref[k])))) for c in cells]
                ok = all(c["result"][k] == 0 for c in cells) and \
                    run[f"{level} {REF_RTOL:g}"]["result"][k] == 0
                curves[name] = (np.array(err), np.array([c["attempts"][k] for c in cells]), ok)
            if not (curves["I"][2] and curves["PI"][2]):
                left_out += 1
                continue
            e_i, n_i, _ = curves["I"]
            e_p, n_p, _ = curves["PI"]
            lo, hi = max(e_p.min(), 1e-15), e_p.max()
            for e, n in zip(e_i, n_i):
                if lo <= e <= hi:
                    ratios.append(interp_loglog(e, e_p, n_p)[0] / n)
        for r in RTOLS:
            time_ratio.append(runs["PI"][f"{level} {r:g}"]["seconds"]
                              / runs["I"][f"{level} {r:g}"]["seconds"])
        ratios_all[level] = ratios
        q = np.percentile(ratios, [10, 50, 90]) if ratios else [np.nan] * 3
        rows.append([level, str(len(ratios)), f"{q[1]:.3f}", f"{q[0]:.2f} - {q[2]:.2f}",
                     f"{np.mean(np.array(ratios) < 1):.0%}" if ratios else "",
                     str(left_out), f"{np.median(time_ratio):.2f}"])
    return rows, ratios_all


def main():
    tops = int(_arg("--tops", "24"))
    seed = int(_arg("--seed", "11"))
    if "--child" in sys.argv:
        child(_arg("--child", None), tops, seed, _arg("--json", None))
        return
    sys.path.insert(0, HERE)
    from _common import machine_line, table, write_section

    runs = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in CONTROLLERS:
            path = os.path.join(tmp, f"{name}.json")
            subprocess.run([sys.executable, __file__, "--child", name, "--json", path,
                            "--tops", str(tops), "--seed", str(seed)], check=True)
            with open(path) as f:
                runs[name] = json.load(f)
    rows, _ = compare(runs)
    groups = sorted(set(runs["I"]["groups"]))
    lines = [
        "## step_control.py: the PI step-size controller against diffrax's I controller",
        "",
        f"`python benchmarks/step_control.py --tops {tops} --seed {seed}` ({machine_line()}). "
        f"{tops} seeded random tops (groups {', '.join(groups)}), theta0 0.05-1.5 rad, spin "
        "0.5-8 n1, 10 s, summary mode, rtol 1e-6 ... 1e-10 (atol rtol/100); error: final axis, "
        "omega (and velocity) against the I controller at rtol 1e-12. PI: "
        f"{runs['PI']['controller']}. Ratio: the PI controller's step attempts (accepted + "
        "rejected) at the error the I controller reached, over the I controller's, one per "
        "top and rtol inside the PI curve's range. Time ratio: the batch of all tops at each "
        "rtol (PI / I, median over the rtols; one run each, equal rtol, not equal error).",
        "",
        table(["level", "points", "PI/I attempts at equal error (median)", "10%-90%",
               "points below 1", "tops left out (ended early)", "time PI/I at equal rtol"],
              rows),
        "",
    ]
    write_section("step_control.py", "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
