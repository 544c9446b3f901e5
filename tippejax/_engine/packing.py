"""A level state packed into a few flat vectors for the solver, and the widths of the packing."""

from __future__ import annotations

import math
from collections.abc import Callable

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import PyTree

from .._models.base import AbstractLevel

PACK_WIDTH = 6
"""Most components in one flat vector of a level state in a batch (see `ravel_state`): a
user's `jax.vmap`, a GPU, and tippejax's own batches compiled with its CPU options
(`tippejax._engine.cpu`) alike: for the full level 4 + 6 + 4, faster in a batch than the
whole state in one vector (see the performance page)."""


ONE_TOP_PACK_WIDTH = 64
"""Most components in one flat vector of a level state in a run of one top: the whole state
in one vector (see `ravel_state`)."""


FORWARD_MODE_PACK_WIDTH = ONE_TOP_PACK_WIDTH
"""Most components in one flat vector of a level state in a run of one top differentiated in
forward mode (`adjoint=diffrax.ForwardMode()`, and the Jacobian of `simulate`'s default
adjoint): the whole state in one vector, as undifferentiated (see `ravel_state`)."""


SHARED_PACK_WIDTH = 4
"""Most components in one flat vector of a member's state in a batch with shared steps
(`run_segment_shared`; see `ravel_state`): SO(3) axis, omega (3 + 3), full position and
velocity, axis, omega (4 + 3 + 3). With the members last (`MEMBER_AXIS`) every component is a
row of the batch, and narrower vectors give XLA:CPU smaller loops over the rows."""


def pack_width_for(*trees, adjoint=None) -> int:
    """A batch's width, `PACK_WIDTH`, where any leaf of `trees` is batched by `jax.vmap` (seen
    at trace time); else `FORWARD_MODE_PACK_WIDTH` with `adjoint=diffrax.ForwardMode()`, else
    `ONE_TOP_PACK_WIDTH`. JAX has no public test for "inside vmap"; where its private
    tracer class is not found, the batch layout is used (only speed depends on the choice). A
    function jitted inside `jax.vmap` is traced unbatched and gets the one-top layout."""
    try:
        from jax._src.interpreters.batching import BatchTracer
    except ImportError:  # pragma: no cover
        return PACK_WIDTH
    leaves = jax.tree_util.tree_leaves(trees)
    if any(isinstance(x, BatchTracer) for x in leaves):
        return PACK_WIDTH
    if isinstance(adjoint, diffrax.ForwardMode):
        return FORWARD_MODE_PACK_WIDTH
    return ONE_TOP_PACK_WIDTH


def ravel_state(y: PyTree, width: int = PACK_WIDTH):
    """A level state as a tuple of flat vectors, with the inverse: the leaves, in order, packed
    whole into vectors of at most `width` components (`PACK_WIDTH`, in a batch: SO(3) axis and
    omega, then frame and spin angle, 6 + 4; full: 4 + 6 + 4; `ONE_TOP_PACK_WIDTH`, for one
    top: one vector).

    diffrax's Runge-Kutta stages combine the state leaf by leaf; with two or three leaves
    instead of the level's five or six, each step runs several times fewer (tiny) operations,
    which on a CPU is what a step of a 10-dimensional system costs. In a batch the leaves are
    not all concatenated into one vector because XLA:CPU runs the stage combinations of a
    batch of some widths much slower than of others (`PACK_WIDTH`).

    A run of one top wants the opposite: with two or more vectors the stage combinations of a
    step are independent chains of operations, and XLA:CPU's thunk executor then runs the step
    on two threads (it runs a program sequentially only if it is a chain or all its buffers
    are at most 512 bytes), which for steps this small costs more than it gains. So one top
    keeps its state in one vector (`ONE_TOP_PACK_WIDTH`), also when differentiated in forward
    mode (each vector then carries a batch of tangents; `FORWARD_MODE_PACK_WIDTH`). A
    vmapped batch keeps `PACK_WIDTH`.
    """
    leaves, treedef = jax.tree_util.tree_flatten(y)
    dtype = jnp.result_type(*leaves)
    shapes = [jnp.shape(x) for x in leaves]
    sizes = [math.prod(shape) for shape in shapes]
    groups, filled = [], width
    for i, size in enumerate(sizes):
        if not groups or filled + size > width:
            groups.append([])
            filled = 0
        groups[-1].append(i)
        filled += size
    flat = tuple(
        jnp.concatenate([jnp.ravel(jnp.asarray(leaves[i], dtype)) for i in group])
        for group in groups
    )

    def unravel(flat):
        out = [None] * len(leaves)
        for group, vector in zip(groups, flat):
            start = 0
            for i in group:
                out[i] = vector[start : start + sizes[i]].reshape(shapes[i])
                start += sizes[i]
        return jax.tree_util.tree_unflatten(treedef, out)

    return flat, unravel


def overflow_safe(norm):
    """`norm` of a scaled error, infinite where it is nan, so that the step is rejected and
    shrunk.

    `diffrax.PIDController` scales the error by `atol + rtol * max(|y0|, |y1|)`. A trial step
    whose stages overflow (a stiff contact pressed far in by too long a step) can end at an
    infinite `y1` with an infinite error: the scaled error is then `inf / inf`, nan, and the
    controller takes nan for its next step size, so that every later step is rejected and the
    run stays at that time until `max_steps` (diffrax replaces a nan `y1` by `y0` in the
    scale, but not an infinite one)."""

    def safe(scaled_error):
        value = norm(scaled_error)
        return jnp.where(jnp.isnan(value), jnp.inf, value)

    return safe


class FlatField(eqx.Module):
    """A level's vector field on its state flattened by `ravel_state` (one or two leaves)."""

    level: AbstractLevel
    unravel: Callable = eqx.field(static=True)
    width: int = eqx.field(static=True, default=PACK_WIDTH)

    def __call__(self, t, y, top):
        return ravel_state(self.level.vector_field(t, self.unravel(y), top), self.width)[0]

    def error_norm(self, scaled_error):
        """The level's norm of the scaled error, infinite where it is nan (`overflow_safe`)."""
        return overflow_safe(self.level.error_norm)(self.unravel(scaled_error))
