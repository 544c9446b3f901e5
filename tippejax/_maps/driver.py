"""The map driver: a grid of launches run, dense or adaptive, into an `OutcomeMap`."""

from __future__ import annotations

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from .._bucket import bucket
from .._engine.solver_choice import default_solver
from .._models.levels import LEVELS, check_friction
from .._simulate.checks import tolerances_for
from .._top import TippeTop
from .auto import auto_models, staged_map
from .axes import MapAxes, base_top
from .refine import base_indices, refine as refine_map
from .result import OutcomeMap
from .runs import chunk_layout, run_launches


def _default_solver(top: TippeTop, grid: MapAxes, model: str) -> diffrax.AbstractSolver:
    """`default_solver` of the stiffest top of the map (every axis sampled at most 64 times,
    its ends included)."""
    slow = LEVELS[model].slow_flow
    if not grid.top_varies:
        return default_solver(top, slow_flow=slow)
    picks = [base_indices(n, max(1, -(-n // 64))) for n in grid.shape]
    gi, gj = np.meshgrid(*picks, indexing="ij")
    return default_solver(grid.tops(top, gi.ravel(), gj.ravel()), slow_flow=slow)


def _legacy(name, grid: MapAxes, top: TippeTop, dtype):
    if name in grid.names:
        return jnp.asarray(grid.values[grid.names.index(name)], dtype)
    if name in grid.fixed:
        return jnp.asarray(grid.fixed[name], dtype)
    return jnp.asarray(getattr(top, name), dtype)


def _map(
    where: str,
    top: TippeTop,
    grid: MapAxes,
    *,
    t1,
    levels,
    model,
    tolerance,
    rtol,
    atol,
    solver,
    max_steps,
    settle_tol,
    chunk_size,
    devices,
    progress,
) -> OutcomeMap:
    """The map of `grid` (see `outcome_map`)."""
    base = base_top(top, grid)
    devices = jax.devices() if devices is None else list(devices)
    dtype = jnp.result_type(top.m)
    shape = grid.shape
    gi, gj = (
        x.ravel() for x in np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    )
    routes, model_index = [model], np.zeros(gi.size, int)
    launch_only = grid.names == ("theta0", "spin") and set(grid.fixed) <= {"theta0", "spin"}
    if model == "auto":
        if levels:
            raise ValueError(
                f"{where}: refine runs one level of model; give model='full' (or another "
                "level), not 'auto'."
            )
        if not launch_only:
            raise ValueError(
                f"{where}: model='auto' maps theta0 x spin only (the launch's other "
                f"quantities 0, the top's own fields); got the axes {grid.names} and the fixed "
                f"values {sorted(grid.fixed)}. Use model='full'."
            )
        if tolerance is None:
            out, routes, index = staged_map(
                base,
                grid.values[0][gi],
                grid.values[1][gj],
                t1,
                rtol=rtol,
                atol=atol,
                solver=solver,
                max_steps=max_steps,
                settle_tol=settle_tol,
                devices=devices,
            )
            nan = np.full(gi.size, np.nan)
            out = dict(out, contact_margin=nan, theta_max=nan)
            return _result(
                top,
                base,
                grid,
                out,
                routes,
                index,
                t1=t1,
                rtol=rtol,
                atol=atol,
                settle_tol=settle_tol,
                dtype=dtype,
            )
        routes, model_index = auto_models(base, grid.values[0][gi], grid.values[1][gj], tolerance)
    for name in routes:
        check_friction(name, base)
    rtol, atol = tolerances_for(dtype, rtol, atol)
    solvers = {
        name: _default_solver(base, grid, name) if solver is None else solver for name in routes
    }
    if levels:
        # every batched call of an adaptive map in one chunk shape: the base grid's size,
        # padded to its bucket (runs of no length), so that maps of similar sizes share it
        n_base = base_indices(shape[0], 2**levels).size * base_indices(shape[1], 2**levels).size
        chunk, block = chunk_layout(bucket(n_base), chunk_size, devices)
    else:
        chunk, block = chunk_layout(gi.size, chunk_size, devices)

    def evaluate(i, j, hint, model=routes[0], tick=None):
        launches = grid.launches(i, j)
        # cost: the steps of the nearest simulated launches, else the spin (the full model's
        # steps follow the nutation, whose frequency grows with it)
        order = np.abs(launches[:, 1]) if hint is None else hint
        return run_launches(
            grid.tops(base, i, j),
            launches,
            t1,
            batched_top=grid.top_varies,
            model=model,
            rtol=rtol,
            atol=atol,
            solver=solvers[model],
            max_steps=max_steps,
            settle_tol=settle_tol,
            chunk=chunk,
            block=block,
            devices=devices,
            order=order,
            progress=tick,
        )

    bar = tqdm(
        total=levels + 2 if levels else -(-gi.size // chunk),
        disable=not progress,
        desc=f"outcome map {shape[0]} x {shape[1]}",
        unit="level" if levels else "chunk",
    )
    with bar:
        if levels:

            def step(points, split):
                bar.update(1)
                bar.set_postfix(launches=points, split=split)

            refined = refine_map(shape, levels, evaluate, t1=float(t1), progress=step)
            fields = refined.fields
            out = {k: v.ravel() for k, v in fields.items()}
            extra = dict(
                simulated=refined.simulated,
                resolved=refined.resolved,
                refine=levels,
                levels=tuple(refined.history),
                unresolved=tuple(
                    (
                        *(float(v) for v in grid.values[0][[i0, i1]]),
                        *(float(v) for v in grid.values[1][[j0, j1]]),
                        dim,
                    )
                    for i0, i1, j0, j1, dim in refined.stopped
                ),
            )
        else:
            out = None
            for k, name in enumerate(routes):
                members = np.flatnonzero(model_index == k)
                part = evaluate(
                    gi[members], gj[members], None, model=name, tick=lambda n: bar.update(1)
                )
                if out is None:
                    out = {
                        key: np.empty((gi.size,) + v.shape[1:], v.dtype) for key, v in part.items()
                    }
                for key, v in part.items():
                    out[key][members] = v
            extra = {}
    out.pop("decision_margin")
    return _result(
        top,
        base,
        grid,
        out,
        routes,
        model_index,
        t1=t1,
        rtol=rtol,
        atol=atol,
        settle_tol=settle_tol,
        dtype=dtype,
        **extra,
    )


def _result(
    top,
    base,
    grid: MapAxes,
    out,
    models,
    index,
    *,
    t1,
    rtol,
    atol,
    settle_tol,
    dtype,
    simulated=None,
    resolved=None,
    **extra,
) -> OutcomeMap:
    shape = grid.shape
    if simulated is None:
        simulated = resolved = np.ones(shape, bool)
    fields = {key: jnp.asarray(np.reshape(v, shape)) for key, v in out.items()}
    return OutcomeMap(
        top=top,
        axes=grid.names,
        axis_values=tuple(jnp.asarray(v, dtype) for v in grid.values),
        fixed=tuple(sorted(grid.fixed.items())),
        theta0=_legacy("theta0", grid, base, dtype),
        spin=_legacy("spin", grid, base, dtype),
        A_over_C=_legacy("A_over_C", grid, base, dtype),
        eps_over_R=_legacy("eps_over_R", grid, base, dtype),
        model_index=jnp.asarray(np.reshape(index, shape), jnp.int8),
        models=tuple(models),
        simulated=jnp.asarray(simulated),
        resolved=jnp.asarray(resolved),
        t1=float(t1),
        rtol=float(rtol),
        atol=float(atol),
        settle_tol=float(settle_tol),
        **fields,
        **extra,
    )
