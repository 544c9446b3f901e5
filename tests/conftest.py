import gc

import jax
import pytest

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


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_code_between_modules():
    """Drop JAX's in-memory caches of traced and compiled functions after each test module.

    One pytest process compiles a few hundred programs (every model, solver and fit stage);
    kept alive all at once they hold gigabytes, and XLA's compiler crashed (SIGSEGV) late in a
    full run on the 2-core CI machine. Each module jits what it needs once, so nothing is lost."""
    yield
    jax.clear_caches()
    gc.collect()


LONGEST_FIRST = ("test_fit.py", "test_shared_steps.py", "test_unrolled.py", "test_engine.py",
                 "test_maps.py", "test_grad.py", "test_projection.py", "test_cache.py",
                 "test_simulate.py", "test_batch.py", "test_gyroscopic.py", "test_inversion.py")
"""The test files that take longest (a serial run's `--durations` on a 2-core machine, longest
first). They are collected first, so that pytest-xdist, which hands out whole files in
collection order (`--dist loadfile`), starts them first and fills in with the short files:
otherwise a long file handed out late keeps one worker busy while the others idle."""


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    # sorted() is stable: the tests of a file keep their order.
    items[:] = sorted(items, key=lambda item: rank.get(item.path.name, len(rank)))
