"""The interface every friction law implements, and the checks their fields share."""

from __future__ import annotations

import abc
import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._errors import branched_error_if


def is_traced(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def as_float(x):
    """`x` as a floating JAX array (a tracer keeps its float dtype; ints become floats)."""
    if is_traced(x):
        if not jnp.issubdtype(x.dtype, jnp.floating):
            x = x.astype(jnp.result_type(float))
        return x
    if isinstance(x, (jax.Array, np.ndarray)) and jnp.issubdtype(x.dtype, jnp.floating):
        return jnp.asarray(x)
    return jnp.asarray(x, dtype=jnp.result_type(float))


def broadcast_fields(owner: str, names, values):
    """`values` broadcast to one batch shape, or a `ValueError` naming the fields' shapes."""
    shapes = [jnp.shape(v) for v in values]
    if len(set(shapes)) <= 1:
        return list(values)
    try:
        shape = np.broadcast_shapes(*shapes)
    except ValueError:
        got = ", ".join(f"{k}: {sh}" for k, sh in zip(names, shapes))
        raise ValueError(
            f"{owner}: the fields' shapes do not broadcast to one batch shape ({got}). Give "
            "every field the same shape, or scalars."
        ) from None
    return [jnp.broadcast_to(v, shape) for v in values]


def describe_failure(failed, names, values, most: int = 3) -> str:
    """Which members broke a rule, and their values: short, whatever the batch's size."""
    failed = np.asarray(failed)

    def show(index) -> str:
        return ", ".join(
            f"{k}={float(np.broadcast_to(v, failed.shape)[index]):.6g}"
            for k, v in zip(names, values)
        )

    if failed.ndim == 0:
        return f"Got {show(())}."
    where = np.argwhere(failed)
    members = [
        f"[{', '.join(str(int(i)) for i in index)}]: {show(tuple(index))}" for index in where[:most]
    ]
    more = f"; and {len(where) - most} more" if len(where) > most else ""
    return (
        f"{len(where)} of the batch's {failed.size} (shape {failed.shape}) break it; at "
        f"index {'; '.join(members)}{more}."
    )


def checked(owner: str, names, values, checks):
    """`values` after the rules `checks(*values)` (a list of (failed, message)).

    Concrete values that break a rule raise `ValueError` with the message and the offending
    members' values (the first few of a batch); traced ones carry a runtime check, attached to
    every value so that whichever one a computation uses keeps it, also under differentiation
    (`tippejax._errors`)."""
    if not any(is_traced(v) for v in values):
        np_values = [np.asarray(v) for v in values]
        for failed, message in checks(*np_values):
            if np.any(failed):
                failed = np.broadcast_to(
                    failed, np.broadcast_shapes(np.shape(failed), *(np.shape(v) for v in np_values))
                )
                raise ValueError(f"{message} {describe_failure(failed, names, np_values)}")
        return list(values)
    rules = checks(*values)
    failed = jnp.stack([jnp.any(f) for f, _ in rules])
    index = jnp.argmax(failed)
    messages = tuple(msg for _, msg in rules)
    return [branched_error_if(v, jnp.any(failed), index, messages) for v in values]


def finite_rules(owner: str, names, values, xp):
    """One rule per field: finite."""
    return [
        (~xp.isfinite(v), f"{owner}.{k} must be finite (got NaN or inf).")
        for k, v in zip(names, values)
    ]


def array_module(*values):
    return jnp if any(is_traced(v) for v in values) else np


class AbstractFriction(eqx.Module):
    r"""A law of friction at the contact point $Q$, per unit normal force.

    A law maps the horizontal slip velocity $v = v_Q$ of the contact point (m/s) and the
    drilling rate $\omega_n = \omega\cdot e_Z$ (rad/s, the spin about the contact normal) to

    - the friction force per unit normal force, $f(v, \omega_n)$: a horizontal vector,
      given as its two components $(f_X, f_Y)$ (dimensionless), so that the table pushes on the
      top with $R_n(e_Z + f)$;
    - the drilling torque per unit normal force, $m(v, \omega_n)$ (m), about $e_Z$ at $Q$:
      the torque is $R_n m\, e_Z$ (zero for a law without drilling friction).

    Every law dissipates: $f\cdot v + m\,\omega_n \le 0$. The full and SO(3) levels take any
    law (`docs/friction.md`); they ask the law through `components`, never its class.

    Every field is a JAX array (batchable with a leading axis, differentiable); invalid
    values raise `ValueError` at construction, or an `equinox` runtime error inside `jit`.

    **Class attributes:**

    - `mu_units`: the units of the law's `mu` (`"s/m"` for the viscous law, `"1"`
      (dimensionless) for the Coulomb laws).
    - `has_drilling_torque`: whether $m$ can be non-zero.
    """

    mu: eqx.AbstractVar[Float[Array, "*batch"]]
    mu_units: eqx.AbstractClassVar[str]
    has_drilling_torque: eqx.AbstractClassVar[bool]

    @abc.abstractmethod
    def components(self, slip_x, slip_y, drilling_rate):
        r"""$(f_X, f_Y, m)$ from $(v_X, v_Y, \omega_n)$, component-wise over any leading shape.

        **Arguments:** the slip velocity's components $v_X, v_Y$ (m/s) and the drilling rate
        $\omega_n$ (rad/s), arrays of one shape (or broadcasting with the law's fields).

        **Returns:** the friction force per unit normal force $(f_X, f_Y)$ (dimensionless) and
        the drilling torque per unit normal force $m$ (m; zeros for a law without it).
        """

    @abc.abstractmethod
    def zero_slip_coefficient(self) -> Float[Array, "*batch"]:
        r"""The equivalent viscous coefficient at zero slip and zero drilling (s/m).

        The largest $|\partial f/\partial v|$, reached at $v = 0$, $\omega_n = 0$: $\mu$ for
        the viscous law, $\mu/\delta$-like for a regularised Coulomb law. It sets the stiffness
        of sliding (`tj.friction_rate`)."""

    def stiffness_coefficient(self) -> Float[Array, "*batch"]:
        r"""The equivalent viscous coefficient at zero slip in the motion of a spinning top
        (s/m), which sets the default solver (`tj.friction_rate`, `tj.default_solver`).

        `zero_slip_coefficient` by default; a law whose drilling softens the sliding friction
        (`CoulombContensou`) gives its coefficient at zero slip while the contact drills."""
        return self.zero_slip_coefficient()

    def _with_slip_floor(self, floor) -> AbstractFriction:
        r"""The law a fit's searches simulate, with slip scales of at least `floor` (m/s): the
        law itself (default), for a law whose motion depends on its slip scale. A law whose
        motion converges as its slip scale goes to 0 (`CoulombContensou`) raises it, so that a
        search's trial tops cost thousands of steps, not the $\sim 1/\delta$ of a top that
        stops drilling (the fit's later stages simulate the law as given)."""
        del floor
        return self

    def inversion_time_caveat(self) -> str | None:
        """Why the law's inversion times are not a property of the top, or None (default):
        `simulate` and `inversion_time` warn with it (`UserWarning`, concrete tops)."""
        return None

    @abc.abstractmethod
    def _rules(self, values, xp) -> list:
        """(failed, message) for every rule on the law's own fields (`values` in field order)."""

    def ball_rules(self, R, xp) -> list:
        """(failed, message) for the rules that involve the ball's radius `R` (checked by
        `TippeTop`); none by default."""
        del R, xp
        return []

    def force_and_torque(
        self, slip_velocity: Float[Array, "*shape 2"], drilling_rate: Float[Array, "*shape"]
    ) -> tuple[Float[Array, "*shape 2"], Float[Array, "*shape"]]:
        r"""The friction force per unit normal force $f$ (horizontal 2-vector, last axis) and
        the drilling torque per unit normal force $m$ (m) at slip velocity $v$ (m/s, 2-vector)
        and drilling rate $\omega_n$ (rad/s); see `components`."""
        fx, fy, torque = self.components(
            slip_velocity[..., 0], slip_velocity[..., 1], drilling_rate
        )
        return jnp.stack([fx, fy], axis=-1), torque

    # -- construction helpers -------------------------------------------------------------

    @classmethod
    def _array_field_names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(cls) if not f.metadata.get("static"))

    @classmethod
    def _static_field_names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(cls) if f.metadata.get("static"))

    def _set_checked(self, values: dict) -> None:
        """Convert, broadcast and check the array fields `values` ({name: value}), and set
        them (for a law's `__init__`)."""
        owner = type(self).__name__
        names = self._array_field_names()
        arrays = broadcast_fields(owner, names, [as_float(values[k]) for k in names])
        arrays = checked(
            owner,
            names,
            arrays,
            lambda *v: (
                finite_rules(owner, names, v, array_module(*v)) + self._rules(v, array_module(*v))
            ),
        )
        for k, v in zip(names, arrays):
            setattr(self, k, v)

    def replace(self, **changes) -> AbstractFriction:
        """The same law with some fields changed, checked like a new law."""
        names = (*self._array_field_names(), *self._static_field_names())
        unknown = sorted(set(changes) - set(names))
        if unknown:
            raise ValueError(
                f"{type(self).__name__}.replace: unknown field(s) {unknown}; the fields are "
                f"{names}."
            )
        return type(self)(**{k: changes.get(k, getattr(self, k)) for k in names})

    def __repr__(self) -> str:
        parts = []
        try:
            for k in self._array_field_names():
                v = np.asarray(getattr(self, k))
                if v.ndim == 0:
                    parts.append(f"{k}={v.item():.6g}")
                elif v.size and np.all(v == v.flat[0]):
                    parts.append(f"{k}={v.flat[0].item():.6g}")
                else:
                    parts.append(f"{k}={np.array2string(v, precision=6, threshold=8)}")
        except Exception:  # noqa: BLE001 - traced fields have no values to show
            return super().__repr__()
        parts += [f"{k}={getattr(self, k)!r}" for k in self._static_field_names()]
        return f"{type(self).__name__}({', '.join(parts)})"
