r"""Thresholds and the classification of tippe tops into six groups (Sec. 4-5).

With $a = A/C$ and $e = \epsilon/R$:

- Group I, $a - 1 < -e$: $\theta = 0$ always stable; intermediate states only for $\theta > \theta_c$.
  Ia if $x_b < -1$ (branch unstable), Ib if $x_b > -1$ (bifurcation at $\theta_b$).
- Group II, $-e < a - 1 < e$: intermediate states for all $\theta$. IIa: $1 - a - e^2 > 0$ and
  $|x_b| < 1$; IIc: $1 - a - e^2 > 0$ and $x_b < -1$; IIb: the rest (branch entirely stable).
- Group III, $a - 1 > e$: $\theta = \pi$ always unstable; intermediate states only for
  $\theta < \theta_c$, all stable.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._top import TippeTop

GROUPS = ("Ia", "Ib", "IIa", "IIb", "IIc", "III")


class Thresholds(eqx.Module):
    r"""Thresholds of a top (nan where undefined), with $a = A/C$ and $e = \epsilon/R$.

    - `n1`: $|n_0|$ above which $\theta = 0$ is unstable (eq. n1); Groups II, III.
    - `n2`: $|n_\pi|$ above which $\theta = \pi$ is stable (eq. n2); Groups I, II.
    - `J1` $= C(R-\epsilon)n_1$, `J2` $= C(R+\epsilon)n_2$: the same thresholds as Jellet values,
      where the intermediate branch meets $\theta = 0$ and $\theta = \pi$.
    - `theta_c`: end of the intermediate branch, $(a-1)\cos\theta_c + e = 0$; Groups I, III.
    - `x_b`: $\cos\theta_b$ of the bifurcation point (eq. eqbif, minus sign) wherever
      $1 - a - e^2 > 0$ (even if $|x_b| > 1$; it classifies the top).
    - `theta_b` $= \arccos x_b$ where $|x_b| < 1$.
    """

    n1: Float[Array, "*batch"]
    n2: Float[Array, "*batch"]
    J1: Float[Array, "*batch"]
    J2: Float[Array, "*batch"]
    theta_c: Float[Array, "*batch"]
    x_b: Float[Array, "*batch"]
    theta_b: Float[Array, "*batch"]

    def __repr__(self) -> str:
        # Show the numbers (equinox's default shows only dtypes and shapes); traced values
        # cannot be shown, so fall back to the default there.
        try:
            values = {name: np.asarray(getattr(self, name)) for name in _THRESHOLD_FIELDS}
        except Exception:  # noqa: BLE001 - tracers
            return super().__repr__()
        body = ", ".join(
            f"{name}={v.item():.6g}" if v.ndim == 0 else f"{name}={v!r}"
            for name, v in values.items()
        )
        return f"Thresholds({body})"


_THRESHOLD_FIELDS = ("n1", "n2", "J1", "J2", "theta_c", "x_b", "theta_b")


def thresholds(top: TippeTop) -> Thresholds:
    r"""The thresholds $n_1, n_2, J_1, J_2, \theta_c, x_b, \theta_b$ of a top (closed forms).

    With $a = A/C$ (inertia ratio) and $e = \epsilon/R$ (eccentricity),

    $$n_1 = \sqrt{\frac{m g\epsilon}{C(a - 1 + e)}}(1 - e),\qquad
      n_2 = \sqrt{\frac{m g\epsilon}{C(1 + e - a)}}(1 + e),$$
    $$x_b = \frac{e}{1-a} - \frac{1}{1-a}\frac{\sqrt3}{3}\sqrt{a}\sqrt{1 - a - e^2}$$
    (eqs. n1, n2, eqbif), $J_1 = C(R-\epsilon)n_1$, $J_2 = C(R+\epsilon)n_2$ and
    $\cos\theta_c = e/(1-a)$. The thresholds do not depend on the friction law. Works on
    batched tops and under `jit`/`grad`.

    **Arguments:**

    - `top`: a `TippeTop` (one, or a batch).

    **Returns:** a `Thresholds` (see there for each field and the groups where it is defined).
    """
    a, e = top.A / top.C, top.eps / top.R
    nan = jnp.nan
    scale = top.m * top.g * top.eps / top.C
    d1 = a - 1.0 + e
    d2 = 1.0 + e - a
    n1 = jnp.where(d1 > 0, jnp.sqrt(scale / jnp.where(d1 > 0, d1, 1.0)) * (1.0 - e), nan)
    n2 = jnp.where(d2 > 0, jnp.sqrt(scale / jnp.where(d2 > 0, d2, 1.0)) * (1.0 + e), nan)
    outside_ii = (a - 1.0 < -e) | (a - 1.0 > e)
    cos_c = e / jnp.where(a == 1.0, 1.0, 1.0 - a)
    theta_c = jnp.where(outside_ii, jnp.arccos(jnp.clip(cos_c, -1.0, 1.0)), nan)
    disc = 1.0 - a - e**2
    safe_disc = jnp.where(disc > 0, disc, 1.0)
    safe_one_minus_a = jnp.where(disc > 0, 1.0 - a, 1.0)
    x_b = jnp.where(
        disc > 0,
        (e - jnp.sqrt(3.0) / 3.0 * jnp.sqrt(a) * jnp.sqrt(safe_disc)) / safe_one_minus_a,
        nan,
    )
    inside = jnp.abs(x_b) < 1
    theta_b = jnp.where(inside, jnp.arccos(jnp.where(inside, x_b, 0.0)), nan)
    return Thresholds(
        n1=n1,
        n2=n2,
        J1=top.C * (top.R - top.eps) * n1,
        J2=top.C * (top.R + top.eps) * n2,
        theta_c=theta_c,
        x_b=x_b,
        theta_b=theta_b,
    )


def group_index(top: TippeTop) -> Int[Array, "*batch"]:
    """Index of the group in `GROUPS` = ("Ia", "Ib", "IIa", "IIb", "IIc", "III"); jit-friendly."""
    a, e = top.A / top.C, top.eps / top.R
    x_b = thresholds(top).x_b
    disc = 1.0 - a - e**2
    group_i = a - 1.0 < -e
    group_iii = a - 1.0 > e
    index_i = jnp.where(x_b < -1, 0, 1)
    index_ii = jnp.where(disc > 0, jnp.where(jnp.abs(x_b) < 1, 2, jnp.where(x_b < -1, 4, 3)), 3)
    return jnp.where(group_i, index_i, jnp.where(group_iii, 5, index_ii))


def classify(top: TippeTop):
    r"""The group of a top: "Ia", "Ib", "IIa", "IIb", "IIc" or "III" (Sec. 5).

    Depends only on $A/C$ and $\epsilon/R$. For a batch of tops, returns a numpy array of strings.
    Not jit-able (it returns strings); use `group_index` inside `jit`.
    """
    if not isinstance(top, TippeTop):
        raise ValueError(
            f"classify takes a tippejax.TippeTop, got {type(top).__name__}. Build one with "
            "tj.TippeTop(m=..., R=..., eps=..., A=..., C=...) or "
            "tj.TippeTop.from_ratios(A_over_C, eps_over_R) (only the two ratios matter)."
        )
    index = np.asarray(group_index(top))
    if index.ndim == 0:
        return GROUPS[int(index)]
    return np.array(GROUPS)[index]
