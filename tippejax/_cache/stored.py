"""The on-disk store of traced programs (`jax.export`): a new process runs them without tracing."""

from __future__ import annotations

import concurrent.futures
import contextlib
import copyreg
import hashlib
import importlib.metadata
import os
import pathlib
import pickle
import re
import tempfile
import threading

import jax
import numpy as np

from .._engine.unrolled import UNROLL_STAGES, unroll_stages
from .context import calling_context
from .persistent import CACHE_DIR

EXPORT_DIR = None if CACHE_DIR is None else CACHE_DIR.rstrip(os.sep) + "-exports"
"""Where `cached_call` keeps traced programs (None: off, with the persistent cache)."""


_LOADED: dict[str, tuple] = {}  # key -> (jitted call of the exported program, output tree)


_LOCKS: dict[str, threading.Lock] = {}  # key -> held while the program is loaded or traced


_PACKAGES = ("jax", "jaxlib", "equinox", "diffrax", "optimistix", "lineax", "optax")


def _missing():
    import equinox._module._flatten as flatten  # equinox's `MISSING` sentinel

    return flatten.MISSING


def _register_missing() -> bool:
    """Unpickle equinox's `MISSING` marker (in every Module's tree) as the singleton itself,
    so that a pickled output tree unflattens again. False if equinox has no such marker."""
    try:
        import equinox._module._flatten as flatten

        copyreg.pickle(type(flatten.MISSING), lambda _: (_missing, ()))
        return True
    except (ImportError, AttributeError):  # pragma: no cover - other equinox versions
        return False


_PICKLABLE_TREES = _register_missing()


def _versions() -> str:
    parts = []
    for name in _PACKAGES:
        try:
            parts.append(f"{name}={importlib.metadata.version(name)}")
        except importlib.metadata.PackageNotFoundError:  # pragma: no cover
            parts.append(f"{name}=?")
    source = hashlib.sha256()
    root = pathlib.Path(__file__).resolve().parents[1]  # (the package, not this folder)
    for path in sorted(root.rglob("*.py")):
        source.update(str(path.relative_to(root)).encode())
        source.update(path.read_bytes())
    return ";".join(parts) + ";tippejax=" + source.hexdigest()


_VERSIONS: str | None = None


_STATIC_TEXT: dict = {}  # id(option) -> (option, its repr): a loop calls with the same options


def _by_value(x):
    """`x` with its dicts as sorted tuples (hashable where their values are)."""
    if isinstance(x, dict):
        return ("dict", tuple((k, _by_value(v)) for k, v in sorted(x.items())))
    return x


def _static_text(static: dict) -> str | None:
    """The options' repr, or None if it would not be stable; remembered by the options'
    identity (an equinox Module's repr costs milliseconds, and a fit calls its programs
    hundreds of times with the same options)."""
    try:  # options equal by value (a new `Dopri5()` per call) share their text
        ident = tuple((k, type(v).__name__, _by_value(v)) for k, v in sorted(static.items()))
        hash(ident)
    except TypeError:
        ident = tuple((k, id(v)) for k, v in sorted(static.items()))
    hit = _STATIC_TEXT.get(ident)
    if hit is not None:
        return hit[1]
    if any(hasattr(x, "shape") for x in jax.tree_util.tree_leaves(static)):
        text = None  # an array among the options: its repr may be abridged
    else:
        text = repr(sorted(static.items()))
        if " at 0x" in text:  # a function or object printed by address: not stable across runs
            text = None
    if len(_STATIC_TEXT) > 10_000:
        _STATIC_TEXT.clear()
    _STATIC_TEXT[ident] = (dict(static), text)  # (the options kept alive: ids stay unique)
    return text


_KEYS: dict = {}  # the inputs of `_key` -> its value: an eager loop calls with the same ones


def _key(name: str, in_tree, leaves, static: dict, fixed: dict) -> str | None:
    text = _static_text(static)
    if text is None:
        return None
    avals = tuple((x.dtype, x.shape, bool(getattr(x, "weak_type", False))) for x in leaves)
    try:
        flags = (jax.config.jax_enable_x64, jax.default_backend(), unroll_stages())
        ident = (name, text, in_tree, avals, tuple(sorted(fixed.items())), flags)
        hash(ident)
    except TypeError:
        return _key_text(name, in_tree, leaves, static, fixed)
    if ident not in _KEYS:
        if len(_KEYS) > 10_000:
            _KEYS.clear()
        _KEYS[ident] = _key_text(name, in_tree, leaves, static, fixed)
    return _KEYS[ident]


def _key_text(name: str, in_tree, leaves, static: dict, fixed: dict) -> str | None:
    global _VERSIONS
    text = _static_text(static)
    fixed_text = repr(sorted(fixed.items()))
    if text is None or " at 0x" in fixed_text:
        return None
    text = text + fixed_text
    if _VERSIONS is None:
        _VERSIONS = _versions()
    avals = ";".join(
        f"{x.dtype}{x.shape}{'w' if getattr(x, 'weak_type', False) else ''}" for x in leaves
    )
    flags = (
        f"x64={jax.config.jax_enable_x64};platform={jax.default_backend()};"
        f"unroll={unroll_stages()};stages={UNROLL_STAGES}"
    )
    blob = "\n".join([name, text, str(in_tree), avals, flags, _VERSIONS])
    return name + "-" + hashlib.sha256(blob.encode()).hexdigest()[:40]


def _single_device(leaves) -> bool:
    for x in leaves:
        sharding = getattr(x, "sharding", None)
        if sharding is not None and len(sharding.device_set) > 1:
            return False
    return True


def _canonical(x) -> np.ndarray:
    """A host value as a numpy array of JAX's canonical dtype (float32 where x64 is off)."""
    x = np.asarray(x)
    return x.astype(jax.dtypes.canonicalize_dtype(x.dtype), copy=False)


def to_device(x, dtype=None) -> jax.Array:
    """A host value as a device array, in the canonical dtype, without a program:
    `jnp.asarray` of a numpy array compiles a small copy program (`stage`) per shape and
    dtype, each a compilation in a new process (warm cache or not), and a fit makes dozens."""
    x = np.asarray(x, dtype)
    return jax.device_put(x.astype(jax.dtypes.canonicalize_dtype(x.dtype), copy=False))


_WITH_OPTIONS: dict = {}  # (jitted function, options) -> the same function jitted with them


def _plain_call(fn, args, static, compiler_options):
    """`fn(*args, **static)` without the store: with `compiler_options` where the call runs
    as a top-level program (`calling_context`: JAX takes compile options only there), else as
    `fn` is."""
    if not compiler_options or calling_context() == "staged":
        return fn(*args, **static)
    import equinox as eqx

    ident = (fn, tuple(sorted(compiler_options.items())))
    if ident not in _WITH_OPTIONS:
        _WITH_OPTIONS[ident] = eqx.filter_jit(
            fn.__wrapped__, compiler_options=dict(compiler_options)
        )
    return _WITH_OPTIONS[ident](*args, **static)


def _entry(fn, args, static, compiler_options=None):
    """The store's key of the call `fn(*args, **static)`, its array inputs and a function
    that puts inputs back into `args`; None where the store does not apply."""
    leaves, in_tree = jax.tree_util.tree_flatten(args)
    leaves = [_canonical(x) if isinstance(x, (np.ndarray, np.generic)) else x for x in leaves]
    dynamic = [i for i, x in enumerate(leaves) if isinstance(x, (jax.Array, np.ndarray))]
    inputs = [leaves[i] for i in dynamic]
    if (
        EXPORT_DIR is None
        or not _PICKLABLE_TREES
        or any(isinstance(x, jax.core.Tracer) for x in leaves)
        or not _single_device(inputs)
        or calling_context() == "staged"  # (concrete inputs inside a caller's `jit`)
    ):
        return None
    fixed = {i: x for i, x in enumerate(leaves) if i not in set(dynamic)}
    name = getattr(fn, "__name__", None) or getattr(
        getattr(fn, "__wrapped__", None), "__name__", "fn"
    )
    keyed = static if not compiler_options else {**static, "compiler_options": compiler_options}
    key = _key(name.strip("_"), in_tree, inputs, keyed, fixed)
    if key is None:
        return None

    def rebuild(flat_inputs):
        full = list(leaves)
        for i, x in zip(dynamic, flat_inputs):
            full[i] = x
        return jax.tree_util.tree_unflatten(in_tree, full)

    # Committed and uncommitted arrays are different signatures to `jit`, and an exported
    # program is compiled again for each. Inputs that are all uncommitted (a user's arrays
    # and host values, which `jit` puts on the device itself) go in as they are; where some
    # are committed, every input is committed to that device, in one transfer call (each
    # call has a fixed cost).
    committed = [x for x in inputs if getattr(x, "committed", False)]
    loose = [i for i, x in enumerate(inputs) if not getattr(x, "committed", False)]
    if committed and loose:
        device = next(iter(committed[0].devices()))
        inputs = list(inputs)
        for i, x in zip(loose, jax.device_put([inputs[i] for i in loose], device)):
            inputs[i] = x
    return key, inputs, rebuild


def _loaded(key, fn, rebuild, inputs, static, compiler_options=None):
    with _LOCKS.setdefault(key, threading.Lock()):
        if key not in _LOADED:
            _LOADED[key] = _load(key, compiler_options) or _export(
                key, fn, rebuild, inputs, static, compiler_options
            )
        return _LOADED[key]


def cached_call(fn, *args, compiler_options=None, **static):
    """`fn(*args, **static)` for a jitted `fn`, through the on-disk store of traced programs
    (see the module docstring). `args` are pytrees; their arrays (jax or numpy) are the
    program's inputs and their other leaves (Python numbers, strings) are fixed in it, as
    `eqx.filter_jit` does. `static` are the options `fn` takes as static (hashable, with a
    stable repr). `compiler_options`: XLA options (`jax.jit`'s) of the program where this call
    is the top-level one; ignored under a trace (the caller's `jit`, `vmap`, `grad`). Returns
    what `fn` returns."""
    entry = _entry(fn, args, static, compiler_options)
    if entry is None:
        return _plain_call(fn, args, static, compiler_options)
    key, inputs, rebuild = entry
    call, out_tree = _loaded(key, fn, rebuild, inputs, static, compiler_options)
    if call is not None:
        try:
            return jax.tree_util.tree_unflatten(out_tree, call(*inputs))
        except Exception:  # the stored program does not take these arguments: trace instead
            _LOADED[key] = (None, None)
    return _plain_call(fn, args, static, compiler_options)


class _Ahead:
    """A program being compiled on the side (`compile_ahead`): a call waits for it, and falls
    back to the jitted program if the compiled one does not take the arguments."""

    def __init__(self, future, call):
        self.future = future
        self.call = call

    def __call__(self, *inputs):
        try:
            compiled = self.future.result()
            return compiled(*inputs)
        except Exception:  # (then `call` compiles, or loads what the side thread stored)
            return self.call(*inputs)


_EXECUTOR = None


def compile_ahead(fn, *args, compiler_options=None, **static) -> bool:
    """Trace `fn(*args, **static)` as `cached_call` would, and compile it on a side thread
    while the caller goes on (XLA's compiler releases the GIL: on two cores a program that a
    call will need later compiles while the caller traces or compiles another). A later
    `cached_call` with arguments of the same shapes waits for it. Nothing is run. Returns
    whether a compilation was started (not where the store does not apply, or the program
    is loaded already)."""
    global _EXECUTOR
    entry = _entry(fn, args, static, compiler_options)
    if entry is None:
        return False
    key, inputs, rebuild = entry
    call, out_tree = _loaded(key, fn, rebuild, inputs, static, compiler_options)
    if call is None or isinstance(call, _Ahead):
        return False
    lowered = call.lower(*inputs)
    if _EXECUTOR is None:
        _EXECUTOR = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="tippejax-compile")
    _LOADED[key] = (_Ahead(_EXECUTOR.submit(lowered.compile), call), out_tree)
    return True


def _load(key: str, compiler_options=None):
    path = os.path.join(EXPORT_DIR, key)
    try:
        with open(path, "rb") as f:
            blob, tree = pickle.load(f)
        exported = jax.export.deserialize(bytearray(blob))
        return jax.jit(exported.call, compiler_options=compiler_options), pickle.loads(tree)
    except FileNotFoundError:
        return None
    except Exception:  # a damaged or stale entry: drop it and trace again
        with contextlib.suppress(OSError):
            os.remove(path)
        return None


def _kernel(target: str) -> bool:
    """A compiled library kernel (LAPACK, cuSOLVER), not a call back into this process's
    Python (a progress meter, a debug print), which no other process could run."""
    return not any(word in target.lower() for word in ("callback", "python"))


def _export_allowing_this_jaxlib(jitted, leaves):
    """`jax.export.export`, allowing the custom calls (LAPACK kernels such as lineax's QR
    solves use) that jax does not promise to keep compatible across versions: an entry is only
    ever loaded by the same jax and jaxlib (they are in its key)."""
    try:
        return jax.export.export(jitted)(*leaves)
    except ValueError as error:
        if "no compatibility guarantees" not in str(error):
            raise
        targets = sorted(set(re.findall(r"custom_call @([A-Za-z0-9_]+)", str(error))))
        if not targets or not all(map(_kernel, targets)):
            raise
    checks = [jax.export.DisabledSafetyCheck.custom_call(t) for t in targets]
    for _ in range(8):  # jax names a few offending targets at a time
        try:
            return jax.export.export(jitted, disabled_checks=checks)(*leaves)
        except ValueError as error:
            more = set(re.findall(r"custom_call @([A-Za-z0-9_]+)", str(error))) - set(targets)
            if "no compatibility guarantees" not in str(error) or not more:
                raise
            if not all(map(_kernel, more)):
                raise
            targets += sorted(more)
            checks += [jax.export.DisabledSafetyCheck.custom_call(t) for t in sorted(more)]
    raise ValueError("too many custom calls without compatibility guarantees")


def _export(key: str, fn, rebuild, leaves, static, compiler_options=None):
    box = {}

    def flat(*flat_args):
        out = fn(*rebuild(flat_args), **static)
        out_leaves, box["tree"] = jax.tree_util.tree_flatten(out)
        return out_leaves

    flat.__name__ = key.split("-")[0]
    try:
        exported = _export_allowing_this_jaxlib(jax.jit(flat), leaves)
        tree = pickle.dumps(box["tree"])
        pickle.loads(tree).unflatten(range(box["tree"].num_leaves))  # it must come back
        blob = pickle.dumps((bytes(exported.serialize()), tree))
    except Exception as error:
        if os.environ.get("TIPPEJAX_EXPORT_DEBUG"):
            print(f"tippejax: not exported ({key}): {type(error).__name__}: {error}"[:2000])
        return (None, None)  # not exportable (a host callback, an unpicklable tree): plain jit
    with contextlib.suppress(OSError):
        os.makedirs(EXPORT_DIR, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=EXPORT_DIR, prefix=".tmp-")
        with os.fdopen(fd, "wb") as f:
            f.write(blob)
        os.replace(tmp, os.path.join(EXPORT_DIR, key))
    return jax.jit(exported.call, compiler_options=compiler_options), box["tree"]
