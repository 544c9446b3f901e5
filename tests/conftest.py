import gc

import jax
import pytest

jax.config.update("jax_enable_x64", True)


@pytest.fixture
def getkey():
    """A fresh PRNG key per call, deterministic per test."""
    keys = iter(jax.random.split(jax.random.key(5678), 1000))
    return lambda: next(keys)


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_code_between_modules():
    """Drop JAX's in-memory caches of traced and compiled functions after each test module.

    One pytest process compiles a few hundred programs (every model, solver and fit stage);
    kept alive all at once they hold gigabytes, and XLA's compiler crashed (SIGSEGV) late in a
    full run on the 2-core CI machine. Each module jits what it needs once, so nothing is lost."""
    yield
    jax.clear_caches()
    gc.collect()
