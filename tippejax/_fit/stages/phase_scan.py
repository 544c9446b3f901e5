r"""Phase scan: find the nutation's valley along the slow loss's valley, in one batch.

The slow observables (`levels.py`) pin the envelope of the tilt, which leaves a valley: a
change of the spin $\delta$ traded against the other parameters keeps the envelope. Along it
the nutation's phase slips by about one cycle per $1/N$ of relative spin, $N$ the number of
nutation cycles in the record, so the raw tilt's loss along the valley has one narrow minimum
per cycle and an optimiser only finds the nearest.

With $H$ the Hessian of the slow loss at the stage's start $u^*$ (central second differences
with step `hessian_step`, all points in one batch of the search's compiled loss) and $s$ the
index of the spin, the valley is, to first order,
$u(\delta) = u^* + \delta\,v$ with $v_s = 1$ and $v_o = -H_{oo}^{-1} H_{os}$ (the other
coordinates re-optimised for each spin). The raw tilt's loss over the whole record is evaluated
at $\delta$ on a grid over `[-span, span]` with a step of `resolution`$/N$ (one batch of
simulations, in chunks), and the stage moves to the grid's best point. The default span is the
global search's box: the slow loss can leave the spin as far off as the box allows. $N$ is estimated from
the fast-top nutation frequency $C|n|/A$ over the record.

Without a free spin the phase is fixed by the known spin, and the stage does nothing.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..setup import SEARCH_RTOL
from .base import AbstractStage, StageRun

CHUNK = 128  # starting points per batch (the global search's batch size: one compilation)


class PhaseScan(AbstractStage):
    """Move to the best point of the raw tilt's loss on a fine grid along the slow valley."""

    span: float = 0.7
    resolution: float = 0.25
    max_points: int = 2048
    hessian_step: float = 0.02

    def run(self, u, setup) -> StageRun:
        free = setup.cfg.free
        if "spin" not in free:
            return StageRun(u=u, histories=[], counts=[], code=None)
        s = free.index("spin")
        batched = u.ndim == 2
        u_np = np.asarray(u).reshape(-1, len(free))
        hessians = self._hessians(u_np, setup, batched, u.dtype)
        directions = []
        for h in hessians:
            others = [i for i in range(len(free)) if i != s]
            v = np.zeros(len(free))
            v[s] = 1.0
            if others:
                h_oo = h[np.ix_(others, others)]
                h_oo = h_oo + 1e-9 * abs(np.trace(h_oo)) * np.eye(len(others))
                v[others] = -np.linalg.solve(h_oo, h[others, s])
            directions.append(v)
        directions = np.stack(directions)  # (bsize, p)
        # the most cycles over the scan: at its fastest spin
        cycles = setup.nutation_cycles(u_np[:, s]) * np.exp(self.span)
        step = self.resolution / max(float(np.max(cycles)), 1.0)
        count = int(min(self.max_points, 2 * np.ceil(self.span / step) + 1))
        deltas = np.linspace(-self.span, self.span, count)
        data = setup.data(rtol=SEARCH_RTOL)
        losses = []
        for lo in range(0, count, CHUNK):
            d = deltas[lo: lo + CHUNK]
            d = np.concatenate([d, np.full(CHUNK - d.size, d[-1])])
            points = u_np[None] + d[:, None, None] * directions[None]  # (CHUNK, bsize, p)
            points = points if batched else points[:, 0]
            losses.append(np.asarray(setup.losses(jnp.asarray(points, u.dtype), data))[: min(CHUNK, count - lo)])
        losses = np.concatenate(losses).reshape(count, -1)
        losses = np.where(np.isfinite(losses), losses, np.inf)
        best = np.argmin(losses, axis=0)  # (bsize,)
        new = u_np + deltas[best][:, None] * directions
        new = new if batched else new[0]
        return StageRun(u=jnp.asarray(new, u.dtype), histories=[], counts=[], code=None)

    def _hessians(self, u_np, setup, batched, dtype):
        """Hessian of the slow loss at each record's `u` by central second differences."""
        p = u_np.shape[1]
        h = self.hessian_step
        eye = np.eye(p)
        offsets = [np.zeros(p)]
        for i in range(p):
            offsets += [2 * h * eye[i], -2 * h * eye[i]]
        pairs = [(i, j) for i in range(p) for j in range(i + 1, p)]
        for i, j in pairs:
            offsets += [h * (eye[i] + eye[j]), h * (eye[i] - eye[j]),
                        h * (-eye[i] + eye[j]), -h * (eye[i] + eye[j])]
        offsets = np.array(offsets)
        count = offsets.shape[0]
        padded = np.concatenate([offsets, np.zeros((CHUNK - count, p))])
        points = u_np[None] + padded[:, None, :]
        points = points if batched else points[:, 0]
        data = setup.data(theta=False, slow=1.0, rtol=SEARCH_RTOL)
        loss = np.asarray(setup.losses(jnp.asarray(points, dtype), data))[:count]
        loss = loss.reshape(count, -1)  # (count, bsize)
        out = np.zeros((loss.shape[1], p, p))
        for i in range(p):
            out[:, i, i] = (loss[1 + 2 * i] - 2 * loss[0] + loss[2 + 2 * i]) / (4 * h * h)
        base = 1 + 2 * p
        for k, (i, j) in enumerate(pairs):
            pp, pm, mp, mm = loss[base + 4 * k: base + 4 * k + 4]
            out[:, i, j] = out[:, j, i] = (pp - pm - mp + mm) / (4 * h * h)
        return out
