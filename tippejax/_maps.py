"""Outcome maps: where a grid of launches (or of tops) ends, batched and sharded over every
device of every process."""

from __future__ import annotations

import functools
import math
from typing import Literal

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._analysis.potential import effective_potential_d2_closed_form
from ._auto import choose_model
from ._devices import cpu_block, gather, run_in_blocks, shard_over
from ._engine.cpu import CpuProgram
from ._engine.solver_choice import default_solver
from ._invariants import jellet
from ._map_stages import staged_outcomes
from ._models.levels import LEVELS
from ._outcome import INTERMEDIATE, OUTCOMES, classify_end
from ._simulate import MODELS, simulate
from ._solution import RESULTS
from ._state import euler_angles, initial_state
from ._top import TippeTop


class OutcomeMap(eqx.Module):
    r"""Where each launch of a map ended (returned by `outcome_map` and `outcome_map_tops`).

    The map's two axes are named in `axes`: `("theta0", "spin")` for `outcome_map` (grid of
    launch tilt x launch spin for one top), `("A_over_C", "eps_over_R")` for
    `outcome_map_tops` (grid of tops for one launch). Every per-launch field has the grid's
    shape `(len(first axis), len(second axis))`.

    **Fields:**

    - `top`: the top (`outcome_map`) or the base top whose ratios are varied.
    - `theta0`, `spin`, `A_over_C`, `eps_over_R`: the axes' values (1-d) or the fixed value (0-d).
    - `outcome`: index into `OUTCOMES` (int8).
    - `settled`: the final tilt is within `settle_tol` of the state it is classified into.
    - `theta_final`: $\theta$ where the run ended (at `t1`, or where it stopped).
    - `theta_expected`: the tilt of the stable state it is classified into (nan if none).
    - `t_invert`: first upward crossing of $\pi/2$ (nan if none).
    - `t_contact_loss`, `t_final`: time $R_n$ reached 0 (nan if never), time the run ended.
    - `jellet`: $J$ of the launch.
    - `result`: the `RESULTS` code of each run (int8); `om.message()` gives the messages
      (`tj.RESULTS.message(om.result)`, elementwise).
    - `num_steps`: solver steps of each run.
    - `model_index`: index into `models`, the level each launch was simulated with; for the
      staged maps of `model="auto"` the route, e.g. `"full->gyroscopic"` (the levels in the
      order they ran; a `"full"` after `"gyroscopic"` is the full model run again from where
      the run last left it, see `tippejax/_map_stages.py`).
    - `t1`, `rtol`, `atol`, `settle_tol`: the settings.
    """

    top: TippeTop
    axes: tuple[str, str] = eqx.field(static=True)
    theta0: Float[Array, "..."]
    spin: Float[Array, "..."]
    A_over_C: Float[Array, "..."]
    eps_over_R: Float[Array, "..."]
    outcome: Int[Array, "n1 n2"]
    settled: Bool[Array, "n1 n2"]
    theta_final: Float[Array, "n1 n2"]
    theta_expected: Float[Array, "n1 n2"]
    t_invert: Float[Array, "n1 n2"]
    t_contact_loss: Float[Array, "n1 n2"]
    t_final: Float[Array, "n1 n2"]
    jellet: Float[Array, "n1 n2"]
    result: Int[Array, "n1 n2"]
    num_steps: Int[Array, "n1 n2"]
    model_index: Int[Array, "n1 n2"]
    models: tuple[str, ...] = eqx.field(static=True)
    t1: float = eqx.field(static=True)
    rtol: float = eqx.field(static=True)
    atol: float = eqx.field(static=True)
    settle_tol: float = eqx.field(static=True)

    def message(self) -> np.ndarray:
        """The message of each run's `result`, a numpy array of `str` with the grid's shape
        (`"successful"` where the run succeeded). Same as `tj.RESULTS.message(om.result)`."""
        return RESULTS.message(self.result)

    def counts(self) -> dict[str, int]:
        """Number of launches per outcome, and of unsettled ones (key `"unsettled"`)."""
        outcome = np.asarray(self.outcome)
        out = {name: int(np.sum(outcome == k)) for k, name in enumerate(OUTCOMES)}
        ended = outcome <= INTERMEDIATE
        out["unsettled"] = int(np.sum(ended & ~np.asarray(self.settled)))
        return out

    def summary(self) -> str:
        """A few lines: the grid, the levels used, and the counts."""
        n = int(np.asarray(self.outcome).size)
        counts = self.counts()
        lines = [
            f"outcome map over {self.axes[0]} x {self.axes[1]}: {np.shape(self.outcome)} = {n} "
            f"launches, t1 = {self.t1:g} s, rtol = {self.rtol:g}",
            "levels: " + ", ".join(
                f"{name} ({int(np.sum(np.asarray(self.model_index) == k))})"
                for k, name in enumerate(self.models)
            ),
        ]
        lines += [f"  {name:>13}: {counts[name]:7d} ({100 * counts[name] / n:5.1f}%)"
                  for name in (*OUTCOMES, "unsettled")]
        return "\n".join(lines)


def _run_chunk_impl(top_fields, top_static, thetas, spins, t1, options, mesh, block=None):
    """Simulate and classify one sharded chunk of launches (summary outputs only), each
    device its own shard (`shard_over`), on CPU devices in blocks of `block` members
    (`run_in_blocks`, see `simulate_batch`)."""
    def local(top_fields, thetas, spins, t1):
        return run_in_blocks(functools.partial(_classified_runs, top_static, options), block,
                             (top_fields, thetas, spins, t1))

    return shard_over(local, mesh, "launch", (top_fields, thetas, spins, t1),
                      (True, True, True, False))


_run_chunk = eqx.filter_jit(_run_chunk_impl)
_run_chunk_cpu = CpuProgram(_run_chunk_impl)


def _classified_runs(top_static, options, top_fields, thetas, spins, t1):
    model, rtol, atol, solver, max_steps, settle_tol = options

    def one(fields, theta0, spin):
        top = eqx.combine(fields, top_static)
        y0 = initial_state(top, theta0, spin)
        sol = simulate(
            top, y0, t1, model=model, summary=True, throw=False, rtol=rtol, atol=atol,
            solver=solver, max_steps=max_steps,
        )
        J = jellet(top, y0)
        theta_f = sol.theta[0]
        outcome, settled, expected = classify_end(
            top, J, theta_f, sol.result, settle_tol=settle_tol
        )
        return dict(
            outcome=outcome, settled=settled, theta_final=theta_f, theta_expected=expected,
            t_invert=sol.t_invert, t_contact_loss=sol.t_contact_loss, t_final=sol.t_final,
            jellet=J, result=sol.result._value.astype(jnp.int8),
            num_steps=sol.num_steps.astype(jnp.int32),
        )

    field_axes = jax.tree_util.tree_map(lambda x: 0 if x.ndim == 1 else None, top_fields)
    return jax.vmap(one, in_axes=(field_axes, 0, 0))(top_fields, thetas, spins)


def _run_flat(top: TippeTop, thetas, spins, t1, *, batched_top: bool, model, rtol, atol,
              solver, max_steps, settle_tol, chunk_size, devices):
    """Run the flat launches in chunks sharded over `devices`; returns numpy arrays."""
    size = thetas.shape[0]
    n_dev = len(devices)
    chunk = max(1, min(int(chunk_size), size))
    chunk = -(-chunk // n_dev) * n_dev
    cpu = devices[0].platform == "cpu"
    block = cpu_block(chunk // n_dev) if cpu else None
    if block is not None:  # each device's shard in equal blocks (see simulate_batch)
        chunk = -(-chunk // (block * n_dev)) * block * n_dev
    run_chunk = _run_chunk_cpu if cpu else _run_chunk
    mesh = Mesh(np.array(devices), ("launch",))
    sharded = NamedSharding(mesh, PartitionSpec("launch"))
    dtype = jnp.result_type(top.m)
    fields, static = eqx.partition(top, eqx.is_array)
    options = (model, rtol, atol, solver, max_steps, settle_tol)
    t1 = jnp.asarray(t1, dtype)

    def put(values):
        # Each process builds only the shards on its own devices.
        return jax.make_array_from_callback(
            values.shape, sharded, lambda index: np.asarray(values[index], dtype=dtype)
        )

    if not batched_top:
        # Replicated scalars (uncommitted host values are replicated onto every device).
        fields = jax.tree_util.tree_map(lambda x: np.asarray(x, dtype=dtype), fields)
    parts = []
    for start in range(0, size, chunk):
        stop = min(start + chunk, size)
        pad = chunk - (stop - start)

        def padded(x):
            x = x[start:stop]
            return np.concatenate([x, np.repeat(x[-1:], pad, axis=0)]) if pad else x

        th, sp = put(padded(thetas)), put(padded(spins))
        if batched_top:
            chunk_fields = jax.tree_util.tree_map(lambda x: put(padded(x)), fields)
        else:
            chunk_fields = fields
        out = run_chunk(chunk_fields, static, th, sp, t1, options, mesh, block)
        parts.append({k: gather(v)[: stop - start] for k, v in out.items()})
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def _check_common(model, t1, rtol, atol, settle_tol, chunk_size):
    if model not in MODELS:
        raise ValueError(f"outcome_map: unknown model {model!r}; choose one of {MODELS}.")
    if not (isinstance(t1, (int, float, np.number)) and math.isfinite(t1) and t1 > 0):
        raise ValueError(f"outcome_map: t1 must be a positive finite time (s), got {t1!r}.")
    for name, value in (("rtol", rtol), ("atol", atol), ("settle_tol", settle_tol)):
        if not (isinstance(value, (int, float, np.number)) and value > 0):
            raise ValueError(f"outcome_map: {name} must be a positive number, got {value!r}.")
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer)) or chunk_size < 1:
        raise ValueError(f"outcome_map: chunk_size must be a positive integer, got {chunk_size!r}.")


def _check_one_top(where: str, top) -> None:
    if not isinstance(top, TippeTop):
        raise ValueError(f"{where}: top must be a tippejax.TippeTop, got {type(top).__name__}.")
    shapes = {np.shape(x) for x in jax.tree_util.tree_leaves(top)}
    if shapes != {()}:
        raise ValueError(
            f"{where} maps one top, but this TippeTop is a batch (field shapes "
            f"{sorted(shapes)}). Map each top in a loop, use tj.outcome_map_tops for a grid of "
            "A/C x eps/R, or tj.simulate_batch(tops, ...) with sol.outcome for a sweep of tops."
        )


def _axis(name, values, *, low=-np.inf, high=np.inf, what=""):
    values = np.atleast_1d(np.asarray(values, dtype=float))
    if values.ndim != 1 or values.size == 0:
        raise ValueError(f"outcome_map: {name} must be a non-empty 1-d list, got shape {values.shape}.")
    if not np.all(np.isfinite(values)):
        raise ValueError(f"outcome_map: {name} must be finite (got NaN or inf).")
    if np.any(values < low) or np.any(values > high):
        raise ValueError(f"outcome_map: {name} must lie in [{low}, {high}]{what}; got "
                         f"{values.min():g} to {values.max():g}.")
    return values


def _auto_models(top: TippeTop, flat_theta, flat_spin, tolerance) -> tuple[list[str], np.ndarray]:
    """The level `model="auto"` picks for each launch: `choose_model`'s rule, evaluated once
    per class of launches that it cannot tell apart (regime x whether the gyroscopic level
    accepts the launch), since the rule depends on nothing else."""
    if tolerance is None:
        return ["full"], np.zeros(flat_theta.size, int)
    y0s = initial_state(top, jnp.asarray(flat_theta), jnp.asarray(flat_spin))
    J = np.asarray(jax.vmap(lambda y: jellet(top, y))(y0s))
    up = np.asarray(effective_potential_d2_closed_form(top, 0.0, J)) > 0
    down = np.asarray(effective_potential_d2_closed_form(top, np.pi, J)) > 0
    accepts = np.asarray(jax.vmap(lambda y: LEVELS["gyroscopic"].in_chart(top, y))(y0s))
    key = up.astype(int) * 4 + down.astype(int) * 2 + accepts.astype(int)
    models: list[str] = []
    index = np.zeros(flat_theta.size, int)
    for k in np.unique(key):
        members = np.flatnonzero(key == k)
        y_rep = jax.tree_util.tree_map(lambda x: x[members[0]], y0s)
        name = choose_model(top, y_rep, tolerance=tolerance)
        if name not in models:
            models.append(name)
        index[members] = models.index(name)
    return models, index


@eqx.filter_jit
def _classify_all(top, J, theta_final, result, settle_tol):
    """`classify_end` of every launch; `result` holds `RESULTS` codes as integers."""
    item = type(RESULTS.successful)

    def one(j, theta, code):
        code = item(code.astype(RESULTS.successful._value.dtype), RESULTS)
        return classify_end(top, j, theta, code, settle_tol=settle_tol)

    return jax.vmap(one)(J, theta_final, result)


def _staged_map(top: TippeTop, flat_theta, flat_spin, t1, *, rtol, atol, solver, max_steps,
                settle_tol, devices):
    """`outcome_map(model="auto")` with `tolerance=None`: the stages of `_map_stages`.

    **Returns:** `(fields, routes, index)`: the per-launch fields of an `OutcomeMap`, the
    distinct routes (levels in the order they ran) and each launch's index into them."""
    dtype = jnp.result_type(top.m)
    y0 = initial_state(top, jnp.asarray(flat_theta, dtype), jnp.asarray(flat_spin, dtype))
    if solver is None:
        solver, slow_solver = default_solver(top), default_solver(top, slow_flow=True)
    else:
        slow_solver = solver
    run = staged_outcomes(top, y0, t1, rtol=rtol, atol=atol, solver=solver,
                          slow_solver=slow_solver, max_steps=max_steps, devices=devices)
    J = np.asarray(jax.vmap(lambda y: jellet(top, y))(y0))
    theta_final = np.asarray(jax.vmap(lambda y: euler_angles(y)[0])(
        jax.tree_util.tree_map(jnp.asarray, run["state"])))
    outcome, settled, expected = _classify_all(
        top, jnp.asarray(J), jnp.asarray(theta_final), jnp.asarray(run["result"]),
        float(settle_tol))
    fields = dict(
        outcome=np.asarray(outcome), settled=np.asarray(settled), theta_final=theta_final,
        theta_expected=np.asarray(expected), t_invert=run["t_invert"],
        t_contact_loss=run["t_contact_loss"], t_final=run["t_final"], jellet=J,
        result=run["result"].astype(np.int8), num_steps=run["num_steps"].astype(np.int32),
    )
    routes, index = np.unique(run["route"], return_inverse=True)
    return fields, [str(r) for r in routes], index


def outcome_map(
    top: TippeTop,
    theta0: ArrayLike,
    spin: ArrayLike,
    *,
    t1: float,
    model: Literal["full", "so3", "routhian", "gyroscopic", "auto"] = "full",
    tolerance: float | None = None,
    rtol: float = 1e-6,
    atol: float = 1e-9,
    solver: diffrax.AbstractSolver | None = None,
    max_steps: int = 200_000,
    settle_tol: float = 0.1,
    chunk_size: int = 4096,
    devices=None,
) -> OutcomeMap:
    r"""Simulate `top` launched from every pair of `theta0` x `spin` and classify where each ends.

    Each launch is `initial_state(top, theta0, spin)`, run to `t1` in summary mode
    (`simulate(..., summary=True)`: only the state where the run ended is kept, so memory per
    launch does not grow with `t1`) and classified against the analysis level, with codes in
    `OUTCOMES`.

    **Classification.** The Jellet integral $J$ of a launch is exactly conserved, so the
    steady states it can end in are those of the analysis level for that $J$
    (`steady_states`): the vertical states $\theta = 0, \pi$ and up to two intermediate states
    on the branch of eq. (Exist), each stable when $W''(\theta; J) > 0$ (eq. stabilityba).
    Energy decreases along the motion, so a launch that does not leave the table ends near a
    stable one. The outcome of a launch is the stable state of its $J$ nearest to the final
    tilt $\theta(t_1)$:

    - `"upright"` ($\theta = 0$), `"inverted"` ($\theta = \pi$), `"intermediate"` (an
      intermediate state; `theta_expected` holds its tilt);
    - `"contact_lost"`: $R_n$ reached 0 (the model stops there; `docs/notes.md`, "Contact
      loss");
    - `"failed"`: any other failure of the solve (max steps, the $R_n$ singularity, NaN, a
      level that cannot describe the launch), and a $J$ with no stable state.

    `settled` says whether the final tilt is within `settle_tol` of that state: a launch still
    on its way at $t_1$ is classified by the stable state it is nearest to, which in the
    bistable groups (Ib, IIa) need not be the one it will reach. Choose `t1` long enough that
    the map is settled where it matters (`OutcomeMap.counts()` reports the unsettled
    fraction).

    **Scale.** The launches are flattened and run in chunks of `chunk_size` (one compilation
    per level of model); each chunk is one array sharded over every device JAX sees
    (`jax.devices()`); on CPU devices each device's launches run in blocks of at most
    `PER_MEMBER_BLOCK` (128), compiled with tippejax's CPU options, as in `simulate_batch`.
    Under `jax.distributed.initialize` that is every device of every process: each process
    simulates only the launches on its own devices (`jax.make_array_from_callback`), and the
    results are gathered on every process. The same call runs on one CPU, on a GPU, on all
    local devices, or on a cluster; see `examples/distributed_map.py` for the launch command.

    **Arguments:**

    - `top`: one `TippeTop`.
    - `theta0`: launch tilts (rad), 1-d, in $[0, \pi]$; `spin`: launch spins (rad/s), 1-d.
    - `t1`: simulated time (s) of every launch; long enough for the map to settle.
    - `model`: a level of `simulate` (default `"full"`, the only level that sees contact
      loss), or `"auto"`. With `tolerance=None`, `"auto"`
      runs each launch at the cheapest level that gives the full model's outcome: the
      gyroscopic level (slow flow) where it holds and the full model where it does not, each
      in batches of its own (`tippejax/_map_stages.py`). A launch the gyroscopic level does not
      accept runs in the full model in windows until it does; the slow flow runs until
      the slow manifold repels, gyroscopic balance is lost, or the nutation the run carries
      comes near lifting the top off the table; from there the full model runs again from where
      the run last left it, so every contact loss is the full model's own. `om.models` names
      the routes (e.g. `"full->gyroscopic"`: a window of the full model, then the slow flow to
      `t1`) and `om.model_index` each launch's. On the maps of the benchmarks it gives the
      full model's outcome for every launch, with fewer solver steps; it is not the default
      because it is not much faster where it matters (see the outcome maps and performance
      pages): most of the cost left is the full model, for the launches whose nutation (at
      tilts above about 0.3 rad, in the full model a mode that barely decays) keeps them out
      of the slow flow's reach, and for the replays. With a `tolerance` (max error in
      theta(t), rad), each launch runs at the level
      `simulate(..., model="auto", tolerance=tolerance)` would use, in separate batches; the
      levels without translation (`"so3"`, `"routhian"`) do not see the contact loss of fast
      launches that the full model sees (they call those launches "inverted"), and
      `tolerance` bounds the error in theta(t), not this.
    - `rtol`, `atol`: solver tolerances. The defaults are looser than `simulate`'s: a map needs
      the end state, not the path (the performance page shows how many outcomes change
      against rtol 1e-9).
    - `solver`: a diffrax solver (default `default_solver(top)`).
    - `max_steps`: per launch; a launch that needs more is `"failed"`.
    - `settle_tol`: tilt distance (rad) within which a launch counts as `settled`.
    - `chunk_size`: launches per compiled batch (rounded up to a multiple of the device count);
      memory grows with it, not with the grid.
    - `devices`: devices to shard over (default `jax.devices()`: all devices of all processes).

    **Returns:** an `OutcomeMap` with grid shape `(len(theta0), len(spin))`.
    """
    _check_common(model, t1, rtol, atol, settle_tol, chunk_size)
    _check_one_top("outcome_map", top)
    theta0 = _axis("theta0", theta0, low=0.0, high=np.pi, what=" rad")
    spin = _axis("spin", spin)
    grid_theta, grid_spin = np.meshgrid(theta0, spin, indexing="ij")
    flat_theta, flat_spin = grid_theta.ravel(), grid_spin.ravel()
    devices = jax.devices() if devices is None else list(devices)
    shape = grid_theta.shape
    dtype = jnp.result_type(top.m)
    common = dict(
        top=top, axes=("theta0", "spin"), theta0=jnp.asarray(theta0, dtype),
        spin=jnp.asarray(spin, dtype), A_over_C=top.A_over_C, eps_over_R=top.eps_over_R,
        t1=float(t1), rtol=float(rtol), atol=float(atol), settle_tol=float(settle_tol),
    )
    if model == "auto" and tolerance is None:
        out, models, index = _staged_map(
            top, flat_theta, flat_spin, t1, rtol=rtol, atol=atol, solver=solver,
            max_steps=max_steps, settle_tol=settle_tol, devices=devices,
        )
        return OutcomeMap(
            model_index=jnp.asarray(index.reshape(shape), jnp.int8), models=tuple(models),
            **common, **{key: jnp.asarray(v.reshape(shape)) for key, v in out.items()},
        )
    if model == "auto":
        models, index = _auto_models(top, flat_theta, flat_spin, tolerance)
    else:
        models, index = [model], np.zeros(flat_theta.size, int)
    solver = default_solver(top) if solver is None else solver
    out = None
    for k, name in enumerate(models):
        members = np.flatnonzero(index == k)
        part = _run_flat(
            top, flat_theta[members], flat_spin[members], t1, batched_top=False, model=name,
            rtol=rtol, atol=atol, solver=solver, max_steps=max_steps, settle_tol=settle_tol,
            chunk_size=chunk_size, devices=devices,
        )
        if out is None:
            out = {key: np.empty((flat_theta.size,) + v.shape[1:], v.dtype) for key, v in part.items()}
        for key, v in part.items():
            out[key][members] = v
    return OutcomeMap(
        model_index=jnp.asarray(index.reshape(shape), jnp.int8), models=tuple(models),
        **common, **{key: jnp.asarray(v.reshape(shape)) for key, v in out.items()},
    )


def outcome_map_tops(
    top: TippeTop,
    A_over_C: ArrayLike,
    eps_over_R: ArrayLike,
    *,
    theta0: float,
    spin: float,
    t1: float,
    model: Literal["full", "so3", "routhian"] = "full",
    rtol: float = 1e-6,
    atol: float = 1e-9,
    solver: diffrax.AbstractSolver | None = None,
    max_steps: int = 200_000,
    settle_tol: float = 0.1,
    chunk_size: int = 4096,
    devices=None,
) -> OutcomeMap:
    r"""Where one launch ends for a grid of tops in the plane of $(A/C, \epsilon/R)$.

    Every top is `top` with $A = (A/C)\,C$ and $\epsilon = (\epsilon/R)\,R$ (its `m`, `R`, `C`,
    `g`, `mu` kept), launched with `initial_state(top_ij, theta0, spin)`; the outcomes are
    classified as in `outcome_map`, each against the steady states of its own top. The group
    map of the analysis level (`tippejax._plot.group_map`) is the linear theory's prediction
    for the same plane.

    `model` is one level for the whole grid (`"auto"` reads a regime per top and is not offered
    here). The solver is chosen for the base top (`default_solver(top)`): keep `mu` moderate.

    **Returns:** an `OutcomeMap` with axes `("A_over_C", "eps_over_R")` and grid shape
    `(len(A_over_C), len(eps_over_R))`.
    """
    _check_common(model, t1, rtol, atol, settle_tol, chunk_size)
    if model not in ("full", "so3", "routhian"):
        raise ValueError(
            f"outcome_map_tops: model must be 'full', 'so3' or 'routhian', got {model!r}."
        )
    _check_one_top("outcome_map_tops", top)
    a = _axis("A_over_C", A_over_C, low=0.5, high=np.inf, what=" (no rigid body has A/C < 1/2)")
    e = _axis("eps_over_R", eps_over_R, low=0.0, high=1.0, what=" (0 < eps < R)")
    if np.any(e <= 0) or np.any(e >= 1):
        raise ValueError("outcome_map_tops: eps_over_R must lie strictly between 0 and 1.")
    if not (0.0 <= float(theta0) <= math.pi) or not math.isfinite(float(spin)):
        raise ValueError("outcome_map_tops: theta0 must lie in [0, pi] and spin be finite.")
    grid_a, grid_e = np.meshgrid(a, e, indexing="ij")
    size = grid_a.size
    dtype = jnp.result_type(top.m)
    tops = TippeTop(
        m=np.full(size, float(top.m)), R=np.full(size, float(top.R)),
        eps=grid_e.ravel() * float(top.R), A=grid_a.ravel() * float(top.C),
        C=np.full(size, float(top.C)), g=np.full(size, float(top.g)),
        mu=np.full(size, float(top.mu)),
    ).astype(dtype)
    solver = default_solver(top) if solver is None else solver
    devices = jax.devices() if devices is None else list(devices)
    out = _run_flat(
        tops, np.full(size, float(theta0)), np.full(size, float(spin)), t1, batched_top=True,
        model=model, rtol=rtol, atol=atol, solver=solver, max_steps=max_steps,
        settle_tol=settle_tol, chunk_size=chunk_size, devices=devices,
    )
    shape = grid_a.shape
    return OutcomeMap(
        top=top, axes=("A_over_C", "eps_over_R"), theta0=jnp.asarray(theta0, dtype),
        spin=jnp.asarray(spin, dtype), A_over_C=jnp.asarray(a, dtype),
        eps_over_R=jnp.asarray(e, dtype), model_index=jnp.zeros(shape, jnp.int8),
        models=(model,), t1=float(t1), rtol=float(rtol), atol=float(atol),
        settle_tol=float(settle_tol),
        **{key: jnp.asarray(v.reshape(shape)) for key, v in out.items()},
    )


__all__ = ["OUTCOMES", "OutcomeMap", "outcome_map", "outcome_map_tops"]
