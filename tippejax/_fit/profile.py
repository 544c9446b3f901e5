r"""The phase check: does the nutation's phase really pin the spin?

The Gauss-Newton standard errors describe the loss near the minimum the fit ended in. For the
spin that curvature comes from the nutation's phase, which slips by one cycle for a relative
change of $1/N$ of the spin ($N$ nutation cycles in the record). When the nutation is small
against the noise, the loss along the slow motion's valley (the curve on which the other
parameters trade against the spin and keep the envelope of the tilt) is a shallow envelope
with ripples one cycle apart: the local curvature of one ripple is large, so the standard
errors are small, yet minima many cycles away fit the record as well or better. A fit that
ends in one of them comes back within the noise, passes every test of its residuals, and is
some ten of its own standard errors from the truth (the fitting suite's seeded records hold
such cases).

So after a fit, the loss is profiled along that valley,

$$u(k) = u^* + \frac{k}{N}\,v, \qquad k \in [-K, K] \text{ cycles, step } 1/4,$$

with $v$ the valley direction of the slow loss ($v_s = 1$ on the spin coordinate $u_s =
\log|n|$, $v_o = -H_{oo}^{-1}H_{os}$, `stages/phase_scan.py`), in batches of simulations of the
whole record, and read in units of chi-square: $\Delta\chi^2(k) = 2(L(k) - L(0))/s^2$ with
$s^2 = 2L(0)/(N_{used} - p)$. Then:

- **a lower point** ($\Delta\chi^2 < -4$) is refined on the whole record, and kept if its
  end is lower (the least-squares estimate is the lowest minimum). This runs for every fit,
  also one whose residuals fail their tests: a fit a few cycles off is rescued by it;
- **a flat profile**: if a point more than 3 standard errors (and more than one cycle) away
  has $\Delta\chi^2 \le 9$ (a likelihood ratio of $e^{-9/2} \approx 0.011$), the data do not
  tell those cycles apart. The covariance is widened along the valley so that the spin's
  standard error in $u_s$ covers a third of the farthest such point, $\Sigma_u \leftarrow
  \Sigma_u + a^2 v v^\top$ with $a = |k|_{max}/(3N)$, mapped to the physical parameters,
  and the fit is flagged `phase_ambiguous` (`converged=False`). When the flat stretch reaches
  the end of the scan, the interval is wider still: the widened error is a lower bound.

The scan covers $\pm$`PROFILE_CYCLES` cycles but no more than $\pm 10\%$ of the spin. The
profile is linear in $u$, so a minimum on a curved valley may be missed (the check can say
"unambiguous" wrongly, never "ambiguous" wrongly: a raw point's loss is an upper bound on the
refined one).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .params import physical
from .stages.phase_scan import valley_directions

PROFILE_CYCLES = 20.0  # cycles scanned either side of the fit
PROFILE_STEP = 0.25  # cycles between profile points
PROFILE_MAX_REL = 0.1  # and no more than this relative change of the spin
AMBIGUOUS_CHI2 = 9.0  # a point within this chi-square of the fit is as good
MOVE_CHI2 = 4.0  # a point this much lower is refined
HESSIAN_STEP = 0.02


class Profile(eqx.Module):
    """The loss along the valley for each record (numpy arrays, batch first)."""

    offsets: np.ndarray  # (bsize, M) offsets in cycles
    dchi2: np.ndarray  # (bsize, M) chi-square above the fit
    points: np.ndarray  # (bsize, M, p) the profile's coordinates
    direction: np.ndarray  # (bsize, p) the valley direction, spin component 1
    cycles: np.ndarray  # (bsize,) nutation cycles in the record at the fit


def phase_profile(u, setup, spin: int) -> Profile:
    """Chi-square along the slow valley through `u` (shape `(p,)` or `(bsize, p)`)."""
    u_np = np.asarray(u, float).reshape(setup.bsize, -1)
    direction = valley_directions(u_np, setup, setup.batched, spin, HESSIAN_STEP)
    cycles = np.asarray(setup.nutation_cycles(u_np[:, spin]), float).reshape(-1)
    reach = np.minimum(PROFILE_CYCLES, PROFILE_MAX_REL * cycles)  # (bsize,)
    # points PROFILE_STEP cycles apart (or closer) over the widest reach of the batch: a
    # shorter reach takes fewer simulations, each record keeping its own reach
    half = max(int(np.ceil(np.max(reach) / PROFILE_STEP - 1e-9)), 1)
    unit = np.arange(-half, half + 1) / half
    offsets = unit[None, :] * reach[:, None]  # (bsize, M) cycles
    points = u_np[:, None, :] + (offsets / cycles[:, None])[..., None] * direction[:, None, :]
    stacked = np.moveaxis(points, 1, 0)  # (M, bsize, p)
    losses = setup.losses(stacked if setup.batched else stacked[:, 0], setup.data())
    losses = np.asarray(losses).reshape(len(unit), setup.bsize).T  # (bsize, M)
    centre = np.argmin(np.abs(unit))
    used = np.sum(setup.mask & setup.fitted, axis=-1)
    s2 = 2 * losses[:, centre] / np.maximum(used - u_np.shape[1], 1)
    dchi2 = 2 * (losses - losses[:, centre : centre + 1]) / s2[:, None]
    return Profile(offsets=offsets, dchi2=dchi2, points=points, direction=direction, cycles=cycles)


def lower_points(profile: Profile) -> tuple[np.ndarray, np.ndarray]:
    """Per record: whether the profile holds a point `MOVE_CHI2` below the fit, and it."""
    best = np.argmin(np.where(np.isfinite(profile.dchi2), profile.dchi2, np.inf), axis=-1)
    rows = np.arange(best.size)
    lower = profile.dchi2[rows, best] < -MOVE_CHI2
    return lower, profile.points[rows, best]


def ambiguity(profile: Profile, se_spin_rel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per record: whether points beyond the local error bars fit as well, and the farthest
    such offset in the spin coordinate ($|k|/N$; 0 where none)."""
    local = 3.0 * np.asarray(se_spin_rel) * profile.cycles  # 3 standard errors, in cycles
    near = np.maximum(local, 1.0)[:, None]
    as_good = (profile.dchi2 <= AMBIGUOUS_CHI2) & (np.abs(profile.offsets) > near)
    farthest = np.max(np.where(as_good, np.abs(profile.offsets), 0.0), axis=-1)
    return as_good.any(axis=-1), farthest / profile.cycles


@eqx.filter_jit
def _physical_jacobian(u, base, free):
    def one(v, b):
        return jax.jacfwd(lambda w: jnp.stack([physical(w, b, free)[n] for n in free]))(v)

    return one(u, base) if u.ndim == 1 else jax.vmap(one)(u, base)


def widen(covariance, u, base, free, direction, reach):
    r"""$\Sigma \leftarrow \Sigma + a^2 (G v)(G v)^\top$, $G = \partial p/\partial u$, with
    $a$ = `reach`/3 (one per record; 0 leaves a record's covariance as it was)."""
    g = np.asarray(_physical_jacobian(jnp.asarray(u), base, free))
    gv = np.einsum("...ij,...j->...i", g, np.asarray(direction).reshape(g.shape[:-1]))
    a = (np.asarray(reach) / 3.0).reshape(gv.shape[:-1] + (1, 1))
    extra = a**2 * gv[..., :, None] * gv[..., None, :]
    return np.asarray(covariance) + extra
