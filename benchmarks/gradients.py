"""gradients: what derivatives through `tj.simulate` cost against the solve (d t_invert and
d sum(theta) / d the top's seven fields), whether they are right, and a new process's first call.

    python benchmarks/gradients.py --cost
"""

from __future__ import annotations

import functools
import os
import tempfile

import _harness as h
import _peers as p
import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

import tippejax as tj

FIELDS = ("m", "R", "eps", "A", "C", "g", "mu")
THROUGH = "reverse through the solve (RecursiveCheckpointAdjoint)"
TS = jnp.linspace(0.0, 20.0, 201)


def run(top, rtol, atol, adjoint, **kw):
    kw.update(rtol=rtol, atol=atol, throw=False, adjoint=adjoint)
    return tj.simulate(top, tj.initial_state(top, 0.1, 150.0), 20.0, **kw)


def t_invert(top, rtol, atol, adjoint=None):
    return run(top, rtol, atol, adjoint, summary=True).t_invert


def sum_theta(top, rtol, atol, adjoint=None):
    return jnp.sum(run(top, rtol, atol, adjoint, saveat=TS).theta)


def as_dict(g) -> dict:
    return {f: float(getattr(g, f)) for f in FIELDS}


def central(value, top, rtol, atol, step=1e-6) -> dict:
    out = {}
    for f in FIELDS:
        x = float(getattr(top, f))
        hh = step * abs(x)
        plus, minus = (
            eqx.tree_at(lambda t: getattr(t, f), top, jnp.asarray(x + d)) for d in (hh, -hh)
        )
        out[f] = (float(value(plus, rtol, atol)) - float(value(minus, rtol, atol))) / (2 * hh)
    return out


def rel(a, b):
    return max(abs(a[f] - b[f]) / max(abs(b[f]), 1e-300) for f in FIELDS)


def cost(args):
    """Each derivative's time against the forward solve of the same quantity (interleaved
    rounds, rtol 1e-8), its compile time, and the agreement of the routes at rtol 1e-12."""
    top, n = tj.default_top(), 1 if args.smoke else (args.rounds or 5)
    r8, a8, r12, a12 = (jnp.asarray(x) for x in (1e-8, 1e-10, 1e-12, 1e-14))
    quantities = {"t_invert (summary)": t_invert, "sum(theta), 201 saves": sum_theta}
    columns, worst = {}, dict(ratio=0.0, compile=0.0, modes=0.0, fd=0.0)
    for name, fn in list(quantities.items())[: 1 if args.smoke else None]:

        def jvp_mu(t, r, a, fn=fn):
            return jax.jvp(
                lambda mu: fn(eqx.tree_at(lambda x: x.mu, t, mu), r, a),
                (t.mu,),
                (jnp.ones_like(t.mu),),
            )[1]

        through = jax.grad(lambda t, r, a, fn=fn: fn(t, r, a, diffrax.RecursiveCheckpointAdjoint()))
        runs = {
            "forward solve": eqx.filter_jit(fn),
            "reverse (jax.grad)": eqx.filter_jit(jax.grad(fn)),
            "forward mode (jax.jacfwd)": eqx.filter_jit(jax.jacfwd(fn)),
            "forward mode, 1 tangent (jax.jvp)": eqx.filter_jit(jvp_mu),
            THROUGH: eqx.filter_jit(through),
        }
        if args.smoke:  # the routes the checks below read
            runs = {k: runs[k] for k in list(runs)[:3] + [THROUGH]}
        timed = h.interleaved({k: functools.partial(f, top, r8, a8) for k, f in runs.items()}, n)
        base = timed["forward solve"][0]
        columns[name] = {
            k: f"{t.wall / base.wall:.2f} / {t.cpu / base.cpu:.2f}, {t.compile:.1f}"
            for k, (t, _) in timed.items()
        }
        for k in ("reverse (jax.grad)", "forward mode (jax.jacfwd)"):
            t = timed[k][0]
            worst["ratio"] = max(worst["ratio"], min(t.wall / base.wall, t.cpu / base.cpu))
            worst["compile"] = max(worst["compile"], t.compile)
        names = ("reverse (jax.grad)", "forward mode (jax.jacfwd)", THROUGH)
        g_rev, g_fwd, g_thr = (as_dict(runs[k](top, r12, a12)) for k in names)
        fd = central(runs["forward solve"], top, r12, a12)
        worst["modes"] = max(worst["modes"], rel(g_rev, g_thr))
        worst["fd"] = max(worst["fd"], rel(g_rev, fd), rel(g_fwd, fd))
    rows = [
        f"{k} | " + " | ".join(c[k] for c in columns.values()) for k in next(iter(columns.values()))
    ]
    targets = [
        f"gradient <= 5x the forward solve (jax.grad, jax.jacfwd) | {worst['ratio']:.1f}x at worst (the better of wall and CPU) | {h.verdict(worst['ratio'] <= 5)}",
        f"gradient compiled in <= 10 s | {worst['compile']:.1f} s at worst | {h.verdict(worst['compile'] <= 10)}",
        f"default adjoint == reverse through the solve | {worst['modes']:.1e} | {h.verdict(worst['modes'] < 1e-6)}",
        f"both modes == central differences | {worst['fd']:.1e} | {h.verdict(worst['fd'] < 1e-4)}",
    ]
    h.write(
        "gradients.py --cost",
        "What a derivative costs against the solve",
        f"""
Timing at rtol 1e-8 ({n} interleaved rounds), correctness at rtol 1e-12; x solve: wall / CPU time against the forward solve.

{h.table("run | " + " | ".join(f"{q}: x solve, compile s" for q in columns), rows)}

{h.table("target | measured | verdict", targets)}

{plain_script(n)}
""",
        args,
    )


def plain_script(n):
    """The same derivatives of the plain diffrax script (`_peers`): the baseline a user has."""

    def solve(prm, r, a, adjoint=diffrax.RecursiveCheckpointAdjoint()):
        kw = dict(saveat=diffrax.SaveAt(t1=True), adjoint=adjoint, max_steps=100_000)
        kw["stepsize_controller"] = diffrax.PIDController(rtol=r, atol=a)
        term, y0 = diffrax.ODETerm(p.so3_field), p.launch(150.0)
        return jnp.sum(
            diffrax.diffeqsolve(term, diffrax.Dopri8(), 0.0, 20.0, None, y0, tuple(prm), **kw).ys[
                -1
            ][:3]
        )

    forward = jax.jacfwd(lambda q, r, a: solve(q, r, a, diffrax.ForwardMode()))
    runs = {
        "forward solve": jax.jit(solve),
        "reverse": jax.jit(jax.grad(solve)),
        "forward mode": jax.jit(forward),
    }
    timed = h.interleaved(
        {k: functools.partial(f, jnp.asarray(p.PARAMS), 1e-8, 1e-10) for k, f in runs.items()}, n
    )
    base = timed["forward solve"][0]
    return (
        "The plain diffrax script, d(sum of the final axis) / d(its seven parameters): "
        + ", ".join(
            f"{k} {t.wall / base.wall:.2f}x ({t.cpu / base.cpu:.2f}x CPU, compile {t.compile:.1f} s)"
            for k, (t, _) in list(timed.items())[1:]
        )
        + "."
    )


FIRST_CALL = r"""
import json, sys, time
t = time.perf_counter()
import jax, numpy as np
import tippejax as tj
t_import, case, top = time.perf_counter() - t, sys.argv[1], tj.default_top()
y0 = tj.initial_state(top, 0.1, 100.0)
block = jax.block_until_ready
if case.startswith("simulate"):
    model = case.partition(":")[2] or "full"
    call = lambda: block(tj.simulate(top, y0, 10.0, model=model).theta)
elif "grad" in case:
    g = lambda top: tj.simulate(top, y0, 8.0, summary=True).t_invert
    gradient = jax.grad(g) if case == "grad" else jax.jit(
        jax.grad(g), compiler_options=tj.compiler_options() if "options" in case else None)
    call = lambda: block(gradient(top))
else:  # fit
    ts = np.linspace(0.0, 6.0, 120)
    obs = np.asarray(tj.simulate(top, tj.initial_state(top, 0.1, 120.0), 6.0, saveat=ts).theta)
    obs = obs + 0.002 * np.random.default_rng(0).normal(size=ts.size)
    guess = top.replace(mu=0.38, eps_over_R=0.24)
    call = lambda: block(tj.fit(guess, tj.initial_state(guess, 0.1, 100.0), ts, obs,
                                free=("mu", "eps", "spin"), strategy="plain", max_steps=5).top.mu)
t = time.perf_counter(); call(); first = time.perf_counter() - t
t = time.perf_counter(); call(); second = time.perf_counter() - t
print(json.dumps(dict(import_s=t_import, first_s=first, second_s=second)))
"""


def first_call(args):
    """The first call in a new process: with the persistent cache off, cold and warm."""
    levels = ["simulate"] + [f"simulate:{m}" for m in ("so3", "routhian", "gyroscopic")] * (
        not args.smoke
    )
    cases = levels + (
        ["grad"] if args.smoke else ["grad", "jit(grad)", "jit(grad), options", "fit"]
    )
    rows, res = [], {}
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    for case in cases:
        with tempfile.TemporaryDirectory() as cache:
            for mode in ("off", "cold", "warm"):
                mode_env = dict(env, TIPPEJAX_COMPILATION_CACHE="0" if mode == "off" else cache)
                r = h.fresh_process(FIRST_CALL, case, env=mode_env)
                res[(case, mode)] = r["first_s"] - r["second_s"]
            rows.append(
                f"{case} | " + " | ".join(f"{res[(case, m)]:.2f}" for m in ("off", "cold", "warm"))
            )
    warm = ", ".join(f"{c.partition(':')[2] or 'full'} {res[(c, 'warm')]:.2f} s" for c in levels)
    fit = f"; the first `fit` {res[('fit', 'warm')]:.2f} s (target < 3 s)" if "fit" in cases else ""
    h.write(
        "gradients.py --first-call",
        "The first call in a new process",
        f"""
The first call less the second (s) in a new process; off: `TIPPEJAX_COMPILATION_CACHE=0`, cold: an empty cache, warm: a second process with it.

{h.table("case | off | cold | warm", rows)}

Warm, per level: {warm} (targets: the first `simulate` < 1 s, <= 2 s per level){fit}.
""",
        args,
    )


MODES = {
    "cost": (cost, "derivatives against the solve; agreement with central differences"),
    "first-call": (first_call, "the first call in a new process, cache off / cold / warm"),
}

if __name__ == "__main__":
    h.run(MODES, h.parse(__doc__, MODES))
