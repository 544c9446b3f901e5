"""The interface of a launch projection onto the slow manifold, and its names."""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx

from ..._state import State
from ..._top import TippeTop
from .state import GyroscopicLevelState

PROJECTIONS = ("averaged", "fibre", "linear")
"""The names `GyroscopicLevel(projection=...)` also accepts in place of a projection object:
`AveragedProjection()`, `FibreProjection()` and `LinearProjection()`."""


class AbstractProjection(eqx.Module):
    r"""How a state of the top (a launch) is put onto the slow manifold of the gyroscopic level.

    A launch with $\omega = n a$ is not on the slow manifold: most of it is the other root's
    mode (a nutation that decays), and the slow flow must start from the launch's slow-mode
    content, not from its tilt. A projection returns that slow state and the amplitude of the
    nutation it sets aside (derivations: `docs/derivations/launch-projection.md`).

    The family: `AveragedProjection` (the default: first-order averaging over the nutation, in
    closed form), `LinearProjection` (the split into the two modes near a pole) and
    `FibreProjection` (`tippejax/_engine/fibre.py`: the launch followed in the SO(3) model until
    its nutation has decayed, a solve per launch).

    **Class attribute:** `name`, the projection's name in `PROJECTIONS`.
    """

    name: ClassVar[str]

    @abc.abstractmethod
    def project(self, top: TippeTop, state: State) -> GyroscopicLevelState:
        """The slow state of a (single) common `State`, with its nutation's amplitude."""


def _final_projections(cls=AbstractProjection):
    for sub in cls.__subclasses__():
        if "name" in vars(sub):
            yield sub
        yield from _final_projections(sub)


def projection_of(projection: AbstractProjection | str) -> AbstractProjection:
    """`projection` as a projection object: an `AbstractProjection` as it is, or one of the
    names of `PROJECTIONS`."""
    if isinstance(projection, AbstractProjection):
        return projection
    if isinstance(projection, str):
        for cls in _final_projections():
            if cls.name == projection:
                return cls()
        if projection in PROJECTIONS:  # (defined above this layer, imported with tippejax)
            raise ValueError(
                f"GyroscopicLevel: the projection {projection!r} is not loaded; "
                "import tippejax first."
            )
    raise ValueError(
        f"GyroscopicLevel: projection must be a projection object (AveragedProjection(), "
        f"FibreProjection() or LinearProjection()) or one of the names {PROJECTIONS}, got "
        f"{projection!r}."
    )
