import gc
import os

# Under pytest-xdist (the README's test command runs `-n auto`) every worker keeps its own
# persistent compilation cache: JAX writes an entry in place, and a worker could read another's
# entry half written. Set before any test module imports tippejax, which turns the cache on.
_worker = os.environ.get("PYTEST_XDIST_WORKER")
if _worker and not (os.environ.get("TIPPEJAX_COMPILATION_CACHE")
                    or os.environ.get("JAX_COMPILATION_CACHE_DIR")):
    _base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    os.environ["TIPPEJAX_COMPILATION_CACHE"] = os.path.join(_base, "tippejax", f"jax-{_worker}")

import jax  # noqa: E402
import pytest  # noqa: E402

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
