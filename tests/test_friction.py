"""Friction laws: the Hertz law against quadrature, limits, regularisation, dissipation, the
top's friction field, the levels that take a law, and simulations under each law (energy,
the Jellet balance, convergence in slip_scale)."""

import math
import re
import warnings

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate

import tippejax as tj
from tippejax._friction.coulomb_contensou import hertz_profiles
from tippejax._models._rigid_body import rigid_body_dynamics, rigid_body_dynamics_by_components

MU, RHO = 0.3, 5e-4

# Leine & Glocker's top (2003), without the stem.
LG = dict(m=0.006, R=0.015, eps=0.003, A=8e-7, C=7e-7, g=9.81)


def lg_top(friction):
    return tj.TippeTop(**LG, friction=friction)


def laws(slip_scale=1e-5):
    return {
        "viscous": tj.Viscous(0.3),
        "coulomb": tj.Coulomb(MU, slip_scale),
        "hertz": tj.CoulombContensou(MU, RHO, slip_scale),
        "ellipse": tj.CoulombContensou(MU, RHO, slip_scale, pressure="ellipse"),
    }


# ---------------- the Hertz law against Coulomb's law integrated over the disc ----------------


def disc_quadrature(u):
    """Coulomb's law integrated over the unit disc with the Hertz pressure (total 1), spinning
    at omega_n = 1 and sliding at v = (u, 0): (F_x, M) per unit normal force and mu."""

    def integrand(phi, r, part):
        x, y = r * np.cos(phi), r * np.sin(phi)
        wx, wy = u - y, x  # v + e_Z x r
        speed = math.hypot(wx, wy)
        if speed == 0.0:
            return 0.0
        weight = 1.5 / np.pi * math.sqrt(max(1.0 - r * r, 0.0)) * r
        return -weight * (wx if part == 0 else x * wy - y * wx) / speed

    opts = dict(epsabs=1e-12, epsrel=1e-12, limit=200)
    return [
        integrate.nquad(integrand, [[0, 2 * np.pi], [0, 1]], args=(part,), opts=[opts, opts])[0]
        for part in (0, 1)
    ]


QUADRATURE_U = (0.0, 0.4, 0.95, 1.0, 1.3, 2.0, 3.0, 12.0)


@pytest.fixture(scope="module")
def quadrature():
    return {u: disc_quadrature(u) for u in QUADRATURE_U}


def test_hertz_closed_form_matches_quadrature(quadrature):
    force, torque = hertz_profiles(jnp.asarray(QUADRATURE_U))
    for i, u in enumerate(QUADRATURE_U):
        fx, m = quadrature[u]
        np.testing.assert_allclose(-float(force[i]), fx, rtol=1e-9, atol=1e-12, err_msg=f"u={u}")
        np.testing.assert_allclose(-float(torque[i]), m, rtol=1e-9, atol=1e-12, err_msg=f"u={u}")


def test_hertz_limits_and_continuity():
    # pure spin, pure slip, small slip (Leine & Glocker eq. 17)
    force, torque = hertz_profiles(jnp.asarray([0.0, 1e-6, 1e8]))
    np.testing.assert_allclose(float(torque[0]), 3 * np.pi / 16, rtol=1e-15)
    np.testing.assert_allclose(float(force[1]) / 1e-6, 3 * np.pi / 8, rtol=1e-9)
    np.testing.assert_allclose(float(force[2]), 1.0, rtol=1e-15)
    np.testing.assert_allclose(float(torque[2]) * 1e8, 0.2, rtol=1e-9)  # M ~ rho/(5u)
    # The branches join at u = 1 with equal values and first and second derivatives (the third
    # is singular there, like sqrt(u - 1)), and at u = 2 (closed form and series of one
    # analytic function) with equal derivatives of every order.
    for i in (0, 1):
        derivatives = [lambda u, i=i: hertz_profiles(u)[i]]
        for _ in range(3):
            derivatives.append(jax.grad(derivatives[-1]))

        def gap(k, u0, h):
            left = float(derivatives[k](jnp.asarray(u0 - h)))
            right = float(derivatives[k](jnp.asarray(u0 + h)))
            return abs(left - right) / (1 + abs(left))

        for k in (0, 1):
            assert gap(k, 1.0, 1e-8) < 1e-6, (i, k)
        assert gap(2, 1.0, 1e-6) < 1e-2 and gap(2, 1.0, 1e-8) < gap(2, 1.0, 1e-6) / 5, i
        for k in range(4):
            assert gap(k, 2.0, 1e-8) < 1e-6, (i, k)


@pytest.mark.parametrize("slip, spin", [(1e-3, 4.0), (2e-3, 4.0), (5e-3, 4.0), (2e-2, 10.0)])
def test_regularised_hertz_law_converges_to_the_exact_law(quadrature, slip, spin):
    """At fixed (v, omega_n) the regularised law tends to Coulomb's law integrated over the
    disc as slip_scale -> 0, with an error of order slip_scale^2."""
    u = slip / (RHO * spin)
    fx, m = disc_quadrature(u) if u not in quadrature else quadrature[u]
    errors = []
    for delta in (1e-4, 1e-5, 1e-6):
        law = tj.CoulombContensou(MU, RHO, delta)
        f, torque = law.force_and_torque(jnp.asarray([slip, 0.0]), jnp.asarray(spin))
        errors.append(max(abs(float(f[0]) / MU - fx), abs(float(torque) / (MU * RHO) - m)))
        assert abs(float(f[1])) < 1e-15
    assert errors[-1] < 1e-6
    assert errors[1] < errors[0] / 50 and errors[2] < errors[1] / 50  # ~ slip_scale^2


def test_ellipse_law_limits():
    law = tj.CoulombContensou(MU, RHO, 1e-9, pressure="ellipse")
    f, m = law.force_and_torque(jnp.asarray([0.3, -0.4]), jnp.asarray(0.0))
    np.testing.assert_allclose(np.asarray(f), [-0.6 * MU, 0.8 * MU], rtol=1e-12)
    f, m = law.force_and_torque(jnp.asarray([0.0, 0.0]), jnp.asarray(-50.0))
    np.testing.assert_allclose(float(m), 3 * np.pi / 16 * MU * RHO, rtol=1e-12)
    # on the friction ball |(f, m / R_b)| = mu when sliding and spinning
    rb = 3 * np.pi * RHO / 16
    f, m = law.force_and_torque(jnp.asarray([1e-3, 2e-3]), jnp.asarray(7.0))
    np.testing.assert_allclose(float(jnp.sqrt(jnp.sum(f**2) + (m / rb) ** 2)), MU, rtol=1e-9)


@pytest.mark.parametrize("name", ["viscous", "coulomb", "hertz", "ellipse"])
def test_every_law_dissipates(getkey, name):
    law = laws(1e-3)[name]
    v = 0.05 * jax.random.normal(getkey(), (2000, 2)) * jax.random.uniform(getkey(), (2000, 1))
    w = 100.0 * jax.random.normal(getkey(), (2000,)) * jax.random.uniform(getkey(), (2000,))
    v, w = v.at[:10].set(0.0), w.at[5:15].set(0.0)
    f, m = law.force_and_torque(v, w)
    power = jnp.sum(f * v, -1) + m * w
    assert bool(jnp.all(power <= 0.0))
    assert bool(jnp.all(jnp.sum(f * v, -1) <= 0.0)) and bool(jnp.all(m * w <= 0.0))
    if not law.has_drilling_torque:
        assert bool(jnp.all(m == 0.0))


@pytest.mark.parametrize("name", ["coulomb", "hertz", "ellipse"])
def test_gradients_are_finite_where_the_law_is_singular(name):
    """No nan gradient at v = 0, omega_n = 0, and (Hertz) u = 1 exactly: at v = 0 and
    omega_n = 0 the regularised speeds are equal; u = 1 and 2 also with slip and spin."""
    law = laws(1e-5)[name]

    def total(v, w, law):
        f, m = law.force_and_torque(v, w)
        return jnp.sum(f) + m / RHO

    grad = jax.jit(jax.grad(total, argnums=(0, 1, 2)))
    points = [((0.0, 0.0), 0.0), ((0.0, 0.0), 3.0), ((1e-3, 0.0), 0.0)]
    delta = float(law.slip_scale)
    for u in (1.0, 2.0):  # s/w = u exactly: |v|^2 + d^2 = u^2 (rho^2 w^2 + d^2)
        w = 4.0
        points.append(((math.sqrt(u**2 * ((RHO * w) ** 2 + delta**2) - delta**2), 0.0), w))
    for v, w in points:
        g = grad(jnp.asarray(v), jnp.asarray(w), law)
        for leaf in jax.tree_util.tree_leaves(g):
            assert bool(jnp.all(jnp.isfinite(leaf))), (name, v, w)


def test_laws_in_float32():
    for name, law in laws(1e-3).items():
        law32 = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32), law)
        v = jnp.asarray([[1e-3, -2e-3], [0.0, 0.0], [0.3, 0.1], [1e-5, 0.0]])
        w = jnp.asarray([50.0, 0.0, -3.0, 120.0])
        f64, m64 = law.force_and_torque(v, w)
        f32, m32 = law32.force_and_torque(v.astype(jnp.float32), w.astype(jnp.float32))
        assert f32.dtype == jnp.float32 and m32.dtype == jnp.float32, name
        np.testing.assert_allclose(np.asarray(f32), np.asarray(f64), rtol=2e-5, atol=1e-9)
        np.testing.assert_allclose(np.asarray(m32), np.asarray(m64), rtol=2e-5, atol=1e-12)


def test_zero_slip_coefficient_is_the_slope_at_zero_slip():
    for name, law in laws(1e-3).items():
        slope = jax.jacfwd(lambda v: law.force_and_torque(v, jnp.asarray(0.0))[0])(jnp.zeros(2))
        np.testing.assert_allclose(
            float(law.zero_slip_coefficient()), -float(slope[0, 0]), rtol=1e-9, err_msg=name
        )


# ---------------- the laws' fields, and the top's friction ----------------


@pytest.mark.parametrize(
    "build, message",
    [
        (lambda: tj.Viscous(-0.1), "Viscous.mu (viscous friction coefficient, s/m) must be >= 0"),
        (
            lambda: tj.Coulomb(-0.1, 1e-3),
            "Coulomb.mu (Coulomb friction coefficient, dimensionless)",
        ),
        (
            lambda: tj.Coulomb(0.3, 0.0),
            "Coulomb.slip_scale (regularisation speed, m/s) must be > 0",
        ),
        (lambda: tj.Coulomb(0.3, float("nan")), "Coulomb.slip_scale must be finite"),
        (
            lambda: tj.CoulombContensou(0.3, 0.0, 1e-5),
            "patch_radius (radius of the contact disc, m)",
        ),
        (lambda: tj.CoulombContensou(0.3, 5e-4, -1e-5), "CoulombContensou.slip_scale"),
        (lambda: tj.CoulombContensou(0.3, 5e-4, 1e-5, pressure="uniform"), "'hertz', 'ellipse'"),
        (lambda: lg_top(tj.CoulombContensou(0.3, 5e-3, 1e-5)), "well below the ball's radius R"),
        (lambda: tj.TippeTop(**LG, mu=0.5, friction=tj.Coulomb(0.3, 1e-3)), "not both"),
        (lambda: lg_top(tj.Coulomb([0.1, 0.2], [1e-3, 1e-3, 1e-3])), "do not broadcast"),
    ],
)
def test_bad_laws_raise(build, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        build()


def test_bad_law_raises_under_jit():
    build = eqx.filter_jit(lambda d: lg_top(tj.CoulombContensou(0.3, 5e-4, d)).mu * 1.0)
    assert float(build(jnp.asarray(1e-5))) == 0.3
    with pytest.raises(Exception, match=re.escape("CoulombContensou.slip_scale")):
        jax.block_until_ready(build(jnp.asarray(-1e-5)))
    build = eqx.filter_jit(lambda r: lg_top(tj.CoulombContensou(0.3, r, 1e-5)).m * 1.0)
    with pytest.raises(Exception, match=re.escape("well below the ball's radius")):
        jax.block_until_ready(build(jnp.asarray(5e-3)))


def test_top_with_a_law():
    law = tj.CoulombContensou(0.3, RHO, 1e-5)
    top = lg_top(law)
    assert float(top.mu) == 0.3 and top.friction.pressure == "hertz"
    assert repr(top) == (
        "TippeTop(m=0.006, R=0.015, eps=0.003, A=8e-07, C=7e-07, g=9.81, friction="
        "CoulombContensou(mu=0.3, patch_radius=0.0005, slip_scale=1e-05, pressure='hertz'))"
    )
    # mu= is the viscous law; giving it equal to its default beside a law is allowed
    viscous = tj.TippeTop(**LG, mu=0.7)
    assert isinstance(viscous.friction, tj.Viscous) and float(viscous.mu) == 0.7
    assert tj.TippeTop(**LG, mu=0.3, friction=law).friction is not None
    # replace: mu replaces the law's mu; friction replaces the law
    batch = top.replace(mu=[0.1, 0.2, 0.4])
    assert batch.batch_shape == (3,) and isinstance(batch.friction, tj.CoulombContensou)
    assert batch.friction.patch_radius.shape == (3,) and batch.m.shape == (3,)
    np.testing.assert_array_equal(np.asarray(batch.mu), [0.1, 0.2, 0.4])
    assert "batch_shape=(3,)" in repr(batch) and "mu=[0.1 0.2 0.4]" in repr(batch)
    assert isinstance(top.replace(friction=tj.Viscous(0.2)).friction, tj.Viscous)
    assert repr(top.replace(friction=tj.Viscous(0.2))).endswith("g=9.81, mu=0.2)")
    with pytest.raises(ValueError, match="not both"):
        top.replace(mu=0.1, friction=tj.Viscous(0.2))
    with pytest.raises(ValueError, match="Coulomb friction coefficient, dimensionless"):
        top.replace(mu=-1.0)
    # from_ratios takes a law; astype casts the law's fields too
    ratio_top = tj.TippeTop.from_ratios(0.9, 0.3, friction=tj.Coulomb(0.2, 1e-3))
    assert float(ratio_top.mu) == 0.2
    top32 = top.astype(jnp.float32)
    assert top32.friction.slip_scale.dtype == jnp.float32
    # a batch of laws' parameters goes through jax.vmap, one top per member
    tops = top.replace(friction=tj.CoulombContensou(0.3, [2e-4, 5e-4], 1e-5))
    rates = jax.vmap(tj.friction_rate)(tops)
    assert rates.shape == (2,)
    # the law's leaves follow the top's own, the viscous law's mu last as before
    assert len(jax.tree_util.tree_leaves(top)) == 9
    assert [float(x) for x in jax.tree_util.tree_leaves(tj.default_top())][-1] == 0.3


def test_stiffness_for_the_solver_choice():
    """A Contensou law's stiffness is its slope at zero slip while the contact drills (the
    regularised bound needs omega_n -> 0 too), so a spinning Contensou top runs an explicit
    solver even at a small slip_scale; pure Coulomb friction near rolling is as stiff as
    1/slip_scale says."""
    from tippejax._friction.coulomb_contensou import REFERENCE_DRILLING_RATE

    for law in (laws()["hertz"], laws()["ellipse"]):
        slope = jax.jacfwd(
            lambda v, law=law: law.force_and_torque(v, jnp.asarray(REFERENCE_DRILLING_RATE))[0]
        )(jnp.zeros(2))
        np.testing.assert_allclose(
            float(law.stiffness_coefficient()), -float(slope[0, 0]), rtol=1e-9
        )
        assert float(law.stiffness_coefficient()) < 1e-3 * float(law.zero_slip_coefficient())
    assert isinstance(tj.default_solver(lg_top(laws(1e-5)["hertz"])), diffrax.Dopri8)
    assert isinstance(tj.default_solver(lg_top(tj.Coulomb(MU, 1e-5))), diffrax.Kvaerno5)


def test_friction_rate_asks_the_law():
    top = lg_top(tj.Coulomb(0.3, 1e-3))
    viscous = tj.TippeTop(**LG, mu=0.3 / 1e-3)
    np.testing.assert_allclose(
        float(tj.friction_rate(top)), float(tj.friction_rate(viscous)), rtol=1e-15
    )


# ---------------- the contact force: R_n from the constraint, every law ----------------


def _random_states(seed, n=12):
    rng = np.random.default_rng(seed)
    theta = rng.uniform(0.1, np.pi - 0.1, n)
    phi, psi = rng.uniform(-3.0, 3.0, (2, n))
    thd, phid, psid = (
        rng.normal(scale=3.0, size=n),
        rng.normal(scale=10.0, size=n),
        rng.normal(scale=150.0, size=n),
    )
    velocity = rng.normal(scale=0.05, size=(n, 2))
    return tj.state_from_euler(theta, phi, psi, thd, phid, psid, velocity=velocity)


def _newton_euler(top, axis, omega, velocity):
    """R_n and omega_dot from Newton-Euler's equations with the contact constraint, as one
    linear system in (omega_dot, R_n), in numpy (the law evaluated by the package)."""
    m, R, eps, A, C, g = (float(getattr(top, k)) for k in ("m", "R", "eps", "A", "C", "g"))
    a, w = np.asarray(axis), np.asarray(omega)
    n = w @ a
    a_dot = np.cross(w, a)
    q = eps * a - np.array([0.0, 0.0, R])
    v_o = np.array([*np.asarray(velocity), -eps * a_dot[2]])
    v_q = v_o + np.cross(w, q)
    f, torque = top.friction.force_and_torque(jnp.asarray(v_q[:2]), jnp.asarray(w[2]))
    force = np.array([*np.asarray(f), 1.0])  # per unit R_n
    tau = np.cross(q, force) + np.array([0.0, 0.0, float(torque)])
    # d/dt (A w + (C - A) n a) = A w' + (C - A)((a.w') a + n a_dot) = R_n tau
    K = np.zeros((4, 4))
    rhs = np.zeros(4)
    K[:3, :3] = A * np.eye(3) + (C - A) * np.outer(a, a)
    K[:3, 3] = -tau
    rhs[:3] = -(C - A) * n * a_dot
    # m z_O'' = R_n - m g with z_O = R - eps a_Z: z_O'' = -eps ((w' x a) + w x a_dot)_Z
    K[3, :3] = -m * eps * np.array([a[1], -a[0], 0.0])  # (w' x a)_Z = w'_x a_y - w'_y a_x
    K[3, 3] = -1.0
    rhs[3] = -m * g + m * eps * np.cross(w, a_dot)[2]
    x = np.linalg.solve(K, rhs)
    return x[3], x[:3]


@pytest.mark.parametrize("name", ["viscous", "coulomb", "hertz", "ellipse"])
def test_normal_force_solves_newton_euler_with_the_constraint(name):
    top = lg_top(laws(1e-3)[name])
    states = _random_states(3)
    vector = jax.jit(rigid_body_dynamics)
    components = jax.jit(rigid_body_dynamics_by_components)
    for i in range(states.axis.shape[0]):
        axis, omega, velocity = states.axis[i], states.omega[i], states.velocity[i]
        rn, omega_dot = _newton_euler(top, axis, omega, velocity)
        out = vector(top, axis, omega, velocity)
        np.testing.assert_allclose(float(out[0]), rn, rtol=1e-10)
        np.testing.assert_allclose(
            np.asarray(out[1]), omega_dot, rtol=1e-9, atol=1e-9 * np.max(np.abs(omega_dot))
        )
        by_components = components(top, axis, omega, velocity)
        for x, y in zip(out, by_components):
            np.testing.assert_allclose(
                np.asarray(y),
                np.asarray(x),
                rtol=1e-12,
                atol=1e-12 * (1 + np.max(np.abs(np.asarray(x)))),
            )


# ---------------- which levels take a law ----------------


def test_levels_that_do_not_take_a_law_refuse_it():
    top = lg_top(laws()["hertz"])
    y0 = tj.initial_state(top, theta=0.1, spin=180.0)
    for model in ("routhian", "gyroscopic"):
        with pytest.raises(ValueError, match=re.escape("'full', 'so3'")):
            tj.simulate(top, y0, t1=0.1, model=model)
    from tippejax._auto import choose_model
    from tippejax._models.levels import levels_taking

    assert choose_model(top, y0, tolerance=10.0) == "full"
    assert levels_taking(top.friction) == ("full", "so3")
    assert levels_taking(tj.Viscous(0.3)) == ("full", "so3", "routhian", "gyroscopic")


# ---------------- simulations under every law ----------------

T1 = 0.3
SAVES = np.linspace(0.0, T1, 601)
RUNS = [
    *[(name, "full") for name in ("coulomb", "hertz", "ellipse")],
    ("hertz", "so3"),
    *[pytest.param(name, "so3", marks=pytest.mark.slow) for name in ("coulomb", "ellipse")],
]
"""The (law, level) pairs the invariant tests run: every law at the full level, and the SO(3)
level with the Hertz law (the other laws there under `-m slow`)."""


class _Runs(dict):
    """One short run per law and level, made when a test first asks for it (LG's top,
    theta0 = 0.1, 180 rad/s; the launch's slipping transient), with a fine save grid."""

    def __missing__(self, key):
        name, model = key
        top = lg_top(laws(1e-4)[name])
        y0 = tj.initial_state(top, theta=0.1, spin=180.0)
        with warnings.catch_warnings():  # (pure Coulomb's caveat: tested below)
            warnings.simplefilter("ignore", UserWarning)
            sol = tj.simulate(
                top,
                y0,
                t1=T1,
                model=model,
                saveat=SAVES,
                rtol=1e-9,
                atol=1e-12,
                solver=diffrax.Tsit5(),
                max_steps=100_000,
            )
        self[key] = (top, sol)
        return self[key]


@pytest.fixture(scope="module")
def runs():
    """The runs of every law (not the viscous one: tests/test_models.py and test_simulate.py
    check it) at the full and SO(3) levels, by `(law, level)`."""
    return _Runs()


@pytest.mark.parametrize("name, model", RUNS)
def test_energy_never_increases(runs, name, model):
    _, sol = runs[name, model]
    energy = np.asarray(sol.energy)
    assert energy[-1] < energy[0] * (1 - 1e-4)  # it dissipates
    assert np.max(np.diff(energy)) <= 1e-10 * abs(energy[0]), np.max(np.diff(energy)) / energy[0]


@pytest.mark.parametrize("name, model", RUNS)
def test_jellet_balance(runs, name, model):
    """J is conserved under a friction force alone; under a drilling torque it follows
    J(t) - J(0) = int M (R - eps cos theta) dt (trapezoids on the fine save grid)."""
    top, sol = runs[name, model]
    J = np.asarray(sol.jellet)
    rate = np.asarray(tj.jellet_rate(top, sol.states, model=model))
    balance = np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(SAVES))])
    change = J - J[0]
    if top.friction.has_drilling_torque:
        assert abs(change[-1]) > 1e-3 * abs(J[0])  # the torque moves J visibly
        np.testing.assert_allclose(change, balance, atol=1e-5 * abs(change[-1]))
    else:
        assert np.all(rate == 0.0)
        np.testing.assert_allclose(J, J[0], rtol=1e-8)


def test_jellet_rate_is_the_derivative_along_the_field():
    """jellet_rate equals dJ/dt = grad J . f(y) along each level's field (random states)."""
    from tippejax._models.levels import LEVELS

    top = lg_top(laws(1e-3)["hertz"])
    states = _random_states(5)
    for model in ("full", "so3"):
        level = LEVELS[model]

        @jax.jit
        def rates(state, level=level, model=model):
            y = level.from_state(top, state)
            dy = level.vector_field(0.0, y, top)
            along = jax.jvp(lambda s: tj.jellet(top, level.to_state(top, s)), (y,), (dy,))[1]
            return along, tj.jellet_rate(top, state, model=model)

        for i in range(states.axis.shape[0]):
            state = jax.tree_util.tree_map(lambda x, i=i: x[i], states)
            if model == "so3":
                state = eqx.tree_at(lambda s: s.velocity, state, jnp.zeros(2))
            along, formula = rates(state)
            np.testing.assert_allclose(
                float(formula),
                float(along),
                rtol=1e-9,
                atol=1e-12 * abs(float(tj.jellet(top, state))),
            )


def _inversion_time(law, t1, solver=None, rtol=1e-8):
    top = lg_top(law)
    y0 = tj.initial_state(top, theta=0.1, spin=180.0)
    sol = tj.simulate(
        top,
        y0,
        t1=t1,
        model="full",
        summary=True,
        rtol=rtol,
        atol=rtol * 1e-3,
        solver=solver,
        max_steps=400_000,
    )
    return float(sol.t_invert)


def test_contensou_inversion_time_converges_in_slip_scale():
    """With a drilling torque the rise is set by the physics: theta first passes pi/2 at
    about 1 s, the same time for every small slip_scale (and no caveat is raised)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        times = [
            _inversion_time(tj.CoulombContensou(MU, RHO, delta), 1.3)
            for delta in (1e-4, 1e-5, 1e-6)
        ]  # (the default solver, explicit: Dopri8)
    assert 0.8 < times[0] < 1.2
    assert abs(times[1] - times[0]) < 1e-6 and abs(times[2] - times[1]) < 1e-6


def test_coulomb_inversion_time_does_not_converge_in_slip_scale():
    """Without a drilling torque the rise goes by creep below slip_scale: the inversion time
    grows roughly like 1/slip_scale and has no limit (in the full model, where the contact
    point can reach rolling; the SO(3) level, which drops the translation from the slip,
    does not show it). simulate (and inversion_time, which runs it) says so, and runs."""
    times = []
    for delta in (1e-2, 3e-3, 1e-3):
        with pytest.warns(
            UserWarning,
            match=rf"depends on slip_scale \(here {delta:.3g} m/s\)"
            r".*1/slip_scale",
        ):
            times.append(_inversion_time(tj.Coulomb(MU, delta), 6.0, diffrax.Tsit5(), rtol=1e-6))
    assert 0.8 < times[0] < 1.4
    assert times[0] < times[1] < times[2]
    assert times[2] - times[0] > 1.0  # far beyond any solver error
    # the increments follow those of 1/delta (a factor 3 between them), not a converging
    # sequence (whose increments would shrink)
    assert 1.5 < (times[2] - times[1]) / (times[1] - times[0]) < 6.0


@pytest.mark.slow
def test_coulomb_inversion_time_grows_like_one_over_slip_scale():
    times = [
        _inversion_time(tj.Coulomb(MU, delta), 40.0, rtol=1e-6) for delta in (1e-3, 3e-4, 1e-4)
    ]  # (default solvers: Tsit5, then Kvaerno5)
    assert times[0] < times[1] < times[2]
    # each tenfold smaller slip_scale: several times longer (about 1/delta)
    assert times[2] / times[0] > 4.0


@pytest.mark.slow
def test_float32_run_agrees_with_float64(runs):
    """Slow: the float32 twin of the runs above; `test_laws_in_float32` holds every law in float32."""
    top, ref = runs["hertz", "full"]
    top32 = top.astype(jnp.float32)
    y0 = jax.tree_util.tree_map(
        lambda x: x.astype(jnp.float32), tj.initial_state(top, theta=0.1, spin=180.0)
    )
    sol = tj.simulate(
        top32, y0, t1=T1, model="full", saveat=SAVES, solver=diffrax.Tsit5(), max_steps=100_000
    )
    assert sol.theta.dtype == jnp.float32
    assert np.max(np.abs(np.asarray(sol.theta) - np.asarray(ref.theta))) < 1e-3
    assert np.max(np.diff(np.asarray(sol.energy, dtype=float))) <= 1e-6 * float(ref.energy[0])


@pytest.mark.slow
def test_vmap_over_a_batch_of_one_law(runs):
    """A batch of tops with one law and batched parameters runs under jax.vmap; the member
    with the fixture's parameters gives its run."""
    top, ref = runs["hertz", "so3"]
    tops = top.replace(mu=[0.3, 0.1])
    y0 = tj.initial_state(top, theta=0.1, spin=180.0)
    theta = jax.vmap(
        lambda t: (
            tj.simulate(
                t,
                y0,
                t1=T1,
                model="so3",
                saveat=SAVES,
                rtol=1e-9,
                atol=1e-12,
                solver=diffrax.Tsit5(),
                max_steps=100_000,
            ).theta
        )
    )(tops)
    np.testing.assert_allclose(np.asarray(theta[0]), np.asarray(ref.theta), rtol=0, atol=1e-9)
    assert np.max(np.abs(np.asarray(theta[1] - theta[0]))) > 1e-4  # mu matters
