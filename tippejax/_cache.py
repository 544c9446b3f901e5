"""The persistent compilation cache: a new process reuses the XLA programs of earlier ones.

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
XLA compilation only: each process still traces the Python functions again (about 3 s for a
first `simulate` on a loaded 2-core machine, `benchmarks/compile_cache.py`).

JAX does not store programs with host callbacks, which every `eqx.error_if` is; see
`cacheable` for how the solve is kept free of them.
"""

from __future__ import annotations

import contextlib
import os

import jax

_OFF = ("0", "false", "no", "off")
MIN_COMPILE_TIME_SECS = 0.0


def default_cache_dir() -> str:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "tippejax", "jax")


def enable_compilation_cache() -> str | None:
    """Turn the persistent cache on (see the module docstring); returns the directory used."""
    setting = os.environ.get("TIPPEJAX_COMPILATION_CACHE", "1").strip()
    if setting.lower() in _OFF:
        return None
    if jax.config.jax_compilation_cache_dir:  # the user's own choice wins
        return None
    path = setting if setting.lower() not in ("1", "true", "yes", "on", "") else default_cache_dir()
    try:
        os.makedirs(path, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", path)
    if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_TIME_SECS)
    return path


@contextlib.contextmanager
def cacheable():
    """Trace the enclosed jitted calls without equinox's runtime checks, so that the compiled
    program can be stored in the persistent cache.

    JAX does not store a program that holds a host callback, and every `eqx.error_if` is one.
    The checks traced inside tippejax's solves are the libraries' own: diffrax checks that the
    save times are ordered and within [t0, t1], optimistix that a bisection's bracket holds a
    root. tippejax checks the save times itself before the solve (in Python when they are
    concrete), and its root finds are bracketed by construction; failures of the solve are
    reported through `RESULTS`, not through `error_if`. So while a cache directory is set these
    library checks are compiled out of the solve (only of the solve: the checks of the inputs,
    `TippeTop` and `initial_state`, stay). With the cache off (`TIPPEJAX_COMPILATION_CACHE=0`)
    or with `EQX_ON_ERROR` set by the user, nothing changes.
    """
    import equinox._errors as errors

    if not jax.config.jax_compilation_cache_dir or "EQX_ON_ERROR" in os.environ:
        yield
        return
    old = errors.EQX_ON_ERROR
    errors.EQX_ON_ERROR = "off"
    try:
        yield
    finally:
        errors.EQX_ON_ERROR = old


CACHE_DIR = enable_compilation_cache()
"""The directory this process caches in (None: off, or a directory the user configured)."""
