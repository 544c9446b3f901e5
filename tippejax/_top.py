"""The tippe top: an eccentric sphere on a hard table, with a law of friction at the contact."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._friction.base import (
    AbstractFriction,
    array_module,
    as_float as _as_float,
    broadcast_fields,
    checked,
    is_traced as _is_traced,
)
from ._friction.viscous import Viscous
from ._plausibility import warn_if_implausible_top
from ._stem import _FIELDS as _STEM_FIELDS, Stem, stem_angle

_FIELDS = ("m", "R", "eps", "A", "C", "g", "mu")
"""The fields of a top with the viscous law (`mu` is the law's, `TippeTop.mu`)."""

_BODY_FIELDS = _FIELDS[:-1]
"""The top's own fields; the law's are in `TippeTop.friction`."""

_DEFAULT_MU = 0.3


def _checks(m, R, eps, A, C, g, mu=None):
    """(predicate-of-failure, message) for every rule a top must obey (with the viscous law of
    coefficient `mu`, unless None). Works on numpy and jax."""
    values = (m, R, eps, A, C, g) if mu is None else (m, R, eps, A, C, g, mu)
    xp = array_module(*values)
    checks = []
    for name, value in zip(_FIELDS, values):
        checks.append((~xp.isfinite(value), f"TippeTop.{name} must be finite (got NaN or inf)."))
    checks += [
        (m <= 0, "TippeTop.m (mass) must be > 0."),
        (R <= 0, "TippeTop.R (radius of the sphere) must be > 0."),
        (A <= 0, "TippeTop.A (transverse moment of inertia) must be > 0."),
        (C <= 0, "TippeTop.C (axial moment of inertia) must be > 0."),
        (g <= 0, "TippeTop.g (gravitational acceleration) must be > 0."),
    ]
    if mu is not None:
        checks.append((mu < 0, "TippeTop.mu (viscous friction coefficient, s/m) must be >= 0."))
    checks += [
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


def _with_stem_rules(rules, n, stem_tree):
    """`rules` on the first `n` values, and the stem's rules with the ball (`Stem.ball_rules`)
    on the values after them, where the top has a stem (`stem_tree` its structure)."""

    def all_rules(*v):
        out = rules(*v)
        if v[n:]:
            stem = jax.tree_util.tree_unflatten(stem_tree, list(v[n:]))
            out = out + stem.ball_rules(v[1], v[2], array_module(*v))
        return out

    return all_rules


def _is_default_mu(mu) -> bool:
    if mu is _DEFAULT_MU:
        return True
    if _is_traced(mu):
        return False
    value = np.asarray(mu)
    return value.ndim == 0 and value.dtype.kind in "fiu" and float(value) == _DEFAULT_MU


class TippeTop(eqx.Module):
    r"""Physical parameters of an eccentric-sphere tippe top and its law of friction.

    A sphere of radius $R$ and mass $m$ whose centre of mass $O$ is a distance $\epsilon$ from
    the geometric centre, with moments of inertia $A = B$ (transverse) and $C$ (axial) about $O$,
    on a horizontal table under gravity $g$. The table pushes on the top at the contact point
    $Q$ with $R_n(e_Z + f)$ and a drilling torque $R_n m\,e_Z$, where $f, m$ come from the
    friction law (`friction`, an `AbstractFriction`). The default is the paper's viscous law
    $\mathbf R_f = -\mu R_n \mathbf v_Q$ (eq. viscfric; $\mu$ in s/m): `mu=0.3` means
    `friction=tj.Viscous(mu=0.3)`. Other laws (`tj.Coulomb`, `tj.CoulombContensou`, with a
    dimensionless $\mu$) run at the full and SO(3) levels (`docs/friction.md`).

    Every field is a JAX array (the law's too), so a `TippeTop` can be passed through
    `jax.jit`, batched with `jax.vmap` (give every field a leading batch axis, or build the
    tops inside `vmap`), and differentiated with respect to any field. A batch holds one law
    class with batched parameters (`top.replace(mu=[...])`).

    Invalid parameters raise `ValueError` at construction for concrete values, and an
    `equinox` runtime error when the top is built inside `jax.jit` from traced values.

    **Arguments:**

    - `m`: mass (kg), > 0.
    - `R`: radius of the sphere (m), > 0.
    - `eps`: distance from the centre of the sphere to the centre of mass (m), $0 < \epsilon < R$.
    - `A`: transverse moment of inertia about the centre of mass (kg m^2), > 0.
    - `C`: axial moment of inertia (kg m^2), > 0, with $C \le 2A$.
    - `g`: gravitational acceleration (m/s^2), > 0. Default 9.81.
    - `mu`: viscous friction coefficient (s/m), >= 0, of the default law `tj.Viscous(mu)`.
      Default 0.3.
    - `friction`: the friction law (keyword only), any `AbstractFriction`; give it or `mu`,
      not both. Default `tj.Viscous(mu)`.
    - `stem`: the stem (keyword only), a `tj.Stem` (a second sphere on the axis beyond the
      ball's centre, which touches the table at the tilt `stem_angle`), or None (default):
      the paper's eccentric sphere alone. A top with a stem runs at the full level, which
      hands over to the stem level before the stem touches (`docs/friction.md`, "The stem").
    """

    m: Float[Array, "*batch"]
    R: Float[Array, "*batch"]
    eps: Float[Array, "*batch"]
    A: Float[Array, "*batch"]
    C: Float[Array, "*batch"]
    g: Float[Array, "*batch"]
    friction: AbstractFriction
    stem: Stem | None

    def __init__(
        self,
        m: ArrayLike,
        R: ArrayLike,
        eps: ArrayLike,
        A: ArrayLike,
        C: ArrayLike,
        g: ArrayLike = 9.81,
        mu: ArrayLike = _DEFAULT_MU,
        *,
        friction: AbstractFriction | None = None,
        stem: Stem | None = None,
    ):
        if friction is not None:
            if not isinstance(friction, AbstractFriction):
                raise TypeError(
                    "TippeTop.friction must be a friction law (tj.Viscous, tj.Coulomb, "
                    f"tj.CoulombContensou, ...), got {type(friction).__name__}."
                )
            if not _is_default_mu(mu):
                raise ValueError(
                    "TippeTop: give mu (the viscous law's coefficient, s/m) or friction (a "
                    "law with its own mu), not both."
                )
        body = [_as_float(v) for v in (m, R, eps, A, C, g)]
        if stem is not None and not isinstance(stem, Stem):
            raise TypeError(f"TippeTop.stem must be a tj.Stem or None, got {type(stem).__name__}.")
        # (the stem's fields are broadcast and checked with the top's; none without a stem)
        stem_leaves, stem_tree = jax.tree_util.tree_flatten(stem)
        stem_names = tuple(f"stem.{k}" for k in _STEM_FIELDS) if stem is not None else ()
        if friction is None:
            # mu is checked here, with the top's messages, then again by Viscous.
            names = (*_FIELDS, *stem_names)
            values = broadcast_fields("TippeTop", names, [*body, _as_float(mu), *stem_leaves])
            values = checked(
                "TippeTop",
                names,
                values,
                _with_stem_rules(lambda *v: _checks(*v[:7]), 7, stem_tree),
            )
            body, friction = values[:6], Viscous(values[6])
            stem = jax.tree_util.tree_unflatten(stem_tree, list(values[7:]))
        else:
            law_leaves, law_tree = jax.tree_util.tree_flatten(friction)
            names = (
                *_BODY_FIELDS,
                *(f"friction.{k}" for k in friction._array_field_names()),
                *stem_names,
            )
            values = broadcast_fields("TippeTop", names, [*body, *law_leaves, *stem_leaves])
            n, n_law = len(body), len(law_leaves)

            def rules(*v):
                law = jax.tree_util.tree_unflatten(law_tree, list(v[n : n + n_law]))
                return _checks(*v[:n]) + law.ball_rules(v[1], array_module(*v))

            values = checked(
                "TippeTop", names, values, _with_stem_rules(rules, n + n_law, stem_tree)
            )
            body = values[:n]
            friction = jax.tree_util.tree_unflatten(law_tree, list(values[n : n + n_law]))
            stem = jax.tree_util.tree_unflatten(stem_tree, list(values[n + n_law :]))
        if not any(_is_traced(v) for v in body):
            warn_if_implausible_top(*body)
        self.m, self.R, self.eps, self.A, self.C, self.g = body
        self.friction = friction
        self.stem = stem

    @property
    def mu(self) -> Float[Array, "*batch"]:
        """The friction law's coefficient $\\mu$ (`friction.mu`; s/m for the viscous law,
        dimensionless for the Coulomb laws)."""
        return self.friction.mu

    @property
    def stem_angle(self) -> Float[Array, "*batch"]:
        r"""The tilt $\theta_s$ (rad) at which the stem touches the table with the ball on it,
        $\cos\theta_s = (r_2 - R)/(a_2 - \epsilon)$ (`Stem`); nan without a stem."""
        if self.stem is None:
            return jnp.full(jnp.shape(self.R), jnp.nan, jnp.result_type(self.R))
        return stem_angle(self.R, self.eps, self.stem)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """Shape of the batch of tops (`()` for one top)."""
        return tuple(np.broadcast_shapes(*(jnp.shape(x) for x in jax.tree_util.tree_leaves(self))))

    def replace(self, **changes) -> TippeTop:
        r"""The same top with some fields changed, checked like a new `TippeTop`.

        `top.replace(mu=0.1)`; `top.replace(mu=np.linspace(0.05, 1.0, 20))` is a batch of 20
        tops (the other fields broadcast), ready for `simulate_batch` or `jax.vmap`. `mu`
        replaces the friction law's coefficient (whatever the law); `friction=` replaces the
        law; `stem=` replaces the stem (`tj.Stem`, or None to take it off). Besides the fields
        `m, R, eps, A, C, g, mu, friction, stem`, the ratios may be given:
        `A_over_C` sets $A = (A/C)\,C$ at the top's $C$, `eps_over_R` sets
        $\epsilon = (\epsilon/R)\,R$ at its $R$ (after any new `C` or `R`).
        """
        allowed = (*_FIELDS, "friction", "stem", "A_over_C", "eps_over_R")
        unknown = sorted(set(changes) - set(allowed))
        if unknown:
            raise ValueError(
                f"TippeTop.replace: unknown field(s) {unknown}; the fields are {allowed}."
            )
        for ratio, field in (("A_over_C", "A"), ("eps_over_R", "eps"), ("mu", "friction")):
            if ratio in changes and field in changes:
                raise ValueError(f"TippeTop.replace: give {ratio} or {field}, not both.")
        values = {k: changes.get(k, getattr(self, k)) for k in _BODY_FIELDS}
        if "A_over_C" in changes:
            values["A"] = _as_float(changes["A_over_C"]) * _as_float(values["C"])
        if "eps_over_R" in changes:
            values["eps"] = _as_float(changes["eps_over_R"]) * _as_float(values["R"])
        friction = changes.get("friction", self.friction)
        stem = changes.get("stem", self.stem)
        if type(friction) is Viscous:  # (the law `mu=` means: the top's own messages)
            return TippeTop(**values, mu=changes.get("mu", friction.mu), stem=stem)
        if "mu" in changes:
            friction = friction.replace(mu=changes["mu"])
        return TippeTop(**values, friction=friction, stem=stem)

    def __repr__(self) -> str:
        try:
            values = {k: np.asarray(getattr(self, k)) for k in _BODY_FIELDS}
            law = repr(self.friction)
            stem = "" if self.stem is None else f", stem={self.stem!r}"
        except Exception:  # noqa: BLE001 - traced fields have no values to show
            return super().__repr__()
        viscous = type(self.friction) is Viscous
        if viscous:
            values["mu"] = np.asarray(self.friction.mu)
        if self.batch_shape == ():
            body = ", ".join(f"{k}={v.item():.6g}" for k, v in values.items())
            body += "" if viscous else f", friction={law}"
            return f"TippeTop({body}{stem})"
        parts = []
        for k, v in values.items():
            if v.size and np.all(v == v.flat[0]):
                parts.append(f"{k}={v.flat[0].item():.6g}")
            else:
                parts.append(f"{k}={np.array2string(v, precision=6, threshold=8)}")
        if not viscous:
            parts.append(f"friction={law}")
        return f"TippeTop(batch_shape={self.batch_shape}, {', '.join(parts)}{stem})"

    @classmethod
    def from_ratios(
        cls,
        A_over_C: ArrayLike,
        eps_over_R: ArrayLike,
        *,
        m: ArrayLike = 0.02,
        R: ArrayLike = 0.025,
        mu: ArrayLike = _DEFAULT_MU,
        g: ArrayLike = 9.81,
        C: ArrayLike | None = None,
        friction: AbstractFriction | None = None,
        stem: Stem | None = None,
    ) -> TippeTop:
        r"""Build a top from the two ratios that fix its group, $A/C$ and $\epsilon/R$.

        $C = 0.4\, m R^2$ (a homogeneous sphere) unless given; $A = (A/C)\, C$,
        $\epsilon = (\epsilon/R)\, R$. `mu` (the viscous law's, s/m) or `friction` (any
        law) and `stem` as in `TippeTop`.
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
            friction=friction,
            stem=stem,
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
