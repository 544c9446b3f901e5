r"""The least-squares problem of a fit: data, settings and residuals.

The residual vector of a trial $p$ stacks up to four parts, each switched on by a weight of the
stage that runs (`Data`):

1. the tilt, $\sqrt{w_k}\,(\theta(t_k; p) - \theta^{obs}_k)$ on the samples of the stage's
   window;
2. the precession angle (if given), $\sqrt{w^\varphi_k}\,\sin\theta^{obs}_k\,
   \mathrm{wrap}(\varphi(t_k; p) - \varphi^{obs}_k)$;
3. the envelope: the kernel-smoothed tilt of the model minus that of the data on a uniform
   grid, $\sqrt{w_e/G}\,(\bar\theta(g_j; p) - \bar\theta^{obs}(g_j))$, the kernel wider than a
   nutation period, so the nutation's phase does not enter;
4. level times: the first times $T_l(p)$ at which the smoothed tilt crosses a ladder of levels,
   $w_l (T_l(p) - T^{obs}_l)/\tau$ with $\tau$ = 0.05 s. A shift of the inversion by 1 s is a
   residual of 1 s, not a plateau, so these are nearly linear in the parameters far from the
   optimum.

A save time at which the trial's simulation has stopped (contact lost, the $R_n$ singularity,
max steps), or that lies after a loss of contact, gets the finite residual `FAILED_RESIDUAL`
($\pi$), so such a trial has a large loss and is rejected, never a NaN.
"""

from __future__ import annotations

import math

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from .._simulate import simulate_tilt
from .params import Base, assemble, physical

NUM_LEVELS = 12
FAILED_RESIDUAL = math.pi
LEVEL_TIME_SCALE = 0.05  # s: level-crossing residuals are divided by this
# Trust region of a fit's coordinates: |u_i| <= 1.6, a factor 5 either way in the log-scaled
# parameters. A guess further off than that from the truth is outside what the global search
# (a factor 2) is built for; the limit keeps the optimisers' trial steps (a Levenberg-Marquardt
# step can jump to mu x 20) away from stiff, costly and meaningless simulations.
U_LIMIT = 1.6


class Config(eqx.Module):
    """Static settings of one fit (hashable: one compilation per configuration)."""

    free: tuple[str, ...]
    model: str
    method: str
    max_steps: int
    sim_max_steps: int
    has_phi: bool
    solver: diffrax.AbstractSolver | None
    learning_rate: float


class Data(eqx.Module):
    """Everything a stage needs that is an array (batched along with the recording)."""

    base: Base
    ts: Float[Array, " N"]
    t0: Float[Array, ""]
    t_end: Float[Array, ""]
    theta_obs: Float[Array, " N"]  # 0 where masked
    weights: Float[Array, " N"]  # 0 where masked or outside the window
    mask: Float[Array, " N"]  # 1 where a sample exists (for the smoothing), whatever the stage
    phi_obs: Float[Array, " N"]
    phi_weights: Float[Array, " N"]
    smoother_bin: Int[Array, " N"]  # the smoother's time bin of each sample (0 for padding)
    smoother_kernel: Float[Array, "G B"]  # Gaussian weights from the bins to the grid
    grid: Float[Array, " G"]
    smooth_obs: Float[Array, " G"]  # the data's smoothed tilt on the grid
    envelope_weight: Float[Array, ""]
    levels: Float[Array, " L"]
    t_levels: Float[Array, " L"]
    level_weight: Float[Array, ""]
    rtol: Float[Array, ""]
    atol: Float[Array, ""]
    slip_floor: Float[Array, ""]  # m/s: the least slip scale of the law simulated (searches)
    tol: Float[Array, ""]  # the optimiser's tolerance in this stage
    pinned: Float[Array, " p"]  # 1 for a coordinate this stage holds where it is, else 0
    steps: Float[Array, ""]  # this optimisation's step budget (at most `Config.max_steps`)


class TiltRun(eqx.Module):
    """What the residuals read of a trial's simulation (`simulate_tilt`)."""

    ts: Float[Array, " N"]
    theta: Float[Array, " N"]
    phi: Float[Array, " N"]
    t_contact_loss: Float[Array, ""]


def simulated(values, data: Data, cfg: Config) -> TiltRun:
    """The trial's simulation at the data's times (theta nan if a value is not finite): the
    run `simulate(..., on_contact_loss="continue")` makes, through `simulate_tilt`, which
    computes only the fields the residuals read."""
    # A trial with a non-finite value (an optimiser step that overflowed) runs the guess
    # instead, and all its samples are marked failed: simulate must not see a NaN state.
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(v)) for v in values.values()]))
    guess = {k: data.base.top[k] if k in data.base.top else data.base.launch[k] for k in values}
    safe = {k: jnp.where(finite, v, guess[k]) for k, v in values.items()}
    top, y0 = assemble(safe, data.base)
    # (a search's law: the slip scale raised to `slip_floor` where the motion converges as it
    # goes to 0; 0 outside the searches, the law as given)
    top = eqx.tree_at(lambda t: t.friction, top, top.friction._with_slip_floor(data.slip_floor))
    saves = jnp.minimum(data.ts, data.t_end)
    t0 = data.t0
    if "t0" in safe:
        # A free launch time: the top is held at its launch state before it (a sample before
        # the launch sees the launch tilt), so the residuals are continuous in t0.
        t0 = jnp.minimum(safe["t0"], data.t_end - 1e-9 * jnp.abs(data.t_end))
        saves = jnp.maximum(saves, t0)
    out = simulate_tilt(
        top,
        y0,
        saves,
        t0=t0,
        t1=data.t_end,
        model=cfg.model,
        rtol=data.rtol,
        atol=data.atol,
        solver=cfg.solver,
        max_steps=cfg.sim_max_steps,
        adjoint=diffrax.ForwardMode(),
    )
    return TiltRun(
        ts=out["ts"],
        theta=jnp.where(finite, out["theta"], jnp.nan),
        phi=out["phi"],
        t_contact_loss=out["t_contact_loss"],
    )


def first_crossings(smooth, grid, levels):
    """Differentiable first time `smooth` (sampled on `grid`) reaches each level."""

    def one(level):
        above = smooth >= level
        k = jnp.maximum(jnp.argmax(above), 1)
        lo, hi = smooth[k - 1], smooth[k]
        frac = jnp.clip((level - lo) / jnp.where(hi > lo, hi - lo, 1.0), 0.0, 1.0)
        t_hit = grid[k - 1] + frac * (grid[k] - grid[k - 1])
        # Never reached: past the end by the missing height, at the mean rate pi per record.
        t_miss = grid[-1] + (level - jnp.max(smooth)) * (grid[-1] - grid[0]) / jnp.pi
        return jnp.where(jnp.any(above), t_hit, t_miss)

    return jax.vmap(one)(levels)


def smoothed(y, mask, bins, kernel):
    """Kernel regression onto the grid through time bins (see `smoothing.smoother`):
    sum_j K_gj sum_{k in j} m_k y_k / sum_j K_gj sum_{k in j} m_k."""
    count = kernel.shape[-1]
    sums = jax.ops.segment_sum(mask * y, bins, num_segments=count)
    weights = jax.ops.segment_sum(mask, bins, num_segments=count)
    return (kernel @ sums) / jnp.maximum(kernel @ weights, 1e-300)


def residuals_of_values(values, data: Data, cfg: Config):
    """The stacked residual vector of a trial (physical values) and its simulation."""
    sol = simulated(values, data, cfg)
    theta = sol.theta
    finite = jnp.isfinite(theta)
    theta_safe = jnp.where(finite, theta, 0.0)
    # Past a contact loss the hard-table model does not hold: those samples get the failure
    # residual. The run itself goes on (on_contact_loss="continue") with the same equations, so
    # the level-crossing times below stay smooth functions of the parameters through the loss.
    lost = sol.ts > sol.t_contact_loss  # False when contact is never lost (nan)
    ok = finite & ~lost
    used = data.weights > 0
    r = jnp.where(used, jnp.where(ok, theta_safe - data.theta_obs, FAILED_RESIDUAL), 0.0)
    parts = [jnp.sqrt(data.weights) * r]
    if cfg.has_phi:
        phi = jnp.where(ok, sol.phi, 0.0)
        dphi = jnp.arctan2(jnp.sin(phi - data.phi_obs), jnp.cos(phi - data.phi_obs))
        used_phi = data.phi_weights > 0
        rphi = jnp.where(used_phi, jnp.where(ok, dphi, FAILED_RESIDUAL), 0.0)
        parts.append(jnp.sqrt(data.phi_weights) * jnp.sin(data.theta_obs) * rphi)
    # Slow observables of the smoothed tilt. Past a contact loss the run goes on with the same
    # equations, so they stay smooth in the parameters across the loss; a sample the run never
    # reached (max steps, the R_n singularity) counts as -pi, below any tilt, never as a value
    # that could mimic the data (pi would look like an inverted top).
    theta_slow = jnp.where(finite, theta_safe, -FAILED_RESIDUAL)
    smooth = smoothed(theta_slow, data.mask, data.smoother_bin, data.smoother_kernel)
    grid_size = data.grid.shape[-1]
    parts.append(jnp.sqrt(data.envelope_weight / grid_size) * (smooth - data.smooth_obs))
    t_cross = first_crossings(smooth, data.grid, data.levels)
    parts.append(data.level_weight * (t_cross - data.t_levels) / LEVEL_TIME_SCALE)
    return jnp.concatenate(parts), sol


def residuals(u, data: Data, cfg: Config):
    r"""The residuals at `u` (see `residuals_and_solution`)."""
    return residuals_and_solution(u, data, cfg)[0]


def residuals_and_solution(u, data: Data, cfg: Config):
    r"""The residuals, and the simulation they came from, at coordinates `u`, with the trust region of `U_LIMIT`: the simulation
    sees `u` clipped to `[-U_LIMIT, U_LIMIT]` and one more residual per coordinate,
    $\sqrt{W}\,(|u_i| - U_{lim})_+$ ($W$ the total weight), pulls a trial back from outside.
    Inside (where every fit ends) the extra residuals are 0 with a 0 Jacobian, so they change
    neither the estimate nor its covariance."""
    # A pinned coordinate enters without its derivative: its Jacobian column is 0, so an
    # optimiser's (damped) step leaves it where it is.
    u = jnp.where(data.pinned > 0, jax.lax.stop_gradient(u), u)
    inside = jnp.clip(u, -U_LIMIT, U_LIMIT)
    r, sol = residuals_of_values(physical(inside, data.base, cfg.free), data, cfg)
    total = jnp.sum(data.weights) + data.envelope_weight + data.level_weight**2 * NUM_LEVELS + 1.0
    excess = jnp.sqrt(total) * jnp.maximum(jnp.abs(u) - U_LIMIT, 0.0)
    excess = jnp.where(jnp.isfinite(u), excess, 0.0)  # a non-finite trial: failed residuals
    return jnp.concatenate([r.astype(u.dtype), excess.astype(u.dtype)]), sol


def value_and_jacobian(u, data, cfg):
    """Residuals and their Jacobian in one forward-mode pass (primal plus p tangents)."""
    value, jac, _ = value_jacobian_solution(u, data, cfg)
    return value, jac


def value_jacobian_solution(u, data, cfg):
    """Residuals, their Jacobian and the primal simulation, in one forward-mode pass: `finish`
    takes the fitted curves from it rather than compiling and running a second solve."""

    def both(v):
        r, sol = residuals_and_solution(v, data, cfg)
        return r, (r, sol)

    jac, (value, sol) = jax.jacfwd(both, has_aux=True)(u)
    return value, jac, sol
