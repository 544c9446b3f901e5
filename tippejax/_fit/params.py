r"""Free parameters of a fit: physical values <-> unconstrained coordinates.

Every free parameter $p_i$ is a smooth function of one unconstrained coordinate $u_i$, with
$u = 0$ at the guess, so that the constraints hold at every trial without clipping:

| parameter | map | keeps |
|---|---|---|
| `m, R, g, mu`, `spin` | $p = p_0 e^{u}$ | positivity, the spin's sign |
| `eps` | $\epsilon = R\,\sigma(u + \mathrm{logit}(\epsilon_0/R))$ | $0 < \epsilon < R$ |
| `A` | $A = C\,(\tfrac12 + (A_0/C_0 - \tfrac12) e^{u})$ | $A/C > 1/2$ |
| `C` (A fixed) | $C = 2A\,\sigma(u + \mathrm{logit}(C_0/2A_0))$ | $C < 2A$ |
| `theta0` | $\theta_0 = \pi\,\sigma(u + \mathrm{logit}(\theta_{0,0}/\pi))$ | $0 < \theta_0 < \pi$ |
| `theta_dot` at a pole | $\dot\theta_0 = \dot\theta_{0,0} e^{u}$ | a launch at $\theta_0 = 0$ leaves it |
| other rates, `vx, vy` | $p = p_0 + \max(|p_0|, s)\,u$ | nothing (any sign) |

$\sigma$ is the logistic function. One unit of $u$ is then about a relative change of 100% in
every parameter, which is what the global search and the optimiser's damping assume.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._state import State, euler_angles, euler_rates, spin, state_from_euler
from .._top import TippeTop

TOP_FIELDS = ("m", "R", "eps", "A", "C", "g", "mu")
LAUNCH_FIELDS = ("theta0", "spin", "theta_dot", "phi_dot", "vx", "vy")
FREE_NAMES = TOP_FIELDS + LAUNCH_FIELDS
_U_MAX = 30.0  # |u| bound: sigmoid(30) = 1 - 1e-13 < 1, exp(30) = 1e13
_POLE_SIN = 1e-9  # a guess with sin(theta0) below this is launched at a pole


def _logit(x):
    return jnp.log(x) - jnp.log1p(-x)


class Base(eqx.Module):
    """The guess: every top field and launch quantity, free or not (arrays, maybe batched).

    `state` is the guess's own initial state: when no launch quantity is free it is simulated
    as given (no round trip through Euler angles), so any valid `State` can be fitted.
    """

    top: dict[str, Array]
    launch: dict[str, Array]
    state: State


@eqx.filter_jit
def launch_of(y0: State) -> dict[str, Array]:
    """The launch quantities of a state (Euler angles and rates, spin, position, velocity).
    (One program: op by op, a fit's guess cost a dozen small compilations per new process.)"""
    theta, phi, psi = euler_angles(y0)
    theta_dot, phi_dot, _ = euler_rates(y0)
    return dict(
        theta0=theta, spin=spin(y0), theta_dot=theta_dot, phi_dot=phi_dot, phi=phi, psi=psi,
        vx=y0.velocity[..., 0], vy=y0.velocity[..., 1], x=y0.position[..., 0],
        y=y0.position[..., 1],
    )


def physical(u: Float[Array, " p"], base: Base, free: tuple[str, ...]) -> dict[str, Array]:
    """Physical values of the free parameters for unconstrained `u` (u = 0 is the guess)."""
    t, lau = base.top, base.launch
    # Bounded arguments keep sigmoids below 1 and exponentials finite in float64 (a guard on
    # the unconstrained coordinates, not a clip of the physical values).
    bound = _U_MAX if u.dtype == jnp.float64 else 15.0  # float32: sigmoid(15) < 1 still
    z = dict(zip(free, jnp.clip(u, -bound, bound)))
    out = {}
    for name in ("m", "R", "g", "mu"):
        if name in z:
            out[name] = t[name] * jnp.exp(z[name])
    if "C" in z and "A" not in z:
        out["C"] = 2 * t["A"] * jax.nn.sigmoid(z["C"] + _logit(t["C"] / (2 * t["A"])))
    elif "C" in z:
        out["C"] = t["C"] * jnp.exp(z["C"])
    C = out.get("C", t["C"])
    if "A" in z:
        out["A"] = C * (0.5 + (t["A"] / t["C"] - 0.5) * jnp.exp(z["A"]))
    if "eps" in z:
        R = out.get("R", t["R"])
        out["eps"] = R * jax.nn.sigmoid(z["eps"] + _logit(t["eps"] / t["R"]))
    if "theta0" in z:
        out["theta0"] = jnp.pi * jax.nn.sigmoid(z["theta0"] + _logit(lau["theta0"] / jnp.pi))
    if "spin" in z:
        out["spin"] = lau["spin"] * jnp.exp(z["spin"])
    if "theta_dot" in z:
        at_pole = jnp.sin(lau["theta0"]) < _POLE_SIN
        additive = lau["theta_dot"] + jnp.maximum(jnp.abs(lau["theta_dot"]), 1.0) * z["theta_dot"]
        out["theta_dot"] = jnp.where(at_pole, lau["theta_dot"] * jnp.exp(z["theta_dot"]), additive)
    for name, floor in (("phi_dot", 1.0), ("vx", 0.01), ("vy", 0.01)):
        if name in z:
            out[name] = lau[name] + jnp.maximum(jnp.abs(lau[name]), floor) * z[name]
    # The coordinates u are in the optimiser's precision (float64 when enabled); the physical
    # values in the top's (float32 tops simulate in float32).
    dtype = jnp.result_type(t["m"])
    return {k: jnp.asarray(v, dtype) for k, v in out.items()}


def assemble(values: dict[str, Array], base: Base) -> tuple[TippeTop, State]:
    """The top and initial state with `values` replacing the guess's fields."""
    # The guess is a checked top; trial values are valid by construction (reparametrised), so
    # they replace its fields without TippeTop's runtime checks: a trial that overflows to
    # inf makes a non-finite simulation, which gets the failure residual, instead of raising.
    top = TippeTop(**base.top)
    changed = [k for k in TOP_FIELDS if k in values]
    if changed:
        top = eqx.tree_at(
            lambda tp: [getattr(tp, k) for k in changed], top, [values[k] for k in changed]
        )
    if not any(k in LAUNCH_FIELDS for k in values):
        return top, base.state
    lau = {**base.launch, **{k: v for k, v in values.items() if k in LAUNCH_FIELDS}}
    y0 = state_from_euler(
        lau["theta0"], lau["phi"], lau["psi"], lau["theta_dot"], lau["phi_dot"],
        lau["spin"] - lau["phi_dot"] * jnp.cos(lau["theta0"]),
        position=jnp.stack([lau["x"], lau["y"]], -1),
        velocity=jnp.stack([lau["vx"], lau["vy"]], -1),
    )
    return top, y0


def coordinate_scale(free: tuple[str, ...]) -> dict[str, float]:
    """Half-width in `u` of the global search's box for each free parameter."""
    # log-scaled fields: 0.7 is a factor 2 either way; logits: about the same relative change
    # for small ratios; additive rates: one guess magnitude (or its floor) either way.
    return {name: 0.7 for name in free}


__all__ = [
    "TOP_FIELDS", "LAUNCH_FIELDS", "FREE_NAMES", "Base", "launch_of", "physical", "assemble",
]
