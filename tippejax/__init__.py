"""tippejax: dynamics of the tippe top in JAX (Ciocci & Langerock, Routhian reduction).

Importing tippejax turns on float64 (`jax_enable_x64`), which the science needs. To stay in
float32, set the environment variable `TIPPEJAX_ENABLE_X64=0` before the import.

Importing tippejax also turns on JAX's persistent compilation cache in a user cache directory
(`$XDG_CACHE_HOME/tippejax/jax`, default `~/.cache/tippejax/jax`), so a new process does not
compile again; `TIPPEJAX_COMPILATION_CACHE=0` turns it off, and a cache directory the user
configured is kept (`tippejax/_cache/`).

The public API is this flat namespace. Internals (vector fields, the Routhian plumbing, the
linear-stability cross-checks, the engine) stay importable from their private modules.
"""

import importlib.metadata as _metadata
import os as _os
import warnings as _warnings

import jax as _jax

from . import _devices as _devices  # every CPU core a JAX device (TIPPEJAX_HOST_DEVICES=1: one)

if _os.environ.get("TIPPEJAX_ENABLE_X64", "1").strip().lower() not in ("0", "false", "no"):
    _jax.config.update("jax_enable_x64", True)

# Persistent compilation cache in ~/.cache/tippejax/jax; TIPPEJAX_COMPILATION_CACHE=0 turns it off.
from . import _cache as _cache  # (turns it on when imported)
from ._analysis.groups import (
    GROUPS as GROUPS,
    Thresholds as Thresholds,
    classify as classify,
    thresholds as thresholds,
)
from ._analysis.potential import (
    effective_potential as effective_potential,
    effective_potential_derivative as effective_potential_derivative,
)
from ._analysis.steady_states import SteadyStates as SteadyStates, steady_states as steady_states
from ._animate import animate as animate
from ._batch import simulate_batch as simulate_batch
from ._engine import fibre as _fibre  # noqa: F401  (GyroscopicLevel(projection="fibre"))
from ._engine.cpu import compiler_options as compiler_options
from ._engine.solver_choice import default_solver as default_solver, friction_rate as friction_rate
from ._fit import (
    FIT_RESULTS as FIT_RESULTS,
    FitResult as FitResult,
    LawComparison as LawComparison,
    compare_laws as compare_laws,
    fit as fit,
)
from ._friction.base import AbstractFriction as AbstractFriction
from ._friction.coulomb import Coulomb as Coulomb
from ._friction.coulomb_contensou import CoulombContensou as CoulombContensou
from ._friction.viscous import Viscous as Viscous
from ._invariants import (
    energy as energy,
    jellet as jellet,
    jellet_rate as jellet_rate,
    normal_force as normal_force,
    normal_force_denominator as _normal_force_denominator,
    slip_velocity as slip_velocity,
)
from ._inversion import inversion_time as inversion_time
from ._maps import (
    MapBoundary as MapBoundary,
    OutcomeMap as OutcomeMap,
    outcome_map as outcome_map,
    outcome_map_tops as outcome_map_tops,
)
from ._models.routhian import CHART_SIN_MIN as _CHART_SIN_MIN
from ._outcome import OUTCOMES as OUTCOMES
from ._simulate import MODELS as MODELS, simulate as simulate
from ._solution import RESULTS as RESULTS, Solution as Solution
from ._state import (
    State as State,
    euler_angles as euler_angles,
    euler_rates as euler_rates,
    initial_state as initial_state,
    state_from_euler as state_from_euler,
)
from ._stem import Stem as Stem
from ._top import TippeTop as TippeTop, default_top as default_top

try:
    __version__ = _metadata.version("tippejax")
except _metadata.PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0"

__all__ = [
    "AbstractFriction",
    "Coulomb",
    "CoulombContensou",
    "GROUPS",
    "FIT_RESULTS",
    "MODELS",
    "OUTCOMES",
    "RESULTS",
    "FitResult",
    "LawComparison",
    "MapBoundary",
    "OutcomeMap",
    "Solution",
    "State",
    "SteadyStates",
    "Stem",
    "Thresholds",
    "TippeTop",
    "Viscous",
    "animate",
    "classify",
    "compare_laws",
    "compiler_options",
    "default_solver",
    "default_top",
    "effective_potential",
    "effective_potential_derivative",
    "energy",
    "euler_angles",
    "euler_rates",
    "fit",
    "friction_rate",
    "initial_state",
    "inversion_time",
    "jellet",
    "jellet_rate",
    "normal_force",
    "outcome_map",
    "outcome_map_tops",
    "simulate",
    "simulate_batch",
    "slip_velocity",
    "state_from_euler",
    "steady_states",
    "thresholds",
]

# Internals that were once exported: still importable as `tippejax.<name>`, with a warning.
_DEPRECATED = {
    "CHART_SIN_MIN": (
        _CHART_SIN_MIN,
        "the Routhian level's chart edge, an internal of model='routhian' "
        "(tippejax._models.routhian.CHART_SIN_MIN)",
    ),
    "normal_force_denominator": (
        _normal_force_denominator,
        "the denominator of R_n (eq. reactie), an internal of the levels "
        "(tippejax._invariants.normal_force_denominator); a run that reaches the singularity "
        "reports RESULTS.normal_force_singular, and tj.normal_force gives R_n",
    ),
}


def __getattr__(name):
    if name in _DEPRECATED:
        value, what = _DEPRECATED[name]
        _warnings.warn(
            f"tippejax.{name} is deprecated and will be removed from the public namespace: it "
            f"is {what}.",
            DeprecationWarning,
            stacklevel=2,
        )
        return value
    raise AttributeError(f"module 'tippejax' has no attribute {name!r}")


def __dir__():
    return sorted([*__all__, "__version__"])
