r"""Valley scan: the nutation's phase found along the slow loss's valley, never across it.

`PhaseScan` finds the spin first, from the raw tilt on an early window with the other
parameters held where the search left them. That holds only while the window is too early for
the others to matter. On a slowly rising record the "early" window (until the tilt has moved)
is most of the record; the scan then moves the spin to make up for the others' error in the
slow motion, and the fit ends tens of percent away (tilted Group IIa and IIc tops whose tilt
first falls, then rises over many seconds). This stage keeps the slow motion matched, so that its scan sees the nutation's phase:

1. **Onto the valley.** The start is refined on the slow loss (`levels.py`: the smoothed
   tilt's envelope and its level-crossing times, blind to the phase) with every free
   parameter free, at most `refine_steps` steps. The slow loss has a valley, not a point: a
   change of the spin traded against the others keeps the envelope.
2. **Along it.** With $H$ the slow loss's Hessian at that point $u^*$, the valley is to
   first order $u(\delta) = u^* + \delta v$, $v_s = 1$, $v_o = -H_{oo}^{-1}H_{os}$
   (`valley_directions`). The raw tilt's loss is scanned along it on windows that grow from
   `first_cycles` nutation cycles by `growth`, over $\pm$`span` in the spin coordinate at
   first, with a step of `resolution`$/N$ for $N$ cycles in the window (the phase slips by
   one cycle per $1/N$ of relative spin). A window narrows the scan, to $\pm$`lobe` cycles
   around its lowest point, only where that point stands out of the noise (a chi-square gap
   above `significance`, `phase_scan._contrast`); otherwise the next, longer window decides.
   A scan is cut to `max_points` points around its centre.
3. **Back onto the valley** when a window has moved the scan's centre by more than
   `recentre` in $u_s$: the others are refitted on the slow loss with the spin held there
   (at most `recentre_steps` steps), and the valley direction is taken again (the valley is
   straight only to first order).
4. **The best few cycles** of the whole-record scan (its `candidates` lowest local minima)
   are each refined on the whole record (at most `candidate_steps` steps), and the lowest
   end wins.

Where the slow loss's floor is itself biased by the noise (a floor that misses the truth, as
on benchmark record 52) the straight valley may pass the truth's cycle by; and where the slow
loss pins only one combination of the parameters (a sheet, not a valley: a top whose rise
time alone is measured, record 8) the scan is along an arbitrary line of the sheet. Both end
in a fit whose residuals are not noise, which is then flagged. Without a free spin there is
no phase to find and the stage does nothing.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..setup import SEARCH_RTOL
from .base import AbstractStage, StageRun
from .phase_scan import _contrast, _local_minima, refine_candidates, valley_directions


class ValleyScan(AbstractStage):
    """The phase along the slow loss's valley, on windows that grow to the whole record (see
    the module docstring)."""

    span: float = 0.7
    resolution: float = 0.25
    first_cycles: float = 10.0
    growth: float = 3.0
    lobe: float = 1.5
    min_samples: int = 32
    max_points: int = 512
    recentre: float = 0.02
    refine_steps: int = 30
    recentre_steps: int = 15
    candidates: int = 4
    candidate_steps: int = 30
    hessian_step: float = 0.02
    significance: float = 25.0

    def run(self, u, setup) -> StageRun:
        free = setup.cfg.free
        if "spin" not in free:
            return StageRun(u=u, histories=[], counts=[], code=None)
        s = free.index("spin")
        batched = u.ndim == 2
        p = len(free)
        dtype = u.dtype

        def as_u(x):  # (bsize, p) numpy -> the stage's coordinates
            return jnp.asarray(x if batched else x[0], dtype)

        def as_np(x):
            return np.asarray(x, float).reshape(-1, p)

        ts = setup.ts
        start, end = ts[0], ts[-1]
        histories, counts = [], []
        # 1. onto the valley: the slow loss, everything free
        slow = setup.data(theta=False, slow=1.0, steps=self.refine_steps, search=True)
        u_v, history, k, _ = setup.optimise(u, slow)
        histories.append(history)
        counts.append(k)
        u_np = as_np(u_v)
        bsize = u_np.shape[0]
        directions = valley_directions(u_np, setup, batched, s, self.hessian_step)
        # 2. along it, on windows that grow
        rate = setup.nutation_cycles(u_np[:, s] + self.span) / max(end - start, 1e-300)
        rate = np.maximum(rate, 1e-300)
        first = ts[min(self.min_samples, ts.size) - 1]
        window = np.clip(start + self.first_cycles / rate, first, end)
        centre = np.zeros(bsize)
        half = np.full(bsize, self.span)
        while True:
            data = setup.data(window_end=window, rtol=SEARCH_RTOL, search=True)
            cycles = np.maximum((window - start) * rate, 1.0)
            step = self.resolution / cycles
            count = int(np.clip(np.max(np.ceil(2 * half / step)) + 1, 3, self.max_points))
            grid = np.linspace(-1.0, 1.0, count)
            width = np.minimum(half, 0.5 * (count - 1) * step)
            deltas = centre[None, :] + grid[:, None] * width[None, :]  # (count, bsize)
            points = u_np[None] + deltas[:, :, None] * directions[None]
            losses = setup.losses(points if batched else points[:, 0], data).reshape(count, -1)
            best = np.argmin(losses, axis=0)
            last = window >= end
            clear = last | (_contrast(losses, setup, window) > self.significance)
            centre = np.where(clear, deltas[best, np.arange(bsize)], centre)
            if np.all(last):
                break
            half = np.where(clear, np.minimum(self.lobe / cycles, self.span), half)
            # 3. back onto the valley where the scan has moved along it
            moved = clear & (np.abs(centre) > self.recentre)
            if moved.any():
                shifted = u_np + np.where(moved, centre, 0.0)[:, None] * directions
                held = setup.data(
                    theta=False, slow=1.0, pin=("spin",), steps=self.recentre_steps, search=True
                )
                new, history, k, _ = setup.optimise(as_u(shifted), held)
                histories.append(history)
                counts.append(k)
                u_np = np.where(moved[:, None], as_np(new), u_np)
                fresh = valley_directions(u_np, setup, batched, s, self.hessian_step)
                directions = np.where(moved[:, None], fresh, directions)
                centre = np.where(moved, 0.0, centre)
            window = np.minimum(start + self.growth * (window - start), end)
        # 4. the best few cycles, each refined on the whole record; the lowest end wins
        minima = _local_minima(losses, deltas, self.candidates)
        new = refine_candidates(
            u_np, minima, directions, setup, batched, dtype, self.candidate_steps
        )
        return StageRun(u=as_u(new), histories=histories, counts=counts, code=None)
