r"""The SO(3) model: the paper's approximation with translation dropped in the friction law.

As in Sec. 2.2 (Routhian reduction), the horizontal velocity of the centre of mass is neglected in
the friction force and in $R_n$ ($R'_n$); the vertical motion of the centre of mass (the
$m\epsilon^2\sin^2\theta\,\dot\theta^2$ term of $L'$) is kept. In vector form this is the full model
with $v_O = (0, 0, \dot h)$: state $(a, \omega)$, regular at the poles. Position and horizontal
velocity are frozen (their derivatives are zero).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._state import State
from .._top import TippeTop
from ._rigid_body import rigid_body_dynamics


def _single(top: TippeTop, y: State) -> State:
    zero = jnp.zeros_like(y.velocity)
    _, omega_dot, _, _ = rigid_body_dynamics(top, y.axis, y.omega, zero)
    return State(
        position=zero,
        velocity=zero,
        axis=jnp.cross(y.omega, y.axis),
        omega=omega_dot,
        body=jnp.cross(y.omega, y.body),
    )


def so3_vector_field(t, y: State, top: TippeTop) -> State:
    r"""Time derivative of the state under the SO(3) model (diffrax signature `f(t, y, args)`).

    Same as `full_vector_field` with the horizontal velocity set to zero in
    $v_Q = v_O + \omega\times q$ and in $R'_n$. The Jellet $J$ is conserved exactly and the
    energy $E' = T_{\rm rot} + \tfrac12 m\dot h^2 + m g h$ never increases:
    $\dot E' = R_f\cdot v_Q = -\mu R_n |v_Q|^2$.
    """
    del t
    fn = _single
    for _ in y.axis.shape[:-1]:
        fn = jax.vmap(fn, in_axes=(None, 0))
    return fn(top, y)
