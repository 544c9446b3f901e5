"""Batching (vmap over states, tops and Jellet values) and jit of the public API."""

import equinox as eqx
import internal as ti
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import GROUP_RATIOS

import tippejax as tj

N_STATES = 8
RATIOS = [GROUP_RATIOS[k] for k in ("Ib", "IIa", "IIb", "III")]


def _assert_trees_close(a, b, rtol=1e-13, atol=0.0):
    leaves_a, tree_a = jax.tree.flatten(a)
    leaves_b, tree_b = jax.tree.flatten(b)
    assert tree_a == tree_b
    for x, y in zip(leaves_a, leaves_b):
        x, y = np.asarray(x), np.asarray(y)
        assert x.shape == y.shape, (x.shape, y.shape)
        if x.dtype == bool or np.issubdtype(x.dtype, np.integer):
            np.testing.assert_array_equal(x, y)
        else:
            np.testing.assert_allclose(x, y, rtol=rtol, atol=atol, equal_nan=True)


def _index(tree, i):
    return jax.tree.map(lambda x: x[i], tree)


def _stack(trees):
    return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)


@pytest.fixture(scope="module")
def top():
    return tj.default_top()


@pytest.fixture(scope="module")
def states(top):
    rng = np.random.default_rng(0)
    theta = rng.uniform(0.2, np.pi - 0.2, N_STATES)
    phi, psi = rng.uniform(-3, 3, (2, N_STATES))
    thd, phid, psid = rng.normal(scale=[3.0, 15.0, 50.0], size=(N_STATES, 3)).T
    velocity = rng.normal(scale=0.2, size=(N_STATES, 2))
    return tj.state_from_euler(theta, phi, psi, thd, phid, psid, velocity=velocity)


@pytest.fixture(scope="module")
def tops():
    """A batch of tops with every field an array of shape (4,), and the same tops one by one."""
    n = len(RATIOS)
    a = jnp.array([r[0] for r in RATIOS])
    e = jnp.array([r[1] for r in RATIOS])
    batch = tj.TippeTop.from_ratios(
        a, e, m=jnp.full(n, 0.02), R=jnp.full(n, 0.025), mu=jnp.full(n, 0.3), g=jnp.full(n, 9.81)
    )
    singles = [tj.TippeTop.from_ratios(ai, ei) for ai, ei in RATIOS]
    return batch, singles


@pytest.mark.parametrize("name", ["full", "so3"])
def test_vmap_vector_fields_over_states(top, states, name):
    field = {"full": ti.full_vector_field, "so3": ti.so3_vector_field}[name]
    looped = _stack([field(0.0, _index(states, i), top) for i in range(N_STATES)])
    vmapped = jax.vmap(lambda y: field(0.0, y, top))(states)
    _assert_trees_close(vmapped, looped)
    # The fields also accept a batched state directly.
    _assert_trees_close(field(0.0, states, top), looped)


def test_vmap_routhian_field_over_states(top, states):
    r, J = ti.routhian_from_state(
        top, eqx.tree_at(lambda s: s.velocity, states, 0 * states.velocity)
    )
    looped = _stack(
        [ti.routhian_vector_field(0.0, _index(r, i), (top, J[i])) for i in range(N_STATES)]
    )
    vmapped = jax.vmap(lambda ri, Ji: ti.routhian_vector_field(0.0, ri, (top, Ji)))(r, J)
    _assert_trees_close(vmapped, looped)
    _assert_trees_close(ti.routhian_vector_field(0.0, r, (top, J)), looped)


def test_vmap_over_tops_effective_potential(tops):
    batch, singles = tops
    theta = jnp.array([0.3, 1.0, 2.0, 2.8])
    J = jnp.array([1e-5, 2e-5, -3e-5, 4e-5])
    looped = jnp.stack([tj.effective_potential(t, theta[i], J[i]) for i, t in enumerate(singles)])
    vmapped = jax.vmap(tj.effective_potential)(batch, theta, J)
    _assert_trees_close(vmapped, looped)
    _assert_trees_close(tj.effective_potential(batch, theta, J), looped)  # broadcasting
    looped2 = jnp.stack(
        [
            tj.effective_potential_derivative(t, theta[i], J[i], order=2)
            for i, t in enumerate(singles)
        ]
    )
    vmapped2 = jax.vmap(lambda t, th, j: tj.effective_potential_derivative(t, th, j, order=2))(
        batch, theta, J
    )
    _assert_trees_close(vmapped2, looped2, rtol=1e-12)


def test_vmap_over_tops_thresholds(tops):
    batch, singles = tops
    looped = _stack([tj.thresholds(t) for t in singles])
    _assert_trees_close(jax.vmap(tj.thresholds)(batch), looped)
    _assert_trees_close(tj.thresholds(batch), looped)
    # Not trivially all-nan: n1 exists for Groups II/III, n2 for Groups I/II.
    n1 = np.asarray(looped.n1)
    n2 = np.asarray(looped.n2)
    assert np.isnan(n1[0]) and np.all(np.isfinite(n1[1:]))
    assert np.all(np.isfinite(n2[:3])) and np.isnan(n2[3])
    np.testing.assert_array_equal(
        np.asarray(jax.vmap(ti.group_index)(batch)), [ti.group_index(t) for t in singles]
    )


def test_vmap_over_tops_jellet(tops, states):
    batch, singles = tops
    y = _index(states, 0)
    looped = jnp.stack([tj.jellet(t, y) for t in singles])
    _assert_trees_close(jax.vmap(lambda t: tj.jellet(t, y))(batch), looped)
    ys = _index(states, slice(0, 4))
    looped = jnp.stack([tj.jellet(t, _index(ys, i)) for i, t in enumerate(singles)])
    _assert_trees_close(jax.vmap(tj.jellet)(batch, ys), looped)


@pytest.mark.slow
def test_steady_states_vmap_over_J(top):
    """vmap (under jit: one compilation) over three Jellet values equals a loop."""
    J_values = jnp.array([0.5, 1.5, 3.0]) * float(tj.thresholds(top).J1)
    looped = _stack([tj.steady_states(top, J) for J in J_values])
    vmapped = eqx.filter_jit(jax.vmap(lambda J: tj.steady_states(top, J)))(J_values)
    _assert_trees_close(vmapped, looped, rtol=1e-10, atol=1e-12)
    # The three Jellet values give different steady states (the test is not vacuous):
    # an intermediate state only for J1 < J < J2.
    valid = np.asarray(looped.intermediate_valid)
    assert valid[1].any() and not valid[0].any()


# ---------------- jit of every public function ----------------


@pytest.fixture(scope="module")
def public_calls(top, states):
    y = _index(states, 1)
    y0 = eqx.tree_at(lambda s: s.velocity, y, jnp.zeros(2))
    r, J = ti.routhian_from_state(top, y0)
    th = jnp.asarray(1.1)
    Jr = jnp.asarray(2.0 * float(tj.thresholds(top).J1))
    return {
        "TippeTop": (
            lambda m, R, e, A, C: tj.TippeTop(m, R, e, A, C),
            (top.m, top.R, top.eps, top.A, top.C),
        ),
        "from_ratios": (tj.TippeTop.from_ratios, (jnp.asarray(0.9), jnp.asarray(0.3))),
        "state_from_euler": (
            tj.state_from_euler,
            tuple(jnp.asarray(v) for v in (1.0, 0.2, 0.3, 1.0, 5.0, 30.0)),
        ),
        "initial_state": (tj.initial_state, (top, jnp.asarray(0.1), jnp.asarray(50.0))),
        "euler_angles": (tj.euler_angles, (y,)),
        "euler_rates": (tj.euler_rates, (y,)),
        "spin": (ti.spin, (y,)),
        "jellet": (tj.jellet, (top, y)),
        "jellet_rate": (
            tj.jellet_rate,
            (top.replace(friction=tj.CoulombContensou(0.3, 5e-4, 1e-4)), y),
        ),
        "energy": (tj.energy, (top, y)),
        "energy_so3": (lambda t, s: tj.energy(t, s, model="so3"), (top, y)),
        "normal_force": (tj.normal_force, (top, y)),
        "normal_force_so3": (lambda t, s: tj.normal_force(t, s, model="so3"), (top, y)),
        "normal_force_denominator": (tj.normal_force_denominator, (top, y)),
        "slip_velocity": (tj.slip_velocity, (top, y)),
        "full_vector_field": (ti.full_vector_field, (0.0, y, top)),
        "so3_vector_field": (ti.so3_vector_field, (0.0, y, top)),
        "routhian_vector_field": (ti.routhian_vector_field, (0.0, r, (top, J))),
        "routhian_from_state": (ti.routhian_from_state, (top, y0)),
        "state_from_routhian": (ti.state_from_routhian, (top, r, J)),
        "routhian_rates": (ti.routhian_rates, (top, r.theta, r.phibar_dot, J)),
        "routhian_normal_force": (
            ti.routhian_normal_force,
            (top, th, jnp.asarray(1.0), jnp.asarray(3.0), jnp.asarray(40.0)),
        ),
        "effective_potential": (tj.effective_potential, (top, th, Jr)),
        "effective_potential_derivative": (
            lambda t, a, b: tj.effective_potential_derivative(t, a, b, order=2),
            (top, th, Jr),
        ),
        "effective_potential_d2_closed_form": (
            ti.effective_potential_d2_closed_form,
            (top, th, Jr),
        ),
        "routhian_terms": (ti.routhian_terms, (top, th, Jr)),
        "thresholds": (tj.thresholds, (top,)),
        "group_index": (ti.group_index, (top,)),
        "intermediate_condition": (ti.intermediate_condition, (top, Jr, jnp.cos(th))),
        "stability_function": (ti.stability_function, (top, jnp.cos(th))),
        "branch_jellet": (ti.branch_jellet, (top, th)),
        "relative_equilibrium": (ti.relative_equilibrium, (top, th, Jr)),
        "characteristic_polynomial": (ti.characteristic_polynomial, (top, th, Jr)),
        "polynomial_eigenvalues": (ti.polynomial_eigenvalues, (top, th, Jr)),
        "max_real_part": (ti.max_real_part, (jnp.array([1.0 + 2.0j, -3.0 + 0.0j]),)),
    }


# Functions whose eager (op-by-op) evaluation is too slow to serve as the reference are checked
# under jit against independent values instead: see the tests below the parametrized one.
EXPENSIVE = {
    "reduced_jacobian_eigenvalues",
    "vector_field_eigenvalues",
    "steady_states",
    "pole_threshold",
}


def test_public_api_is_covered(public_calls):
    """Every public function of the physics core (state, invariants, models, analysis) is jitted here."""
    core = (
        "tippejax._top",
        "tippejax._state",
        "tippejax._invariants",
        "tippejax._models",
        "tippejax._analysis",
    )
    names = {
        n
        for n in dir(tj)
        if not n.startswith("_")
        and callable(getattr(tj, n))
        and n[0].islower()
        and getattr(getattr(tj, n), "__module__", "").startswith(core)
    }
    assert "jellet" in names and "steady_states" in names
    covered = (
        {n.removesuffix("_so3") for n in public_calls} | EXPENSIVE | {"default_top", "classify"}
    )
    assert names <= covered, names - covered


@pytest.mark.parametrize(
    "name",
    [
        "TippeTop",
        "from_ratios",
        "state_from_euler",
        "initial_state",
        "euler_angles",
        "euler_rates",
        "spin",
        "jellet",
        "jellet_rate",
        "energy",
        "energy_so3",
        "normal_force",
        "normal_force_so3",
        "normal_force_denominator",
        "slip_velocity",
        "full_vector_field",
        "so3_vector_field",
        "routhian_vector_field",
        "routhian_from_state",
        "state_from_routhian",
        "routhian_rates",
        "routhian_normal_force",
        "effective_potential",
        "effective_potential_derivative",
        "effective_potential_d2_closed_form",
        "routhian_terms",
        "thresholds",
        "group_index",
        "intermediate_condition",
        "stability_function",
        "branch_jellet",
        "relative_equilibrium",
        "characteristic_polynomial",
        "polynomial_eigenvalues",
        "max_real_part",
    ],
)
def test_jit_public_function(public_calls, name):
    fn, args = public_calls[name]
    eager = fn(*args)
    jitted = jax.jit(fn)(*args)
    _assert_trees_close(jitted, eager, rtol=1e-12, atol=1e-300)
    if name != "thresholds":  # thresholds are nan where undefined
        for leaf in jax.tree.leaves(eager):
            assert np.all(np.isfinite(np.asarray(leaf)))


def test_jit_eigenvalue_functions(top):
    """At a relative equilibrium (J on the branch at theta0), the jitted reduced-Jacobian and
    SO(3) eigenvalues equal the roots of the characteristic polynomial."""
    theta0 = jnp.asarray(1.1)
    J = ti.branch_jellet(top, theta0)
    reduced = np.sort_complex(np.asarray(jax.jit(ti.reduced_jacobian_eigenvalues)(top, theta0, J)))
    so3 = np.sort_complex(np.asarray(jax.jit(ti.vector_field_eigenvalues)(top, theta0, J)))
    poly = np.sort_complex(np.asarray(ti.polynomial_eigenvalues(top, theta0, J)))
    scale = np.abs(poly).max()
    np.testing.assert_allclose(reduced, poly, rtol=0, atol=1e-8 * scale)
    np.testing.assert_allclose(so3, poly, rtol=0, atol=1e-8 * scale)


def test_jit_pole_threshold(top):
    """jax.jit around pole_threshold: equals the closed form n1 (eq. n1)."""
    n1 = float(tj.thresholds(top).n1)
    got = float(jax.jit(ti.pole_threshold)(top))
    np.testing.assert_allclose(got, n1, rtol=1e-6)
