import gc
import os

# The programs a test compiles itself (a `jax.jit`, `jax.vmap` or `jax.grad` around `simulate`,
# which a user's process compiles with XLA's defaults) are compiled with the options of
# tippejax's own CPU programs (`tippejax._engine.cpu.CPU_COMPILER_OPTIONS`): LLVM level 1 and
# XLA:CPU's element-wise loop emitter. The suite's time is mostly XLA compiling, and these
# flags compile sooner. Compile options change the rounding, not the arithmetic; the suite's
# comparisons of two programs hold at level 1 (level 0 moves some of them past their bounds).
# The tests that start a new process with a device count of their own pass these flags on too
# (`helpers.host_devices_env`). TIPPEJAX_TEST_XLA_DEFAULTS=1 runs the suite with XLA's
# defaults.
TEST_XLA_FLAGS = ("--xla_backend_optimization_level=1", "--xla_cpu_use_fusion_emitters=false")
if os.environ.get("TIPPEJAX_TEST_XLA_DEFAULTS", "0") in ("0", ""):
    _flags = os.environ.get("XLA_FLAGS", "")
    _extra = [f for f in TEST_XLA_FLAGS if f.split("=")[0] not in _flags]
    os.environ["XLA_FLAGS"] = " ".join([_flags, *_extra]).strip()

import jax  # noqa: E402  (after XLA_FLAGS: XLA reads them when its CPU backend starts)
import pytest  # noqa: E402

# Under pytest-xdist (the README's test command runs `-n auto`) the workers share the persistent
# compilation cache, so that a program one worker compiled is loaded by the others. JAX writes
# an entry in place; a worker that reads an entry another is still writing gets a truncated
# compressed stream, which JAX reports as a warning and compiles again (`_cache_read`), and
# tippejax's export cache writes through a temporary file.

jax.config.update("jax_enable_x64", True)


@pytest.fixture
def getkey():
    """A fresh PRNG key per call, deterministic per test."""
    keys = iter(jax.random.split(jax.random.key(5678), 1000))
    return lambda: next(keys)


# Implicit rank promotion (an array of shape (3,) broadcast against one of shape (n, 3)) is an
# error in every test: a batch dimension is added by `vmap` or written out, never guessed.
jax.config.update("jax_numpy_rank_promotion", "raise")


@pytest.fixture(autouse=True)
def _strict_promotion():
    """Every test runs under JAX's strict dtype promotion (`jax.numpy_dtype_promotion`): an
    implicit promotion (a float32 array meeting a float64 one, an int meeting a float) is an
    error, not a silent widening. (A test that starts a process of its own runs that process
    under JAX's defaults.)"""
    with jax.numpy_dtype_promotion("strict"):
        yield


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_code_between_modules():
    """Drop JAX's in-memory caches of traced and compiled functions after each test module.

    One pytest process compiles a few hundred programs (every model, solver and fit stage);
    kept alive all at once they hold gigabytes, and XLA's compiler crashed (SIGSEGV) late in a
    full run on the 2-core CI machine. Each module jits what it needs once, so nothing is lost."""
    yield
    jax.clear_caches()
    gc.collect()


LONGEST_FIRST = (
    "test_fit.py",
    "test_simulate.py",
    "test_shared_steps.py",
    "test_engine.py",
    "test_gyroscopic.py",
    "test_docs.py",
    "test_friction.py",
    "test_maps.py",
    "test_maps_adaptive.py",
    "test_grad.py",
    "test_batch.py",
    "test_errors.py",
    "test_stem.py",
    "test_projection.py",
    "test_unrolled.py",
    "test_cache.py",
    "test_inversion.py",
)
"""The test files that take longest (`--durations=0` of the README's test command, summed per
file, longest first). They are collected first, so that
pytest-xdist, which hands out whole files in collection order (`--dist loadfile`), starts them
first and fills in with the short files: otherwise a long file handed out late keeps one worker
busy while the others idle."""


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    # sorted() is stable: the tests of a file keep their order.
    items[:] = sorted(items, key=lambda item: rank.get(item.path.name, len(rank)))
