"""tippejax: dynamics of the tippe top in JAX (Ciocci & Langerock, Routhian reduction).

Importing tippejax turns on float64 (`jax_enable_x64`), which the science needs. To stay in
float32, set the environment variable `TIPPEJAX_ENABLE_X64=0` before the import.
"""

import importlib.metadata
import os

import jax

if os.environ.get("TIPPEJAX_ENABLE_X64", "1").strip().lower() not in ("0", "false", "no"):
    jax.config.update("jax_enable_x64", True)

from ._analysis.groups import (
    GROUPS as GROUPS,
    Thresholds as Thresholds,
    classify as classify,
    group_index as group_index,
    thresholds as thresholds,
)
from ._analysis.potential import (
    RouthianTerms as RouthianTerms,
    effective_potential as effective_potential,
    effective_potential_d2_closed_form as effective_potential_d2_closed_form,
    effective_potential_derivative as effective_potential_derivative,
    routhian_terms as routhian_terms,
)
from ._analysis.stability import (
    characteristic_polynomial as characteristic_polynomial,
    max_real_part as max_real_part,
    polynomial_eigenvalues as polynomial_eigenvalues,
    reduced_jacobian_eigenvalues as reduced_jacobian_eigenvalues,
    relative_equilibrium as relative_equilibrium,
    vector_field_eigenvalues as vector_field_eigenvalues,
)
from ._analysis.steady_states import (
    SteadyStates as SteadyStates,
    branch_jellet as branch_jellet,
    intermediate_condition as intermediate_condition,
    pole_threshold as pole_threshold,
    stability_function as stability_function,
    steady_states as steady_states,
)
from ._invariants import (
    energy as energy,
    jellet as jellet,
    normal_force as normal_force,
    normal_force_denominator as normal_force_denominator,
    slip_velocity as slip_velocity,
)
from ._models.full import full_vector_field as full_vector_field
from ._models.routhian import (
    RouthianState as RouthianState,
    routhian_from_state as routhian_from_state,
    routhian_normal_force as routhian_normal_force,
    routhian_rates as routhian_rates,
    routhian_vector_field as routhian_vector_field,
    state_from_routhian as state_from_routhian,
)
from ._models.so3 import so3_vector_field as so3_vector_field
from ._state import (
    State as State,
    euler_angles as euler_angles,
    euler_rates as euler_rates,
    initial_state as initial_state,
    spin as spin,
    state_from_euler as state_from_euler,
)
from ._top import TippeTop as TippeTop, default_top as default_top

try:
    __version__ = importlib.metadata.version("tippejax")
except importlib.metadata.PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0"

from ._batch import simulate_batch as simulate_batch
from ._simulate import (
    CHART_SIN_MIN as CHART_SIN_MIN,
    default_solver as default_solver,
    friction_rate as friction_rate,
    simulate as simulate,
)
from ._solution import RESULTS as RESULTS, Solution as Solution
