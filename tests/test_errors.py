"""A failed solve is reported under every transformation, never returned as a plausible number.

`eqx.error_if` checks a value in the primal computation; a `jax.jit` of a `jax.grad` whose
gradient does not need that primal value drops the check as dead code. These tests run every
public differentiable quantity, for runs that fail in each documented way (contact loss,
`max_steps`, the R_n singularity), under `jit(grad)`, `jit(jacfwd)` and `vmap(grad)`: each must
raise (or, where it cannot raise, be nan).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tippejax as tj
from tippejax._errors import error_if

RAISES = (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError, RuntimeError)


# --------------------------------------------------------------------------------------------
# The mechanism, on a toy function (cheap): a check whose primal value the derivative ignores
# --------------------------------------------------------------------------------------------


def _toy(x):
    # The derivative of sin does not need the checked value sin(x): with eqx.error_if the
    # check vanished under jit(grad).
    return error_if(jnp.sin(x), x > 1.0, "x is too large")


def _toy_eqx(x):
    return eqx.error_if(jnp.sin(x), x > 1.0, "x is too large")


def test_the_plain_check_vanishes_under_jit_grad():
    """The bug this module exists for, shown on equinox's own check."""
    assert float(jax.jit(jax.grad(_toy_eqx))(2.0)) == pytest.approx(np.cos(2.0))


TRANSFORMS = {
    # name: (transform, whether it takes a batch of x)
    "jit-grad": (lambda f: jax.jit(jax.grad(f)), False),
    "jit-jacfwd": (lambda f: jax.jit(jax.jacfwd(f)), False),
    "jit-jvp": (lambda f: jax.jit(lambda x: jax.jvp(f, (x,), (jnp.ones_like(x),))[1]), False),
    "grad": (lambda f: jax.grad(f), False),
    "vmap-grad": (lambda f: jax.vmap(jax.grad(f)), True),
    "jit-vmap-grad": (lambda f: jax.jit(jax.vmap(jax.grad(f))), True),
    "jit-grad-vmap": (lambda f: jax.jit(jax.grad(lambda x: jax.vmap(f)(x).sum())), True),
}


@pytest.mark.parametrize("name", TRANSFORMS)
def test_the_check_survives(name):
    transform, batched = TRANSFORMS[name]
    g = transform(_toy)
    bad, good = (jnp.array([0.5, 2.0]), jnp.array([0.5, 0.7])) if batched else (2.0, 0.7)
    with pytest.raises(RAISES, match="x is too large"):
        jax.block_until_ready(g(bad))
    assert np.allclose(np.asarray(g(good)), np.cos(np.asarray(good)))


def test_the_derivative_of_a_failed_member_is_nan_when_errors_are_values():
    """With EQX_ON_ERROR=nan the check cannot raise: the derivative is nan, not a number."""
    x = jnp.array([0.5, 2.0])
    for on_error in ("default", "nan"):
        grads = jax.jit(
            jax.vmap(
                jax.grad(lambda x: error_if(jnp.sin(x), x > 1.0, "too large", on_error=on_error))
            )
        )
        if on_error == "default":
            with pytest.raises(RAISES):
                grads(x)
            continue
        out = np.asarray(grads(x))
        assert out[0] == pytest.approx(np.cos(0.5)) and np.isnan(out[1])


# --------------------------------------------------------------------------------------------
# The package: every public differentiable quantity, for each way a run fails
# --------------------------------------------------------------------------------------------

TOP = tj.default_top()


def _contact_loss(mu):
    # the standard top at 200 rad/s loses contact during the rise, at about 5.2 s
    top = TOP.replace(mu=mu)
    return top, tj.initial_state(top, 0.1, 200.0), dict(t1=6.0)


def _max_steps(mu):
    top = TOP.replace(mu=mu)
    return top, tj.initial_state(top, 0.1, 100.0), dict(t1=2.0, max_steps=16)


def _singular(mu):
    # beyond the Painleve-type bound on theta_dot at theta = 1 (ERRATA item 5), for mu = 2 s/m
    top = TOP.replace(mu=mu)
    m, R, eps, A = 0.02, 0.025, 0.0075, 4.5e-6
    h, hp = R - eps * np.cos(1.0), eps * np.sin(1.0)
    bound = -(A / m + hp**2) / (2.0 * h**2 * hp)
    return top, tj.initial_state(top, 1.0, 50.0, theta_dot=1.05 * bound), dict(t1=0.5)


FAILURES = {
    "contact_lost": (_contact_loss, 0.3),
    "max_steps": (_max_steps, 0.3),
    "singular": (_singular, 2.0),
}


def _quantities(scene):
    def inversion(mu):
        top, y0, kw = scene(mu)
        return tj.inversion_time(top, y0, t1=kw["t1"], max_steps=kw.get("max_steps", 1_000_000))

    def field(name):
        def fn(mu):
            top, y0, kw = scene(mu)
            sol = tj.simulate(top, y0, summary=True, **kw)
            value = getattr(sol, name)
            return value if jnp.ndim(value) == 0 else value[-1]

        return fn

    out = {"inversion_time": inversion}
    for name in ("t_invert", "theta", "energy", "normal_force", "jellet", "t_contact_loss"):
        out[f"simulate.{name}"] = field(name)
    return out


# Each case is a compilation of its own. The default run covers every failure under jit(grad)
# on inversion_time, every transformation on inversion_time, and one of simulate's fields
# (every field of a Solution goes through the one check); `-m slow` runs the whole matrix.
FAST = {("contact_lost", "inversion_time", t) for t in ("jit-grad", "jit-jacfwd", "vmap-grad")}
FAST |= {(f, "inversion_time", "jit-grad") for f in ("max_steps", "singular")}
FAST.add(("contact_lost", "simulate.t_invert", "jit-grad"))


def _cases():
    cases = []
    for failure, (scene, _) in FAILURES.items():
        for name in _quantities(scene):
            for transform in ("jit-grad", "jit-jacfwd", "vmap-grad"):
                marks = () if (failure, name, transform) in FAST else (pytest.mark.slow,)
                cases.append(pytest.param(failure, name, transform, marks=marks))
    return cases


@pytest.mark.parametrize("failure, quantity, transform", _cases())
def test_failed_runs_raise_under_every_transformation(failure, quantity, transform):
    scene, mu = FAILURES[failure]
    fn = _quantities(scene)[quantity]
    if transform == "jit-grad":
        run = jax.jit(jax.grad(fn))
        arg = mu
    elif transform == "jit-jacfwd":
        run = jax.jit(jax.jacfwd(fn))
        arg = mu
    else:
        run = jax.vmap(jax.grad(fn))
        arg = jnp.array([mu, mu])
    with pytest.raises(RAISES):
        out = jax.block_until_ready(run(arg))
        # (reached only if nothing raised: say what came back instead)
        pytest.fail(
            f"{quantity} under {transform} returned {out} for a run that failed ({failure})"
        )
