r"""The slow stage: fit the envelope and the level-crossing times of the smoothed tilt.

Both are blind to the nutation's phase (the kernel averages over more than two nutation
periods), so this loss has one wide valley where the loss of the raw tilt has one per slipped
nutation cycle. It brings a start within reach of the raw tilt's valley: the inversion's timing
and shape pin $\mu$, $\epsilon$ and the spin to a few percent.
"""

from __future__ import annotations

from .base import AbstractStage, StageRun


class Levels(AbstractStage):
    """One optimisation of the slow observables alone (no raw tilt samples)."""

    def run(self, u, setup) -> StageRun:
        data = setup.data(theta=False, slow=1.0)
        u, history, k, code = setup.optimise(u, data)
        return StageRun(u=u, histories=[history], counts=[k], code=code)
