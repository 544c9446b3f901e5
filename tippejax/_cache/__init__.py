"""The persistent compilation cache: a new process reuses the XLA programs of earlier ones.

The cache's configuration is in `persistent.py`, the store of traced programs in `stored.py`
and the test of where a call runs in `context.py`.

Importing tippejax points JAX's persistent compilation cache (`jax_compilation_cache_dir`) at a
user cache directory, `$XDG_CACHE_HOME/tippejax/jax` (`~/.cache/tippejax/jax` by default), so
that `simulate`, `grad` and `fit` compile once per machine and version rather than once per
process. It does nothing when:

- the environment variable `TIPPEJAX_COMPILATION_CACHE` is `0` (or `false`, `no`, `off`): the
  one opt-out;
- the user configured a cache already (`JAX_COMPILATION_CACHE_DIR`, or
  `jax.config.update("jax_compilation_cache_dir", ...)` before importing tippejax): theirs is
  kept;
- the directory cannot be created (read-only home): no cache, no error.

`TIPPEJAX_COMPILATION_CACHE` may also name a directory, used instead of the default. Every
program is stored, however quick to compile, unless the user set
`JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS` (JAX's default, 1 s, leaves out the many small
programs a first call also compiles: about 1 s of a warm first `simulate`). The cache saves
XLA compilation only: each process still traces the Python functions again (a few seconds
for a first `simulate`; the gradients suite's first-call mode measures it).

JAX does not store programs with host callbacks, which every `eqx.error_if` is; see
`cacheable` for how the solve is kept free of them. Programs that span several CPU devices (a
batch sharded over the cores) are kept out of the cache: loading them crashed processes
(`guard_multi_device_programs`).

**Traced programs too.** The XLA cache does not spare a new process the tracing of the Python
functions (diffrax's loop, the events, the fit's optimiser), seconds for a first `simulate`
and more for a first `fit`. `cached_call` keeps the traced programs as well: the first call with a
configuration exports the jitted function (`jax.export`) and stores the serialized program
beside the XLA cache (`<cache>-exports`); a later process deserializes it and runs it, compiled
from the XLA cache, without tracing. The entry's key holds everything the trace depended on:
the static options' repr, the arguments' tree, shapes and dtypes, the platform (and whether the
stages are written out, `TIPPEJAX_UNROLL_STAGES`), the versions of
jax, jaxlib, equinox, diffrax, optimistix, lineax and optax, and a hash of tippejax's own
source. Anything unusual falls back to the plain jitted call: traced arguments (under `jit`,
`vmap` or `grad`), a static option whose repr is not stable (one that prints a memory address),
arguments on several devices, the cache off, or any error while exporting or loading (set
`TIPPEJAX_EXPORT_DEBUG=1` to print why a program was not stored). Entries of older versions
are never read again; the directory may be deleted at any time.
"""

from .context import calling_context as calling_context
from .persistent import (  # (turns the cache on when imported)
    CACHE_DIR as CACHE_DIR,
    MIN_COMPILE_TIME_SECS as MIN_COMPILE_TIME_SECS,
    MULTI_DEVICE_GUARD as MULTI_DEVICE_GUARD,
    cacheable as cacheable,
    default_cache_dir as default_cache_dir,
    enable_compilation_cache as enable_compilation_cache,
    guard_multi_device_programs as guard_multi_device_programs,
)
from .stored import (
    cached_call as cached_call,
    compile_ahead as compile_ahead,
    to_device as to_device,
)
