r"""The final stage: the raw tilt of the whole (fitted) record alone, at the fit's tolerance.

This is the loss the covariance describes: $\tfrac12\sum_k w_k(\theta(t_k; p) -
\theta^{obs}_k)^2$ with nothing else in it, so the estimate is the least-squares one and its
standard errors are the Gauss-Newton ones.
"""

from __future__ import annotations

from .base import AbstractStage, StageRun


class Final(AbstractStage):
    """One optimisation of the whole record's tilt at the fit's own tolerances; with
    `final=False`, at the intermediate stages' looser ones (most of the steps, at a fraction
    of the cost of the fit's simulation tolerance)."""

    final: bool = True

    def run(self, u, setup) -> StageRun:
        if self.final:
            data = setup.data(tol=setup.tol, final=True)
        else:
            data = setup.data()
        u, history, k, code = setup.optimise(u, data)
        return StageRun(u=u, histories=[history], counts=[k], code=code)
