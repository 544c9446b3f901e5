"""Runtime checks that survive `jax.grad`, `jax.jacfwd` and `jax.vmap` under `jax.jit`."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import PyTree


def _is_float_array(x) -> bool:
    return isinstance(x, jax.Array | jax.core.Tracer) and jnp.issubdtype(x.dtype, jnp.inexact)


def _checked_leaf(x, pred, index, failed, messages, on_error):
    x = jnp.asarray(x)
    y = eqx.branched_error_if(x, pred, index, messages, on_error=on_error)
    # The value is the checked `y`; the derivative is `x`'s times a gate computed from `y`. In
    # reverse mode JAX keeps of the forward pass only what the backward pass uses; the gate is
    # such a residual, so the check runs before any gradient is returned. (A plain
    # `eqx.error_if` passes the tangent straight through, and under `jit(grad(...))` its
    # check, whose primal output nothing uses, is removed as dead code: the gradient came back
    # as a silent value.) The gate is nan for a failed member, so that where the check does
    # not raise (`EQX_ON_ERROR=nan`) the derivative is nan, never a plausible number. Plain
    # operations, not a `custom_jvp`: under `jax.jacfwd` a `custom_jvp` of an undifferentiated
    # leaf comes out batched, and what follows is traced again for a batch.
    y_const = jax.lax.stop_gradient(y)
    finite = jnp.where(jnp.isfinite(y_const), y_const, jnp.zeros_like(y_const))
    gate = jnp.where(failed, jnp.nan, 1.0).astype(y.dtype) + jnp.zeros_like(y) * finite
    x_finite = jnp.where(jnp.isfinite(x), x, jnp.zeros_like(x))
    tangent_path = (x_finite - jax.lax.stop_gradient(x_finite)) * gate
    return y_const + tangent_path


def error_if(x: PyTree, pred, msg: str, *, on_error: str = "default") -> PyTree:
    """`eqx.error_if(x, pred, msg)` on every floating leaf of `x`, kept under differentiation.

    With `eqx.error_if` the check lives in the primal computation, and a `jax.jit` of a
    `jax.grad` whose gradient does not need that primal value drops it: the failure vanishes and
    the gradient comes back as a number. Here each floating leaf's derivative is gated on the
    checked value, so `jit(grad)`, `jit(jacfwd)` and `vmap(grad)` raise like the value does
    (and give nan where `EQX_ON_ERROR=nan`). Non-floating leaves (result codes) are returned as
    they are. `on_error` is `eqx.error_if`'s (default: the `EQX_ON_ERROR` setting).
    """
    return branched_error_if(x, pred, 0, (msg,), on_error=on_error)


def branched_error_if(x: PyTree, pred, index, messages, *, on_error: str = "default") -> PyTree:
    """`error_if` with the message `messages[index]` (`eqx.branched_error_if`'s signature)."""
    pred = jnp.asarray(pred)
    index = jnp.asarray(index)
    messages = tuple(messages)

    def check(leaf):
        if not _is_float_array(leaf):
            return leaf
        # the members' failures, aligned with the leaf's leading (batch) axes where they are
        # the leaf's, else any failure of the batch
        shape = jnp.shape(leaf)
        if pred.ndim <= len(shape) and shape[: pred.ndim] == pred.shape:
            failed = pred.reshape(pred.shape + (1,) * (len(shape) - pred.ndim))
        else:
            failed = jnp.any(pred)
        return _checked_leaf(leaf, pred, index, failed, messages, on_error)

    return jax.tree_util.tree_map(check, x)


def result_error_if(x: PyTree, result, pred) -> PyTree:
    """`result.error_if(x, pred)` for a `RESULTS` item (its message), kept under
    differentiation (see `error_if`)."""
    enumeration = result._enumeration
    return branched_error_if(x, pred, result._value, enumeration._index_to_message)
