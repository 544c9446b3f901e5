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
jax.config.update("jax_log_compiles", True)
import tippejax as tj
top = tj.default_top()
sol = tj.simulate(top, tj.initial_state(top, 0.1, 50.0), 0.2, saveat=[0.0, 0.1, 0.2])
print(repr(float(sol.theta[-1])), int(sol.outcome), str(sol.result == tj.RESULTS.successful))
"""


def test_the_solve_is_stored_and_a_second_process_loads_it(tmp_path):
    cache = str(tmp_path / "cache")
    first, log1 = _run(SIMULATE, TIPPEJAX_COMPILATION_CACHE=cache)
    assert "Not writing persistent cache entry" not in log1
    # the traced program (the solve with its outcome, one program) is kept beside the XLA
    # programs
    exports = os.listdir(cache + "-exports")
    assert [name.split("-")[0] for name in exports] == ["run"], exports
    assert os.listdir(cache)
    # a second process neither traces nor compiles it: it loads it
    second, log2 = _run(SIMULATE, TIPPEJAX_COMPILATION_CACHE=cache)
    traced = [line for line in log2.splitlines() if "Finished tracing" in line]
    assert not any(" run " in line or "_run" in line or "outcome" in line for line in traced), (
        traced
    )
    assert "persistent compilation cache hit" in log2.lower()
    assert first == second  # the loaded program computes the same numbers
    # ... as a process that traces the functions anew, with no cache at all
    third, log3 = _run(SIMULATE, TIPPEJAX_COMPILATION_CACHE="0")
    assert any("_run" in line for line in log3.splitlines() if "Finished tracing" in line)
    assert third == first


@pytest.mark.slow
def test_a_stored_program_that_cannot_be_read_is_traced_again(tmp_path):
    """Slow: a second process, for a fault the store's reader handles."""
    cache = str(tmp_path / "cache")
    first, _ = _run(SIMULATE, TIPPEJAX_COMPILATION_CACHE=cache)
    for name in os.listdir(cache + "-exports"):
        with open(os.path.join(cache + "-exports", name), "wb") as f:
            f.write(b"not a program")
    second, log2 = _run(SIMULATE, TIPPEJAX_COMPILATION_CACHE=cache)
    assert second == first
    traced = [line for line in log2.splitlines() if "Finished tracing" in line]
    assert any("run" in line for line in traced), traced  # traced again, not failed


def test_cached_call_stores_only_what_another_process_could_reuse(tmp_path, monkeypatch):
    """In one process: a call is stored and loaded back with the same result; a traced call
    (under `jit`), and an option printed by its memory address, take the plain path."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import tippejax._cache.stored as cache

    monkeypatch.setattr(cache, "EXPORT_DIR", str(tmp_path))
    monkeypatch.setattr(cache, "_LOADED", {})

    @eqx.filter_jit
    def affine(x, *, scale, shift):
        return {"y": x * scale + shift, "n": jnp.sum(x > 0)}

    x = jnp.array([1.0, -2.0, 3.0])
    out = cache.cached_call(affine, x, scale=2.0, shift=jnp.float64(0.5).item())
    assert jnp.allclose(out["y"], x * 2.0 + 0.5) and int(out["n"]) == 2
    assert len(os.listdir(tmp_path)) == 1
    monkeypatch.setattr(cache, "_LOADED", {})  # as a new process would: read from disk
    again = cache.cached_call(affine, x, scale=2.0, shift=0.5)
    assert jnp.array_equal(again["y"], out["y"]) and int(again["n"]) == 2
    # another option value is another program
    assert jnp.allclose(cache.cached_call(affine, x, scale=3.0, shift=0.5)["y"], 3.0 * x + 0.5)
    assert len(os.listdir(tmp_path)) == 2
    # traced arguments: the plain jitted call, nothing stored
    traced = jax.jit(lambda v: cache.cached_call(affine, v, scale=5.0, shift=0.0)["y"])(x)
    assert jnp.allclose(traced, 5.0 * x)
    assert len(os.listdir(tmp_path)) == 2

    @eqx.filter_jit
    def apply(x, *, op):
        return op(x)

    assert jnp.allclose(cache.cached_call(apply, x, op=lambda v: v + 1.0), x + 1.0)
    assert len(os.listdir(tmp_path)) == 2  # a lambda's repr holds its address: not stored


def test_cached_call_compiles_with_the_callers_options(tmp_path, monkeypatch):
    """`compiler_options` reach XLA on every path of a top-level call (stored, loaded from
    disk, and the plain jitted call where nothing is stored), are part of the entry's key, and
    are left out under a trace, where JAX takes none: XLA rejects an option it does not know,
    so an unknown one raising proves the options were passed."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import tippejax._cache.stored as cache
    from tippejax._engine.cpu import CPU_COMPILER_OPTIONS

    monkeypatch.setattr(cache, "EXPORT_DIR", str(tmp_path))
    monkeypatch.setattr(cache, "_LOADED", {})

    @eqx.filter_jit
    def cube(x, *, shift):
        return x**3 + shift

    x = jnp.array([1.0, -2.0, 3.0])
    plain = cache.cached_call(cube, x, shift=1.0)
    fast = cache.cached_call(cube, x, shift=1.0, compiler_options=CPU_COMPILER_OPTIONS)
    assert jnp.allclose(fast, plain) and len(os.listdir(tmp_path)) == 2  # two entries
    monkeypatch.setattr(cache, "_LOADED", {})  # a new process: loaded from disk
    assert jnp.allclose(
        cache.cached_call(cube, x, shift=1.0, compiler_options=CPU_COMPILER_OPTIONS), plain
    )
    bad = {"not_an_xla_option": 1}
    with pytest.raises(Exception, match="not_an_xla_option"):
        cache.cached_call(cube, x, shift=2.0, compiler_options=bad)  # stored path
    monkeypatch.setattr(cache, "EXPORT_DIR", None)
    with pytest.raises(Exception, match="not_an_xla_option"):
        cache.cached_call(cube, x, shift=3.0, compiler_options=bad)  # plain path
    traced = jax.jit(lambda v: cache.cached_call(cube, v, shift=0.0, compiler_options=bad))(x)
    assert jnp.allclose(traced, x**3)


def test_calling_context_tells_top_level_calls_from_staged_ones():
    """A jitted call runs as a top-level program (compile options allowed) with no
    transformation, under eager `jax.vmap`s (JAX runs the batched program at the top level)
    and in an eager derivative's rules; it is part of a program being traced under a `jit`
    or in a loop's body, with or without a `vmap` inside."""
    import jax
    import jax.numpy as jnp

    from tippejax._cache import calling_context

    seen = {}

    def record(name):
        def f(x):
            seen[name] = calling_context()
            return x

        return f

    record("top")(1.0)
    jax.vmap(record("vmap"))(jnp.ones(2))
    jax.vmap(jax.vmap(record("vmap of vmap")))(jnp.ones((2, 2)))
    jax.grad(record("grad"))(1.0)
    jax.jvp(record("jvp"), (1.0,), (1.0,))
    jax.jit(record("jit"))(1.0)
    jax.jit(jax.vmap(record("jit of vmap")))(jnp.ones(2))
    jax.vmap(jax.jit(record("vmap of jit")))(jnp.ones(2))
    jax.lax.scan(lambda c, x: (record("scan")(c), x), 0.0, jnp.ones(2))
    assert seen == {
        "top": "eager",
        "vmap": "vmap",
        "vmap of vmap": "vmap",
        "grad": "eager",
        "jvp": "eager",
        "jit": "staged",
        "jit of vmap": "staged",
        "vmap of jit": "staged",
        "scan": "staged",
    }


def test_options_reach_an_eager_vmap_and_stay_out_of_a_callers_jit(tmp_path, monkeypatch):
    """Under an eager `jax.vmap` the batched call is a top-level program and gets the
    options (an unknown one raising proves it). Inside a caller's `jit` the call is nested and
    gets none, even when its inputs are concrete arrays closed over by the caller (JAX refuses
    options on a nested `jit`: such a call raised before), and nothing is stored for it."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import tippejax._cache.stored as cache

    monkeypatch.setattr(cache, "EXPORT_DIR", str(tmp_path))
    monkeypatch.setattr(cache, "_LOADED", {})

    @eqx.filter_jit
    def cube(x, *, shift):
        return x**3 + shift

    bad = {"not_an_xla_option": 1}
    x = jnp.array([1.0, -2.0, 3.0])
    with pytest.raises(Exception, match="not_an_xla_option"):
        jax.vmap(lambda v: cache.cached_call(cube, v, shift=1.0, compiler_options=bad))(x)
    batched = jax.jit(
        jax.vmap(lambda v: cache.cached_call(cube, v, shift=1.0, compiler_options=bad))
    )(x)
    assert jnp.allclose(batched, x**3 + 1.0)
    closed_over = jax.jit(lambda: cache.cached_call(cube, x, shift=2.0, compiler_options=bad))()
    assert jnp.allclose(closed_over, x**3 + 2.0)
    assert os.listdir(tmp_path) == []


def test_compile_ahead_compiles_on_the_side_and_the_call_uses_it(tmp_path, monkeypatch):
    """`compile_ahead` stores the traced program and compiles it on a side thread without
    running it; the later call with arguments of the same shapes runs that compiled program
    and gives the plain call's numbers. Other shapes, and a call whose compiled program
    refuses its arguments, still work."""
    import equinox as eqx
    import jax.numpy as jnp

    import tippejax._cache.stored as cache

    monkeypatch.setattr(cache, "EXPORT_DIR", str(tmp_path))
    monkeypatch.setattr(cache, "_LOADED", {})
    runs = []

    @eqx.filter_jit
    def poly(x, *, power):
        return jnp.cumsum(x**power)

    x = jnp.linspace(0.0, 1.0, 7)
    assert cache.compile_ahead(poly, jnp.zeros(7), power=3)
    assert not cache.compile_ahead(poly, jnp.zeros(7), power=3)  # started already
    assert len(os.listdir(tmp_path)) == 1  # traced and stored at once
    (entry,) = cache._LOADED.values()
    ahead = entry[0]
    assert isinstance(ahead, cache._Ahead)
    compiled = ahead.future.result()
    monkeypatch.setattr(
        ahead, "future", type("F", (), {"result": lambda self: runs.append(1) or compiled})()
    )
    out = cache.cached_call(poly, x, power=3)
    assert runs == [1]  # the side thread's program ran
    assert jnp.array_equal(out, jnp.cumsum(x**3))
    # another length is another program, traced as usual
    assert jnp.allclose(cache.cached_call(poly, jnp.ones(5), power=3), jnp.arange(1.0, 6.0))

    def refuses(*inputs):
        raise TypeError("not these arguments")

    monkeypatch.setattr(ahead, "future", type("F", (), {"result": lambda self: refuses})())
    assert jnp.array_equal(cache.cached_call(poly, x, power=3), jnp.cumsum(x**3))


SHARDED = """
import jax, jax.numpy as jnp, numpy as np
import tippejax
from tippejax import _cache
from jax.sharding import Mesh, NamedSharding, PartitionSpec
assert len(jax.devices()) == 2
mesh = Mesh(np.array(jax.devices()), ("batch",))
x = jax.device_put(jnp.arange(8.0), NamedSharding(mesh, PartitionSpec("batch")))
jax.jit(lambda v: jnp.sin(v) * 3.0)(x).block_until_ready()  # over both devices
jax.jit(lambda v: jnp.cos(v) * 5.0)(jnp.arange(8.0)).block_until_ready()  # on one
print(_cache.MULTI_DEVICE_GUARD)
"""


def test_programs_over_several_cpu_devices_bypass_the_cache(tmp_path):
    """Loading a program sharded over host devices from the persistent cache crashed new
    processes (`guard_multi_device_programs`): such programs are neither stored nor read,
    while the program of one device is stored as before."""
    cache = str(tmp_path / "cache")
    env = dict(TIPPEJAX_COMPILATION_CACHE=cache, TIPPEJAX_HOST_DEVICES="2", JAX_PLATFORMS="cpu")
    guard, _ = _run(SHARDED + "import jax; jax.config.update('jax_log_compiles', False)", **env)
    assert guard == "True"
    names = os.listdir(cache)
    assert any("jit__lambda" in name for name in names), names  # the one-device program
    assert sum("jit__lambda" in name for name in names) == 1, names  # ... only
