r"""Derivatives of a solve by forward sensitivities, for `jax.grad` as well as `jax.jacfwd`.

A run of one top depends on a few numbers: the seven fields of the top, the launch state (13),
the times and tolerances. Its sensitivities with respect to the $k$ of them that are
differentiated are the forward-mode Jacobian

$$J = \frac{\partial\,\mathrm{outputs}}{\partial p}\in\mathbb{R}^{n\times k},$$

obtained in one solve that carries $k$ tangents (`diffrax.ForwardMode`). Every derivative is
then a product with $J$: a Jacobian-vector product $J\dot p$ (`jax.jvp`, `jax.jacfwd`) or a
vector-Jacobian product $\bar y^{\mathsf T} J$ (`jax.grad`, `jax.vjp`: the transpose of the
former, which JAX derives since $J$ is a constant of the primal inputs).

Reverse mode through the solve itself (`diffrax.RecursiveCheckpointAdjoint`) instead runs the
solve's thousands of steps backwards through every Runge-Kutta stage, the event watch and
the step-size controller, which for a top's few inputs costs more than $J$ (the gradients
suite on the performance page compares both). It remains the better choice for many differentiated
inputs, which a single run of a top does not have (a batch of tops is `jax.vmap` of single
runs).

`forward_sensitivities(primal, forward)` wraps a function of arrays in `jax.custom_jvp`: its
value is `primal(*args)` (any solve, not differentiated), its derivative rule builds $J$
with `forward(*args)` (the same computation with a forward-mode solve) for the inputs JAX
marks as differentiated (`symbolic_zeros`: the others cost nothing).
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from .solver_choice import is_traced


class ForwardSensitivities(eqx.Module):
    """The adjoint `simulate` uses by default: derivatives of the run, in forward and in
    reverse mode, from its forward-mode Jacobian in the inputs that are differentiated (see
    the module docstring). Not a diffrax adjoint: the engine runs the solve itself with
    `diffrax.RecursiveCheckpointAdjoint` (not differentiated) and the Jacobian with
    `diffrax.ForwardMode`."""


def _is_float(x) -> bool:
    return jnp.issubdtype(jnp.result_type(x), jnp.inexact)


def forward_sensitivities(
    primal: Callable, forward: Callable, *, jacobian: Callable | None = None
) -> Callable:
    """`primal` (a function of pytrees of arrays) with its derivatives computed from the
    forward-mode Jacobian of `forward`, which must compute the same function (see the module
    docstring). Integer outputs have zero derivatives (`float0`). `primal` and `forward` may
    be one jitted function: `simulate` passes its solve, staged with `diffrax.ForwardMode`, as
    both, so that JAX, which traces the value of a `custom_jvp` under `jit` eagerly, finds
    the same trace in `jit`'s cache when the rule differentiates it.

    `jacobian(args, live)`, if given, is called instead of `jacobian_of(forward, args, live)`
    when the rule's primal inputs are concrete arrays (an eager `jax.grad` or `jax.jacfwd`):
    the Jacobian is then a program of its own, which may be compiled with options and stored
    (`simulate` passes one)."""

    @jax.custom_jvp
    def fn(*args):
        return primal(*args)

    def rule(primals, tangents):
        flat, tree = jax.tree_util.tree_flatten(primals)
        flat_tangents = tree.flatten_up_to(tangents)
        live = tuple(
            i
            for i, t in enumerate(flat_tangents)
            if not isinstance(t, SymbolicZero) and _is_float(flat[i])
        )
        if not live:
            out = primal(*primals)
            return out, jax.tree_util.tree_map(_zero_tangent, out)
        if jacobian is not None and not any(map(is_traced, flat)):
            out, jac = jacobian(primals, live)
        else:
            out, jac = jacobian_of(forward, primals, live)
        direction = jnp.concatenate(
            [jnp.ravel(jnp.asarray(flat_tangents[i], jnp.result_type(flat[i]))) for i in live]
        )

        def tangent(o, j):
            if not _is_float(o):
                return _zero_tangent(o)
            return jnp.tensordot(direction.astype(j.dtype), j, axes=1)

        return out, jax.tree_util.tree_map(tangent, out, jac)

    fn.defjvp(rule, symbolic_zeros=True)
    return fn


def jacobian_of(forward: Callable, args: tuple, live: tuple[int, ...]):
    """`forward(*args)` and its Jacobian in the leaves `live` of `args` (indices into
    `jax.tree_util.tree_leaves(args)`): `(out, jac)`, where each leaf of `jac` is the leaf of
    `out` with a leading axis of the $k$ differentiated numbers (one `jax.jvp` per unit
    tangent, `jax.vmap`-ed: one solve carrying $k$ tangents)."""
    flat, tree = jax.tree_util.tree_flatten(args)
    inputs = [jnp.asarray(flat[i]) for i in live]

    def of_live(*values):
        leaves = list(flat)
        for i, value in zip(live, values):
            leaves[i] = value
        return forward(*jax.tree_util.tree_unflatten(tree, leaves))

    # The k unit tangents, one leaf of the differentiated inputs at a time.
    sizes = [x.size for x in inputs]
    k = sum(sizes)
    eye = jnp.eye(k, dtype=jnp.result_type(*inputs))
    offsets = np.cumsum([0] + sizes)
    basis = [
        eye[:, a:b].reshape((k,) + x.shape).astype(x.dtype)
        for a, b, x in zip(offsets[:-1], offsets[1:], inputs)
    ]
    return jax.vmap(lambda *t: jax.jvp(of_live, tuple(inputs), t), out_axes=(None, 0))(*basis)


def _zero_tangent(x):
    if _is_float(x):
        return jnp.zeros_like(x)
    return np.zeros(np.shape(x), dtype=jax.dtypes.float0)
