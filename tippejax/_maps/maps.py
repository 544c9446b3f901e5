"""`outcome_map` and `outcome_map_tops`: where a grid of launches (or of tops) ends, dense or
adaptive, batched and sharded over every device of every process."""

from __future__ import annotations

import math
from typing import Literal

import diffrax
import numpy as np
from jaxtyping import ArrayLike

from .._engine.solver_choice import default_solver
from .._outcome import OUTCOMES
from .._top import TippeTop
from .axes import map_axes
from .checks import _check_common, _check_one_top, _check_refine, _ratio_axis
from .driver import _map
from .result import OutcomeMap


def outcome_map(
    top: TippeTop,
    theta0: ArrayLike | None = None,
    spin: ArrayLike | None = None,
    *,
    t1: float,
    axes: tuple[str, str] | None = None,
    refine: int | None = None,
    model: Literal["full", "so3", "routhian", "gyroscopic", "auto"] = "full",
    tolerance: float | None = None,
    rtol: float = 1e-6,
    atol: float = 1e-9,
    solver: diffrax.AbstractSolver | None = None,
    max_steps: int = 200_000,
    settle_tol: float = 0.1,
    chunk_size: int = 4096,
    devices=None,
    progress: bool = False,
    **quantities: ArrayLike,
) -> OutcomeMap:
    r"""Simulate `top` over a grid of two quantities and classify where each launch ends.

    The grid's axes are any two of the launch quantities of `simulate_batch` (`theta0`,
    `spin`, `theta_dot`, `phi_dot`, `phi`, `psi`, `vx`, `vy`: the arguments of
    `initial_state`) and the fields of the top (`m`, `R`, `eps`, `A`, `C`, `g`, `mu`,
    `A_over_C`, `eps_over_R`, as in `TippeTop.replace`, and its friction law's parameters,
    e.g. `slip_scale`, `patch_radius`), given as 1-d lists; every other quantity given is a
    number, the same for every launch (the launch's others 0, the top's its own):

    ```python
    tj.outcome_map(top, theta0=th0s, spin=spins, t1=30.0)             # theta0 x spin
    tj.outcome_map(top, mu=mus, spin=spins, theta0=0.1, t1=30.0)      # spin x mu
    tj.outcome_map(top, theta0=th0s, spin=spins, t1=30.0, refine=3)   # adaptive
    ```

    The axes are the quantities given as lists, in the order above (launch quantities
    first), or `axes=(first, second)`; the result has shape `(len(first), len(second))`.
    Where fewer than two lists are given, `theta0` and `spin` are the axes (a number: an
    axis of length 1). Each axis must be strictly monotone. Each launch is
    `initial_state(top_ij, theta0, spin, theta_dot=..., ...)`, run to `t1` as
    `simulate(..., summary=True, throw=False)` runs it (only the state where the run ended
    is kept: memory per launch does not grow with `t1`) and classified against the analysis
    level, with codes in `OUTCOMES`.

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

    **Adaptive maps** (`refine=k`): the outcome changes only across curves, so most launches
    of a fine map need not be simulated. The map is the same grid, computed from a base grid
    of every $2^k$-th value of each axis (and the last):

    1. the base grid is simulated;
    2. a cell (the rectangle between four simulated launches) is split into four (its edge
       midpoints and centre simulated) where its corners disagree, or where a continuous
       indicator hints at a change inside it: the closest approach to contact loss
       (`contact_margin`) or the final tilt's distance from flipping its classification
       come near zero (`refine.NEAR_ZERO`), the largest tilt reached (`theta_max`) of
       upright launches or the inversion (contact-loss) times of inverted (contact-lost)
       ones spread widely (`TILT_JUMP`, `TIME_JUMP` in `tippejax/_maps/refine.py`);
    3. repeated down to cells one launch wide; a cell kept whole is split after all where a
       finer neighbour finds another outcome on its edge;
    4. the launches inside a cell kept whole take its corners' outcome (`simulated` False).

    Each step is one batched call over every device, as the chunks of a dense map, with
    the launches sorted by the solver steps their neighbours took (`levels` counts them; the
    cost follows the boundaries' length, not the map's area: `share_simulated`). Where the
    number of cells on a boundary grows under refinement faster than a curve's
    (box-counting dimension above `DIMENSION_STOP`, riddled or fractal basins) refinement
    stops in that base cell: its launches take the nearest simulated one's outcome
    (`resolved` False, `unresolved` with the dimension).

    What it cannot see: a feature smaller than the base grid (an island of another outcome,
    a thin tongue) that no corner lands on and that no indicator hints at, e.g. a change of
    outcome that the runs' tilt, inversion time, contact margin and settling do not feel
    before it happens. Choose the base grid (`refine`) fine enough for the smallest region
    that matters, and compare with a dense map of the same ranges at a coarse resolution.
    The benchmarks page (`benchmarks/maps.py`) measures agreement with dense maps.

    **Scale.** The launches are run in chunks of `chunk_size` (one compilation per level of
    model and chunk shape); each chunk is one array sharded over every device JAX sees
    (`jax.devices()`); on CPU devices each device's launches run in blocks of at most
    `PER_MEMBER_BLOCK` (128), compiled with tippejax's CPU options, as in `simulate_batch`.
    Under `jax.distributed.initialize` that is every device of every process: each process
    simulates only the launches on its own devices (`jax.make_array_from_callback`), and the
    results are gathered on every process (the refinement, decided from them, is the same
    on every process). The same call runs on one CPU, on a GPU, on all local devices, or on
    a cluster; see `examples/distributed_map.py` for the launch command.

    **Arguments:**

    - `top`: one `TippeTop`.
    - `theta0`: launch tilt(s) (rad), in $[0, \pi]$; `spin`: launch spin(s) (rad/s): each a
      number or an axis (both needed).
    - `**quantities`: the other axis or fixed values (see above), e.g. `mu=[...]`,
      `theta_dot=0.5`.
    - `t1`: simulated time (s) of every launch; long enough for the map to settle.
    - `axes`: the two axes' names in order (default: see above).
    - `refine`: None (default) or 0 for a dense map; `k` > 0 for an adaptive map from a base
      grid $2^k$ times coarser.
    - `model`: a level of `simulate` (default `"full"`, the only level that sees contact
      loss), or `"auto"` (theta0 x spin maps, not adaptive). With `tolerance=None`, `"auto"`
      runs each launch at the cheapest level that gives the full model's outcome: the
      gyroscopic level (slow flow) where it holds and the full model where it does not, each
      in batches of its own (`tippejax/_maps/stages.py`). A launch the gyroscopic level does not
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
    - `solver`: a diffrax solver (default `default_solver` of the stiffest top of the map).
    - `max_steps`: per launch; a launch that needs more is `"failed"`.
    - `settle_tol`: tilt distance (rad) within which a launch counts as `settled`.
    - `chunk_size`: launches per compiled batch (rounded up to a multiple of the device count);
      memory grows with it, not with the grid.
    - `devices`: devices to shard over (default `jax.devices()`: all devices of all processes).
    - `progress`: show a progress bar (tqdm): per level of an adaptive map, per chunk of a
      dense one.

    **Returns:** an `OutcomeMap` with grid shape `(len(first axis), len(second axis))`.
    """
    _check_common("outcome_map", model, t1, rtol, atol, settle_tol, chunk_size)
    _check_one_top("outcome_map", top)
    levels = _check_refine("outcome_map", refine)
    grid = map_axes("outcome_map", top, dict(theta0=theta0, spin=spin, **quantities), axes)
    return _map(
        "outcome_map",
        top,
        grid,
        t1=t1,
        levels=levels,
        model=model,
        tolerance=tolerance,
        rtol=rtol,
        atol=atol,
        solver=solver,
        max_steps=max_steps,
        settle_tol=settle_tol,
        chunk_size=chunk_size,
        devices=devices,
        progress=progress,
    )


def outcome_map_tops(
    top: TippeTop,
    A_over_C: ArrayLike,
    eps_over_R: ArrayLike,
    *,
    theta0: float,
    spin: float,
    t1: float,
    refine: int | None = None,
    model: Literal["full", "so3", "routhian"] = "full",
    rtol: float = 1e-6,
    atol: float = 1e-9,
    solver: diffrax.AbstractSolver | None = None,
    max_steps: int = 200_000,
    settle_tol: float = 0.1,
    chunk_size: int = 4096,
    devices=None,
    progress: bool = False,
) -> OutcomeMap:
    r"""Where one launch ends for a grid of tops in the plane of $(A/C, \epsilon/R)$.

    Every top is `top` with $A = (A/C)\,C$ and $\epsilon = (\epsilon/R)\,R$ (its `m`, `R`, `C`,
    `g`, `mu` kept), launched with `initial_state(top_ij, theta0, spin)`; the outcomes are
    classified as in `outcome_map`, each against the steady states of its own top. The group
    map of the analysis level (`tippejax._plot.group_map`) is the linear theory's prediction
    for the same plane. The same as `outcome_map(top, A_over_C=..., eps_over_R=...,
    theta0=theta0, spin=spin, t1=t1)` (with `refine` too), but that the solver is chosen for
    the base top (`default_solver(top)`: keep `mu` moderate) and that `theta0` and `spin`
    are numbers: for a map over a launch quantity and a field of the top, use `outcome_map`.

    `model` is one level for the whole grid (`"auto"` reads a regime per top and is not offered
    here).

    **Returns:** an `OutcomeMap` with axes `("A_over_C", "eps_over_R")` and grid shape
    `(len(A_over_C), len(eps_over_R))`.
    """
    where = "outcome_map_tops"
    _check_common(where, model, t1, rtol, atol, settle_tol, chunk_size)
    if model not in ("full", "so3", "routhian"):
        raise ValueError(f"{where}: model must be 'full', 'so3' or 'routhian', got {model!r}.")
    _check_one_top(where, top)
    levels = _check_refine(where, refine)
    for name, value in (("theta0", theta0), ("spin", spin)):
        if np.ndim(value) != 0:
            raise ValueError(
                f"{where} maps tops for one launch: {name} must be a number, got shape "
                f"{np.shape(value)}. For a map over a launch quantity and a field of the top "
                f"use tj.outcome_map(top, {name}=[...], A_over_C=[...], ...)."
            )
    a = _ratio_axis(
        "A_over_C", A_over_C, low=0.5, high=np.inf, what=" (no rigid body has A/C < 1/2)"
    )
    e = _ratio_axis("eps_over_R", eps_over_R, low=0.0, high=1.0, what=" (0 < eps < R)")
    if np.any(e <= 0) or np.any(e >= 1):
        raise ValueError(f"{where}: eps_over_R must lie strictly between 0 and 1.")
    if not (0.0 <= float(theta0) <= math.pi) or not math.isfinite(float(spin)):
        raise ValueError(f"{where}: theta0 must lie in [0, pi] and spin be finite.")
    grid = map_axes(
        where,
        top,
        dict(A_over_C=a, eps_over_R=e, theta0=theta0, spin=spin),
        ("A_over_C", "eps_over_R"),
    )
    return _map(
        where,
        top,
        grid,
        t1=t1,
        levels=levels,
        model=model,
        tolerance=None,
        rtol=rtol,
        atol=atol,
        solver=default_solver(top) if solver is None else solver,
        max_steps=max_steps,
        settle_tol=settle_tol,
        chunk_size=chunk_size,
        devices=devices,
        progress=progress,
    )


__all__ = ["OUTCOMES", "OutcomeMap", "outcome_map", "outcome_map_tops"]
