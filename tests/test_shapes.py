"""jaxtyping's runtime checks of the shapes the public results declare: every array field of a
`Solution` and of its `State`s against its annotation, with the dimensions shared across the
fields (one save count `n`, one batch shape)."""

import types
import typing

import jax.numpy as jnp
import jaxtyping
import numpy as np
import pytest

import tippejax as tj

N_SAVE = 6


def _array_hints(cls) -> dict:
    """The fields of `cls` annotated with a jaxtyping array type (or that type or None)."""
    out = {}
    for name, hint in typing.get_type_hints(cls).items():
        args = (
            typing.get_args(hint)
            if typing.get_origin(hint) in (typing.Union, types.UnionType)
            else (hint,)
        )
        if any(isinstance(a, type) and issubclass(a, jaxtyping.AbstractArray) for a in args):
            out[name] = hint
    return out


def _check(obj, hints):
    bad = [name for name, hint in hints.items() if not isinstance(getattr(obj, name), hint)]
    assert not bad, {name: np.shape(getattr(obj, name)) for name in bad}


@pytest.fixture(scope="module")
def runs():
    top = tj.default_top()
    ts = jnp.linspace(0.0, 1.0, N_SAVE)
    one = tj.simulate(top, tj.initial_state(top, 0.1, 150.0), 1.0, saveat=ts, model="so3")
    batch = tj.simulate_batch(top, 0.1, [120.0, 150.0, 180.0], 1.0, saveat=ts, model="so3")
    return one, batch


def test_the_annotations_are_checked():
    # (the check itself: a field of the wrong rank or a save count that disagrees fails)
    with jaxtyping.jaxtyped("context"):
        assert isinstance(jnp.zeros((N_SAVE,)), jaxtyping.Float[jaxtyping.Array, "*batch n"])
        assert not isinstance(
            jnp.zeros((N_SAVE + 1, 2)), jaxtyping.Float[jaxtyping.Array, "*batch n 2"]
        )
    assert len(_array_hints(tj.Solution)) >= 15 and len(_array_hints(tj.State)) >= 5


def test_a_single_run_has_the_declared_shapes(runs):
    one, _ = runs
    with jaxtyping.jaxtyped("context"):
        _check(one, _array_hints(tj.Solution))
    with jaxtyping.jaxtyped("context"):
        _check(one.states, _array_hints(tj.State))
    assert one.theta.shape == (N_SAVE,)


def test_a_batch_has_the_declared_shapes(runs):
    _, batch = runs
    with jaxtyping.jaxtyped("context"):
        _check(batch, _array_hints(tj.Solution))
    with jaxtyping.jaxtyped("context"):
        _check(batch.states, _array_hints(tj.State))
    assert batch.theta.shape == (1, 3, N_SAVE)
