"""An explicit Runge-Kutta step written out stage by stage.

diffrax runs the stages of a Runge-Kutta step in a loop (`eqxi.while_loop` over the stage
index): stage $i$ reads row $i$ of the tableau with a dynamic index and forms
$y_i = y_0 + \\sum_{j<s} a_{ij} k_j$ over the whole buffer of $s$ stages, zeros included, and
each stage is one trip of a loop. `UnrolledERK` takes the same tableau and writes the stages
out in Python: the coefficients are constants, the zero ones are skipped, and the step is
straight-line code that the compiler can fuse across stages. The maths is the tableau's: for
stages $i = 1, \\dots, s-1$,

$$k_0 = h f(t_0, y_0),\\qquad y_i = y_0 + \\sum_{j<i} a_{ij} k_j,\\qquad
k_i = h f(t_0 + c_i h, y_i),$$

$y_1 = y_0 + \\sum_j b_j k_j$, error estimate $\\sum_j (b_j - \\hat b_j) k_j$ (diffrax's
`b_error`), dense output from the same $k_j$ with the base solver's interpolation. With a
first-same-as-last tableau (Dopri8, Dopri5, Tsit5) the last stage is $f(t_1, y_1)$ and is kept
as the next step's first stage, as diffrax does.

The results equal the base solver's to rounding (`tests/test_unrolled.py`); what differs is the
program: one copy of the vector field per stage instead of one inside a loop, so it compiles
slower and, on a GPU, runs much faster. On a GPU every trip of the stage loop is a round of
small kernels and, in a batch of few members, a wait for the loop's predicate; written out,
the stages fuse into a few large kernels. On XLA:CPU, under tippejax's CPU options, the same
program runs slower and compiles slower, so tippejax writes the stages out on accelerators
only (`unroll_stages`; the GPU suite on the performance page compares both).

On CPUs it runs the stages in its own loop, `StageLoopERK`: diffrax's loop, but each stage's
$\\sum_j a_{ij} k_j$ a sum over the slices of the stage buffer instead of `jnp.tensordot`,
which under `jax.vmap` XLA:CPU computes through a transposed copy of the whole buffer at
every stage.
"""

from __future__ import annotations

import os
from typing import ClassVar

import diffrax
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "UNROLL_STAGES",
    "AbstractTableauSolver",
    "StageLoopERK",
    "UnrolledERK",
    "own_stage_loop",
    "unroll_stages",
    "unrollable",
]


def _setting() -> str:
    value = os.environ.get("TIPPEJAX_UNROLL_STAGES", "auto").strip().lower()
    if value in ("", "auto"):
        return "auto"
    if value in ("1", "true", "yes", "on"):
        return "on"
    if value in ("0", "false", "no", "off"):
        return "off"
    if value == "diffrax":
        return "diffrax"
    raise ValueError(
        f"TIPPEJAX_UNROLL_STAGES must be 'auto' (stages written out on accelerators only), "
        f"'1' (always), '0' (never: tippejax's stage loop) or 'diffrax' (never: diffrax's "
        f"own stage loop), got {value!r}."
    )


UNROLL_STAGES = _setting()
"""How tippejax runs the stages of an explicit Runge-Kutta solver with a first-same-as-last
tableau: the environment variable `TIPPEJAX_UNROLL_STAGES` at import, `auto` (default:
written out, `UnrolledERK`, where JAX's default backend is not a CPU, else in a loop,
`StageLoopERK`), `1` (always written out), `0` (always `StageLoopERK`, which compiles about
twice as fast as the stages written out) or `diffrax` (diffrax's own stage loop: the same
steps to rounding, slower on a CPU)."""


def unroll_stages() -> bool:
    """Whether tippejax's solves write the stages out here (`UNROLL_STAGES`)."""
    if UNROLL_STAGES == "auto":
        return jax.default_backend() != "cpu"
    return UNROLL_STAGES == "on"


def own_stage_loop() -> bool:
    """Whether tippejax's solves run the stages in `StageLoopERK` here (`UNROLL_STAGES`)."""
    return UNROLL_STAGES != "diffrax" and not unroll_stages()


def _combine(y0, coeffs, ks):
    """$y_0 + \\sum_j c_j k_j$ over the nonzero static coefficients $c_j$."""
    out = y0
    for c, k in zip(coeffs, ks):
        c = float(c)
        if c != 0.0:
            out = jax.tree_util.tree_map(lambda o, x, c=c: o + c * x, out, k)
    return out


def _sum(coeffs, ks, like):
    """$\\sum_j c_j k_j$ over the nonzero static coefficients $c_j$ (zeros shaped as `like`
    when every coefficient is zero)."""
    out = None
    for c, k in zip(coeffs, ks):
        c = float(c)
        if c != 0.0:
            term = jax.tree_util.tree_map(lambda x, c=c: c * x, k)
            out = term if out is None else jax.tree_util.tree_map(jnp.add, out, term)
    return jax.tree_util.tree_map(jnp.zeros_like, like) if out is None else out


def unrollable(solver) -> bool:
    """Whether `UnrolledERK` can run `solver`'s tableau: an explicit Runge-Kutta solver of
    diffrax with one first-same-as-last Butcher tableau (Dopri8, Dopri5, Tsit5, Bosh3...)."""
    tableau = getattr(type(solver), "tableau", None)
    return (
        isinstance(solver, diffrax.AbstractERK)
        and isinstance(tableau, diffrax.ButcherTableau)
        and tableau.fsal
        and tableau.ssal
        and not tableau.implicit
    )


def _refresh_first_stage(terms, t0, y0, args, f0, made_jump):
    """The kept last stage of the previous step as this step's first, evaluated again at
    `(t0, y0)` for the members that jumped (under vmap, `unvmap_any` keeps the others' cheap
    branch)."""
    if made_jump is False:
        return f0
    return jax.lax.cond(
        eqxi.unvmap_any(made_jump),
        lambda: jax.tree_util.tree_map(
            lambda a, b: jnp.where(made_jump, a, b), terms.vf(t0, y0, args), f0
        ),
        lambda: f0,
    )


class AbstractTableauSolver(diffrax.AbstractSolver):
    """What `UnrolledERK` and `StageLoopERK` share: `base`, an explicit Runge-Kutta solver of
    diffrax with one first-same-as-last tableau (`unrollable(base)`), whose order, error order
    and interpolation they keep; their state between steps is the last stage $f(t_1, y_1)$,
    the next step's first. Subclasses write `step`."""

    base: diffrax.AbstractERK
    term_structure: ClassVar = diffrax.AbstractTerm

    def __check_init__(self):
        if not unrollable(self.base):
            raise ValueError(
                f"{type(self).__name__} takes an explicit Runge-Kutta solver of diffrax with "
                "a first-same-as-last Butcher tableau (Dopri8, Dopri5, Tsit5, Bosh3), got "
                f"{type(self.base).__name__}."
            )

    @property
    def interpolation_cls(self):  # pyright: ignore
        return self.base.interpolation_cls

    def order(self, terms):
        return self.base.order(terms)

    def error_order(self, terms):
        return self.base.error_order(terms)

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)

    def init(self, terms, t0, t1, y0, args):
        # the first stage of the first step: f(t0, y0)
        return terms.vf(t0, y0, args)


class UnrolledERK(AbstractTableauSolver):
    """`base`'s step with its stages written out (see the module's docstring). `base`: an
    explicit Runge-Kutta solver of diffrax for which `unrollable(base)` holds."""

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        tableau = type(self.base).tableau
        # after a jump the kept last stage is stale
        f0 = _refresh_first_stage(terms, t0, y0, args, solver_state, made_jump)
        control = terms.contr(t0, t1)
        dt = t1 - t0
        ks = [terms.prod(f0, control)]
        y_stage, f_stage = y0, f0
        for c, a_row in zip(tableau.c, tableau.a_lower):
            y_stage = _combine(y0, a_row, ks)
            t_stage = t1 if c == 1 else t0 + float(c) * dt
            f_stage = terms.vf(t_stage, y_stage, args)
            ks.append(terms.prod(f_stage, control))
        y1 = y_stage  # ssal: the last stage is evaluated at y1
        y_error = _sum(tableau.b_error, ks, y0)
        k = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *ks)
        dense_info = dict(y0=y0, y1=y1, k=k)
        return y1, y_error, dense_info, f_stage, diffrax.RESULTS.successful


class StageLoopERK(AbstractTableauSolver):
    r"""`base`'s step with the stages in a loop, as diffrax runs them, but each stage's
    combination written as a sum over the stage buffer's slices.

    diffrax forms $y_i = y_0 + \sum_j a_{ij} k_j$ with `jnp.tensordot` over the stage axis of
    its buffer of stages. Under `jax.vmap` that axis is the buffer's middle one (members x
    stages x state), and XLA:CPU transposes the whole buffer into a copy before every stage's
    product, the largest single kernel of a batch of tops. Here the stage index is a loop counter as in diffrax, the row
    $a_{i\cdot}$ is read with it, and $y_i = y_0 + \sum_{j} a_{ij} k_j$ is a sum over the $s$
    slices $k_j$ of the buffer (zeros included, as in diffrax), which XLA fuses into one loop
    over the state with no copy. The end of the step is written out with the tableau's
    static coefficients: $y_1$ is the last stage's point (first-same-as-last tableaux), the
    error estimate $\sum_j (b_j - \hat b_j) k_j$ skips the zero coefficients, the dense
    output is the base solver's interpolation of the same buffer. The results equal the base
    solver's to rounding (`tests/test_unrolled.py`). `base`: as for `UnrolledERK`."""

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        tableau = type(self.base).tableau
        stages = len(tableau.c) + 1
        rows = np.zeros((stages - 1, stages))
        for i, row in enumerate(tableau.a_lower):
            rows[i, : len(row)] = row
        f0 = _refresh_first_stage(terms, t0, y0, args, solver_state, made_jump)
        control = terms.contr(t0, t1)
        dt = t1 - t0
        k0 = terms.prod(f0, control)
        ks = jax.tree_util.tree_map(
            lambda k: jnp.zeros((stages,) + k.shape, k.dtype).at[0].set(k), k0
        )

        def stage(carry):
            i, ks, _, _ = carry
            # Reading the buffer whole is safe under autodiff as in diffrax's loop: stage i
            # reads only the slots written before it, each written once.
            # (mapped over `y0`'s structure: inside the loop each leaf of `ks` is a buffer)
            unsafe_ks = jax.tree_util.tree_map(lambda _, x: x[...], y0, ks)

            def point(y, k):
                a = jnp.asarray(rows, k.dtype)[i]
                return y + sum(a[j] * k[j] for j in range(stages))

            y_stage = jax.tree_util.tree_map(point, y0, unsafe_ks)
            c = jnp.asarray(tableau.c, jnp.result_type(t0))[i]
            # t1 itself where c = 1, as diffrax and `UnrolledERK` take it
            t_stage = jnp.where(c == 1, t1, t0 + c * dt)
            f_stage = terms.vf(t_stage, y_stage, args)
            k_stage = terms.prod(f_stage, control)
            ks = jax.tree_util.tree_map(lambda _, kk, k: kk.at[i + 1].set(k), y0, ks, k_stage)
            return i + 1, ks, y_stage, f_stage

        # diffrax's loop (`eqxi.while_loop` with the stage buffer as a buffer): reverse mode
        # through it keeps no copy of the buffer per stage; `kind` as `_prepared_solver` set
        # it for the adjoint ("lax" for forward mode).
        kind = getattr(self.base, "scan_kind", None) or "checkpointed"
        _, ks, y1, f1 = eqxi.while_loop(
            lambda carry: carry[0] < stages - 1,
            stage,
            (jnp.asarray(0), ks, y0, f0),
            max_steps=stages - 1,
            buffers=lambda carry: carry[1],
            kind=kind,
            checkpoints=stages - 1,
            base=stages - 1,
        )
        slices = [jax.tree_util.tree_map(lambda k, j=j: k[j], ks) for j in range(stages)]
        y_error = _sum(tableau.b_error, slices, y0)
        dense_info = dict(y0=y0, y1=y1, k=ks)
        return y1, y_error, dense_info, f1, diffrax.RESULTS.successful
