r"""Jellet integral, energy, normal force and slip velocity of a state."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._models._rigid_body import (
    centre_of_mass_velocity,
    contact_vector,
    contact_velocity,
    friction_per_normal_force,
    rigid_body_dynamics,
)
from ._models.stem import elastic_energy
from ._state import State
from ._top import TippeTop

_MODELS = ("full", "so3", "routhian")


def _check_model(model: str) -> str:
    if model not in _MODELS:
        raise ValueError(f"model must be one of {_MODELS} here, got {model!r}.")
    return model


def _batched(fn, y: State):
    for _ in y.axis.shape[:-1]:
        fn = jax.vmap(fn)
    return fn(y)


def _friction_velocity(y: State, model: str):
    return y.velocity if model == "full" else jnp.zeros_like(y.velocity)


def jellet(top: TippeTop, y: State) -> Float[Array, "*batch"]:
    r"""The Jellet integral $J = -L\cdot q$ (eqs. Jellet, jello).

    $J = C n (R\cos\theta - \epsilon) + A\dot\varphi R\sin^2\theta$; exactly conserved by the full,
    SO(3) and Routhian models under any friction *force*. A drilling torque (a Contensou law)
    changes it at the rate `jellet_rate`.
    """

    def one(y):
        n = jnp.dot(y.omega, y.axis)
        angular_momentum = top.A * y.omega + (top.C - top.A) * n * y.axis
        return -jnp.dot(angular_momentum, contact_vector(top, y.axis))

    return _batched(one, y)


def jellet_rate(top: TippeTop, y: State, *, model: str = "full") -> Float[Array, "*batch"]:
    r"""The rate of change of the Jellet integral, $\dot J = M(R - \epsilon\cos\theta)$.

    With $J = -L\cdot q$, $\dot L = q\times F + M e_Z$ and $\dot q = \epsilon\,\omega\times a$
    (which is orthogonal to $L$), $\dot J = -M\,q\cdot e_Z = M(R - \epsilon\cos\theta)$, where
    $M = R_n m(v_Q, \omega_n)$ is the friction law's drilling torque about the contact normal.
    Zero for a law without drilling torque (the viscous and Coulomb laws: $J$ is conserved);
    for a Contensou law it gives the balance $J(t) - J(0) = \int_0^t M(R - \epsilon\cos
    \theta)\,dt$ (`docs/friction.md`). `model` as in `normal_force` (the level's $R_n$ and
    $v_Q$: `"full"`, or `"so3"`/`"routhian"` without the horizontal velocity).

    **Arguments:**

    - `top`: the `TippeTop`.
    - `y`: a `State` (or a batch of them, leading axes).
    - `model`: `"full"` (default), `"so3"` or `"routhian"`.

    **Returns:** $\dot J$ (kg m^2/s^2), one per state.
    """
    _check_model(model)

    def one(y):
        velocity = _friction_velocity(y, model)
        rn = rigid_body_dynamics(top, y.axis, y.omega, velocity)[0]
        _, drilling = friction_per_normal_force(top, y.axis, y.omega, velocity)
        return rn * drilling * (top.R - top.eps * y.axis[2])

    return _batched(one, y)


def energy(top: TippeTop, y: State, *, model: str = "full") -> Float[Array, "*batch"]:
    r"""Total energy $E = \tfrac12 m |v_O|^2 + \tfrac12\omega\cdot I\omega + m g h$ (Sec. 2.1).

    $v_O = (\dot x, \dot y, \dot h)$, $h = R - \epsilon\cos\theta$; for a state with a
    height (`State.height`, a top with a stem) $h$ and $\dot h$ are the state's, and the elastic
    energy of the compliant contacts, $\sum_i \tfrac25 k_i\delta_i^{5/2}$ (`tj.Stem`), is
    added. For `model="so3"` or
    `"routhian"` the horizontal velocity is dropped ($E'$ of the Lagrangian $L'$). Along every
    model's flow $\dot E = R_n(f\cdot v_Q + m\,\omega_n) \le 0$ while $R_n \ge 0$, for every
    friction law (force $R_n f$, drilling torque $R_n m$); $-\mu R_n |v_Q|^2$ for the viscous law
    (eq. derE).
    """
    _check_model(model)

    def one(y):
        v_o = centre_of_mass_velocity(top, y.axis, y.omega, _friction_velocity(y, model))
        n = jnp.dot(y.omega, y.axis)
        rotational = 0.5 * (top.A * jnp.dot(y.omega, y.omega) + (top.C - top.A) * n**2)
        height = top.R - top.eps * y.axis[2]
        elastic = 0.0
        if y.height is not None:  # a top with a stem: the height is a state, and the
            # compliant contacts store elastic energy (zero at the ball's rigid contact)
            height, v_o = y.height, v_o.at[2].set(y.height_rate)
            elastic = elastic_energy(top, y.axis, y.height)
        return 0.5 * top.m * jnp.dot(v_o, v_o) + rotational + top.m * top.g * height + elastic

    return _batched(one, y)


def normal_force(top: TippeTop, y: State, *, model: str = "full") -> Float[Array, "*batch"]:
    r"""Normal force $R_n$ of the table, from $m\ddot h = R_n - m g$ and the equations of motion.

    Agrees with the paper's closed form (eq. reactie). With `model="so3"` or `"routhian"` the
    horizontal velocity is dropped ($R'_n$). $R_n \le 0$ means the top has left the table and the
    model no longer applies (`docs/notes.md`, "Contact loss").
    """
    _check_model(model)
    return _batched(
        lambda y: rigid_body_dynamics(top, y.axis, y.omega, _friction_velocity(y, model))[0], y
    )


def normal_force_denominator(
    top: TippeTop, y: State, *, model: str = "full"
) -> Float[Array, "*batch"]:
    r"""The denominator $1/m + h'(h' + \mu h^2\dot\theta)/A + \dots$ of $R_n$ (eq. reactie).

    Its zero is a Painleve-type singularity of friction proportional to $R_n$ (`docs/notes.md`, "The R_n singularity");
    it is positive in every regular state.
    """
    _check_model(model)
    return _batched(
        lambda y: rigid_body_dynamics(top, y.axis, y.omega, _friction_velocity(y, model))[3], y
    )


def slip_velocity(top: TippeTop, y: State, *, model: str = "full") -> Float[Array, "*batch 3"]:
    r"""Velocity of the contact point, $v_Q = v_O + \omega\times q$ (horizontal)."""
    _check_model(model)
    return _batched(
        lambda y: contact_velocity(top, y.axis, y.omega, _friction_velocity(y, model)), y
    )
