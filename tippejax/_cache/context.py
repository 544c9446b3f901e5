"""Where a jitted function is being called, as JAX sees it."""

from __future__ import annotations


def _trace_classes():
    """JAX's private trace context and the trace classes `calling_context` tells apart, or
    None where they are not found (another JAX)."""
    try:
        from jax._src import core
        from jax._src.interpreters.batching import BatchTrace
        from jax._src.interpreters.partial_eval import DynamicJaxprTrace

        core.trace_ctx.trace  # noqa: B018 (present in this JAX)
    except (ImportError, AttributeError):  # pragma: no cover - another jax
        return None
    return core.trace_ctx, BatchTrace, DynamicJaxprTrace


_TRACES = _trace_classes()


def calling_context() -> str:
    """Where a jitted function is being called, as JAX sees it:

    - `"staged"`: inside a program being traced (a caller's `jit`, or a loop's body). The
      call becomes part of that program: JAX refuses compile options on it (even when every
      input is a concrete array), and there is nothing of its own to store.
    - `"vmap"`: under eager `jax.vmap`s only. JAX batches the jitted function and runs the
      batched one as a top-level program, with its compile options.
    - `"eager"`: otherwise (no transformation, or an eager `jax.grad`, `jax.jvp` or
      `jax.jacfwd`, whose derivative rules call with concrete inputs). A call with concrete
      inputs runs as a top-level program.

    Reads JAX's private trace context (`jax._src.core.trace_ctx`); `"staged"` where that is
    not found (another JAX), which costs only the options and the store."""
    if _TRACES is None:  # pragma: no cover - another jax
        return "staged"
    context, batch_trace, staging_trace = _TRACES
    trace, batched = context.trace, True
    while getattr(trace, "parent_trace", None) is not None:  # (the innermost first)
        if isinstance(trace, staging_trace):
            return "staged"
        batched = batched and isinstance(trace, batch_trace)
        trace = trace.parent_trace
    if isinstance(trace, staging_trace):
        return "staged"
    return "vmap" if batched and trace is not context.trace else "eager"
