"""Checks of `real_top_reference`, the independent model of a real top (friction laws, stem).

Against the paper's idealised top (`vector_reference`, `euler_reference`), the limits of the
friction laws, and the invariants: energy never increases, and Jellett's J obeys
dJ/dt = M (R - eps cos theta) until the stem touches. No tippejax is imported.
"""

import math

import euler_reference as er
import numpy as np
import pytest
import real_top_reference as rr
import vector_reference as vr

LG = rr.LEINE_GLOCKER
RHO = 5e-4  # Leine & Glocker's contact radius, m


# --------------------------------------------------------------------------------------------
# Friction laws
# --------------------------------------------------------------------------------------------


def _slip(u, w, rho=RHO, angle=0.9):
    return u * rho * abs(w) * np.array([math.cos(angle), math.sin(angle)])


def test_hertz_limits_and_inner_branch():
    """Pure slip |F| = 1, pure spin |M| = 3 pi rho/16, small slip F = -(3 pi/8) v/(rho |w|); for
    u = |v|/(rho |w|) <= 1 the quadrature gives |F| = (3 pi/8)(u - u^3/4) and
    |M| = (3 pi/16) rho (1 - u^2 + 3 u^4/8) (per unit mu R_n)."""
    F, M = rr.hertz_contensou([0.02, -0.01], 0.0, RHO, 1e-9)
    assert np.linalg.norm(F) == pytest.approx(1.0, abs=1e-12) and M == pytest.approx(0, abs=1e-18)
    np.testing.assert_allclose(F, -np.array([0.02, -0.01]) / math.hypot(0.02, 0.01), atol=1e-12)
    for w in (180.0, -40.0):
        F, M = rr.hertz_contensou([0.0, 0.0], w, RHO, 1e-12)
        assert np.abs(F).max() < 1e-14
        assert M == pytest.approx(-math.copysign(3 * math.pi / 16 * RHO, w), rel=1e-9)
        for u in (1e-3, 0.1, 0.5, 0.9, 0.99):
            v = _slip(u, w)
            F, M = rr.hertz_contensou(v, w, RHO, 1e-9, n_ray=200, n_angle=800)
            np.testing.assert_allclose(
                F, -v / np.linalg.norm(v) * 3 * math.pi / 8 * (u - u**3 / 4), rtol=0, atol=1e-9
            )
            assert M == pytest.approx(
                -math.copysign(3 * math.pi / 16 * RHO, w) * (1 - u**2 + 3 * u**4 / 8), rel=1e-8
            )
    # small slip: the viscous-like limit (LG eq. 17)
    v = _slip(1e-4, 180.0)
    F, _ = rr.hertz_contensou(v, 180.0, RHO, 1e-9)
    np.testing.assert_allclose(F, -3 * math.pi / 8 * v / (RHO * 180.0), rtol=1e-7)
    # large slip: |F| -> 1, M -> 0
    F, M = rr.hertz_contensou(_slip(1e3, 180.0), 180.0, RHO, 1e-9)
    assert 1 - 1e-6 < np.linalg.norm(F) <= 1 and abs(M) < 1e-3 * RHO


def test_hertz_two_quadrature_routes_agree():
    """Rays from the slip pole (default) and from the centre (converging slowly) agree."""
    for u in (0.01, 0.3, 0.7, 0.9, 1.5, 4.0):
        v = _slip(u, 150.0, angle=-2.0)
        F, M = rr.hertz_contensou(v, 150.0, RHO, 1e-8)
        F2, M2 = rr.hertz_contensou(v, 150.0, RHO, 1e-8, n_ray=400, n_angle=1600, pole_rays=False)
        assert np.abs(F - F2).max() < 3e-6 and abs(M - M2) < 3e-6 * RHO
        F3, M3 = rr.hertz_contensou(v, 150.0, RHO, 1e-8, n_ray=200, n_angle=800)
        assert np.abs(F - F3).max() < 1e-9 and abs(M - M3) < 1e-9 * RHO


@pytest.mark.parametrize("law", list(rr.LAWS))
def test_laws_dissipate_and_are_isotropic(law):
    """F . v + M w_n <= 0; rotating the slip rotates the force; w_n -> -w_n mirrors."""
    rng = np.random.default_rng(3)
    for _ in range(40):
        v = rng.normal(size=2) * 10.0 ** rng.uniform(-6, -1)
        w = rng.normal() * 100
        F, M = rr.friction(law, v, w, mu=0.3, rho=RHO, delta=1e-6)
        assert F @ v + M * w <= 0
        tol = 1e-6 if law == "hertz" else 1e-12  # the fixed quadrature's error near |v| = rho w_n
        c, s = math.cos(1.1), math.sin(1.1)
        rot = np.array([[c, -s], [s, c]])
        F2, M2 = rr.friction(law, rot @ v, w, mu=0.3, rho=RHO, delta=1e-6)
        np.testing.assert_allclose(F2, rot @ F, rtol=0, atol=tol * np.linalg.norm(F))
        assert M2 == pytest.approx(M, rel=tol, abs=1e-18)
        F3, M3 = rr.friction(law, v * [1, -1], -w, mu=0.3, rho=RHO, delta=1e-6)
        np.testing.assert_allclose(F3, F * [1, -1], rtol=0, atol=tol * np.linalg.norm(F))
        assert M3 == pytest.approx(-M, rel=tol, abs=1e-18)


def test_ellipse_matches_hertz_at_the_limits():
    """Moeller's ellipse is exact for pure slip and pure spin (Rb = 3 pi rho/16) only."""
    for v, w in (([0.03, 0.0], 0.0), ([0.0, 0.0], 180.0)):
        F, M = rr.friction("ellipse", v, w, rho=RHO, delta=1e-9)
        Fh, Mh = rr.friction("hertz", v, w, rho=RHO, delta=1e-9)
        np.testing.assert_allclose(F, Fh, atol=1e-9)
        assert M == pytest.approx(Mh, rel=1e-8, abs=1e-15)
    # small slip: ellipse 16/(3 pi) against Hertz 3 pi/8, a 44% stiffer slip damping
    v = _slip(1e-3, 180.0)
    ratio = np.linalg.norm(rr.friction("ellipse", v, 180.0, rho=RHO)[0]) / np.linalg.norm(
        rr.friction("hertz", v, 180.0, rho=RHO)[0]
    )
    assert ratio == pytest.approx(128 / (9 * math.pi**2), rel=1e-4)


# --------------------------------------------------------------------------------------------
# The paper's top (viscous, no stem) against the two references
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def viscous_rigid():
    return rr.solve(
        rr.STANDARD, "viscous", 0.1, 100.0, 6.0, mu=0.3, stem=False, contact="rigid", rtol=1e-10
    )


def test_viscous_matches_vector_reference(viscous_rigid):
    """Standard top, theta0 = 0.1, 100 rad/s: theta(t) and the pi/2 crossing (5.70 s)."""
    ref = vr.solve(dict(rr.STANDARD, mu=0.3), 0.1, 100.0, viscous_rigid["t"])
    assert viscous_rigid["t_half"] == pytest.approx(ref["t_invert"], abs=1e-6)
    assert viscous_rigid["t_half"] == pytest.approx(5.70, abs=0.005)
    assert np.max(np.abs(viscous_rigid["theta"] - ref["theta"])) < 1e-6
    assert np.max(np.abs(viscous_rigid["normal_ball"] - ref["normal_force"])) < 1e-8
    np.testing.assert_allclose(viscous_rigid["jellett"], ref["jellet"], rtol=1e-8)
    np.testing.assert_allclose(viscous_rigid["energy"], ref["energy"], rtol=1e-8)


def test_viscous_matches_euler_reference():
    """A launch past the equator, while the Euler chart stays 0.08 rad from the poles."""
    r = rr.solve(
        rr.STANDARD, "viscous", 1.7, 60.0, 1.0, mu=0.3, stem=False, contact="rigid", rtol=1e-10
    )
    near = np.nonzero(np.minimum(r["theta"], math.pi - r["theta"]) < 0.08)[0]
    keep = r["t"] < (r["t"][near[0]] if near.size else 2.0)
    assert keep.sum() > 400
    ref = er.solve(dict(rr.STANDARD, mu=0.3), 1.7, 60.0, r["t"][keep])
    assert np.max(np.abs(r["theta"][keep] - ref["theta"])) < 1e-7
    assert np.max(np.abs(r["normal_ball"][keep] - ref["normal_force"])) < 1e-8


def test_viscous_invariants(viscous_rigid):
    """J conserved, dE/dt = friction power (rigid contact), E decreasing."""
    J, E = viscous_rigid["jellett"], viscous_rigid["energy"]
    assert np.max(np.abs(J - J[0])) < 1e-9 * abs(J[0])
    assert np.all(np.diff(E) < 1e-12 * E[0])
    np.testing.assert_allclose(
        E - E[0], viscous_rigid["friction_work"], rtol=0, atol=1e-8 * (E[0] - E[-1])
    )


def test_compliant_contact_matches_rigid():
    """Hunt-Crossley ball (E* = 5 GPa) against the rigid contact: the same motion to 1e-5 rad."""
    rigid = rr.solve(rr.STANDARD, "viscous", 0.1, 100.0, 1.5, mu=0.3, stem=False, contact="rigid")
    soft = rr.solve(
        rr.STANDARD, "viscous", 0.1, 100.0, 1.5, mu=0.3, stem=False, contact="compliant"
    )
    assert soft["compliant"].all() and not rigid["compliant"].any()
    assert np.max(np.abs(soft["theta"] - rigid["theta"])) < 1e-5
    assert np.all(soft["depth_ball"] > 0)  # stays in contact
    np.testing.assert_allclose(soft["normal_ball"], rigid["normal_ball"], rtol=0.02)
    E = soft["energy"]
    assert np.all(np.diff(E) < 1e-12 * E[0])


# --------------------------------------------------------------------------------------------
# Leine & Glocker's top: Contensou friction, the stem
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def lg_ellipse():
    return rr.solve(LG, "ellipse", 0.1, 180.0, 2.0, mu=0.3, rho=RHO, delta=1e-6)


def test_energy_never_increases(lg_ellipse):
    E = lg_ellipse["energy"]
    assert np.all(np.diff(E) <= 1e-12 * E[0])
    rigid = ~lg_ellipse["compliant"]
    np.testing.assert_allclose(
        (E - E[0])[rigid], lg_ellipse["friction_work"][rigid], rtol=0, atol=1e-7 * (E[0] - E[-1])
    )


def test_jellett_balance_under_drilling_torque(lg_ellipse):
    """J(t) - J(0) = int M (R - eps cos theta) dt until the stem touches; J falls by >1%."""
    r = lg_ellipse
    before = r["t"] < r["t_stem"]
    J = r["jellett"]
    np.testing.assert_allclose(
        (J - J[0])[before], r["jellett_source"][before], rtol=0, atol=1e-7 * abs(J[0])
    )
    assert J[before][-1] < 0.99 * J[0]


def test_stem_touch(lg_ellipse):
    """The stem touches at cos theta_s = (r2 - R)/(a2 - eps), then the ball lifts off."""
    r = lg_ellipse
    assert 2.448 < rr.stem_touch_angle(LG) < 2.449
    assert r["theta_stem"] == pytest.approx(rr.stem_touch_angle(LG), abs=1e-3)
    assert 0.5 < r["t_half"] < r["t_stem"] < 2.0
    names = [name for _, name, _ in r["events"]]
    assert names.index("switch") < names.index("stem_touch") < names.index("ball_liftoff")
    assert r["theta"][-1] > r["theta_stem"] + 0.2  # rises on the stem


@pytest.mark.parametrize("law", ["viscous", "coulomb"])
def test_force_only_laws_conserve_jellett(law):
    mu = 0.3 if law == "coulomb" else 3.0
    r = rr.solve(LG, law, 0.1, 180.0, 0.4, mu=mu, delta=1e-2, stem=False, contact="rigid")
    J = r["jellett"]
    assert np.max(np.abs(J - J[0])) < 1e-8 * abs(J[0])
    assert np.all(np.diff(r["energy"]) <= 1e-12 * r["energy"][0])


def test_hertz_law_jellett_balance():
    r = rr.solve(
        LG, "hertz", 0.1, 180.0, 0.3, mu=0.3, rho=RHO, delta=1e-6, stem=False, contact="rigid"
    )
    J = r["jellett"]
    np.testing.assert_allclose(J - J[0], r["jellett_source"], rtol=0, atol=1e-7 * abs(J[0]))
    assert J[-1] < J[0] * (1 - 1e-3)


def test_contensou_converges_in_slip_scale():
    t = [
        rr.solve(
            LG, "ellipse", 0.1, 180.0, 1.2, mu=0.3, rho=RHO, delta=d, stem=False, contact="rigid"
        )["t_half"]
        for d in (1e-5, 1e-6)
    ]
    assert 0.5 < t[0] < 1.2 and abs(t[0] - t[1]) < 1e-6


def test_pure_coulomb_inversion_time_grows_as_slip_scale_shrinks():
    """Without Contensou friction the rise is creep below delta: t_half grows like 1/delta."""
    t = [
        rr.solve(LG, "coulomb", 0.1, 180.0, 3.0, mu=0.3, delta=d, stem=False, contact="rigid")[
            "t_half"
        ]
        for d in (1e-2, 3e-3)
    ]
    assert 0.5 < t[0] < t[1] - 0.2


def test_bad_input():
    with pytest.raises(ValueError, match="law"):
        rr.make_params(LG, "stribeck", mu=0.3)
    with pytest.raises(ValueError, match="stem"):
        rr.make_params(dict(LG, a2=0.002), "ellipse", mu=0.3)
    with pytest.raises(ValueError, match="contact"):
        rr.solve(LG, "ellipse", 0.1, 180.0, 0.1, mu=0.3, contact="soft")
