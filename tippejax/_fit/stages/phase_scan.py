r"""Phase scan: find the nutation's phase by scanning the spin on windows that grow.

The raw tilt's loss has one narrow minimum per slipped nutation cycle: the nutation's phase
slips by about one cycle per $1/N$ of relative spin, $N$ the number of nutation cycles in
the window fitted, so an optimiser only finds the nearest minimum. The slow observables
(`levels.py`) pin the envelope of the tilt but leave a valley: a change of the spin traded
against the other parameters keeps the envelope. So the stage finds the spin from the nutation
first and the rest from the envelope, as a frequency is found from a short stretch of signal
and then refined on longer ones:

1. **The spin alone, early in the record.** On a first window of `first_cycles` nutation
   cycles ($N_0$, at least `min_samples` samples) the raw tilt's loss is evaluated along the
   spin coordinate $u_s + \delta$ on a grid over `[-span, span]` with a step of
   `resolution`$/N_0$: a window that short has one minimum per $1/N_0$ of relative spin, and
   the grid resolves it. The window then grows by `growth` ($N_{k+1} = g N_k$) and the loss is
   evaluated over `lobe`$/N_k$ either side of the last best point with a step of
   `resolution`$/N_{k+1}$, until the data's smoothed tilt has moved by `rise` from its start
   (early on, the other parameters barely change the tilt; the nutation's frequency,
   $\approx C|n|/(2\pi A)$, is the spin's). For a launch at a pole with a free tilt rate the
   scan moves $\log\dot\theta_0$ with the spin: the early tilt's size is about
   $\dot\theta_0 A/(C n)$, so the scan changes the frequency alone.
   A window narrows the scan only where its best point stands out of the noise: its
   chi-square gap between the scan's median and its lowest point (`_contrast`) must exceed
   `significance`. When the early nutation is below the noise, the lowest point of a short
   window is a draw from the noise, and narrowing around it would lock every later window
   onto a wrong cycle; such a window leaves the centre and the width as they were, and the
   next, longer window (which averages more samples) decides.
2. **The other parameters from the slow observables, the spin held**: without the spin's
   freedom the envelope and the level-crossing times have a valley floor, not a valley. That
   floor is narrow and the slow loss has plateaus (where a trial top does not turn over at
   all, a small change does not change the loss), so the other coordinates are first ranked
   on `search_points` points of a low-discrepancy set in the box `|u_o| <= search_box` around
   the guess (and the point itself), one batch; optimisations run from the `refine` best
   (at most `refine_steps` steps each: on the slow loss's plateaus an optimisation would
   otherwise use the fit's whole budget), and the lowest end point is kept. The slow loss has several
   local minima along the curve of matching inversion times, and the least-squares ranking
   of a coarse set does not always put the global one's basin first.
3. **Along the valley, on windows that grow to the whole record.** With $H$ the Hessian of
   the slow loss at the new point $u^*$ (central second differences with step
   `hessian_step`, in one batch), the valley is, to first order, $u(\delta) = u^* + \delta v$
   with $v_s = 1$ and $v_o = -H_{oo}^{-1} H_{os}$ (the other coordinates re-optimised for
   each spin). The scan of step 1 goes on along $v$ from the last window to the whole record.
4. **The best few cycles.** The valley is straight only to first order, so the last scan's
   best point can be a neighbouring cycle's. Its `candidates` lowest local minima are each
   refined on the whole record (at most `candidate_steps` steps each: enough to settle each
   in its cycle; the final stage polishes the winner), and the lowest end wins.

Each evaluation is a batch of simulations (`setup.CHUNK` at a time) that stop at the window's
end, so the whole scan costs about as much as a few batches over the record; a grid over the
whole record at the final resolution would take some 2000 simulations of it for 300 cycles.
$N$ is estimated from the fast-top nutation frequency at the fastest spin of the first scan.

Without a free spin the phase is fixed by the known spin, and the stage does nothing.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..params import _POLE_SIN
from ..setup import SEARCH_RTOL
from .base import AbstractStage, StageRun
from .global_search import low_discrepancy


class PhaseScan(AbstractStage):
    """Spin from the early nutation, the others from the envelope, then the phase along the
    slow valley over the whole record (see the module docstring)."""

    span: float = 0.7
    resolution: float = 0.25
    first_cycles: float = 10.0
    growth: float = 3.0
    lobe: float = 1.5
    min_samples: int = 32
    rise: float = 0.25
    search_points: int = 127
    search_box: float = 0.7
    refine: int = 8
    candidates: int = 4
    hessian_step: float = 0.02
    refine_steps: int = 20
    candidate_steps: int = 30
    significance: float = 25.0

    def run(self, u, setup) -> StageRun:
        free = setup.cfg.free
        if "spin" not in free:
            return StageRun(u=u, histories=[], counts=[], code=None)
        s = free.index("spin")
        batched = u.ndim == 2
        p = len(free)
        u_np = np.asarray(u, float).reshape(-1, p)
        bsize = u_np.shape[0]
        ts = setup.ts
        start, end = ts[0], ts[-1]
        # nutation cycles per second at the fastest spin of the scan, per record
        rate = setup.nutation_cycles(u_np[:, s] + self.span) / max(end - start, 1e-300)
        rate = np.maximum(rate, 1e-300)
        first = ts[min(self.min_samples, ts.size) - 1]
        window = np.clip(start + self.first_cycles / rate, first, end)  # (bsize,)
        # the early part: until the data's smoothed tilt has moved by `rise`
        grid = np.broadcast_to(
            np.asarray(setup.template.grid), (bsize, setup.template.grid.shape[-1])
        )
        smooth = np.asarray(setup.template.smooth_obs).reshape(bsize, -1)
        moved = np.abs(smooth - smooth[:, :1]) > self.rise
        early = np.where(moved.any(1), grid[np.arange(bsize), np.argmax(moved, 1)], end)
        early = np.maximum(early, window)

        # 1. the spin alone
        along_spin = np.zeros((bsize, p))
        along_spin[:, s] = 1.0
        if "theta_dot" in free:  # a launch at a pole: the early tilt's size is ~ theta_dot / n
            at_pole = (
                np.sin(np.asarray(setup.template.base.launch["theta0"])).reshape(-1) < _POLE_SIN
            )
            along_spin[:, free.index("theta_dot")] = np.broadcast_to(at_pole, (bsize,)).astype(
                float
            )
        centre, window, _ = self._scan(
            u_np,
            along_spin,
            setup,
            rate,
            window,
            np.full(bsize, self.span),
            early,
            batched,
            u.dtype,
        )
        u_np = u_np + centre[:, None] * along_spin
        # 2. the others from the slow observables, the spin held
        histories, counts, code = [], [], None
        if p > 1:
            others = [i for i in range(p) if i != s]
            offsets = np.zeros((self.search_points + 1, p))
            offsets[1:, others] = self.search_box * low_discrepancy(self.search_points, p - 1)
            points = np.repeat(u_np[None], offsets.shape[0], 0)  # (K, bsize, p)
            points[1:, :, others] = offsets[1:, None, others]  # around the guess (u = 0)
            losses = setup.losses(
                points if batched else points[:, 0],
                setup.data(theta=False, slow=1.0, rtol=SEARCH_RTOL, search=True),
            )
            order = np.argsort(losses.reshape(points.shape[0], -1), axis=0)[: self.refine]
            starts = points[order, np.arange(bsize)[None, :]]  # (refine, bsize, p)
            slow = setup.data(
                theta=False, slow=1.0, pin=("spin",), steps=self.refine_steps, search=True
            )
            ends, _ = setup.optimise_many(
                jnp.asarray(starts if batched else starts[:, 0], u.dtype), slow
            )
            ends = np.asarray(ends, float).reshape(self.refine, bsize, p)
            end_losses = setup.losses(ends if batched else ends[:, 0], slow)
            best = np.argmin(end_losses.reshape(self.refine, -1), axis=0)
            u_np = ends[best, np.arange(bsize)]
        # 3. along the valley, from the last window to the whole record
        if np.any(window < end):
            directions = valley_directions(u_np, setup, batched, s, self.hessian_step)
            cycles = np.maximum((window - start) * rate, 1.0)
            half = np.minimum(self.lobe / cycles, self.span)
            nxt = np.minimum(start + self.growth * (window - start), end)
            _, _, minima = self._scan(
                u_np, directions, setup, rate, nxt, half, np.full(bsize, end), batched, u.dtype
            )
            # 4. the best few cycles of the last scan, each refined on the whole record; the
            # lowest end wins (the valley is only straight to first order, so the
            # scan's best point can be a neighbouring cycle's)
            u_np = refine_candidates(
                u_np, minima, directions, setup, batched, u.dtype, self.candidate_steps
            )
        new = u_np if batched else u_np[0]
        return StageRun(u=jnp.asarray(new, u.dtype), histories=histories, counts=counts, code=code)

    def _scan(self, u_np, directions, setup, rate, window, half, stop, batched, dtype):
        """Coarse-to-fine scan of the raw tilt's loss along `directions` on windows from
        `window` to `stop` (per record); returns the best offset and the last window."""
        start = setup.ts[0]
        centre = np.zeros(u_np.shape[0])
        while True:
            data = setup.data(window_end=window, rtol=SEARCH_RTOL, search=True)
            cycles = np.maximum((window - start) * rate, 1.0)
            step = self.resolution / cycles
            count = int(max(np.max(np.ceil(2 * half / step)) + 1, 3))
            grid = np.linspace(-1.0, 1.0, count)
            deltas = centre[None, :] + grid[:, None] * half[None, :]  # (count, bsize)
            points = u_np[None] + deltas[:, :, None] * directions[None]  # (count, bsize, p)
            points = points if batched else points[:, 0]
            losses = setup.losses(points, data).reshape(count, -1)
            best = np.argmin(losses, axis=0)
            # Narrow only where the window's best point stands out of the noise: on a window
            # whose nutation is below the noise the lowest point is a draw from it, and
            # narrowing around it would lock the scan onto a wrong cycle for good.
            clear = (window >= stop) | (_contrast(losses, setup, window) > self.significance)
            centre = np.where(clear, deltas[best, np.arange(deltas.shape[1])], centre)
            if np.all(window >= stop):
                return centre, window, _local_minima(losses, deltas, self.candidates)
            half = np.where(clear, np.minimum(self.lobe / cycles, self.span), half)
            window = np.minimum(start + self.growth * (window - start), stop)


def refine_candidates(u_np, offsets, directions, setup, batched, dtype, steps):
    """Each record's candidates `u + offset * direction` (`offsets` of shape `(K, bsize)`)
    refined on the whole record for at most `steps` steps; the lowest end wins. Returns the
    winners, shape `(bsize, p)`."""
    points = u_np[None] + offsets[:, :, None] * directions[None]  # (K, bsize, p)
    full = setup.data(steps=steps, search=True)
    ends, _ = setup.optimise_many(jnp.asarray(points if batched else points[:, 0], dtype), full)
    ends = np.asarray(ends, float).reshape(points.shape)
    end_losses = setup.losses(ends if batched else ends[:, 0], full)
    best = np.argmin(end_losses.reshape(points.shape[0], -1), axis=0)
    return ends[best, np.arange(points.shape[1])]


def _contrast(losses, setup, window):
    r"""How far each record's scan stands out of the noise: the chi-square gap between the
    scan's median and its lowest point, $n\,(L_{med} - L_{min}) / L_{min}$ with $n$ the
    samples in the window. The noise variance is taken from the lowest point itself
    ($2 L_{min} / n$ with unit weights, an upper bound on it), so the gap is never
    overstated."""
    n = np.sum(setup.mask & setup.fitted & (setup.ts[None, :] <= window[:, None] + 1e-12), 1)
    low = np.min(losses, axis=0)
    gap = np.median(losses, axis=0) - low
    return np.where(low > 0, n * gap / np.maximum(low, 1e-300), np.inf)


def valley_directions(u_np, setup, batched, s, step):
    """The slow loss's valley direction at each record's `u` (shape `(bsize, p)`; spin
    component 1): $v_o = -H_{oo}^{-1} H_{os}$, the other coordinates re-optimised for a change
    of the spin coordinate, from the Hessian by central second differences of size `step`."""
    p = u_np.shape[1]
    directions = []
    for h in _hessians(u_np, setup, batched, step):
        others = [i for i in range(p) if i != s]
        v = np.zeros(p)
        v[s] = 1.0
        if others:
            h_oo = h[np.ix_(others, others)]
            h_oo = h_oo + 1e-9 * abs(np.trace(h_oo)) * np.eye(len(others))
            v[others] = -np.linalg.solve(h_oo, h[others, s])
        directions.append(v)
    return np.stack(directions)


def _hessians(u_np, setup, batched, h):
    """Hessian of the slow loss at each record's `u` by central second differences."""
    p = u_np.shape[1]
    eye = np.eye(p)
    offsets = [np.zeros(p)]
    for i in range(p):
        offsets += [2 * h * eye[i], -2 * h * eye[i]]
    pairs = [(i, j) for i in range(p) for j in range(i + 1, p)]
    for i, j in pairs:
        offsets += [
            h * (eye[i] + eye[j]),
            h * (eye[i] - eye[j]),
            h * (-eye[i] + eye[j]),
            -h * (eye[i] + eye[j]),
        ]
    offsets = np.array(offsets)
    count = offsets.shape[0]
    points = u_np[None] + offsets[:, None, :]
    points = points if batched else points[:, 0]
    data = setup.data(theta=False, slow=1.0, rtol=SEARCH_RTOL, search=True)
    loss = setup.losses(points, data).reshape(count, -1)  # (count, bsize)
    out = np.zeros((loss.shape[1], p, p))
    for i in range(p):
        out[:, i, i] = (loss[1 + 2 * i] - 2 * loss[0] + loss[2 + 2 * i]) / (4 * h * h)
    base = 1 + 2 * p
    for k, (i, j) in enumerate(pairs):
        pp, pm, mp, mm = loss[base + 4 * k : base + 4 * k + 4]
        out[:, i, j] = out[:, j, i] = (pp - pm - mp + mm) / (4 * h * h)
    return out


def _local_minima(losses, deltas, k):
    """The offsets of the `k` lowest local minima of each record's scan (shape `(k, bsize)`;
    the best one repeated where there are fewer)."""
    count, bsize = losses.shape
    out = np.empty((k, bsize))
    for b in range(bsize):
        f = losses[:, b]
        left = np.concatenate([[np.inf], f[:-1]])
        right = np.concatenate([f[1:], [np.inf]])
        idx = np.flatnonzero((f <= left) & (f <= right) & np.isfinite(f))
        if idx.size == 0:
            idx = np.array([int(np.argmin(f))])
        idx = idx[np.argsort(f[idx])][:k]
        idx = np.concatenate([idx, np.full(k - idx.size, idx[0])])
        out[:, b] = deltas[idx, b]
    return out
