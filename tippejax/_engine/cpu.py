"""XLA compile options of tippejax's own programs on CPU devices."""

from __future__ import annotations

import equinox as eqx
import jax

CPU_COMPILER_OPTIONS = {"xla_backend_optimization_level": 1, "xla_cpu_use_fusion_emitters": False}
"""XLA compile options of tippejax's own programs on CPU devices.

A batch of tiny ODE systems on XLA:CPU is bound by the hundreds of small fused loops each step
runs, not by arithmetic, and how those loops are compiled matters more than anything in them.
tippejax compiles the programs it calls at the top level (`simulate` outside the user's `jit`
and `grad`, an eager `jax.vmap` of it, `simulate_batch`, `outcome_map`, the fit's batches)
with:

- LLVM optimisation level 1 (see `tippejax._devices.PER_MEMBER_BLOCK`);
- XLA:CPU's element-wise loop emitter instead of its MLIR fusion emitters
  (`xla_cpu_use_fusion_emitters`), which compiles a step's many small loops sooner and to
  faster code.

They are options of one program (`jax.jit`'s `compiler_options`), not process-wide flags: as
`XLA_FLAGS` they would change the user's own programs too, and not always for the better. The
performance page compares both.
"""


def own_compiler_options() -> dict | None:
    """`CPU_COMPILER_OPTIONS` where JAX's default backend is a CPU, else None (XLA's)."""
    return CPU_COMPILER_OPTIONS if jax.default_backend() == "cpu" else None


def compiler_options(backend: str | None = None) -> dict | None:
    r"""The XLA compile options tippejax compiles its own programs with on `backend` (default:
    JAX's default backend), for your own top-level `jax.jit` of code that calls tippejax:

    ```python
    loss_grad = jax.jit(jax.grad(loss), compiler_options=tj.compiler_options())
    ```

    JAX takes compile options only at the top-level `jax.jit`, so a function of yours that
    calls `simulate` (a loss and its gradient) is compiled with XLA's defaults unless you pass
    them. On a CPU they are `CPU_COMPILER_OPTIONS` (LLVM optimisation level 1 and XLA:CPU's
    element-wise loop emitter): they compile a solve's many small loops sooner, and batches of
    solves (your own `jax.jit(jax.vmap(...))` of `simulate`) usually run faster with them. Their
    run-time effect depends on the program (a plain diffrax script in one wide `jax.vmap` can
    run slower with them): measure yours; the performance page compares both. Elsewhere (a
    GPU) None: XLA's defaults, as tippejax's own programs use there. Options of one program,
    not a process-wide flag: the rest of your programs keep XLA's defaults.

    **Returns:** a new dict of options for `jax.jit(..., compiler_options=...)` (or
    `eqx.filter_jit`'s), or None.
    """
    backend = jax.default_backend() if backend is None else backend
    if not isinstance(backend, str):
        raise TypeError(f"backend must be a platform name such as 'cpu' or 'gpu', got {backend!r}.")
    return dict(CPU_COMPILER_OPTIONS) if backend == "cpu" else None


class CpuProgram:
    """`eqx.filter_jit(impl)` compiled with `CPU_COMPILER_OPTIONS`; a top-level call only (JAX
    takes compile options there)."""

    def __init__(self, impl):
        self.impl = impl
        self.jitted = eqx.filter_jit(impl, compiler_options=CPU_COMPILER_OPTIONS)

    def __call__(self, *args, **kwargs):
        return self.jitted(*args, **kwargs)

    def lower(self, *args, **kwargs):
        """The program lowered for these arguments (`eqx.filter_jit`'s `lower`)."""
        return self.jitted.lower(*args, **kwargs)
