"""The gyroscopic level (`tippejax/_models/gyroscopic/`): the slow flow re-derived in sympy from
the paper's L' and Q', checked against the linearisations of the Routhian and SO(3) models,
its fixed points and their stability against the analysis level in all six groups, and the
level run through `simulate` (error against SO(3) shrinking with spin, the poles, a launch
below n1, the intermediate state, and the launches it must refuse).

Every gyroscopic `simulate` call uses the save grid `grid()` and the default tolerances, and
every SO(3) reference run `REF`, so that each compiles once.
"""

import diffrax
import internal as ti
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import sympy as sp
from helpers import GROUP_RATIOS

import tippejax as tj
from tippejax._models.gyroscopic import (
    BALANCE_MARGIN,
    SETTLE_TIME_MAX,
    GyroscopicLevel,
    GyroscopicLevelState,
    limit_theta_dot,
    nutation_damping,
    nutation_frequency,
    precession_rate,
    project_launch,
    settle_time,
    slow_manifold,
)
from tippejax._models.levels import LEVELS
from tippejax._simulate.programs import _run

N = 201  # one save-grid length for every run
REF = dict(rtol=1e-10, atol=1e-12)  # SO(3) reference runs
LEVEL = GyroscopicLevel()


def run_level(level, top, y0, t1, ts=None):
    """One level as configured (e.g. without its hand-over to the full model), Dopri5 at rtol
    1e-8: a dict of `Solution` fields (summary mode unless `ts`)."""
    f = lambda x: jnp.asarray(x, jnp.result_type(top.m))  # noqa: E731
    ts = None if ts is None else f(ts)
    return _run(
        top,
        y0,
        ts,
        f(0.0),
        f(t1),
        f(1e-8),
        f(1e-10),
        level=level,
        solver=diffrax.Dopri5(),
        guard_stiff=False,
        stop_on_contact=True,
        max_steps=100_000,
        adjoint=diffrax.RecursiveCheckpointAdjoint(),
        progress=False,
        pieces=1,
    )


def grid(t1):
    return jnp.linspace(0.0, t1, N)


def _np(x):
    return np.asarray(x, dtype=np.float64)


def is_ok(sol):
    return bool(np.all(np.asarray(sol.result == tj.RESULTS.successful)))


def jellet_of(top, spin, theta=0.0):
    return float(tj.jellet(top, tj.initial_state(top, theta, spin)))


def on_manifold(top, theta, spin):
    """A state on the slow manifold at `theta`, with the Jellet of a vertical launch at `spin`."""
    y = GyroscopicLevelState.from_theta(
        theta, phi=0.0, psi=0.0, nutation=-30.0, jellet=jellet_of(top, spin)
    )
    return LEVEL.to_state(top, y)


# ------------------------------------------------------------------------------------------------
# (a) The derivation, independently in sympy from the paper's L' and Q' (Sec. 2.2)


def _sympy_slow_flow():
    """theta_dot, Omega, n on the slow manifold as sympy expressions, derived from L' and Q'.

    Returns lambdified functions of (m, g, eps, R, A, C, mu, J, theta, Omega) and the quadratic
    for Omega, plus the checks that are symbolic (R'_n = m g on the balance, dL'/dpsid = C n).
    """
    t = sp.Symbol("t")
    m, g, eps, R, A, C, mu = sp.symbols("m g epsilon R A C mu", positive=True)
    J, th, Om, n = sp.symbols("J theta Omega n", real=True)
    TH, PH, PS = (sp.Function(k)(t) for k in ("theta", "phi", "psi"))
    thd, phd, psd = TH.diff(t), PH.diff(t), PS.diff(t)
    # L' of Sec. 2.2 (translation dropped)
    L = sp.Rational(1, 2) * (
        (eps**2 * m * sp.sin(TH) ** 2 + A) * thd**2
        + A * sp.sin(TH) ** 2 * phd**2
        + C * (psd + phd * sp.cos(TH)) ** 2
    ) - m * g * (R - eps * sp.cos(TH))
    no_acceleration = {TH.diff(t, 2): 0}
    slow = {thd: 0, phd: Om, psd: n - Om * sp.cos(th)}

    def at_slow(expr):
        expr = expr.subs(no_acceleration).subs(slow)
        return expr.subs(TH, th)

    # theta-equation, d/dt dL'/dthd - dL'/dth = Q'_theta = -mu R'_n h^2 thd = 0 on the manifold
    theta_eq = at_slow(sp.diff(L.diff(thd), t) - L.diff(TH))
    balance = sp.simplify(theta_eq / sp.sin(th))  # (G1) up to sign
    # the spin is the momentum of psi: dL'/dpsid = C n
    assert sp.simplify(at_slow(L.diff(psd)) - C * n) == 0
    # the normal force, eq. reactie with xd = yd = 0 and thd = 0
    h1 = eps * sp.sin(th)
    rn = (g + h1 * Om * sp.sin(th) * (Om * sp.cos(th) - C * n / A)) / (1 / m + h1 * h1 / A)
    g_on_balance = sp.solve(balance, g)[0]
    assert sp.simplify(rn.subs(g, g_on_balance) - m * g_on_balance) == 0  # R'_n = m g
    # Jellet, eq. jello
    jellet = C * n * (R * sp.cos(th) - eps) + A * Om * R * sp.sin(th) ** 2
    # psi-equation: d(C n)/dt = Q'_psi = -mu R'_n R sin^2 (R psid + eps phid), R'_n = m g
    n_dot = -mu * m * g * R * sp.sin(th) ** 2 * (R * (n - Om * sp.cos(th)) + eps * Om) / C
    # dn/dtheta along {balance = 0, jellet = J}: implicit function theorem
    F = sp.Matrix([balance, jellet - J])
    dF_dvars = F.jacobian([Om, n])
    dF_dth = F.diff(th)
    d_vars = -dF_dvars.LUsolve(dF_dth)
    theta_dot = n_dot / d_vars[1]
    # n from the Jellet, and the quadratic for Omega (G2)
    n_of_om = sp.solve(jellet - J, n)[0]
    quadratic = sp.numer(sp.together(balance.subs(n, n_of_om)))
    args = (m, g, eps, R, A, C, mu, J, th, Om)
    return (
        sp.lambdify(args, theta_dot.subs(n, n_of_om), "mpmath"),
        sp.lambdify(args, n_of_om, "mpmath"),
        sp.Poly(quadratic, Om),
        args,
    )


def test_slow_flow_derivation_sympy(getkey):
    theta_dot_fn, n_fn, quadratic, args = _sympy_slow_flow()
    rng = np.random.default_rng(0)
    checked = 0
    for _ in range(12):
        a, e = rng.uniform(0.6, 1.4), rng.uniform(0.05, 0.5)
        top = tj.TippeTop.from_ratios(
            a, e, m=rng.uniform(0.01, 0.1), R=rng.uniform(0.01, 0.05), mu=rng.uniform(0.1, 1.0)
        )
        theta = rng.uniform(0.1, 3.0)
        if abs(np.cos(theta) - e) < 0.05:
            continue  # the sympy route divides by R cos(theta) - eps
        J = jellet_of(top, rng.uniform(30, 300) * rng.choice([-1, 1]))
        vals = [float(getattr(top, k)) for k in ("m", "g", "eps", "R", "A", "C", "mu")] + [J, theta]
        coeffs = [float(c.subs(dict(zip(args[:-1], vals)))) for c in quadratic.all_coeffs()]
        roots = np.roots(coeffs)
        if np.any(np.abs(roots.imag) > 0):
            continue  # no balance
        omega = roots[np.argmax(np.abs(roots.real))].real  # the level's root: the larger |Omega|
        expected = float(theta_dot_fn(*vals, omega))
        sm = slow_manifold(top, theta, J)
        np.testing.assert_allclose(float(sm.precession), omega, rtol=1e-9)
        np.testing.assert_allclose(float(sm.spin), float(n_fn(*vals, omega)), rtol=1e-9)
        np.testing.assert_allclose(float(sm.theta_dot), expected, rtol=1e-8, atol=1e-14)
        checked += 1
    assert checked >= 6
    # the large-spin limit (the rise rate of the GBC): independent of the spin
    top = tj.default_top()
    for theta in (0.3, 1.2, 2.5):
        J = jellet_of(top, 1e6)
        np.testing.assert_allclose(
            float(slow_manifold(top, theta, J).theta_dot),
            float(limit_theta_dot(top, theta)),
            rtol=1e-5,
        )


def test_nutation_frequency_sympy():
    """nu^2 = U''/M_theta of the heavy top at fixed momenta p_phi, p_psi, at the balance point."""
    names = "theta A C m g epsilon R p_phi p_psi"
    th, A, C, m, g, eps, R, pphi, ppsi = sp.symbols(names, real=True)
    U = (pphi - ppsi * sp.cos(th)) ** 2 / (2 * A * sp.sin(th) ** 2) + m * g * (R - eps * sp.cos(th))
    U2 = sp.lambdify((th, A, C, m, g, eps, R, pphi, ppsi), sp.diff(U, th, 2))
    for name in ("IIb", "Ib", "III"):
        top = tj.TippeTop.from_ratios(*GROUP_RATIOS[name])
        pars = [float(getattr(top, k)) for k in ("A", "C", "m", "g", "eps", "R")]
        for theta, spin in ((0.4, 80.0), (1.3, 150.0), (2.4, 300.0)):
            J = jellet_of(top, spin)
            sm = slow_manifold(top, theta, J)
            A_, C_ = pars[0], pars[1]
            p_psi = C_ * float(sm.spin)
            p_phi = A_ * np.sin(theta) ** 2 * float(sm.precession) + p_psi * np.cos(theta)
            inertia = A_ + pars[2] * pars[4] ** 2 * np.sin(theta) ** 2
            nu2 = U2(theta, *pars, p_phi, p_psi) / inertia
            nu = float(nutation_frequency(top, theta, J))
            np.testing.assert_allclose(nu**2, nu2, rtol=1e-8)


def _nutation_damping_by_autodiff(top, theta, J):
    """sigma ("The nutation it drops", docs/derivations/gyroscopic-averaging.md) with every
    x-derivative taken by jax.jvp of its definition (the level writes them out in closed
    form)."""
    m, g, eps, R, A, C, mu = (top.m, top.g, top.eps, top.R, top.A, top.C, top.mu)
    x, s2 = jnp.cos(theta), jnp.sin(theta) ** 2
    one = jnp.ones_like(x)
    sm = slow_manifold(top, theta, J)
    p = sm.slip
    big_s = eps**2 + R**2

    def d_of(x):
        return R**2 * A * (1 - x**2) + C * (R * x - eps) ** 2

    def kappa_of(x):
        return R * A * eps * (1 - x**2) + C * (R * x - eps) * (R + eps * x)

    def normal_force_at_rest(x, p):  # eq. reactie at rest, phi_dot and n from eq. routh1
        c_dot = (J * big_s - kappa_of(x) * p) / d_of(x)
        w = (eps * p + R * c_dot) / big_s
        n = (R * p - eps * c_dot) / big_s + w * x
        return (
            m * (g + eps * (1 - x**2) * w * (w * x - C * n / A)) / (1 + m * eps**2 * (1 - x**2) / A)
        )

    def nu_squared(x):
        omega = precession_rate(top, x, J)
        n = (A * omega**2 * x - m * g * eps) / (C * omega)
        return ((C * n - 2 * A * omega * x) ** 2 + A**2 * omega**2 * (1 - x**2)) / (
            A * (A + m * eps**2 * (1 - x**2))
        )

    rn, rn_x = jax.jvp(lambda xx: normal_force_at_rest(xx, p), (x,), (one,))
    _, rn_p = jax.jvp(lambda pp: normal_force_at_rest(x, pp), (p,), (one,))
    _, dm_x = jax.jvp(lambda xx: A * C * (1 - xx**2) / d_of(xx), (x,), (one,))
    _, dbeta_x = jax.jvp(lambda xx: J / big_s * kappa_of(xx) / d_of(xx), (x,), (one,))
    nu2, nu2_x = jax.jvp(nu_squared, (x,), (one,))
    coupling = -(dm_x * p + dbeta_x)
    inertia_phibar = A * C / d_of(x)
    inertia = A + m * eps**2 * s2
    drive = (
        mu * (rn + p * rn_p) * coupling / inertia_phibar + mu * s2 * p * rn_x - 2 * mu * p * rn * x
    )
    h = R - eps * x
    friction = -(mu * rn * h**2 + coupling * drive / (inertia_phibar * nu2)) / (2 * inertia)
    log_m_nu_x = -2 * m * eps**2 * x / inertia + 0.5 * nu2_x / nu2
    return friction + 0.5 * sm.rate * s2 * log_m_nu_x


def test_nutation_damping_closed_form_matches_autodiff():
    """The level's closed-form derivatives in sigma against jax.jvp of their definitions, all six
    groups, both signs of J, wherever (G2) has a real root."""
    thetas = jnp.linspace(0.0, np.pi, 23)

    @jax.jit
    def both(top, J):
        one = jax.vmap(
            lambda th: (
                _nutation_damping_by_autodiff(top, th, J),
                nutation_damping(top, th, J),
                slow_manifold(top, th, J).discriminant,
            )
        )
        return one(thetas)

    checked = 0
    for name in GROUP_RATIOS:
        top = tj.TippeTop.from_ratios(*GROUP_RATIOS[name], mu=0.7)
        for spin in (15.0, 40.0, 100.0, 400.0, -80.0):
            expected, got, discriminant = (np.asarray(v) for v in both(top, jellet_of(top, spin)))
            real = discriminant > 0
            np.testing.assert_allclose(
                got[real], expected[real], rtol=1e-8, atol=1e-10, err_msg=f"{name}, n0 = {spin}"
            )
            checked += int(real.sum())
    assert checked > 500


def test_nutation_against_the_linearisations():
    """At the relative equilibria on the level's root, the nutation pair of the reduced system
    (steady_states' autodiff Jacobian) is nu and sigma; at the poles (SO(3) model, a regular
    chart) sigma is the decay rate of the other root's mode."""
    checked = 0
    for name in GROUP_RATIOS:
        top = tj.TippeTop.from_ratios(*GROUP_RATIOS[name])
        for spin in (20.0, 40.0, 80.0, 200.0):
            J = jellet_of(top, spin)
            ss = tj.steady_states(top, J)
            for k in range(2):
                if not bool(ss.intermediate_valid[k]):
                    continue
                theta = float(ss.intermediate_theta[k])
                sm = slow_manifold(top, theta, J)
                if abs(float(sm.slip)) > 1e-9 * abs(float(sm.precession)) * float(top.R):
                    continue  # on the other root
                ev = np.asarray(ss.intermediate_eigenvalues_reduced[k])
                pair = ev[np.argmax(np.abs(ev.imag))]
                nu, sigma = (
                    float(nutation_frequency(top, theta, J)),
                    float(nutation_damping(top, theta, J)),
                )
                assert abs(abs(pair.imag) - nu) < 0.03 * nu, (name, spin)
                assert abs(pair.real - sigma) < 0.03 * abs(pair.real), (name, spin, pair, sigma)
                checked += 1
    assert checked >= 12


def test_pole_slopes_match_so3_linearisation():
    """At a pole the slow flow's slope is the real part of the SO(3) mode whose frequency is its
    precession rate (a chart regular there); the other root's mode decays at its rate (the
    nutation the level drops). The relative difference shrinks with the spin."""
    top = tj.default_top()
    rel = []
    for spin in (30.0, 60.0, 150.0, 400.0):
        J = jellet_of(top, spin)
        ev = np.asarray(ti.vector_field_eigenvalues(top, 0.0, J, model="so3", pole=True))
        outer, inner = slow_manifold(top, 0.0, J), slow_manifold(top, 0.0, J, branch=-1)
        mode = ev[np.argmin(np.abs(ev.imag - float(outer.precession)))]
        other = ev[np.argmin(np.abs(ev.imag - float(inner.precession)))]
        rel.append(abs(float(outer.rate) - mode.real) / abs(mode.real))
        assert abs(float(inner.rate) - other.real) < 0.02 * abs(other.real)
        assert abs(float(nutation_damping(top, 0.0, J)) - other.real) < 0.02 * abs(other.real)
    print(
        "pole slope vs SO(3) eigenvalue, relative difference at n0 = 30, 60, 150, 400: "
        + ", ".join(f"{r:.1e}" for r in rel)
    )
    assert rel[-1] < rel[0] and max(rel) < 0.01


# ------------------------------------------------------------------------------------------------
# (b) Fixed points and their stability against the analysis level, all six groups


def _jellets(top):
    C, R, eps = (float(getattr(top, k)) for k in ("C", "R", "eps"))
    Js = [C * (R - eps) * n for n in (5.0, 15.0, 60.0, 400.0)]
    th = tj.thresholds(top)
    for Jx in (float(th.J1), float(th.J2)):
        if np.isfinite(Jx):
            Js += [f * Jx for f in (0.7, 0.97, 1.03, 1.5)]
    return sorted(Js)


def _slope(top, theta, J, branch):
    return float(jax.grad(lambda t: slow_manifold(top, t, J, branch=branch).theta_dot)(theta))


@pytest.mark.parametrize("group", list(GROUP_RATIOS))
def test_fixed_points_and_stability(group):
    a, e = GROUP_RATIOS[group]
    top = tj.TippeTop.from_ratios(a, e)
    level_root_carries_all = a > (1 + e) / 2  # else relative equilibria near pi lie on the other
    counts = dict(intermediate=0, other_root=0, poles=0, poles_by_nutation=0)
    for J in _jellets(top):
        ss = tj.steady_states(top, J)
        level_states = []
        for theta_i, stable in ss.intermediate:
            out, other = slow_manifold(top, theta_i, J), slow_manifold(top, theta_i, J, branch=-1)
            scale = abs(float(out.precession)) * float(top.R)
            branch = 1 if abs(float(out.slip)) < abs(float(other.slip)) else -1
            sm = out if branch == 1 else other
            # a relative equilibrium: no slip, and a fixed point of the flow on its root
            assert abs(float(sm.slip)) < 1e-9 * scale
            assert abs(float(sm.theta_dot)) < 1e-9 * abs(float(limit_theta_dot(top, 1.0)))
            # stable exactly where W'' > 0
            assert (_slope(top, theta_i, J, branch) < 0) == stable, (group, J, theta_i)
            if branch == 1:
                counts["intermediate"] += 1
                level_states.append(theta_i)
            else:
                assert not level_root_carries_all
                counts["other_root"] += 1
        # the poles, where gyroscopic balance exists
        for k, pole in enumerate((0.0, np.pi)):
            sm = slow_manifold(top, pole, J)
            if float(sm.discriminant) <= 0:
                continue
            slope = float(sm.rate) * np.cos(pole)  # d(rate sin)/dtheta at the pole
            stable = bool(ss.vertical_stable[k])
            if (slope < 0) == stable:
                counts["poles"] += 1
            else:
                # only where the other root carries the pole's instability: it is the nutation
                # about the level's root, which grows there (the level watches it and stops)
                assert not level_root_carries_all and k == 1
                assert float(nutation_damping(top, pole, J)) > 0
                assert _slope(top, pole, J, -1) > 0
                counts["poles_by_nutation"] += 1
        # no other zeros of the flow on the level's root, where it has a root
        thetas = np.linspace(0.02, np.pi - 0.02, 400)
        sm = slow_manifold(top, jnp.asarray(thetas), J)
        x = np.cos(thetas)
        h = float(top.R) - float(top.eps) * x
        lever = np.abs(float(top.R) * x - float(top.eps))
        scale = J**2 + 4 * float(top.A * top.m * top.g * top.eps) * h * lever
        ok = _np(sm.discriminant) / scale > BALANCE_MARGIN
        rate = _np(sm.rate)
        changes = np.nonzero(ok[1:] & ok[:-1] & (np.sign(rate[1:]) != np.sign(rate[:-1])))[0]
        for i in changes:
            assert any(thetas[i] - 0.01 <= t <= thetas[i + 1] + 0.01 for t in level_states), (
                group,
                J,
                thetas[i],
            )
    print(f"{group}: {counts}")
    assert counts["intermediate"] > 0 and counts["poles"] > 0


# ------------------------------------------------------------------------------------------------
# The projection of a launch


def test_projection_is_exact_on_the_manifold_and_linear_at_the_pole():
    top = tj.default_top()
    for theta, spin in ((0.0, 100.0), (0.03, 100.0), (0.8, 150.0), (2.0, 80.0), (3.1, 120.0)):
        y = on_manifold(top, theta, spin)
        theta_s, _, _, log_a, J = project_launch(top, y)
        assert abs(float(theta_s) - theta) < 1e-10
        assert float(log_a) < np.log(1e-9)
        assert abs(float(J) - jellet_of(top, spin)) < 1e-12 * abs(float(J))
    # a launch omega = n a near the pole: the slow component is the SO(3) modal projection
    for spin in (60.0, 150.0):
        J = jellet_of(top, spin)

        def field(z):
            axis = jnp.array([z[0], z[1], jnp.sqrt(1 - z[0] ** 2 - z[1] ** 2)])
            omega = jnp.array([z[2], z[3], spin])
            from tippejax._models._rigid_body import rigid_body_dynamics

            _, omega_dot, _, _ = rigid_body_dynamics(top, axis, omega, jnp.zeros(2))
            axis_dot = jnp.cross(omega, axis)
            return jnp.stack([axis_dot[0], axis_dot[1], omega_dot[0], omega_dot[1]])

        jr = np.asarray(jax.jacfwd(field)(jnp.zeros(4)))
        M = np.array(
            [[jr[2 * j, 2 * k] + 1j * jr[2 * j + 1, 2 * k] for k in range(2)] for j in range(2)]
        )
        lam, V = np.linalg.eig(M)
        slow = np.argmin(np.abs(lam.imag - float(slow_manifold(top, 0.0, J).precession)))
        theta0 = 1e-4
        y0 = tj.initial_state(top, theta0, spin)
        xi = complex(float(y0.axis[0]), float(y0.axis[1]))
        w = complex(float(y0.omega[0]), float(y0.omega[1]))
        c = np.linalg.solve(V, np.array([xi, w]))
        expected = abs(c[slow] * V[0, slow])
        theta_s = float(project_launch(top, y0)[0])
        print(
            f"n0 = {spin}: launch at {theta0} projects to {theta_s:.4e} (SO(3) modes: "
            f"{expected:.4e})"
        )
        assert abs(theta_s - expected) < 0.02 * expected
        assert theta_s < 0.2 * theta0


# ------------------------------------------------------------------------------------------------
# Runs through simulate


@pytest.fixture(scope="module")
def top():
    return tj.default_top()


def test_run_fields_and_invariants(top):
    y0 = tj.initial_state(top, 0.1, 100.0)
    sol = tj.simulate(top, y0, 10.0, model="gyroscopic", saveat=grid(10.0))
    assert is_ok(sol) and sol.model == "gyroscopic"
    for name in ("theta", "theta_dot", "spin", "jellet", "energy"):
        assert np.all(np.isfinite(_np(getattr(sol, name)))), name
    # what the slow flow does not model is reported as not computed, not as numbers
    for name in ("psi", "normal_force", "slip_speed", "position", "velocity"):
        assert np.all(np.isnan(_np(getattr(sol, name)))), name
    J = _np(sol.jellet)
    assert np.max(np.abs(J / J[0] - 1)) < 1e-12  # exact, by construction
    assert abs(J[0] - float(tj.jellet(top, y0))) < 1e-12 * abs(J[0])
    E = _np(sol.energy)
    assert np.all(np.diff(E) <= 1e-12 * np.abs(E[1:]))  # friction only takes energy
    assert 5.0 < float(sol.t_invert) < 6.5


def test_error_shrinks_with_spin(top):
    """Launched on the slow manifold, the gyroscopic level and the SO(3) model differ only by
    the slow-manifold approximation, which shrinks with the spin."""
    errors, dt = [], []
    for spin in (50.0, 100.0, 200.0):
        y0 = on_manifold(top, 0.02, spin)
        # the slow flow alone: at n0 = 200 the level hands over to the full model during the rise
        g = run_level(GyroscopicLevel(hand_over=False), top, y0, 10.0, grid(10.0))
        o = tj.simulate(top, y0, 10.0, model="so3", saveat=grid(10.0), **REF)
        assert is_ok(o)
        before = _np(g["ts"]) < 0.9 * min(float(g["t_invert"]), float(o.t_invert))
        errors.append(np.max(np.abs(np.log(_np(g["theta"])) - np.log(_np(o.theta)))[before]))
        dt.append(abs(float(g["t_invert"]) - float(o.t_invert)))
    rates = np.diff(np.log(dt)) / np.log(2.0)
    print(
        "launched on the slow manifold at theta = 0.02, n0 = 50, 100, 200: |dt_invert| = "
        + ", ".join(f"{x:.2e}" for x in dt)
        + " s; max |d ln theta| before inversion = "
        + ", ".join(f"{x:.2e}" for x in errors)
        + f"; order in 1/n0: {rates.round(2)}"
    )
    assert dt[0] > dt[1] > dt[2] and errors[0] > errors[1] > errors[2]
    assert dt[2] < 0.01


def test_regular_at_the_poles(top):
    # exactly vertical: stays vertical
    sol = tj.simulate(
        top, tj.initial_state(top, 0.0, 100.0), 5.0, model="gyroscopic", saveat=grid(5.0)
    )
    assert is_ok(sol) and np.all(_np(sol.theta) == 0.0)
    # next to the poles: finite, and the stable inverted state keeps the top there
    for theta0, spin in ((1e-6, 100.0), (np.pi - 1e-6, 100.0), (np.pi, 100.0)):
        sol = tj.simulate(
            top, tj.initial_state(top, theta0, spin), 5.0, model="gyroscopic", saveat=grid(5.0)
        )
        assert is_ok(sol)
        for name in ("theta", "theta_dot", "spin", "jellet", "energy"):
            assert np.all(np.isfinite(_np(getattr(sol, name)))), (theta0, name)
        if theta0 > 1:
            assert np.all(_np(sol.theta) > np.pi - 1e-5)
    # the flow itself: odd in theta about each pole, zero there, finite derivative
    J = jellet_of(top, 100.0)
    for pole in (0.0, np.pi):
        f = lambda t: slow_manifold(top, t, J).theta_dot  # noqa: E731
        assert float(f(pole)) == pytest.approx(0.0, abs=1e-15)
        assert float(f(pole + 1e-3)) == pytest.approx(-float(f(pole - 1e-3)), rel=1e-9)
        assert np.isfinite(float(jax.grad(f)(pole)))


def test_launch_below_n1_does_not_invert(top):
    n1 = float(tj.thresholds(top).n1)
    sol = tj.simulate(
        top, tj.initial_state(top, 0.1, 0.5 * n1), 10.0, model="gyroscopic", saveat=grid(10.0)
    )
    assert is_ok(sol)
    assert np.isnan(float(sol.t_invert))
    theta = _np(sol.theta)
    assert np.all(np.diff(theta) <= 0) and theta[-1] < 0.2 * theta[0]


def test_iib_between_j1_and_j2_settles_on_the_intermediate_state(top):
    th = tj.thresholds(top)
    J = 0.5 * (float(th.J1) + float(th.J2))
    spin = J / jellet_of(top, 1.0, theta=0.1)
    y0 = tj.initial_state(top, 0.1, spin)
    target = tj.steady_states(top, J).intermediate
    assert len(target) == 1 and target[0][1]  # one, stable (IIb)
    sol = tj.simulate(top, y0, 30.0, model="gyroscopic", saveat=grid(30.0))
    assert is_ok(sol)
    print(
        f"IIb, J = (J1 + J2)/2: theta(30 s) = {float(sol.theta[-1]):.6f}, intermediate state "
        f"{target[0][0]:.6f}"
    )
    assert abs(float(sol.theta[-1]) - target[0][0]) < 1e-6
    assert np.isfinite(float(sol.t_invert)) == (target[0][0] > np.pi / 2)


def test_launch_without_gyroscopic_balance_hands_over_to_the_full_model(top):
    """Upside down with |n_pi| < n_* = 2 sqrt(A m g eps)/C: (G2) has no real root. The level
    does not describe it and the whole run is the full model's, reported as such."""
    A, C, m, g, eps = (float(getattr(top, k)) for k in ("A", "C", "m", "g", "eps"))
    n_star = 2 * np.sqrt(A * m * g * eps) / C
    y0 = tj.initial_state(top, np.pi - 0.2, 0.5 * n_star)
    assert float(slow_manifold(top, np.pi - 0.2, float(tj.jellet(top, y0))).discriminant) < 0
    assert not bool(LEVELS["gyroscopic"].in_chart(top, y0))
    sol = tj.simulate(top, y0, 1.0, model="gyroscopic", saveat=grid(1.0), throw=False)
    full = tj.simulate(top, y0, 1.0, model="full", saveat=grid(1.0), throw=False)
    assert sol.model == "gyroscopic->full" and float(sol.t_chart_switch) == 0.0
    assert np.allclose(_np(sol.theta), _np(full.theta), rtol=0, atol=1e-6)
    # the level alone (no hand-over) refuses it and says why
    alone = run_level(GyroscopicLevel(hand_over=False), top, y0, 1.0)
    assert bool(alone["result"] == tj.RESULTS.no_gyroscopic_balance)


def test_repelling_manifold_hands_over_before_contact_loss(top):
    """At n0 = 400 the slow manifold repels during the rise (sigma > 0): the run continues in the
    full model from there, and the full model finds the contact loss that the slow flow, whose
    R_n is m g, cannot."""
    J = jellet_of(top, 400.0, theta=0.1)
    assert max(float(nutation_damping(top, t, J)) for t in (0.8, 1.2, 1.6)) > 10
    sol = tj.simulate(
        top,
        tj.initial_state(top, 0.1, 400.0),
        10.0,
        model="gyroscopic",
        summary=True,
        throw=False,
        on_contact_loss="continue",
    )
    assert sol.model == "gyroscopic->full"
    switch = float(sol.t_chart_switch)
    assert 2.0 < switch < float(sol.t_contact_loss) < 10.0
    assert bool(sol.result == tj.RESULTS.contact_lost)
    # where it handed over, the nutation about the slow manifold had just stopped decaying
    alone = run_level(
        GyroscopicLevel(hand_over=False), top, tj.initial_state(top, 0.1, 400.0), 10.0
    )
    assert bool(alone["result"] == tj.RESULTS.no_gyroscopic_balance)
    assert float(alone["t_final"]) > switch


def test_fibre_projection_of_a_spun_launch(top):
    """omega = n a at theta0 = 0.1, n0 = 225: the launch's nutation, followed in the SO(3) model
    until it has decayed and the slow flow run back to t = 0, puts t_invert within 0.4% of the
    SO(3) model's (the linear projection: 1.6%)."""
    y0 = tj.initial_state(top, 0.1, 225.0)
    o = tj.simulate(top, y0, 10.0, model="so3", summary=True, **REF)
    fibre = run_level(GyroscopicLevel(hand_over=False, projection="fibre"), top, y0, 10.0)
    linear = run_level(GyroscopicLevel(hand_over=False, projection="linear"), top, y0, 10.0)
    ref = float(o.t_invert)
    e_fibre = abs(float(fibre["t_invert"]) - ref) / ref
    e_linear = abs(float(linear["t_invert"]) - ref) / ref
    print(
        f"n0 = 225: t_invert so3 {ref:.4f} s, fibre projection {e_fibre:.2%}, linear {e_linear:.2%}"
    )
    assert e_fibre < 0.004 < e_linear
    # the settle time is what the projection's decay rate says, and zero on the manifold
    assert 0.2 < float(settle_time(top, y0)) <= SETTLE_TIME_MAX
    assert float(settle_time(top, on_manifold(top, 0.3, 150.0))) == 0.0


@pytest.mark.slow
def test_stop_at_hand_over_and_the_carried_nutation(top):
    """`stop_at_hand_over` ends the slow flow where `hand_over=True` hands over to the full model,
    with `RESULTS.no_gyroscopic_balance`. With `contact_margin` it ends earlier, where the
    nutation the state carries (ln a changing at its own `nutation_rate`, not sigma) would lift
    that fraction of g off the normal force: eps sin(theta) a nu^2 = contact_margin g there."""
    from tippejax._engine.chain import run_chain

    y0 = tj.initial_state(top, 0.1, 400.0)
    chain = tj.simulate(
        top, y0, 10.0, model="gyroscopic", summary=True, throw=False, on_contact_loss="continue"
    )
    switch = float(chain.t_chart_switch)
    stopped = run_level(GyroscopicLevel(stop_at_hand_over=True), top, y0, 10.0)
    assert bool(stopped["result"] == tj.RESULTS.no_gyroscopic_balance)
    assert abs(float(stopped["t_final"]) - switch) < 1e-6

    level = GyroscopicLevel(stop_at_hand_over=True, contact_margin=0.5)
    start = LEVEL.from_state(top, y0)
    a0, rate = 0.03, -0.1
    carried = GyroscopicLevelState(
        log_tan_half_theta=start.log_tan_half_theta,
        phi=start.phi,
        psi=start.psi,
        nutation=jnp.log(a0),
        jellet=start.jellet,
        nutation_rate=jnp.asarray(rate),
    )
    out = jax.jit(
        lambda y: run_chain(
            level,
            top,
            y0,
            0.0,
            10.0,
            None,
            stop_on_contact=True,
            solver=diffrax.Dopri5(),
            rtol=1e-8,
            atol=1e-10,
            max_steps=10_000,
            adjoint=diffrax.RecursiveCheckpointAdjoint(),
            progress_meter=diffrax.NoProgressMeter(),
            pieces=1,
            y0=y,
        )
    )(carried)
    t_stop = float(out.t_final)
    assert bool(out.result == tj.RESULTS.no_gyroscopic_balance) and 1.0 < t_stop < switch
    theta = float(tj.euler_angles(out.state_end)[0])
    nu2 = float(nutation_frequency(top, theta, start.jellet)) ** 2
    lift = float(top.eps) * np.sin(theta) * a0 * np.exp(rate * t_stop) * nu2
    np.testing.assert_allclose(lift, 0.5 * float(top.g), rtol=1e-5)


def test_pole_linearisation_is_the_full_models(top):
    """The complex 3 x 3 form of the full model linearised at the vertical state
    (`pole_linearisation`) has the eigenvalues of the real Jacobian of the full level's vector
    field there. One of them is the slow manifold's mode (growing at the slow flow's rate at the
    pole, precessing at its Omega); of the other root's mode of the SO(3) model (decaying at
    sigma) the full model makes two, and one of them barely decays."""
    from tippejax._models.full import FullLevel, pole_linearisation
    from tippejax._state import State

    for north in (True, False):
        J = jellet_of(top, 200.0, theta=0.0 if north else np.pi)
        m = np.asarray(pole_linearisation(top, J, north=north))
        sign = 1.0 if north else -1.0
        omega_z = J / (float(top.C) * (float(top.R) - sign * float(top.eps)))
        level = FullLevel(body=False)

        def field(z, level=level, sign=sign, omega_z=omega_z):
            y = level.from_state(
                top,
                State(
                    position=z[:2],
                    velocity=z[2:4],
                    axis=z[4:7],
                    omega=z[7:10],
                    body=jnp.array([1.0, 0.0, 0.0]),
                ),
            )
            dy = level.vector_field(0.0, y, top)
            return jnp.concatenate([dy.position, dy.velocity, dy.axis, dy.omega])

        z = jnp.array([0, 0, 0, 0, 0, 0, sign, 0, 0, omega_z])
        real = np.linalg.eigvals(np.asarray(jax.jacfwd(field)(z)))
        values = np.linalg.eigvals(m)
        for lam in values:
            assert np.min(np.abs(real - lam)) < 1e-6 * abs(lam) + 1e-9, (lam, real)
        theta = 0.0 if north else np.pi
        sm = slow_manifold(top, theta, J)
        slow = values[np.argmax(np.abs(values.imag))]
        np.testing.assert_allclose(abs(slow.imag), abs(float(sm.precession)), rtol=0.01)
        np.testing.assert_allclose(slow.real, sign * float(sm.rate), rtol=0.02)
        others = np.sort(values[np.abs(values.imag) < 0.5 * abs(slow.imag)].real)
        sigma = float(nutation_damping(top, theta, J))
        assert others.size == 2 and others[0] < sigma < others[1] < 0
        assert others[1] > 0.1 * sigma  # the rolling mode decays ten times slower at least
