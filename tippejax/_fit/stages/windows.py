r"""Window continuation: the raw tilt of a window that doubles from a short first one.

The nutation's phase error grows with time and with the error in the spin: 1% in the spin
slips it by a cycle over the rise of the standard top, so a fit of a long record from a start a
few percent off lands in another valley. The first window holds 1/64 of the record (at least
10 samples), short enough that the phase error is under a cycle; each next window is twice as
long and starts from where the previous one ended, until the window is the record. With
`slow=True` the slow observables stay in the loss, pinning the directions an early window
leaves free.
"""

from __future__ import annotations

import numpy as np

from .base import AbstractStage, StageRun


def window_ends(ts: np.ndarray) -> list[float]:
    """Ends of the growing windows (the last one is the record's end)."""
    span = ts[-1] - ts[0]
    width = max(span / 64, ts[min(10, ts.size - 1)] - ts[0])
    ends = []
    while width < span:
        ends.append(float(ts[0] + width))
        width *= 2
    return ends + [float(ts[-1])]


class Windows(AbstractStage):
    """Optimisations on the tilt up to each window end in turn (the last window excluded:
    that is the final stage's)."""

    slow: bool = True

    def run(self, u, setup) -> StageRun:
        histories, counts, code = [], [], None
        slow = 1.0 if self.slow else 0.0
        for end in window_ends(setup.ts)[:-1]:
            u, history, k, code = setup.optimise(u, setup.data(window_end=end, slow=slow))
            histories.append(history)
            counts.append(k)
        return StageRun(u=u, histories=histories, counts=counts, code=code)
