r"""Free parameters of a fit: physical values <-> unconstrained coordinates.

Every free parameter $p_i$ is a smooth function of one unconstrained coordinate $u_i$, with
$u = 0$ at the guess, so that the constraints hold at every trial without clipping:

| parameter | map | keeps |
|---|---|---|
| `m, R, g`, the law's `mu` and `slip_scale`, `spin` | $p = p_0 e^{u}$ | positivity, the spin's sign |
| `patch_radius` | $\rho = \tfrac{R}{10}\,\sigma(u + \mathrm{logit}(10\rho_0/R))$ | $0 < \rho < R/10$ (`TippeTop`'s rule) |
| `eps` | $\epsilon = R\,\sigma(u + \mathrm{logit}(\epsilon_0/R))$ | $0 < \epsilon < R$ |
| `A` | $A = C\,(\tfrac12 + (A_0/C_0 - \tfrac12) e^{u})$ | $A/C > 1/2$ |
| `C` (A fixed) | $C = 2A\,\sigma(u + \mathrm{logit}(C_0/2A_0))$ | $C < 2A$ |
| `theta0` | $\theta_0 = \pi\,\sigma(u + \mathrm{logit}(\theta_{0,0}/\pi))$ | $0 < \theta_0 < \pi$ |
| `theta_dot` at a pole | $\dot\theta_0 = \dot\theta_{0,0} e^{u}$ | a launch at $\theta_0 = 0$ leaves it |
| other rates, `vx, vy` | $p = p_0 + \max(|p_0|, s)\,u$ | nothing (any sign) |
| `t0` (the launch time) | $t_0 = t_{0,0} + d\,u$, $d = \max(t_1 - t_{0,0}, T/4, \Delta t)$ | nothing: before $t_0$ the top is held at its launch |

$\sigma$ is the logistic function. One unit of $u$ is then about a relative change of 100% in
every parameter, which is what the global search and the optimiser's damping assume. ($t_1$ is
the first observation, $T = 2\pi A/(C|n|)$ the guess's nutation period and $\Delta t$ the median
sample interval: one unit of $u$ moves the launch by its guessed distance to the first frame, or
by a quarter of a nutation period, whichever is longer.)
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._friction.base import AbstractFriction
from .._friction.coulomb_contensou import PATCH_FRACTION
from .._friction.viscous import Viscous
from .._state import State, euler_angles, euler_rates, spin, state_from_euler
from .._top import TippeTop

BODY_FIELDS = ("m", "R", "eps", "A", "C", "g")
"""The top's own fields (`TippeTop`)."""

TOP_FIELDS = BODY_FIELDS + ("mu",)
"""The fields of a top with the viscous law; `mu` is every law's coefficient."""

LAW_FIELDS = ("mu", "patch_radius", "slip_scale")
"""The friction laws' fields a fit can free (each where the top's law has it)."""

LAUNCH_FIELDS = ("theta0", "spin", "theta_dot", "phi_dot", "vx", "vy")

TIME_FIELDS = ("t0",)
"""The launch time: the time of `y0_guess` in the record's clock."""

FREE_NAMES = TOP_FIELDS + LAUNCH_FIELDS
"""The names of free parameters for a top with the viscous law."""

NAMES = BODY_FIELDS + LAW_FIELDS + LAUNCH_FIELDS + TIME_FIELDS
"""Every name `fit(free=...)` knows; which law fields a top has depends on its law."""

FIELD_UNITS = dict(
    m="kg",
    R="m",
    eps="m",
    A="kg m^2",
    C="kg m^2",
    g="m/s^2",
    patch_radius="m",
    slip_scale="m/s",
    theta0="rad",
    spin="rad/s",
    theta_dot="rad/s",
    phi_dot="rad/s",
    vx="m/s",
    vy="m/s",
    t0="s",
)
"""The units of every free name but `mu`, whose units are its law's (`mu_units`)."""
_U_MAX = 30.0  # |u| bound: sigmoid(30) = 1 - 1e-13 < 1, exp(30) = 1e13
_POLE_SIN = 1e-9  # a guess with sin(theta0) below this is launched at a pole


def _logit(x):
    return jnp.log(x) - jnp.log1p(-x)


def law_fields(law: type[AbstractFriction] | AbstractFriction) -> tuple[str, ...]:
    """The array fields of a friction law (class or instance), in their order."""
    cls = law if isinstance(law, type) else type(law)
    return tuple(f.name for f in dataclasses.fields(cls) if not f.metadata.get("static"))


def law_options(law: AbstractFriction) -> tuple[tuple[str, object], ...]:
    """The static fields of a friction law (e.g. `pressure`), as `(name, value)` pairs."""
    return tuple(
        (f.name, getattr(law, f.name))
        for f in dataclasses.fields(type(law))
        if f.metadata.get("static")
    )


def identifiable(law: AbstractFriction) -> tuple[str, ...]:
    """The law's fields a record of the tilt determines, which `fit` may free.

    Every field, but the slip scale of a law with a drilling torque: with Contensou friction the
    motion converges as `slip_scale` -> 0 (`docs/friction.md`), so a record does not pin it.
    Under the pure Coulomb law it sets the creep of near-rolling (a viscous law of coefficient
    `mu / slip_scale`), which a record of the rise does see."""
    names = law_fields(law)
    if law.has_drilling_torque:
        names = tuple(n for n in names if n != "slip_scale")
    return names


def units(name: str, law: AbstractFriction) -> str:
    """The units of a free name for a top with the friction law `law`."""
    return law.mu_units if name == "mu" else FIELD_UNITS[name]


class Base(eqx.Module):
    """The guess: every top field (the law's too) and launch quantity, free or not (arrays,
    maybe batched).

    `top` holds the top's own fields and its law's array fields by name (`mu`, and e.g.
    `patch_radius`, `slip_scale`); `law` is the law's class and `options` its static fields,
    from which `assemble` builds the law again. `state` is the guess's own initial state: when
    no launch quantity is free it is simulated as given (no round trip through Euler angles),
    so any valid `State` can be fitted. `launch` may also hold the launch time's guess `t0`
    and its scale `t0_scale` (s), read when `t0` is free.
    """

    top: dict[str, Array]
    launch: dict[str, Array]
    state: State
    law: type[AbstractFriction] = eqx.field(static=True, default=Viscous)
    options: tuple = eqx.field(static=True, default=())


@eqx.filter_jit
def launch_of(y0: State) -> dict[str, Array]:
    """The launch quantities of a state (Euler angles and rates, spin, position, velocity).
    (One program: op by op, a fit's guess cost a dozen small compilations per new process.)"""
    theta, phi, psi = euler_angles(y0)
    theta_dot, phi_dot, _ = euler_rates(y0)
    return dict(
        theta0=theta,
        spin=spin(y0),
        theta_dot=theta_dot,
        phi_dot=phi_dot,
        phi=phi,
        psi=psi,
        vx=y0.velocity[..., 0],
        vy=y0.velocity[..., 1],
        x=y0.position[..., 0],
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
    for name in ("m", "R", "g", "mu", "slip_scale"):
        if name in z:
            out[name] = t[name] * jnp.exp(z[name])
    if "patch_radius" in z:
        R = out.get("R", t["R"])
        out["patch_radius"] = (
            PATCH_FRACTION
            * R
            * jax.nn.sigmoid(
                z["patch_radius"] + _logit(t["patch_radius"] / (PATCH_FRACTION * t["R"]))
            )
        )
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
    if "t0" in z:
        out["t0"] = lau["t0"] + lau["t0_scale"] * z["t0"]
    # The coordinates u are in the optimiser's precision (float64 when enabled); the physical
    # values in the top's (float32 tops simulate in float32).
    dtype = jnp.result_type(t["m"])
    return {k: jnp.asarray(v, dtype) for k, v in out.items()}


def guess_top(base: Base) -> TippeTop:
    """The guess's top, its law included."""
    fields = law_fields(base.law)
    law = base.law(**{k: base.top[k] for k in fields}, **dict(base.options))
    return TippeTop(**{k: base.top[k] for k in BODY_FIELDS}, friction=law)


def assemble(values: dict[str, Array], base: Base) -> tuple[TippeTop, State]:
    """The top (its law included) and initial state with `values` replacing the guess's
    fields. (The launch time `t0`, if among them, is not part of either.)"""
    # The guess is a checked top; trial values are valid by construction (reparametrised), so
    # they replace its fields without TippeTop's runtime checks: a trial that overflows to
    # inf makes a non-finite simulation, which gets the failure residual, instead of raising.
    top = guess_top(base)
    changed = [k for k in BODY_FIELDS if k in values]
    if changed:
        top = eqx.tree_at(
            lambda tp: [getattr(tp, k) for k in changed], top, [values[k] for k in changed]
        )
    changed = [k for k in law_fields(base.law) if k in values]
    if changed:
        top = eqx.tree_at(
            lambda tp: [getattr(tp.friction, k) for k in changed], top, [values[k] for k in changed]
        )
    if not any(k in LAUNCH_FIELDS for k in values):
        return top, base.state
    lau = {**base.launch, **{k: v for k, v in values.items() if k in LAUNCH_FIELDS}}
    y0 = state_from_euler(
        lau["theta0"],
        lau["phi"],
        lau["psi"],
        lau["theta_dot"],
        lau["phi_dot"],
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
    "BODY_FIELDS",
    "TOP_FIELDS",
    "LAW_FIELDS",
    "LAUNCH_FIELDS",
    "TIME_FIELDS",
    "FREE_NAMES",
    "NAMES",
    "FIELD_UNITS",
    "Base",
    "launch_of",
    "physical",
    "assemble",
    "guess_top",
    "law_fields",
    "law_options",
    "identifiable",
    "units",
]
