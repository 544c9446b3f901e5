"""Fitting: one stage per file (`stages/`), behind one interface (`stages/base.py`)."""

from .compare import (
    CRITERIA as CRITERIA,
    LawComparison as LawComparison,
    compare_laws as compare_laws,
    law_name as law_name,
)
from .fit import fit as fit
from .inputs import FIT_MODELS as FIT_MODELS, METHODS as METHODS
from .params import (
    FREE_NAMES as FREE_NAMES,
    LAUNCH_FIELDS as LAUNCH_FIELDS,
    TOP_FIELDS as TOP_FIELDS,
)
from .problem import FAILED_RESIDUAL as FAILED_RESIDUAL
from .result import FIT_RESULTS as FIT_RESULTS, FitResult as FitResult
from .strategies import STRATEGIES as STRATEGIES
