"""Derivatives of `simulate` on seeded random tops: the default adjoint against reverse mode
through the solve.

The default adjoint (`tippejax/_engine/sensitivity.py`) builds the forward-mode Jacobian of a
run in its differentiated inputs and transposes it for `jax.grad`; reverse mode through the
solve's steps (`diffrax.RecursiveCheckpointAdjoint`) differentiates the same discrete solve by
another route, sharing neither the tangent solve nor its state layout. The two must agree to
about the solver's rounding on any top, not only the standard one that `tests/test_grad.py`
and `benchmarks/gradients.py` use.

Records: `_common.random_top` (A/C in [0.6, 1.7], eps/R in [0.03, 0.4], mu log-uniform in
[0.05, 1] s/m), launched at theta0 uniform in [0.05, 0.5] rad with a spin 1.5-4x the top's
threshold spin, run 8 s in summary mode at rtol 1e-10. Outputs theta, theta_dot and the
energy at the end, and t_invert where the top inverts by then; derivatives in the seven
fields of the top and the launch (theta0, spin), by `jax.jacrev` in both modes (each
compiled once: the top is traced). The default adjoint is also called eagerly (no `jax.jit`),
where the Jacobian of the solve is a program of its own (`_run_jacobian`, compiled with
tippejax's options): 'eager vs jit' is its largest disagreement with the `jit`-ed default.

    python benchmarks/gradient_check.py [N]      # N records (default 24), seed 0
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import machine_line, random_top, table, verdict, write_section  # noqa: E402

SEED = 0
T1 = 8.0
SOLVE = dict(rtol=1e-10, atol=1e-12)
FIELDS = ("m", "R", "eps", "A", "C", "g", "mu")
OUTPUTS = ("theta(t1)", "theta_dot(t1)", "energy(t1)", "t_invert")
AGREE = 1e-6  # both modes differentiate the same discrete solve (test_grad.py: ~1e-12)


def main() -> None:
    import diffrax
    import jax
    import jax.numpy as jnp

    import tippejax as tj

    n = int(sys.argv[1]) if len(sys.argv) > 1 else 24
    rng = np.random.default_rng(SEED)

    def outputs(top, launch, adjoint=None):
        y0 = tj.initial_state(top, launch[0], launch[1])
        sol = tj.simulate(top, y0, T1, summary=True, throw=False, adjoint=adjoint, **SOLVE)
        return jnp.stack([sol.theta[0], sol.theta_dot[0], sol.energy[0], sol.t_invert]), \
            sol.result == tj.RESULTS.successful

    def jacobian(adjoint):
        return jax.jit(jax.jacrev(lambda top, launch: outputs(top, launch, adjoint)[0],
                                  argnums=(0, 1)))

    default = jacobian(None)
    eager = jax.jacrev(lambda top, launch: outputs(top, launch)[0], argnums=(0, 1))
    through = jacobian(diffrax.RecursiveCheckpointAdjoint())
    value = jax.jit(outputs)

    def as_matrix(jac):
        d_top, d_launch = jac
        return np.column_stack([np.asarray(getattr(d_top, f)) for f in FIELDS]
                               + [np.asarray(d_launch)])

    rows, worst, worst_eager, start = [], 0.0, 0.0, time.perf_counter()
    for i in range(n):
        top, a_c, e_r, mu, n_ref = random_top(rng)
        launch = jnp.asarray([rng.uniform(0.05, 0.5), n_ref * rng.uniform(1.5, 4.0)])
        group = str(tj.classify(top))
        out, ok = value(top, launch)
        head = [i, group, f"{a_c:.2f}", f"{e_r:.3f}", f"{mu:.3f}", f"{float(launch[1]):.0f}"]
        if not bool(ok):
            rows.append(head + ["failed run", "", "", ""])
            continue
        got, want = as_matrix(default(top, launch)), as_matrix(through(top, launch))
        got_eager = as_matrix(eager(top, launch))
        live = np.isfinite(np.asarray(out))  # t_invert is nan where the top has not inverted
        got, want, got_eager = got[live], want[live], got_eager[live]
        # relative to each output's largest derivative (entries near zero carry no digits)
        scale = np.max(np.abs(want), axis=1, keepdims=True)
        disagreement = float(np.max(np.abs(got - want) / scale))
        eager_vs_jit = float(np.max(np.abs(got_eager - got) / scale))
        worst, worst_eager = max(worst, disagreement), max(worst_eager, eager_vs_jit)
        rows.append(head + [", ".join(o for o, keep in zip(OUTPUTS, live) if keep),
                            f"{disagreement:.1e}", f"{eager_vs_jit:.1e}",
                            bool(np.all(np.isfinite(got)) and np.all(np.isfinite(got_eager)))])
        print(rows[-1], flush=True)
    elapsed = time.perf_counter() - start
    checked = sum(1 for r in rows if r[7] != "")
    body = "\n".join([
        "## gradient_check.py: derivatives on seeded random tops",
        "",
        f"`python benchmarks/gradient_check.py {n}` ({elapsed:.0f} s, compilation included). "
        + machine_line() + ". " + __doc__.split("\n\n")[2].replace("\n", " ")
        + " 'disagreement': the largest |default - through| over the derivatives of an output, "
        "relative to that output's largest derivative, over all outputs.",
        "",
        table(["record", "group", "A/C", "eps/R", "mu (s/m)", "spin (rad/s)", "outputs",
               "disagreement", "eager vs jit", "finite"], rows),
        "",
        f"Default adjoint == reverse mode through the solve within {AGREE:g} on every record "
        f"that ran ({checked} of {n}; a run that fails, such as one that leaves the table, "
        f"has no derivative to check): largest disagreement {worst:.1e}: "
        f"{verdict(worst < AGREE and checked > 0)}. The eager default adjoint == the `jit`-ed "
        f"one within {AGREE:g}: largest disagreement {worst_eager:.1e}: "
        f"{verdict(worst_eager < AGREE and checked > 0)}.",
    ])
    write_section("gradient_check.py", body)
    print(body)


if __name__ == "__main__":
    main()
