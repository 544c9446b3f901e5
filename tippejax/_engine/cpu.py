"""tippejax's own programs on CPU devices: their XLA compile options.

A batch of tiny ODE systems on XLA:CPU is bound by the hundreds of small fused loops each
step runs, not by arithmetic (`benchmarks/RESULTS.md`, peers.py's profile), and how XLA
compiles those loops matters more than anything in the loop. tippejax compiles the programs
it owns, the ones it calls at the top level (`simulate` outside the user's `jit` and `grad`,
an eager `jax.vmap` of it included; `simulate_batch`, `outcome_map` and the inversion map's
batches), with `CPU_COMPILER_OPTIONS`. A user's own `jax.jit` keeps XLA's defaults: these are
options of one program (`jax.jit`'s `compiler_options`), not process-wide flags. (Their batches are
traced in the state layout of any batch, `tippejax._engine.segment.PACK_WIDTH`.)

The largest single kernel of such a batch is not the vector field. `perf record` on one
pinned core running `simulate_batch` (500 SO(3) tops, peers.py's scene, Intel Xeon,
2026-11-28) put about 45% of the samples in one loop: the copy that transposes the stage
buffer (members x 14 stages x 6) before each stage's combination $\\sum_j a_{ij} k_j$, which
diffrax forms with `jnp.tensordot` over the stage axis, under `jax.vmap` the buffer's middle
axis; under these options it is scalar moves with an index division per element. It is
diffrax's loop and the plain script pays it too. Two ways round it were slower: the
combination written as a product and a sum over the stage axis (XLA:CPU hands both to
YNNPACK; the plain script in blocks 1.90 -> 2.65 s per call) and the stages written out
(`UnrolledERK`, 1.7x the plain script in blocks against 1.2-1.3x with the loop, also with
optimisation barriers between the stages). The combination written as a sum of the
buffer's slices, in a stage loop of tippejax's own (`StageLoopERK`, the CPU default),
fuses into one loop with no copy and halves the batch's time
(`tippejax._engine.unrolled`).
"""

from __future__ import annotations

import equinox as eqx
import jax

CPU_COMPILER_OPTIONS = {"xla_backend_optimization_level": 1, "xla_cpu_use_fusion_emitters": False}
"""XLA compile options of tippejax's own programs on CPU devices.

- LLVM optimisation level 1 (see `tippejax._devices.PER_MEMBER_BLOCK`).
- XLA:CPU's element-wise loop emitter instead of its MLIR fusion emitters
  (`xla_cpu_use_fusion_emitters`): it compiles a step's many small fused loops to code that
  runs them faster, and compiles faster. peers.py's scene (1000 SO(3) tops, 20 s), ms per
  top, on the 2-core machine of `benchmarks/RESULTS.md`: `simulate_batch` 2.38 -> 1.76 on 1
  device, 1.16 -> 0.92 on 2 (the plain diffrax script in the same blocks 1.80 -> 1.18 and
  0.95 -> 0.63); the first `simulate` of a new process 3.5-3.9 -> 2.6-2.7 s. As a process-wide
  flag (`XLA_FLAGS`) it would change the user's programs too, and not always for the better:
  the plain script in one `jax.vmap` at XLA's default level ran 2.84 -> 3.68 ms per top.
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
    element-wise loop emitter), which compile a solve's many small loops sooner. On the 2-core
    AMD EPYC of `benchmarks/RESULTS.md` (2026-11-29), the first call of
    `jax.jit(jax.grad(...))` of `t_invert` over an 8 s run in a new process took 8.3 s with
    them against 14.5 s with XLA's defaults (cache off; 9.5 s against 10.7 s with an empty
    cache; `benchmarks/compile_cache.py`), and the compiled gradient of a 20 s run took 0.77x
    (t_invert) and 1.02x (201 saved theta) the default-compiled one's time
    (`benchmarks/gradients.py`). A batch in your own `jax.jit(jax.vmap(...))` of `simulate`
    (1000 tops, 20 s, `benchmarks/user_vmap.py`, 2026-11-29): 0.88-0.90x the time with XLA's
    defaults at the SO(3) level and 0.69-0.73x for the full model, compiled 0.7x sooner. Their
    run-time effect depends on the program (the plain diffrax script in one `jax.vmap` ran
    1.2-1.3x slower with them): measure yours.
    Elsewhere (a GPU) None: XLA's defaults, as tippejax's own programs use there. Options of
    one program, not a process-wide flag: the rest of your programs keep XLA's defaults.

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
