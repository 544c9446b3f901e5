"""`inversion_time`: when a top first turns over, as a differentiable function of the top."""

from __future__ import annotations

from typing import Literal

import diffrax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._custom_types import RealScalarLike
from ._engine.solver_choice import is_traced
from ._engine.watch import EVENT_PIECES
from ._errors import result_error_if
from ._simulate import MODELS, simulate
from ._solution import RESULTS
from ._state import State
from ._top import TippeTop


def inversion_time(
    top: TippeTop,
    y0: State,
    *,
    t1: RealScalarLike,
    model: Literal["full", "so3", "routhian", "gyroscopic", "auto"] = "full",
    t0: RealScalarLike = 0.0,
    rtol: RealScalarLike = 1e-8,
    atol: RealScalarLike = 1e-10,
    solver: diffrax.AbstractSolver | None = None,
    max_steps: int = 1_000_000,
    adjoint: diffrax.AbstractAdjoint | None = None,
    throw: bool = True,
    tolerance: float | None = None,
    event_pieces: int = EVENT_PIECES,
) -> Float[Array, ""]:
    r"""The first upward crossing $t^*$ of $\theta = \pi/2$ after `t0` (nan if none by `t1`).

    $t^*$ is the first root of $a_Z(t) = \cos\theta(t) = 0$ where $\theta$ increases, located
    by a root find on the dense output of the solver step that holds it, so it does not depend
    on any save grid (a nutation that crosses $\pi/2$ and back inside one step is still seen:
    `simulate`'s `event_pieces`). A top launched beyond $\pi/2$ has no crossing unless
    it falls back and rises again.

    **Derivatives.** $t^*$ is differentiable with respect to every field of `top`
    ($m, R, \epsilon, A, C, g, \mu$) and of `y0` (and so, through `initial_state`, with respect
    to the launch tilt and spin). With $p$ any of them, $\theta(t^*(p); p) = \pi/2$ and the
    implicit function theorem give
    $$\frac{dt^*}{dp} = -\frac{\partial\theta/\partial p}{\dot\theta}\Big|_{t = t^*},$$
    where $\partial\theta/\partial p$ is the sensitivity of the trajectory, obtained by
    differentiating the discrete solve (`adjoint`), and the root find is differentiated by
    the same theorem (`optimistix.root_find`). The derivative grows like $1/\dot\theta(t^*)$:
    where the crossing is grazing (a nutation that just touches $\pi/2$), $t^*$ jumps and its
    derivative means little. Where $t^*$ is nan (no crossing) its derivative is returned as
    0, as for `jnp.where`, so that losses that mask the nan members, e.g.
    `jnp.where(jnp.isfinite(t), t, penalty)`, differentiate cleanly.

    **For design, use `model="gyroscopic"`.** With the full (or SO(3), Routhian) model, $t^*$
    as a function of any parameter is a staircase: the crossing is made by the nutation, so
    $t^*$ moves by about one nutation period each time a parameter change makes an earlier or
    later nutation cycle reach $\pi/2$, and between steps it follows that one cycle. Its exact
    gradient is then the slope of one stair, not the trend an optimiser needs. The gyroscopic
    level's $t^*$ is the crossing of the nutation-averaged $\theta$: smooth, and its gradient
    is the trend. Where the slow manifold repels before the crossing (fast spins) the run
    continues in the full model and its $t^*$ is the full model's again
    (`simulate(...).model` says `"gyroscopic->full"`). The full-model gradient remains the right
    tool for the sensitivity of one actual run's crossing (fitting a recorded inversion), not
    for shaping the top.

    **Accuracy.** The derivative is that of the computed $t^*$, so it is as accurate as the
    solve: at the default `rtol` expect agreement with the exact derivative to a few parts in
    $10^5$, and tighten `rtol` (with `atol`) for more (the gradients suite measures it: see
    the performance page).

    **Pure Coulomb friction** (`tj.Coulomb`) has no inversion time of its own: the crossing
    grows about like 1/`slip_scale` as the slip scale goes to 0 (`docs/friction.md`). It is
    returned all the same, with a `UserWarning` (from `simulate`) for a concrete top.

    **Same crossing as `simulate`.** This runs `simulate` in summary mode, which does not carry
    the body vector ($\psi$). `simulate(...).t_invert` with its save grid carries it, so the
    two solves take different steps and their $t^*$ agree to the solve's tolerance, not to
    rounding; `simulate(..., summary=True).t_invert` is the same computation as this one.

    **Failures.** Only the run up to $t^*$ matters: a solve that fails *after* the crossing
    (say a contact loss when the top lands on its stem) still returns $t^*$. A solve that
    fails before any crossing (contact loss, the $R_n$ singularity, `max_steps`, NaN, loss of
    gyroscopic balance, a very stiff top under trace: the `RESULTS` of `simulate`) cannot say
    whether or when the top inverts. With `throw=True` (default) that raises: a `RuntimeError`
    with the `RESULTS` message for concrete arguments, an equinox runtime error under
    `jit`/`vmap` (any failing member raises), also under `jax.grad`, `jax.jacfwd` and their
    `jit` and `vmap` (where errors are turned into values, `EQX_ON_ERROR=nan`, the derivative
    is nan). With `throw=False` it returns nan, the same as
    "no inversion by `t1`"; to tell them apart use
    `tj.simulate(top, y0, t1, summary=True, throw=False).result`. A contact loss always ends
    the run (`on_contact_loss="stop"`): past it the model describes no real top.

    **Arguments:**

    - `top`: one `TippeTop` (use `jax.vmap` for a batch of tops).
    - `y0`: the launch `State` (see `initial_state`).
    - `t1`: the latest time looked at (s); keyword-only.
    - `model`: the level of model, as in `simulate`: `"full"`, `"so3"`, `"routhian"`,
      `"gyroscopic"` (the crossing of the slow flow, nutation averaged out) or `"auto"`
      (with `tolerance`).
    - `t0`: the launch time (s).
    - `rtol`, `atol`: tolerances of the step-size controller (as in `simulate`).
    - `solver`: any diffrax solver with an error estimate (default `default_solver(top)`).
    - `max_steps`: maximum number of solver steps per segment.
    - `adjoint`: how the solve is differentiated, passed to `simulate`: by default from
      its forward-mode Jacobian, for `jax.grad` and `jax.jacfwd`/`jax.jvp` alike (a few
      solves' cost for the seven fields of a top); or a diffrax adjoint (`diffrax.RecursiveCheckpointAdjoint()`: reverse mode through the
      solve's steps; `diffrax.ForwardMode()`: forward mode).
    - `throw`: raise where the solve failed before a crossing (see above).
    - `tolerance`: for `model="auto"`, the largest acceptable error in $\theta(t)$ (rad).
    - `event_pieces`: parts of each step on which the conditions' quintics are checked for a
      crossing and back (see `simulate`).

    **Returns:** $t^*$ (s), a scalar of the top's dtype; nan if no crossing by `t1`.
    """
    if model not in MODELS:
        raise ValueError(f"Unknown model {model!r}; choose one of {MODELS}.")
    if not isinstance(top, TippeTop):
        raise TypeError(f"top must be a tippejax.TippeTop, got {type(top).__name__}.")
    if jnp.shape(top.m) != ():
        raise ValueError(
            f"inversion_time takes one top, but this TippeTop has fields of shape "
            f"{jnp.shape(top.m)}. For a batch use "
            "jax.vmap(lambda top: tj.inversion_time(top, y0, t1=...))(tops)."
        )
    if not isinstance(y0, State):
        raise TypeError(
            f"y0 must be a tippejax.State (see tj.initial_state), got {type(y0).__name__}."
        )
    sol = simulate(
        top,
        y0,
        t1,
        model=model,
        summary=True,
        t0=t0,
        rtol=rtol,
        atol=atol,
        solver=solver,
        max_steps=max_steps,
        adjoint=adjoint,
        throw=False,
        on_contact_loss="stop",
        tolerance=tolerance,
        event_pieces=event_pieces,
    )
    t_invert = sol.t_invert
    if not throw:
        return t_invert
    # A crossing located before a failure stands; a failure with no crossing before it does not.
    failed = (sol.result != RESULTS.successful) & jnp.isnan(t_invert)
    if not is_traced(failed):
        if bool(np.asarray(failed)):
            raise RuntimeError(
                f"tippejax.inversion_time failed before any inversion: {RESULTS[sol.result]} "
                "(pass throw=False to get nan instead)."
            )
        return t_invert
    return result_error_if(t_invert, sol.result, failed)


__all__ = ["inversion_time"]
