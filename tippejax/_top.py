"""The tippe top: an eccentric sphere on a hard table with viscous sliding friction."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._errors import branched_error_if

_FIELDS = ("m", "R", "eps", "A", "C", "g", "mu")


def _is_traced(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def _as_float(x):
    if _is_traced(x):
        if not jnp.issubdtype(x.dtype, jnp.floating):
            x = x.astype(jnp.result_type(float))
        return x
    if isinstance(x, (jax.Array, np.ndarray)) and jnp.issubdtype(x.dtype, jnp.floating):
        return jnp.asarray(x)
    return jnp.asarray(x, dtype=jnp.result_type(float))


def _checks(m, R, eps, A, C, g, mu):
    """(predicate-of-failure, message) for every rule a top must obey. Works on numpy and jax."""
    xp = jnp if any(_is_traced(v) for v in (m, R, eps, A, C, g, mu)) else np
    checks = []
    for name, value in zip(_FIELDS, (m, R, eps, A, C, g, mu)):
        checks.append(
            (~xp.isfinite(value), f"TippeTop.{name} must be finite (got NaN or inf).")
        )
    checks += [
        (m <= 0, "TippeTop.m (mass) must be > 0."),
        (R <= 0, "TippeTop.R (radius of the sphere) must be > 0."),
        (A <= 0, "TippeTop.A (transverse moment of inertia) must be > 0."),
        (C <= 0, "TippeTop.C (axial moment of inertia) must be > 0."),
        (g <= 0, "TippeTop.g (gravitational acceleration) must be > 0."),
        (mu < 0, "TippeTop.mu (viscous friction coefficient, s/m) must be >= 0."),
        (
            (eps <= 0) | (eps >= R),
            "TippeTop.eps (offset of the centre of mass from the centre of the sphere) "
            "must satisfy 0 < eps < R.",
        ),
        (
            2 * A < C,
            "TippeTop: A/C must be >= 1/2; no rigid body has 2A < C "
            "(C <= A + B = 2A for an axisymmetric body).",
        ),
    ]
    return checks


def _describe_failure(failed, values, most: int = 3) -> str:
    """Which members broke a rule, and their values: short, whatever the batch's size."""
    failed = np.asarray(failed)

    def show(v) -> str:
        return ", ".join(f"{k}={float(x):.6g}" for k, x in zip(_FIELDS, v))

    if failed.ndim == 0:
        return f"Got {show(values)}."
    where = np.argwhere(failed)
    members = []
    for index in where[:most]:
        index = tuple(int(i) for i in index)
        members.append(f"[{', '.join(map(str, index))}]: {show(v[index] for v in values)}")
    more = f"; and {len(where) - most} more" if len(where) > most else ""
    return (f"{len(where)} of the batch's {failed.size} tops (shape {failed.shape}) break it; "
            f"at index {'; '.join(members)}{more}.")


class TippeTop(eqx.Module):
    r"""Physical parameters of an eccentric-sphere tippe top.

    A sphere of radius $R$ and mass $m$ whose centre of mass $O$ is a distance $\epsilon$ from
    the geometric centre, with moments of inertia $A = B$ (transverse) and $C$ (axial) about $O$,
    on a horizontal table under gravity $g$, with the viscous sliding friction
    $\mathbf R_f = -\mu R_n \mathbf v_Q$ (eq. viscfric; $\mu$ in s/m).

    Every field is a JAX array, so a `TippeTop` can be passed through `jax.jit`, batched with
    `jax.vmap` (give every field a leading batch axis, or build the tops inside `vmap`), and
    differentiated with respect to any field.

    Invalid parameters raise `ValueError` at construction for concrete values, and an
    `equinox` runtime error when the top is built inside `jax.jit` from traced values.

    **Arguments:**

    - `m`: mass (kg), > 0.
    - `R`: radius of the sphere (m), > 0.
    - `eps`: distance from the centre of the sphere to the centre of mass (m), $0 < \epsilon < R$.
    - `A`: transverse moment of inertia about the centre of mass (kg m^2), > 0.
    - `C`: axial moment of inertia (kg m^2), > 0, with $C \le 2A$.
    - `g`: gravitational acceleration (m/s^2), > 0. Default 9.81.
    - `mu`: viscous friction coefficient (s/m), >= 0. Default 0.3.
    """

    m: Float[Array, "*batch"]
    R: Float[Array, "*batch"]
    eps: Float[Array, "*batch"]
    A: Float[Array, "*batch"]
    C: Float[Array, "*batch"]
    g: Float[Array, "*batch"]
    mu: Float[Array, "*batch"]

    def __init__(
        self,
        m: ArrayLike,
        R: ArrayLike,
        eps: ArrayLike,
        A: ArrayLike,
        C: ArrayLike,
        g: ArrayLike = 9.81,
        mu: ArrayLike = 0.3,
    ):
        values = [_as_float(v) for v in (m, R, eps, A, C, g, mu)]
        traced = any(_is_traced(v) for v in values)
        shapes = [jnp.shape(v) for v in values]
        if len(set(shapes)) > 1:
            # A sweep of one field (mu=[...]) makes a batch of tops: every field gets its shape.
            try:
                shape = np.broadcast_shapes(*shapes)
            except ValueError:
                got = ", ".join(f"{k}: {sh}" for k, sh in zip(_FIELDS, shapes))
                raise ValueError(
                    "TippeTop: the fields' shapes do not broadcast to one batch shape "
                    f"({got}). Give every field the same shape, or scalars."
                ) from None
            values = [jnp.broadcast_to(v, shape) for v in values]
        if not traced:
            np_values = [np.asarray(v) for v in values]
            for failed, message in _checks(*np_values):
                if np.any(failed):
                    raise ValueError(f"{message} {_describe_failure(failed, np_values)}")
        else:
            checks = _checks(*values)
            failed = jnp.stack([jnp.any(f) for f, _ in checks])
            index = jnp.argmax(failed)
            messages = tuple(msg for _, msg in checks)
            # Attach the check to every field, so that whichever field a computation uses
            # carries it (an unused `error_if` output would be dropped by XLA).
            values = [
                branched_error_if(v, jnp.any(failed), index, messages) for v in values
            ]
        self.m, self.R, self.eps, self.A, self.C, self.g, self.mu = values

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """Shape of the batch of tops (`()` for one top)."""
        return tuple(np.broadcast_shapes(*(jnp.shape(getattr(self, k)) for k in _FIELDS)))

    def replace(self, **changes) -> TippeTop:
        r"""The same top with some fields changed, checked like a new `TippeTop`.

        `top.replace(mu=0.1)`; `top.replace(mu=np.linspace(0.05, 1.0, 20))` is a batch of 20
        tops (the other fields broadcast), ready for `simulate_batch` or `jax.vmap`. Besides the
        fields `m, R, eps, A, C, g, mu`, the ratios may be given: `A_over_C` sets $A = (A/C)\,C$
        at the top's $C$, `eps_over_R` sets $\epsilon = (\epsilon/R)\,R$ at its $R$ (after
        any new `C` or `R`).
        """
        allowed = (*_FIELDS, "A_over_C", "eps_over_R")
        unknown = sorted(set(changes) - set(allowed))
        if unknown:
            raise ValueError(
                f"TippeTop.replace: unknown field(s) {unknown}; the fields are {allowed}."
            )
        for ratio, field in (("A_over_C", "A"), ("eps_over_R", "eps")):
            if ratio in changes and field in changes:
                raise ValueError(f"TippeTop.replace: give {ratio} or {field}, not both.")
        values = {k: changes.get(k, getattr(self, k)) for k in _FIELDS}
        if "A_over_C" in changes:
            values["A"] = _as_float(changes["A_over_C"]) * _as_float(values["C"])
        if "eps_over_R" in changes:
            values["eps"] = _as_float(changes["eps_over_R"]) * _as_float(values["R"])
        return TippeTop(**values)

    def __repr__(self) -> str:
        try:
            values = {k: np.asarray(getattr(self, k)) for k in _FIELDS}
        except Exception:  # noqa: BLE001 - traced fields have no values to show
            return super().__repr__()
        if all(v.ndim == 0 for v in values.values()):
            body = ", ".join(f"{k}={v.item():.6g}" for k, v in values.items())
            return f"TippeTop({body})"
        parts = []
        for k, v in values.items():
            if np.all(v == v.flat[0]):
                parts.append(f"{k}={v.flat[0].item():.6g}")
            else:
                parts.append(f"{k}={np.array2string(v, precision=6, threshold=8)}")
        return f"TippeTop(batch_shape={self.batch_shape}, {', '.join(parts)})"

    @classmethod
    def from_ratios(
        cls,
        A_over_C: ArrayLike,
        eps_over_R: ArrayLike,
        *,
        m: ArrayLike = 0.02,
        R: ArrayLike = 0.025,
        mu: ArrayLike = 0.3,
        g: ArrayLike = 9.81,
        C: ArrayLike | None = None,
    ) -> TippeTop:
        r"""Build a top from the two ratios that fix its group, $A/C$ and $\epsilon/R$.

        $C = 0.4\, m R^2$ (a homogeneous sphere) unless given; $A = (A/C)\, C$,
        $\epsilon = (\epsilon/R)\, R$.
        """
        m_ = _as_float(m)
        R_ = _as_float(R)
        C_ = 0.4 * m_ * R_**2 if C is None else _as_float(C)
        return cls(
            m=m_,
            R=R_,
            eps=_as_float(eps_over_R) * R_,
            A=_as_float(A_over_C) * C_,
            C=C_,
            g=g,
            mu=mu,
        )

    @property
    def A_over_C(self) -> Float[Array, "*batch"]:
        """Inertia ratio $A/C$."""
        return self.A / self.C

    @property
    def eps_over_R(self) -> Float[Array, "*batch"]:
        r"""Eccentricity $\epsilon/R$."""
        return self.eps / self.R

    def astype(self, dtype) -> TippeTop:
        """The same top with every field cast to `dtype` (e.g. `jnp.float32`)."""
        return jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), self)


def default_top() -> TippeTop:
    """The standard top of the examples: A/C = 0.9, eps/R = 0.3, m = 20 g, R = 25 mm, mu = 0.3 s/m."""
    return TippeTop.from_ratios(0.9, 0.3, m=0.02, R=0.025, mu=0.3)
