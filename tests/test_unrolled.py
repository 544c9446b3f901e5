"""`UnrolledERK` (a Runge-Kutta step with its stages written out, the accelerator default) and
`StageLoopERK` (tippejax's stage loop, the CPU default): a step of each equals diffrax's stage
loop (the independent route: diffrax's own implementation of the same tableau), and
tippejax's solves with either equal the same solves with diffrax's loop."""

import json
import os
import subprocess
import sys

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tippejax._engine import segment
from tippejax._engine.unrolled import StageLoopERK, UnrolledERK, unrollable

SOLVERS = [diffrax.Dopri8, diffrax.Dopri5, diffrax.Tsit5]


def _field(t, y, args):
    # nonlinear, time-dependent and coupled, so that every stage's coefficients matter
    a, b = args
    return {
        "x": jnp.stack([y["x"][1] * y["v"], -jnp.sin(y["x"][0]) + a * jnp.cos(t)]),
        "v": b * y["x"][0] * y["x"][1] - 0.3 * y["v"] ** 3,
    }


Y0 = {"x": jnp.array([0.7, -0.4]), "v": jnp.array(1.3)}
ARGS = (0.5, -1.1)


WRAPPERS = [UnrolledERK, StageLoopERK]


@pytest.mark.parametrize("wrapper", WRAPPERS)
@pytest.mark.parametrize("solver_cls", SOLVERS)
def test_a_step_equals_the_stage_loop(solver_cls, wrapper):
    term = diffrax.ODETerm(_field)
    base = solver_cls()
    unrolled = wrapper(base)
    t0, t1 = 0.3, 0.55
    state = base.init(term, t0, t1, Y0, ARGS)
    want = base.step(term, t0, t1, Y0, ARGS, state, False)
    got = unrolled.step(term, t0, t1, Y0, ARGS, unrolled.init(term, t0, t1, Y0, ARGS), False)
    y1, err, dense, f1 = want[0], want[1], want[2], want[3][1]
    for a, b in [(got[0], y1), (got[1], err), (got[2]["k"], dense["k"]), (got[3], f1)]:
        for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
            assert x.shape == y.shape
            np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-14)
    # the error estimate is not identically zero: the comparison above tests something
    assert float(jnp.abs(err["v"])) > 1e-10
    # the dense output is the base solver's interpolation of the same stages
    interp = unrolled.interpolation_cls(t0=t0, t1=t1, **got[2])
    reference = base.interpolation_cls(t0=t0, t1=t1, **dense)
    np.testing.assert_allclose(
        interp.evaluate(0.41)["x"], reference.evaluate(0.41)["x"], rtol=1e-12
    )


@pytest.mark.parametrize("wrapper", WRAPPERS)
def test_a_solve_with_jumps_equals_the_stage_loop(wrapper):
    # jump_ts makes diffrax pass a traced `made_jump`: the kept last stage is recomputed
    def solve(solver, a):
        return diffrax.diffeqsolve(
            diffrax.ODETerm(_field),
            solver,
            0.0,
            3.0,
            0.05,
            Y0,
            (a, -1.1),
            stepsize_controller=diffrax.PIDController(
                rtol=1e-9, atol=1e-12, jump_ts=jnp.array([0.77, 1.9])
            ),
            saveat=diffrax.SaveAt(ts=jnp.linspace(0.0, 3.0, 7)),
        )

    args = jnp.array([0.5, 0.9])
    want = jax.vmap(lambda a: solve(diffrax.Dopri5(), a))(args)
    got = jax.vmap(lambda a: solve(wrapper(diffrax.Dopri5()), a))(args)
    np.testing.assert_array_equal(got.stats["num_steps"], want.stats["num_steps"])
    np.testing.assert_allclose(got.ys["x"], want.ys["x"], rtol=1e-10, atol=1e-12)
    # a wrong stage after a jump would be an O(1) error in the first step after it
    wrong = solve(wrapper(diffrax.Dopri5()), 0.5)
    assert np.max(np.abs(wrong.ys["x"] - want.ys["x"][0])) < 1e-9


@pytest.mark.parametrize("wrapper", WRAPPERS)
@pytest.mark.parametrize("solver", [diffrax.Kvaerno5(), diffrax.Euler(), diffrax.Heun()])
def test_refuses_what_it_cannot_write_out(solver, wrapper):
    assert not unrollable(solver)
    with pytest.raises(ValueError, match="first-same-as-last"):
        wrapper(solver)


SCRIPT = """
import json, sys, jax, numpy as np, diffrax, tippejax as tj
from tippejax._engine import segment
from tippejax._engine.unrolled import UnrolledERK
from test_unrolled import final_height_and_spin
prepared = segment._prepared_solver(diffrax.Dopri8(), diffrax.PIDController(rtol=1e-8, atol=1e-8),
                                    diffrax.RecursiveCheckpointAdjoint())
out = {"prepared": type(prepared).__name__}
for model, steps in (("so3", "shared"), ("full", "per_member")) if "solves" in sys.argv else ():
    sol = tj.simulate_batch(tj.default_top(), theta0=0.1, spin=[120.0, 150.0, 185.0], t1=12.0,
                            model=model, steps=steps, saveat=[1.0, 5.0])
    out[steps] = dict(t_invert=np.asarray(sol.t_invert).tolist(),
                      axis=np.asarray(sol.states.axis).tolist(),
                      omega=np.asarray(sol.states.omega).tolist(),
                      result=np.asarray(sol.result._value).tolist())
if "grad" in sys.argv:
    grad = jax.grad(final_height_and_spin)(tj.default_top())
    out["grad"] = [float(grad.mu), float(grad.eps), float(grad.C)]
print(json.dumps(out))
"""


def final_height_and_spin(top):
    """A scalar of a 3 s so3 run, to differentiate (the fit's path: forward-mode sensitivity)."""
    import tippejax as tj

    sol = tj.simulate(top, tj.initial_state(top, 0.1, 150.0), 3.0, model="so3", summary=True)
    return sol.states.axis[-1, 2] + 1e-3 * sol.states.omega[-1, 2]


def _run(setting, *parts, prepared="UnrolledERK"):
    """SCRIPT in a new process with `TIPPEJAX_UNROLL_STAGES=setting`; `parts`: "solves",
    "grad"; `prepared`: the solver class the process must run Dopri8 as."""
    # (the same device count as here: shared steps are shared within a device's shard, so the
    # batches below are compared shard for shard)
    env = dict(
        os.environ,
        TIPPEJAX_UNROLL_STAGES=setting,
        TIPPEJAX_HOST_DEVICES=str(jax.device_count()),
        PYTHONPATH=os.pathsep.join(
            [os.path.dirname(os.path.abspath(__file__))]
            + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
        ),
    )
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT, *parts], env=env, capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert got["prepared"] == prepared
    return got


def _assert_same_solves(got):
    """`got` (SCRIPT's "solves") against the same batches run here."""
    import tippejax as tj

    for model, steps in (("so3", "shared"), ("full", "per_member")):
        sol = tj.simulate_batch(
            tj.default_top(),
            theta0=0.1,
            spin=[120.0, 150.0, 185.0],
            t1=12.0,
            model=model,
            steps=steps,
            saveat=[1.0, 5.0],
        )
        mine = got[steps]
        np.testing.assert_array_equal(mine["result"], np.asarray(sol.result._value))
        assert np.isfinite(mine["t_invert"]).sum() >= 2  # inversions to compare
        np.testing.assert_allclose(mine["t_invert"], sol.t_invert, rtol=1e-7, equal_nan=True)
        np.testing.assert_allclose(mine["axis"], sol.states.axis, rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(mine["omega"], sol.states.omega, rtol=1e-6, atol=1e-5)


def test_the_cpu_default_is_tippejaxs_stage_loop():
    prepared = segment._prepared_solver(
        diffrax.Dopri8(),
        diffrax.PIDController(rtol=1e-8, atol=1e-8),
        diffrax.RecursiveCheckpointAdjoint(),
    )
    if os.environ.get("TIPPEJAX_UNROLL_STAGES", "auto") in ("", "auto"):
        assert isinstance(prepared, StageLoopERK)


@pytest.mark.slow
def test_stages_written_out_give_tippejax_the_stage_loops_results():
    """The accelerator path (`TIPPEJAX_UNROLL_STAGES=1`) run on the CPU: the same events,
    states and result codes as the CPU default's stage loop, per member and with shared
    steps. Slow (65-90 s under CI's load: the written-out programs compile in a fresh
    process) and for a path CI never runs (accelerators): the step tests above hold
    `UnrolledERK`'s step to diffrax's in CI, and `-m slow` runs this whole-solve check."""
    _assert_same_solves(_run("1", "solves"))


@pytest.mark.slow
def test_tippejaxs_stage_loop_gives_diffraxs_results():
    """The CPU default (`StageLoopERK`) against diffrax's own stage loop
    (`TIPPEJAX_UNROLL_STAGES=diffrax`, the independent route): the same events, states and
    result codes, per member and with shared steps. Slow: the step tests above hold
    `StageLoopERK`'s step to diffrax's in every run; this is the whole-solve route."""
    _assert_same_solves(_run("diffrax", "solves", prepared="Dopri8"))


@pytest.mark.slow
def test_stages_written_out_give_the_stage_loops_gradient():
    """The gradient through `simulate` (the fit's forward-mode path on an accelerator) with
    the stages written out equals the stage loop's. Slow (a forward-mode program of each kind
    to compile, about a minute on 2 cores under CI's load): the step tests above show the two
    programs compute the same step, which JAX's forward mode then differentiates alike."""
    import tippejax as tj

    got = _run("1", "grad")
    grad = jax.grad(final_height_and_spin)(tj.default_top())
    want = [float(grad.mu), float(grad.eps), float(grad.C)]
    assert all(abs(w) > 0 for w in want)
    np.testing.assert_allclose(got["grad"], want, rtol=1e-6)


def test_a_bad_setting_is_refused_at_import():
    proc = subprocess.run(
        [sys.executable, "-c", "import tippejax"],
        capture_output=True,
        text=True,
        env=dict(os.environ, TIPPEJAX_UNROLL_STAGES="sometimes"),
    )
    assert proc.returncode != 0
    assert "TIPPEJAX_UNROLL_STAGES must be" in proc.stderr
