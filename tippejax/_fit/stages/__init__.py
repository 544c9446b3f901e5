"""The stages of a fit, one per file, behind `AbstractStage` (see `base.py`)."""

from .base import (
    AbstractSearch as AbstractSearch,
    AbstractStage as AbstractStage,
    StageRun as StageRun,
)
from .final import Final as Final
from .global_search import GlobalSearch as GlobalSearch
from .levels import Levels as Levels
from .phase_scan import PhaseScan as PhaseScan
from .valley_scan import ValleyScan as ValleyScan
from .windows import Windows as Windows
