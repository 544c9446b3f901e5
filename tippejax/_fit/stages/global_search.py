r"""Global search: many starting points simulated in one batch, ranked by the slow loss.

The loss of the slow observables (see `levels.py`) is evaluated at `candidates` points of a
low-discrepancy set (the $R_p$ sequence of Roberts, $x_k = \{\tfrac12 + k\,\alpha\}$ with
$\alpha_i = \phi_p^{-i}$ and $\phi_p$ the positive root of $x^{p+1} = x + 1$) in the box
$|u_i| \le$ `box` around the guess, and at the guess itself, all in one vmapped batch of
simulations at a loose tolerance. The `keep` best distinct points are the starts the
refinement stages try in turn, best first. With `box = 0.7` the box spans a factor of 2 either
way in every log-scaled parameter, so a guess 30% off (0.36 in $u$) is well inside it.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..setup import SEARCH_RTOL
from .base import AbstractSearch


def low_discrepancy(n: int, dim: int) -> np.ndarray:
    """`n` points of the R_dim sequence in [-1, 1]^dim."""
    phi = 2.0
    for _ in range(64):  # fixed point of x = (1 + x)^(1/(dim+1))
        phi = (1.0 + phi) ** (1.0 / (dim + 1))
    alpha = phi ** -np.arange(1, dim + 1)
    k = np.arange(1, n + 1)[:, None]
    return 2.0 * np.mod(0.5 + k * alpha[None, :], 1.0) - 1.0


class GlobalSearch(AbstractSearch):
    """Rank `candidates` points of the box `|u| <= box` (and the guess) by the slow loss."""

    candidates: int = 127  # with the guess: four batches of `setup.CHUNK` (32)
    keep: int = 3
    box: float = 0.7

    def starts(self, u, setup):
        p = u.shape[-1]
        points = self.box * low_discrepancy(self.candidates, p)
        points = np.concatenate([np.zeros((1, p)), points])  # the guess itself first
        shape = (points.shape[0],) + u.shape
        starts = (
            jnp.asarray(
                np.broadcast_to(
                    points.reshape((points.shape[0],) + (1,) * (u.ndim - 1) + (p,)), shape
                ),
                u.dtype,
            )
            + u[None]
        )
        losses = setup.losses(
            starts, setup.data(theta=False, slow=1.0, rtol=SEARCH_RTOL, search=True)
        )
        order = np.argsort(losses, axis=0)[: self.keep]  # (keep, *batch)
        starts_np = np.asarray(starts)
        if u.ndim == 1:
            return jnp.asarray(starts_np[order])
        picked = np.stack([starts_np[order[:, b], b] for b in range(u.shape[0])], axis=1)
        return jnp.asarray(picked)
