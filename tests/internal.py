"""Internals the tests cross-check, imported from their private modules (not the public API)."""

from tippejax._analysis.branch import (
    branch_jellet as branch_jellet,
    intermediate_condition as intermediate_condition,
    stability_function as stability_function,
)
from tippejax._analysis.groups import group_index as group_index
from tippejax._analysis.potential import (
    effective_potential_d2_closed_form as effective_potential_d2_closed_form,
    routhian_terms as routhian_terms,
)
from tippejax._analysis.stability import (
    characteristic_polynomial as characteristic_polynomial,
    max_real_part as max_real_part,
    polynomial_eigenvalues as polynomial_eigenvalues,
    reduced_jacobian_eigenvalues as reduced_jacobian_eigenvalues,
    relative_equilibrium as relative_equilibrium,
    vector_field_eigenvalues as vector_field_eigenvalues,
)
from tippejax._analysis.steady_states import pole_threshold as pole_threshold
from tippejax._models.full import full_vector_field as full_vector_field
from tippejax._models.routhian import (
    RouthianState as RouthianState,
    routhian_from_state as routhian_from_state,
    routhian_normal_force as routhian_normal_force,
    routhian_rates as routhian_rates,
    routhian_vector_field as routhian_vector_field,
    state_from_routhian as state_from_routhian,
)
from tippejax._models.so3 import so3_vector_field as so3_vector_field
from tippejax._simulate.single import _raise_if_failed as raise_if_failed  # noqa: F401
from tippejax._state import spin as spin
