"""The persistent compilation cache: on by default, one opt-out, the user's own directory kept,
and the solve stored (no host callbacks in it) and loaded by a second process."""

import os
import subprocess
import sys

import pytest

PRINT_DIR = "import jax, tippejax; print(jax.config.jax_compilation_cache_dir)"


def _run(code, **env_changes):
    env = dict(os.environ)
    for key in ("JAX_COMPILATION_CACHE_DIR", "TIPPEJAX_COMPILATION_CACHE", "XDG_CACHE_HOME"):
        env.pop(key, None)
    env.update(env_changes)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout.strip().splitlines()[-1], out.stderr


def test_default_directory_follows_xdg_cache_home(tmp_path):
    got, _ = _run(PRINT_DIR, XDG_CACHE_HOME=str(tmp_path))
    assert got == os.path.join(str(tmp_path), "tippejax", "jax")
    assert os.path.isdir(got)


@pytest.mark.parametrize("value", ["0", "false", "off"])
def test_opt_out(tmp_path, value):
    got, _ = _run(PRINT_DIR, XDG_CACHE_HOME=str(tmp_path), TIPPEJAX_COMPILATION_CACHE=value)
    assert got == "None"
    assert not os.path.exists(os.path.join(str(tmp_path), "tippejax"))


def test_a_directory_the_user_configured_is_kept(tmp_path):
    mine = str(tmp_path / "mine")
    got, _ = _run(PRINT_DIR, JAX_COMPILATION_CACHE_DIR=mine, XDG_CACHE_HOME=str(tmp_path))
    assert got == mine
    assert not os.path.exists(os.path.join(str(tmp_path), "tippejax"))


SIMULATE = """
import logging, jax
logging.basicConfig()
logging.getLogger("jax._src.compiler").setLevel(logging.DEBUG)
import tippejax as tj
top = tj.default_top()
sol = tj.simulate(top, tj.initial_state(top, 0.1, 50.0), 0.2, saveat=[0.0, 0.1, 0.2])
print(float(sol.theta[-1]))
"""


def test_the_solve_is_stored_and_a_second_process_loads_it(tmp_path):
    cache = str(tmp_path / "cache")
    first, log1 = _run(SIMULATE, TIPPEJAX_COMPILATION_CACHE=cache)
    assert "Not writing persistent cache entry for 'jit__run'" not in log1
    assert any(name.startswith("jit__run") for name in os.listdir(cache)), os.listdir(cache)
    second, log2 = _run(SIMULATE, TIPPEJAX_COMPILATION_CACHE=cache)
    assert "cache hit for 'jit__run'" in log2.lower()
    assert "cache hit for 'jit__outcome'" in log2.lower()
    assert first == second  # the loaded program computes the same numbers
