"""Jellet, energy, normal force and slip velocity, each against an independent formula.

The normal force (and the accelerations of the full and SO(3) vector fields) are also checked
against the Euler-Lagrange equations of the Euler-angle Lagrangian with the height z of the
centre of mass left free, the table's force applied at the contact point as a generalized force,
and the contact constraint z = R - eps cos(theta) imposed with R_n as its multiplier. That
derivation (sympy, below) shares no code with the package.
"""

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


def _params(top):
    return {k: float(getattr(top, k)) for k in ("m", "R", "eps", "A", "C", "g", "mu")}


def _random_euler(seed, n=N_STATES, translation=True):
    """theta away from the poles, all angles and rates random."""
    rng = np.random.default_rng(seed)
    theta = rng.uniform(0.1, np.pi - 0.1, n)
    phi = rng.uniform(-np.pi, np.pi, n)
    psi = rng.uniform(-np.pi, np.pi, n)
    thd = rng.normal(scale=4.0, size=n)
    phid = rng.normal(scale=20.0, size=n)
    psid = rng.normal(scale=60.0, size=n)
    if translation:
        xd, yd = rng.normal(scale=0.3, size=(2, n))
    else:
        xd = yd = np.zeros(n)
    return theta, phi, psi, thd, phid, psid, xd, yd


def _state(theta, phi, psi, thd, phid, psid, xd, yd):
    velocity = np.stack([xd, yd], axis=-1)
    return tj.state_from_euler(theta, phi, psi, thd, phid, psid, velocity=velocity)


def _reactie(p, theta, phi, thd, phid, psid, xd, yd):
    """The paper's eq. reactie, written out with numpy."""
    m, R, eps, A, C, g, mu = (p[k] for k in ("m", "R", "eps", "A", "C", "g", "mu"))
    h = R - eps * np.cos(theta)
    h1 = eps * np.sin(theta)
    h2 = eps * np.cos(theta)
    n = psid + phid * np.cos(theta)
    terms = np.stack(
        [
            g + 0 * theta,
            thd**2 * h2,
            h1 * phid * np.sin(theta) * phid * np.cos(theta),
            -h1 * phid * np.sin(theta) * C * n / A,
        ]
    )
    denominator = 1 / m + h1 / A * (-h * mu * (np.sin(phi) * xd - np.cos(phi) * yd - thd * h) + h1)
    return terms.sum(0) / denominator, np.abs(terms).sum(0) / np.abs(denominator)


# --------------------------------------------------------------------------------------
# Independent Lagrangian derivation (sympy), built once per module.
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def lagrange_system():
    m, R, eps, A, C, g, mu = sp.symbols("m R eps A C g mu", positive=True)
    x, y, z, ph, th, ps = sp.symbols("x y z phi theta psi", real=True)
    xd, yd, zd, phd, thd, psd = sp.symbols("xd yd zd phid thd psid", real=True)
    q = [x, y, z, ph, th, ps]
    qd = [xd, yd, zd, phd, thd, psd]
    n = psd + phd * sp.cos(th)
    kinetic = sp.Rational(1, 2) * m * (xd**2 + yd**2 + zd**2) + sp.Rational(1, 2) * (
        A * thd**2 + A * sp.sin(th) ** 2 * phd**2 + C * n**2
    )
    lagrangian = kinetic - m * g * z
    e_z = sp.Matrix([0, 0, 1])
    axis = sp.Matrix([sp.sin(th) * sp.sin(ph), -sp.sin(th) * sp.cos(ph), sp.cos(th)])
    nodes = sp.Matrix([sp.cos(ph), sp.sin(ph), 0])
    omega = phd * e_z + thd * nodes + psd * axis
    contact = eps * axis - R * e_z
    v_q = sp.Matrix([xd, yd, zd]) + omega.cross(contact)
    # Table force per unit normal force: e_Z - mu v_Q (v_Q is horizontal on the constraint).
    force = e_z - mu * sp.Matrix([v_q[0], v_q[1], 0])
    generalized_force = sp.Matrix([force.dot(v_q.diff(v)) for v in qd])
    momenta = sp.Matrix([lagrangian.diff(v) for v in qd])
    mass_matrix = momenta.jacobian(qd)
    rest = momenta.jacobian(q) * sp.Matrix(qd) - sp.Matrix([lagrangian.diff(c) for c in q])
    args = [ph, th, ps, xd, yd, zd, phd, thd, psd, m, R, eps, A, C, g, mu]
    fn = sp.lambdify(args, [mass_matrix, rest, generalized_force, v_q], modules="numpy", cse=True)

    def solve(p, theta, phi, psi, thd_, phid_, psid_, xd_, yd_):
        """(R_n, qdd = (xdd, ydd, zdd, phidd, thdd, psidd), v_Q) from the Lagrangian."""
        eps_ = p["eps"]
        zd_ = eps_ * np.sin(theta) * thd_  # on the constraint z = R - eps cos(theta)
        mm, rr, ff, vq = fn(
            phi,
            theta,
            psi,
            xd_,
            yd_,
            zd_,
            phid_,
            thd_,
            psid_,
            *(p[k] for k in ("m", "R", "eps", "A", "C", "g", "mu")),
        )
        mm = np.asarray(mm, dtype=float)
        rr = np.asarray(rr, dtype=float).ravel()
        ff = np.asarray(ff, dtype=float).ravel()
        # Unknowns (qdd, R_n): M qdd + rest = R_n f;  zdd - h' thdd = h'' thd^2.
        system = np.zeros((7, 7))
        system[:6, :6] = mm
        system[:6, 6] = -ff
        system[6, 2] = 1.0
        system[6, 4] = -eps_ * np.sin(theta)
        rhs = np.concatenate([-rr, [eps_ * np.cos(theta) * thd_**2]])
        sol = np.linalg.solve(system, rhs)
        return sol[6], sol[:6], np.asarray(vq, dtype=float).ravel()

    return solve


# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("top", TOPS, ids=TOP_IDS)
def test_jellet_closed_form(top):
    p = _params(top)
    theta, phi, psi, thd, phid, psid, xd, yd = _random_euler(1)
    y = _state(theta, phi, psi, thd, phid, psid, xd, yd)
    n = psid + phid * np.cos(theta)
    R, eps, A, C = p["R"], p["eps"], p["A"], p["C"]
    terms = np.stack([C * n * (R * np.cos(theta) - eps), A * phid * R * np.sin(theta) ** 2])
    expected = terms.sum(0)
    got = np.asarray(tj.jellet(top, y))
    assert got.shape == (N_STATES,)
    np.testing.assert_array_less(np.abs(got - expected), 1e-13 * np.abs(terms).sum(0))
    # Independent of position, velocity and body vector.
    y2 = tj.state_from_euler(theta, phi, psi + 1.0, thd, phid, psid, position=(3.0, -1.0))
    np.testing.assert_allclose(np.asarray(tj.jellet(top, y2)), got, rtol=1e-13)


@pytest.mark.parametrize("top", TOPS, ids=TOP_IDS)
def test_energy_from_euler_lagrangian(top):
    p = _params(top)
    m, R, eps, A, C, g = (p[k] for k in ("m", "R", "eps", "A", "C", "g"))
    theta, phi, psi, thd, phid, psid, xd, yd = _random_euler(2)
    y = _state(theta, phi, psi, thd, phid, psid, xd, yd)
    n = psid + phid * np.cos(theta)
    s = np.sin(theta)
    rotation_and_height = (
        0.5 * (m * eps**2 * s**2 + A) * thd**2
        + 0.5 * A * s**2 * phid**2
        + 0.5 * C * n**2
        + m * g * (R - eps * np.cos(theta))
    )
    translation = 0.5 * m * (xd**2 + yd**2)
    full = np.asarray(tj.energy(top, y))
    so3 = np.asarray(tj.energy(top, y, model="so3"))
    np.testing.assert_allclose(full, translation + rotation_and_height, rtol=1e-13)
    np.testing.assert_allclose(so3, rotation_and_height, rtol=1e-13)
    # The translational part is not negligible in these states (the test can tell them apart).
    assert np.all(translation > 1e-9 * rotation_and_height)


@pytest.mark.parametrize("top", TOPS, ids=TOP_IDS)
def test_normal_force_matches_reactie(top):
    p = _params(top)
    theta, phi, psi, thd, phid, psid, xd, yd = _random_euler(3)
    y = _state(theta, phi, psi, thd, phid, psid, xd, yd)
    expected, scale = _reactie(p, theta, phi, thd, phid, psid, xd, yd)
    got = np.asarray(tj.normal_force(top, y))
    err = np.abs(got - expected) / scale
    print(f"R_n vs eq. reactie: max rel diff = {err.max():.2e}")
    assert err.max() < 1e-12, err.max()
    # so3 (and routhian): reactie with xd = yd = 0.
    expected0, scale0 = _reactie(p, theta, phi, thd, phid, psid, 0 * xd, 0 * yd)
    for model in ("so3", "routhian"):
        got0 = np.asarray(tj.normal_force(top, y, model=model))
        assert (np.abs(got0 - expected0) / scale0).max() < 1e-12
    # The translation matters for R_n when mu > 0.
    assert np.abs(expected - expected0).max() > 1e-6 * p["m"] * p["g"]


@pytest.mark.parametrize("top", TOPS, ids=TOP_IDS)
def test_normal_force_denominator_matches_reactie(top):
    p = _params(top)
    m, R, eps, A, mu = (p[k] for k in ("m", "R", "eps", "A", "mu"))
    theta, phi, psi, thd, phid, psid, xd, yd = _random_euler(4)
    y = _state(theta, phi, psi, thd, phid, psid, xd, yd)
    h, h1 = R - eps * np.cos(theta), eps * np.sin(theta)
    expected = 1 / m + h1 / A * (-h * mu * (np.sin(phi) * xd - np.cos(phi) * yd - thd * h) + h1)
    np.testing.assert_allclose(
        np.asarray(tj.normal_force_denominator(top, y)), expected, rtol=1e-12
    )


@pytest.mark.parametrize("top", TOPS, ids=TOP_IDS)
def test_normal_force_from_lagrangian(lagrange_system, top):
    p = _params(top)
    theta, phi, psi, thd, phid, psid, xd, yd = _random_euler(5, n=6)
    y = _state(theta, phi, psi, thd, phid, psid, xd, yd)
    got_full = np.asarray(tj.normal_force(top, y))
    got_so3 = np.asarray(tj.normal_force(top, y, model="so3"))
    for i in range(6):
        rn, _, v_q = lagrange_system(
            p, theta[i], phi[i], psi[i], thd[i], phid[i], psid[i], xd[i], yd[i]
        )
        assert abs(v_q[2]) < 1e-12 * np.abs(v_q).max()  # sanity of the derivation
        np.testing.assert_allclose(got_full[i], rn, rtol=1e-10)
        rn0, _, _ = lagrange_system(p, theta[i], phi[i], psi[i], thd[i], phid[i], psid[i], 0.0, 0.0)
        np.testing.assert_allclose(got_so3[i], rn0, rtol=1e-10)


@pytest.fixture(scope="module")
def euler_accelerations():
    """d/dt of (thd, phid, psid) and of (xd, yd) along a vector field, by jax.jvp."""

    def accelerations(field, top, y):
        dy = field(0.0, y, top)
        _, rates_dot = jax.jvp(tj.euler_rates, (y,), (dy,))
        return dy.velocity, rates_dot

    return jax.jit(accelerations, static_argnums=0)


@pytest.mark.parametrize("top", TOPS, ids=TOP_IDS)
def test_vector_fields_match_lagrangian(lagrange_system, euler_accelerations, top):
    """Full and SO(3) vector fields: xdd, ydd, and the Euler-angle accelerations."""
    p = _params(top)
    theta, phi, psi, thd, phid, psid, xd, yd = _random_euler(6, n=6)
    y = _state(theta, phi, psi, thd, phid, psid, xd, yd)
    vel_dot, (thdd, phidd, psidd) = euler_accelerations(ti.full_vector_field, top, y)
    y0 = _state(theta, phi, psi, thd, phid, psid, 0 * xd, 0 * yd)
    vel_dot0, (thdd0, phidd0, psidd0) = euler_accelerations(ti.so3_vector_field, top, y0)
    np.testing.assert_array_equal(np.asarray(vel_dot0), 0.0)
    for i in range(6):
        _, qdd, _ = lagrange_system(
            p, theta[i], phi[i], psi[i], thd[i], phid[i], psid[i], xd[i], yd[i]
        )
        got = np.array([*np.asarray(vel_dot[i]), phidd[i], thdd[i], psidd[i]])
        want = qdd[[0, 1, 3, 4, 5]]
        scale = np.abs(want[2:]).max()
        np.testing.assert_allclose(
            got[:2], want[:2], rtol=1e-10, atol=1e-12 * np.abs(want[:2]).max()
        )
        np.testing.assert_allclose(got[2:], want[2:], rtol=0, atol=1e-10 * scale)
        _, qdd0, _ = lagrange_system(
            p, theta[i], phi[i], psi[i], thd[i], phid[i], psid[i], 0.0, 0.0
        )
        got0 = np.array([phidd0[i], thdd0[i], psidd0[i]])
        np.testing.assert_allclose(got0, qdd0[3:], rtol=0, atol=1e-10 * np.abs(qdd0[3:]).max())


@pytest.mark.parametrize("top", TOPS, ids=TOP_IDS)
def test_slip_velocity(top):
    """v_Q from the paper's Q_x, Q_y (the bracket is the slip velocity); horizontal."""
    p = _params(top)
    R, eps = p["R"], p["eps"]
    theta, phi, psi, thd, phid, psid, xd, yd = _random_euler(7)
    y = _state(theta, phi, psi, thd, phid, psid, xd, yd)
    h = R - eps * np.cos(theta)
    roll = np.sin(theta) * (R * psid + eps * phid)
    vx = xd - np.sin(phi) * thd * h + np.cos(phi) * roll
    vy = yd + np.cos(phi) * thd * h + np.sin(phi) * roll
    scale = np.abs(xd) + np.abs(yd) + (np.abs(thd) + np.abs(phid) + np.abs(psid)) * R
    got = np.asarray(tj.slip_velocity(top, y))
    assert got.shape == (N_STATES, 3)
    np.testing.assert_array_equal(got[:, 2], 0.0)
    assert np.all(np.abs(got[:, 0] - vx) < 1e-13 * scale)
    assert np.all(np.abs(got[:, 1] - vy) < 1e-13 * scale)
    got0 = np.asarray(tj.slip_velocity(top, y, model="so3"))
    assert np.all(np.abs(got0[:, 0] - (vx - xd)) < 1e-13 * scale)
    assert np.all(np.abs(got0[:, 1] - (vy - yd)) < 1e-13 * scale)


@pytest.mark.parametrize("top", TOPS, ids=TOP_IDS)
@pytest.mark.parametrize("theta0", [0.3, 1.2, 2.0, 2.9])
def test_slip_velocity_vanishes_at_relative_equilibrium(top, theta0):
    J = 2.0 * float(top.C * top.R) * 40.0
    axis, omega, _ = ti.relative_equilibrium(top, theta0, J)
    body = jnp.cross(axis, jnp.array([1.0, 0.0, 0.0]))
    body = body / jnp.linalg.norm(body)
    zero = jnp.zeros(2)
    y = tj.State(position=zero, velocity=zero, axis=axis, omega=omega, body=body)
    v_q = np.asarray(tj.slip_velocity(top, y))
    scale = float(jnp.linalg.norm(omega)) * float(top.R)
    assert np.all(np.abs(v_q) < 1e-14 * scale)
    # Pure rolling: R psid + eps phid = 0; and the Jellet of the state is J.
    np.testing.assert_allclose(float(tj.jellet(top, y)), J, rtol=1e-13)
    # Any spin about the axis on top of it makes the contact point slip.
    y_slip = tj.State(position=zero, velocity=zero, axis=axis, omega=omega + 1.0 * axis, body=body)
    assert np.abs(np.asarray(tj.slip_velocity(top, y_slip))).max() > 0.1 * float(top.R) * np.sin(
        theta0
    )


# ---------------- every friction law ----------------

LG_TOP = dict(m=0.006, R=0.015, eps=0.003, A=8e-7, C=7e-7)
LAW_TOPS = [
    tj.TippeTop(**LG_TOP, friction=tj.Coulomb(0.3, 1e-3)),
    tj.TippeTop(**LG_TOP, friction=tj.CoulombContensou(0.3, 5e-4, 1e-4)),
    tj.TippeTop(**LG_TOP, friction=tj.CoulombContensou(0.3, 5e-4, 1e-4, pressure="ellipse")),
]
LAW_IDS = ["coulomb", "hertz", "ellipse"]


@pytest.mark.parametrize("model", ["full", "so3"])
@pytest.mark.parametrize("top", LAW_TOPS, ids=LAW_IDS)
def test_energy_rate_is_the_power_of_the_friction_law(top, model):
    """Along each level's field, dE/dt = R_n (f . v_Q + m omega_n): the power of the law's
    force at the contact point and of its drilling torque, <= 0 where R_n >= 0; and the Jellet
    changes at `jellet_rate`, zero for a law without drilling torque."""
    from tippejax._models.levels import LEVELS

    level = LEVELS[model]
    states = _state(*_random_euler(9, translation=model == "full"))

    @jax.jit
    def rates(state):
        y = level.from_state(top, state)
        dy = level.vector_field(0.0, y, top)
        energy_rate = jax.jvp(
            lambda s: tj.energy(top, level.to_state(top, s), model=model), (y,), (dy,)
        )[1]
        jellet_rate = jax.jvp(lambda s: tj.jellet(top, level.to_state(top, s)), (y,), (dy,))[1]
        return energy_rate, jellet_rate

    for i in range(N_STATES):
        state = jax.tree_util.tree_map(lambda x, i=i: x[i], states)
        energy_rate, jellet_rate = rates(state)
        rn = float(tj.normal_force(top, state, model=model))
        v_q = tj.slip_velocity(top, state, model=model)[:2]
        w_n = state.omega[2]
        f, m = top.friction.force_and_torque(v_q, w_n)
        power = rn * float(jnp.dot(f, v_q) + m * w_n)
        np.testing.assert_allclose(
            float(energy_rate), power, rtol=1e-9, atol=1e-12 * float(tj.energy(top, state))
        )
        if rn >= 0:
            assert power <= 0.0
        expected = float(tj.jellet_rate(top, state, model=model))
        np.testing.assert_allclose(
            float(jellet_rate), expected, rtol=1e-9, atol=1e-12 * abs(float(tj.jellet(top, state)))
        )
        if not top.friction.has_drilling_torque:
            assert expected == 0.0
