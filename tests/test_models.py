"""The full, SO(3) and Routhian vector fields: invariants, mutual agreement, poles, Routhian terms."""

import equinox as eqx
import internal as ti
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import sympy as sp
from helpers import MIXED_TOP_IDS, mixed_tops

import tippejax as tj

N_STATES = 20


TOPS = mixed_tops()
TOP_IDS = MIXED_TOP_IDS


def _random_state(seed, n=N_STATES, translation=True, margin=0.1):
    rng = np.random.default_rng(seed)
    theta = rng.uniform(margin, np.pi - margin, n)
    phi, psi = rng.uniform(-np.pi + 1e-3, np.pi - 1e-3, (2, n))
    thd = rng.normal(scale=4.0, size=n)
    phid = rng.normal(scale=20.0, size=n)
    psid = rng.normal(scale=60.0, size=n)
    velocity = rng.normal(scale=0.3, size=(n, 2)) if translation else np.zeros((n, 2))
    return tj.state_from_euler(theta, phi, psi, thd, phid, psid, velocity=velocity)


def _norm(x):
    return jnp.linalg.norm(x, axis=-1)


def _angular_momentum(top, y):
    n = jnp.sum(y.omega * y.axis, -1)[..., None]
    return top.A * y.omega + (top.C - top.A) * n * y.axis


# ---------------- jit once per module ----------------


@eqx.filter_jit
def _jellet_rate(field, top, y):
    dy = field(0.0, y, top)
    return jax.jvp(lambda s: tj.jellet(top, s), (y,), (dy,))[1]


@eqx.filter_jit
def _energy_rate(field, model, top, y):
    dy = field(0.0, y, top)
    return jax.jvp(lambda s: tj.energy(top, s, model=model), (y,), (dy,))[1]


def _routhian_energy(top, r, J):
    return tj.energy(top, ti.state_from_routhian(top, r, J), model="so3")


@eqx.filter_jit
def _routhian_energy_rate(top, r, J):
    dr = ti.routhian_vector_field(0.0, r, (top, J))
    return jax.jvp(lambda s: _routhian_energy(top, s, J), (r,), (dr,))[1]


@eqx.filter_jit
def _so3_euler_accelerations(top, y):
    dy = ti.so3_vector_field(0.0, y, top)
    return jax.jvp(tj.euler_rates, (y,), (dy,))[1]


_routhian_field = eqx.filter_jit(ti.routhian_vector_field)

FIELDS = {"full": ti.full_vector_field, "so3": ti.so3_vector_field}


# ---------------- Jellet ----------------


@pytest.mark.parametrize("top", TOPS, ids=TOP_IDS)
@pytest.mark.parametrize("model", ["full", "so3"])
def test_jellet_conserved(top, model):
    y = _random_state(10, translation=(model == "full"))
    rate = np.asarray(_jellet_rate(FIELDS[model], top, y))
    q = y.axis * top.eps - jnp.array([[0.0, 0.0, 1.0]]) * top.R
    rn = jnp.abs(tj.normal_force(top, y, model=model))
    # |J| <= |L||q|; dJ/dt = -dL/dt.q - L.dq/dt with |dL/dt| <= |q| R_n (1 + mu |v_Q|).
    v_q = _norm(tj.slip_velocity(top, y, model=model))
    scale = _norm(_angular_momentum(top, y)) * _norm(q) * _norm(y.omega) + _norm(q) ** 2 * rn * (
        1 + top.mu * v_q
    )
    rel = np.abs(rate) / np.asarray(scale)
    print(f"dJ/dt [{model}]: max relative = {rel.max():.2e}")
    assert rel.max() < 1e-13, rel.max()


@pytest.mark.parametrize("top", TOPS, ids=TOP_IDS)
def test_jellet_is_not_conserved_by_a_wrong_field(top):
    """Control: the same measure detects a broken field (torque without the lever arm q)."""
    y = _random_state(10)

    def broken(t, s, top):
        dy = ti.full_vector_field(t, s, top)
        return eqx.tree_at(
            lambda d: d.omega, dy, dy.omega + jnp.zeros_like(dy.omega).at[..., 0].set(1.0)
        )

    rate = np.asarray(_jellet_rate(broken, top, y))
    q = y.axis * top.eps - jnp.array([[0.0, 0.0, 1.0]]) * top.R
    scale = _norm(_angular_momentum(top, y)) * _norm(q) * _norm(y.omega)
    assert np.median(np.abs(rate) / np.asarray(scale)) > 1e-8


@pytest.mark.parametrize("top", TOPS, ids=TOP_IDS)
def test_routhian_reconstruction_has_jellet_J(top):
    """The Routhian flow has J as a parameter; J is conserved iff the reconstruction (eq. routh1)
    returns a state whose Jellet is J, for every reduced state."""
    rng = np.random.default_rng(11)
    r = ti.RouthianState(
        theta=jnp.asarray(rng.uniform(0.1, np.pi - 0.1, N_STATES)),
        phibar=jnp.asarray(rng.normal(size=N_STATES) * 0.01),
        c=jnp.asarray(rng.normal(size=N_STATES) * 0.01),
        theta_dot=jnp.asarray(rng.normal(scale=4.0, size=N_STATES)),
        phibar_dot=jnp.asarray(rng.normal(scale=1.0, size=N_STATES)),
    )
    J = jnp.asarray(rng.normal(size=N_STATES)) * top.C * top.R * 50.0
    y = ti.state_from_routhian(top, r, J)
    np.testing.assert_allclose(np.asarray(tj.jellet(top, y)), np.asarray(J), rtol=1e-12)


# ---------------- energy ----------------


@pytest.mark.parametrize("top", TOPS, ids=TOP_IDS)
@pytest.mark.parametrize("model", ["full", "so3"])
def test_energy_dissipation(top, model):
    y = _random_state(12, translation=(model == "full"))
    rn = np.asarray(tj.normal_force(top, y, model=model))
    keep = rn > 0
    assert keep.sum() >= 10
    rate = np.asarray(_energy_rate(FIELDS[model], model, top, y))
    v_q = np.asarray(tj.slip_velocity(top, y, model=model))
    expected = -float(top.mu) * rn * np.sum(v_q**2, -1)
    kinetic = np.asarray(tj.energy(top, y, model=model)) - float(top.m * top.g) * np.asarray(
        top.R - top.eps * y.axis[:, 2]
    )
    scale = kinetic * np.asarray(_norm(y.omega)) + np.abs(expected)
    err = np.abs(rate - expected) / scale
    assert err[keep].max() < 1e-12, err[keep].max()
    assert np.all(rate[keep] <= 1e-12 * scale[keep])
    assert np.all(expected[keep] < 0)


@pytest.mark.parametrize("top", TOPS, ids=TOP_IDS)
def test_energy_dissipation_routhian(top):
    y = _random_state(13, translation=False)
    r, J = ti.routhian_from_state(top, y)
    rn = np.asarray(tj.normal_force(top, y, model="so3"))
    keep = rn > 0
    rate = np.asarray(_routhian_energy_rate(top, r, J))
    v_q = np.asarray(tj.slip_velocity(top, y, model="so3"))
    expected = -float(top.mu) * rn * np.sum(v_q**2, -1)
    kinetic = np.asarray(tj.energy(top, y, model="so3")) - float(top.m * top.g) * np.asarray(
        top.R - top.eps * y.axis[:, 2]
    )
    scale = kinetic * np.asarray(_norm(y.omega)) + np.abs(expected)
    err = np.abs(rate - expected) / scale
    assert err[keep].max() < 1e-11, err[keep].max()
    assert np.all(rate[keep] <= 1e-11 * scale[keep])


# ---------------- Routhian vs SO(3) ----------------


@pytest.mark.parametrize("top", TOPS, ids=TOP_IDS)
def test_routhian_accelerations_equal_so3(top):
    y = _random_state(14, translation=False, margin=0.2)
    r, J = ti.routhian_from_state(top, y)
    dr = _routhian_field(0.0, r, (top, J))
    thdd, phidd, psidd = _so3_euler_accelerations(top, y)
    pbdd = top.eps * phidd + top.R * psidd
    thd, phid, psid = tj.euler_rates(y)
    # Typical rates: |omega|^2 for angular accelerations.
    scale_th = np.asarray(_norm(y.omega) ** 2)
    err_th = np.abs(np.asarray(dr.theta_dot - thdd)) / np.maximum(
        np.abs(np.asarray(thdd)), scale_th
    )
    err_pb = np.abs(np.asarray(dr.phibar_dot - pbdd)) / np.maximum(
        np.abs(np.asarray(pbdd)), scale_th * float(top.R)
    )
    assert err_th.max() < 1e-10, err_th.max()
    assert err_pb.max() < 1e-10, err_pb.max()
    # First-order part: the state's own rates, and cdot = R phid - eps psid.
    np.testing.assert_allclose(np.asarray(dr.theta), np.asarray(thd), rtol=1e-13)
    np.testing.assert_allclose(
        np.asarray(dr.phibar),
        np.asarray(top.eps * phid + top.R * psid),
        rtol=1e-10,
        atol=1e-12 * float(top.R) * scale_th.max() ** 0.5,
    )
    np.testing.assert_allclose(
        np.asarray(dr.c),
        np.asarray(top.R * phid - top.eps * psid),
        rtol=1e-10,
        atol=1e-12 * float(top.R) * scale_th.max() ** 0.5,
    )


@pytest.mark.parametrize("top", TOPS, ids=TOP_IDS)
def test_routhian_normal_force(top):
    y = _random_state(15, translation=False)
    theta, _, _ = tj.euler_angles(y)
    thd, phid, _ = tj.euler_rates(y)
    rn, den = ti.routhian_normal_force(top, theta, thd, phid, ti.spin(y))
    np.testing.assert_allclose(
        np.asarray(rn), np.asarray(tj.normal_force(top, y, model="so3")), rtol=1e-12
    )
    np.testing.assert_allclose(
        np.asarray(den), np.asarray(tj.normal_force_denominator(top, y, model="so3")), rtol=1e-12
    )


@pytest.mark.parametrize("top", TOPS, ids=TOP_IDS)
def test_routhian_round_trips(top):
    # vector state -> reduced -> vector state
    y = _random_state(16, translation=False)
    r, J = ti.routhian_from_state(top, y)
    y2 = ti.state_from_routhian(top, r, J)
    omega_scale = float(jnp.max(_norm(y.omega)))
    np.testing.assert_allclose(np.asarray(y2.axis), np.asarray(y.axis), atol=1e-14)
    np.testing.assert_allclose(np.asarray(y2.body), np.asarray(y.body), atol=1e-13)
    np.testing.assert_allclose(np.asarray(y2.omega), np.asarray(y.omega), atol=1e-12 * omega_scale)
    np.testing.assert_array_equal(np.asarray(y2.velocity), 0.0)
    # reduced -> vector state -> reduced (phi, psi in (-pi, pi) so no wrapping)
    rng = np.random.default_rng(17)
    phi, psi = rng.uniform(-3.0, 3.0, (2, N_STATES))
    R, eps = float(top.R), float(top.eps)
    r = ti.RouthianState(
        theta=jnp.asarray(rng.uniform(0.1, 3.0, N_STATES)),
        phibar=jnp.asarray(eps * phi + R * psi),
        c=jnp.asarray(R * phi - eps * psi),
        theta_dot=jnp.asarray(rng.normal(scale=4.0, size=N_STATES)),
        phibar_dot=jnp.asarray(rng.normal(scale=1.0, size=N_STATES)),
    )
    J = jnp.asarray(rng.normal(size=N_STATES)) * top.C * top.R * 50.0
    r2, J2 = ti.routhian_from_state(top, ti.state_from_routhian(top, r, J))
    for f in ("theta", "phibar", "c", "theta_dot", "phibar_dot"):
        a, b = np.asarray(getattr(r2, f)), np.asarray(getattr(r, f))
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * max(1.0, np.abs(b).max()))
    np.testing.assert_allclose(np.asarray(J2), np.asarray(J), rtol=1e-12)


# ---------------- poles ----------------


@pytest.mark.parametrize("theta0", [0.0, np.pi])
def test_poles(theta0):
    """Full and SO(3) fields are regular at theta = 0, pi; the Routhian chart is not.

    Documented behaviour: the Routhian field does not raise at theta = 0 exactly, it returns a
    non-finite phibar acceleration (M_phibar = 0 there); the Routhian level says the pole is
    outside its chart, so no run integrates it there (it starts in the SO(3) level).
    """
    top = TOPS[0]
    y = tj.initial_state(top, theta0, 50.0, theta_dot=1.5, phi_dot=0.0, vx=0.1, vy=-0.2)
    for field in (ti.full_vector_field, ti.so3_vector_field):
        dy = field(0.0, y, top)
        assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(dy))
    assert np.isfinite(float(tj.normal_force(top, y)))
    if theta0 != 0.0:
        return  # sin(float(pi)) = 1.2e-16 is not 0: the Routhian chart is merely ill-conditioned there.
    from tippejax._models.levels import LEVELS

    assert not bool(LEVELS["routhian"].in_chart(top, y))
    sol = tj.simulate(top, y, 0.05, model="routhian", saveat=[0.0, 0.05])
    assert sol.model == "routhian->so3" and float(sol.t_chart_switch) == 0.0
    assert np.all(np.isfinite(np.asarray(sol.theta)))
    r = ti.RouthianState(*[jnp.asarray(v) for v in (theta0, 0.1, 0.2, 1.5, 0.3)])
    dr = ti.routhian_vector_field(0.0, r, (top, 1e-5))
    assert not all(bool(jnp.isfinite(leaf)) for leaf in jax.tree.leaves(dr))


def test_fields_continuous_at_pole():
    """Regular at the pole: the field at theta = 1e-7 is close to the one at theta = 0."""
    top = TOPS[0]
    y0 = tj.initial_state(top, 0.0, 50.0, theta_dot=1.5, vx=0.1)
    y1 = tj.initial_state(top, 1e-7, 50.0, theta_dot=1.5, vx=0.1)
    for field in (ti.full_vector_field, ti.so3_vector_field):
        d0, d1 = field(0.0, y0, top), field(0.0, y1, top)
        np.testing.assert_allclose(np.asarray(d1.omega), np.asarray(d0.omega), rtol=0, atol=1e-3)


# ---------------- Routhian coefficients from L' (sympy) ----------------


@pytest.fixture(scope="module")
def routhian_sympy():
    m, R, eps, A, C, g, J = sp.symbols("m R eps A C g J", real=True)
    th, thd, pbd, cd = sp.symbols("theta thd pbd cd", real=True)
    S = eps**2 + R**2
    # Inverse of phibar = eps phi + R psi, c = R phi - eps psi.
    phid = (eps * pbd + R * cd) / S
    psid = (R * pbd - eps * cd) / S
    s, c = sp.sin(th), sp.cos(th)
    lagrangian = sp.Rational(1, 2) * (
        (eps**2 * m * s**2 + A) * thd**2 + A * s**2 * phid**2 + C * (psid + phid * c) ** 2
    ) - m * g * (R - eps * c)
    cd_solution = sp.solve(sp.Eq(lagrangian.diff(cd), J / S), cd)
    assert len(cd_solution) == 1
    routhian = (lagrangian - J * cd / S).subs(cd, cd_solution[0])
    zero = {thd: 0, pbd: 0}
    coefficients = [
        routhian.diff(thd, 2).subs(zero),  # inertia_theta
        routhian.diff(pbd, 2).subs(zero),  # inertia_phibar
        routhian.diff(pbd).subs(zero),  # gyroscopic
        -routhian.subs(zero) - m * g * R,  # potential
        routhian.diff(thd).subs(zero),  # must vanish (no T1 in thd)
        routhian.diff(thd, pbd).subs(zero),  # must vanish (no cross term)
        cd_solution[0],  # eq. routh1
    ]
    return sp.lambdify((th, pbd, m, R, eps, A, C, g, J), coefficients, modules="numpy", cse=True)


@pytest.mark.parametrize("top", TOPS, ids=TOP_IDS)
def test_routhian_terms_from_sympy(routhian_sympy, top):
    rng = np.random.default_rng(18)
    theta = rng.uniform(0.05, np.pi - 0.05, 12)
    J = rng.normal(size=12) * float(top.C * top.R) * 50.0
    pbd = rng.normal(size=12)
    p = [float(getattr(top, k)) for k in ("m", "R", "eps", "A", "C", "g")]
    m_th, m_pb, beta, w, lin_th, cross, cdot = (
        np.broadcast_to(np.asarray(v, dtype=float), theta.shape)
        for v in routhian_sympy(theta, pbd, *p, J)
    )
    terms = ti.routhian_terms(top, jnp.asarray(theta), jnp.asarray(J))
    np.testing.assert_allclose(np.asarray(terms.inertia_theta), m_th, rtol=1e-13)
    np.testing.assert_allclose(np.asarray(terms.inertia_phibar), m_pb, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(terms.gyroscopic), beta, rtol=1e-12)
    # W is a difference of two terms; compare relative to their size.
    w_scale = np.abs(J) ** 2 / (2 * float(top.C) * float(top.R) ** 2) + p[0] * p[5] * p[2]
    assert np.all(np.abs(np.asarray(terms.potential) - w) < 1e-13 * w_scale * 10)
    np.testing.assert_allclose(
        np.asarray(tj.effective_potential(top, jnp.asarray(theta), jnp.asarray(J))),
        w,
        rtol=0,
        atol=1e-12 * w_scale.max(),
    )
    assert np.all(lin_th == 0) and np.all(cross == 0)
    c_dot = np.asarray(
        ti.routhian_rates(top, jnp.asarray(theta), jnp.asarray(pbd), jnp.asarray(J))[0]
    )
    np.testing.assert_allclose(c_dot, cdot, rtol=1e-12, atol=1e-13 * np.abs(cdot).max())


# ---------------- the component form of the rigid-body algebra ----------------


LG_TOP = dict(m=0.006, R=0.015, eps=0.003, A=8e-7, C=7e-7)
LAW_TOPS = [  # Leine & Glocker's top with each friction law besides the viscous one
    tj.TippeTop(**LG_TOP, friction=tj.Coulomb(0.3, 1e-3)),
    tj.TippeTop(**LG_TOP, friction=tj.CoulombContensou(0.3, 5e-4, 1e-4)),
    tj.TippeTop(**LG_TOP, friction=tj.CoulombContensou(0.3, 5e-4, 1e-4, pressure="ellipse")),
]


@pytest.mark.parametrize(
    "top", TOPS + LAW_TOPS, ids=TOP_IDS + ["LG-coulomb", "LG-hertz", "LG-ellipse"]
)
@pytest.mark.parametrize("name", ["full", "so3"])
def test_levels_by_components_equal_the_vector_form(top, name):
    """`by_components=True` (the shared-step batch's form, the algebra written out by
    components) gives the vector form's field and conditions, on random states with
    translation (the full level's slip velocity sees it), member by member: for the Jellet
    and energy checks above, which test the vector form, to hold for both."""
    import dataclasses

    from tippejax._models.levels import LEVELS

    states = _random_state(11)
    vector = LEVELS[name]
    components = dataclasses.replace(vector, by_components=True)

    @jax.jit
    def both(state):
        y = vector.from_state(top, state)
        return (
            (vector.vector_field(0.0, y, top), vector.conditions(top, y)),
            (components.vector_field(0.0, y, top), components.conditions(top, y)),
        )

    for i in range(N_STATES):
        one = jax.tree_util.tree_map(lambda x, i=i: x[i], states)
        a, b = both(one)
        for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
            np.testing.assert_allclose(
                np.asarray(y),
                np.asarray(x),
                rtol=1e-12,
                atol=1e-12 * (1 + np.max(np.abs(np.asarray(x)))),
            )
