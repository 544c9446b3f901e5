"""The persistent compilation cache: its directory, and the programs kept out of it."""

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


def _spans_cpu_devices(backend, devices) -> bool:
    try:
        return backend.platform == "cpu" and len(devices) > 1
    except Exception:  # pragma: no cover - another jaxlib's objects
        return False


def guard_multi_device_programs() -> bool:
    """Keep XLA:CPU programs that span several devices out of JAX's persistent cache: they
    are neither read from it nor written to it, and compile in every process.

    Loading such a program from the cache crashed some new processes (SIGABRT, no message;
    jax 0.10, 2 host devices, a sharded `simulate_batch`), while the same program compiled
    afresh, one-device programs loaded from the cache and a plain diffrax batch sharded the
    same way never did. The programs of one device (every `simulate`, `grad` and `fit` of one record) are
    still cached. JAX has no public switch per program, so this wraps its private
    `compiler._cache_read` and `_cache_write`; where they are not found (another jax) nothing
    is changed.

    **Returns:** whether the guard is in place.
    """
    try:
        from jax._src import compiler
    except ImportError:  # pragma: no cover
        return False
    read = getattr(compiler, "_cache_read", None)
    write = getattr(compiler, "_cache_write", None)
    if read is None or write is None:  # pragma: no cover - another jax
        return False
    if getattr(read, "_tippejax_guard", False):
        return True

    def guarded_read(
        module_name, cache_key, compile_options, backend, executable_devices, *args, **kwargs
    ):
        if _spans_cpu_devices(backend, executable_devices):
            return None, None
        return read(
            module_name, cache_key, compile_options, backend, executable_devices, *args, **kwargs
        )

    def guarded_write(
        cache_key, compile_time_secs, module_name, backend, executable, *args, **kwargs
    ):
        devices = getattr(executable, "local_devices", lambda: ())()
        if _spans_cpu_devices(backend, devices):
            return None
        return write(
            cache_key, compile_time_secs, module_name, backend, executable, *args, **kwargs
        )

    guarded_read._tippejax_guard = True
    compiler._cache_read, compiler._cache_write = guarded_read, guarded_write
    return True


CACHE_DIR = enable_compilation_cache()
"""The directory this process caches in (None: off, or a directory the user configured)."""


MULTI_DEVICE_GUARD = guard_multi_device_programs()
"""Whether programs over several CPU devices bypass the persistent cache (see
`guard_multi_device_programs`)."""
