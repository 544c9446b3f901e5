r"""The interface of a fit's stages.

A fit is a search for starting points followed by a chain of refinement stages, in the way an
optimistix solver is a small Module with one interface:

- an `AbstractSearch` maps the guess's coordinates $u_0$ (shape `(*batch, p)`) to ranked
  starting points (shape `(S, *batch, p)`), best first;
- an `AbstractStage` maps coordinates to coordinates by one or more optimisations, each of
  which sees the loss the stage chooses (`Setup.data`: which tilt samples, which slow
  observables, which tolerances), and reports the losses after each step.

Adding a stage is a new file with a final Module that implements `run`, and a place in a
strategy (`tippejax/_fit/strategies.py`).
"""

from __future__ import annotations

import abc

import equinox as eqx
from jaxtyping import Array, Float


class StageRun(eqx.Module):
    """What a stage returns: the coordinates it ended at, the loss after each optimiser step
    of each of its optimisations, their step counts, and the last optimisation's code."""

    u: Float[Array, "*batch p"]
    histories: list
    counts: list
    code: object


class AbstractStage(eqx.Module):
    """Refines coordinates `u` (shape `(*batch, p)`)."""

    @abc.abstractmethod
    def run(self, u, setup) -> StageRun: ...


class AbstractSearch(eqx.Module):
    """Ranks starting points around the guess (`u = 0`); returns shape `(S, *batch, p)`."""

    @abc.abstractmethod
    def starts(self, u, setup) -> Float[Array, "S *batch p"]: ...
