"""Outcome maps: dense or adaptive, over any two launch quantities or fields of the top."""

from .boundaries import MapBoundary as MapBoundary
from .maps import (
    OUTCOMES as OUTCOMES,
    outcome_map as outcome_map,
    outcome_map_tops as outcome_map_tops,
)
from .result import OutcomeMap as OutcomeMap
