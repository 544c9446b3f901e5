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

`TIPPEJAX_COMPILATION_CACHE` may also name a directory, used instead of the default. Programs
that compile in under 0.2 s are not stored unless the user set
`JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS` (JAX's default, 1 s, would leave out the many
small programs a first call also compiles). The cache only saves XLA compilation: tracing the
Python functions again in each process still costs a fraction of a second.
"""

from __future__ import annotations

import os

import jax

_OFF = ("0", "false", "no", "off")
MIN_COMPILE_TIME_SECS = 0.2


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
