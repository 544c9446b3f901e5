"""The vector-form reference integrator (`vector_reference`) against the Euler-angle one.

`vector_reference` (Newton-Euler in the space frame, regular at the poles) and `euler_reference`
(Lagrange's equations in Euler angles) are derived independently, so agreement to ~1e-8 away from
the poles checks both. Then what only the vector form can do: an upright launch (theta0 = 0 with
a tilt rate), checked by handing its state, once tilted, to the Euler-angle integrator.
No tippejax is imported. One numba compilation per session (cached on disk).
"""

import math

import euler_reference as er
import numpy as np
import pytest
import vector_reference as vr

STANDARD = dict(
    m=0.02,
    R=0.025,
    eps=0.0075,
    A=0.9 * 0.4 * 0.02 * 0.025**2,
    C=0.4 * 0.02 * 0.025**2,
    g=9.81,
    mu=0.3,
)
# Group III (A/C - 1 > eps/R), heavier, less friction, smaller ball
GROUP_III = dict(
    m=0.045,
    R=0.015,
    eps=0.0015,
    A=1.3 * 0.4 * 0.045 * 0.015**2,
    C=0.4 * 0.045 * 0.015**2,
    g=9.81,
    mu=0.2,
)
POLE_MARGIN = 0.08  # compare only while theta stays this far from 0 and pi


def _euler_window(vec, t_max):
    """Last time before theta comes within POLE_MARGIN of a pole (the Euler chart's limit)."""
    theta = vec["theta"]
    near = np.nonzero(np.minimum(theta, math.pi - theta) < POLE_MARGIN)[0]
    return t_max if near.size == 0 else vec["t"][max(near[0] - 1, 0)]


LAUNCHES = [
    dict(theta0=1.2, spin=100.0, theta_dot=0.3, phi_dot=1.0, phi=0.3, vx=0.01, vy=-0.02),
    dict(theta0=0.6, spin=150.0, theta_dot=-0.5, phi_dot=-2.0, phi=-1.1, vx=-0.005, vy=0.0),
    dict(theta0=1.7, spin=60.0, theta_dot=0.0, phi_dot=0.0, phi=0.0, vx=0.0, vy=0.0),
]


@pytest.mark.parametrize("variant", ["full", "so3"])
@pytest.mark.parametrize("top", [STANDARD, GROUP_III], ids=["standard", "III"])
@pytest.mark.parametrize("launch", LAUNCHES, ids=["tilted", "negative-rates", "past-equator"])
def test_agrees_with_euler_reference(variant, top, launch):
    kw = dict(launch)
    theta0, spin = kw.pop("theta0"), kw.pop("spin")
    ts = np.linspace(0.0, 3.0, 601)
    vec = vr.solve(top, theta0, spin, ts, variant=variant, **kw)
    t1 = _euler_window(vec, 3.0)
    # these launches turn over fast: compare until the Euler chart's pole, >= 0.4 s (>= 6 nutations)
    assert t1 >= 0.4, "launch reaches a pole too soon to be compared"
    keep = ts <= t1
    eul = er.solve(top, theta0, spin, ts[keep], variant=variant, **kw)
    for name, tol in [
        ("theta", 1e-8),
        ("theta_dot", 1e-6),
        ("spin", 1e-7),
        ("normal_force", 1e-8),
        ("x", 1e-10),
        ("y", 1e-10),
        ("vx", 1e-9),
        ("vy", 1e-9),
        ("energy", 1e-11),
    ]:
        err = np.max(np.abs(vec[name][keep] - eul[name]))
        assert err < tol, (name, err)
    # the vector form of Jellet's J equals the Euler-angle formula
    np.testing.assert_allclose(vec["jellet"][keep], eul["jellet"], rtol=1e-8, atol=0)
    # and the precession angle (defined away from the poles)
    dphi = np.angle(np.exp(1j * (vec["phi"][keep] - eul["phi"])))
    assert np.max(np.abs(dphi)) < 1e-6


@pytest.mark.parametrize("variant", ["full", "so3"])
def test_invariants_over_an_inversion(variant):
    """J conserved, E non-increasing while R_n > 0, |a| = 1; the top turns over (t_invert)."""
    ts = np.linspace(0.0, 8.0, 1601)
    sol = vr.solve(STANDARD, 0.1, 150.0, ts, variant=variant, rtol=1e-11, atol=1e-12)
    assert np.isfinite(sol["t_invert"]) and 0 < sol["t_invert"] < 8
    assert sol["theta"][-1] > 2.5  # inverted
    i = np.searchsorted(ts, sol["t_invert"])
    assert sol["theta"][i - 1] < math.pi / 2 <= sol["theta"][i]
    assert np.all(sol["normal_force"] > 0) and not sol["contact_lost"]
    J = sol["jellet"]
    assert np.max(np.abs(J - J[0])) < 1e-9 * abs(J[0])
    dE = np.diff(sol["energy"])
    assert np.all(dE < 1e-12 * sol["energy"][0])
    assert sol["energy"][-1] < sol["energy"][0] * (1 - 1e-3)  # friction did dissipate
    np.testing.assert_allclose(np.linalg.norm(sol["state"][:, 4:7], axis=1), 1.0, atol=1e-10)


def _euler_launch_of(sol, i):
    """Euler-angle launch (theta, spin, theta_dot, phi_dot, phi, vx, vy) of the vector state i."""
    a, w = sol["axis"][i], sol["omega"][i]
    th = math.atan2(math.hypot(a[0], a[1]), a[2])
    ph = math.atan2(a[0], -a[1])
    e_n = np.array([math.cos(ph), math.sin(ph), 0.0])
    e_perp = np.array([-math.sin(ph), math.cos(ph), 0.0])  # a . e_perp = -sin th
    thd = float(w @ e_n)
    psd = -float(w @ e_perp) / math.sin(th)
    phd = w[2] - psd * math.cos(th)
    return dict(
        theta0=th,
        spin=float(w @ a),
        theta_dot=thd,
        phi_dot=phd,
        phi=ph,
        vx=sol["vx"][i],
        vy=sol["vy"][i],
    )


@pytest.mark.parametrize("variant", ["full", "so3"])
def test_upright_launch_is_regular(variant):
    """theta0 = 0 with a tilt rate: tips towards (sin phi, -cos phi, 0), agrees with the
    Euler-angle integrator restarted once tilted, and the pole case is the limit of tilted ones."""
    phi, thd0, spin = 0.4, 1.0, 120.0
    ts = np.linspace(0.0, 4.5, 901)  # theta passes 0.15 near t = 3 s
    sol = vr.solve(STANDARD, 0.0, spin, ts, theta_dot=thd0, phi=phi, variant=variant)
    # initial state: a = e_z, da/dt = thd0 (sin phi, -cos phi, 0), spin = w . a
    np.testing.assert_allclose(sol["axis"][0], [0, 0, 1], atol=0)
    adot0 = np.cross(sol["omega"][0], sol["axis"][0])
    np.testing.assert_allclose(
        adot0, thd0 * np.array([math.sin(phi), -math.cos(phi), 0]), atol=1e-15
    )
    assert sol["spin"][0] == pytest.approx(spin, rel=1e-15)
    assert sol["theta"][1] == pytest.approx(thd0 * ts[1], rel=0.05)
    J = sol["jellet"]
    assert np.max(np.abs(J - J[0])) < 1e-9 * abs(J[0])
    # a launch tilted by 1e-7 rad with the same rates is continuous with the upright one
    near = vr.solve(STANDARD, 1e-7, spin, ts, theta_dot=thd0, phi=phi, variant=variant)
    assert np.max(np.abs(near["theta"] - sol["theta"])) < 1e-5
    # restart the Euler-angle integrator from the vector state once theta > 0.15
    i = int(np.argmax(sol["theta"] > 0.15))
    assert i > 0
    launch = _euler_launch_of(sol, i)
    tail = ts[i:] - ts[i]
    eul = er.solve(
        STANDARD,
        launch.pop("theta0"),
        launch.pop("spin"),
        tail[tail <= 1.0],
        variant=variant,
        **launch,
    )
    m = len(eul["t"])
    assert m > 50
    assert np.max(np.abs(eul["theta"] - sol["theta"][i : i + m])) < 1e-8
    assert np.max(np.abs(eul["normal_force"] - sol["normal_force"][i : i + m])) < 1e-8


def test_scipy_backend_matches_port():
    """The DOP853 port agrees with scipy's own DOP853 on the same right-hand side."""
    ts = np.linspace(0.0, 1.0, 101)
    a = vr.solve(STANDARD, 0.0, 100.0, ts, theta_dot=0.7, backend="scipy", rtol=1e-11)
    b = vr.solve(STANDARD, 0.0, 100.0, ts, theta_dot=0.7, rtol=1e-11)
    assert np.max(np.abs(a["state"] - b["state"])) < 1e-8


def test_bad_input():
    with pytest.raises(ValueError, match="variant"):
        vr.solve(STANDARD, 0.1, 100.0, [0.0, 1.0], variant="routhian")
    with pytest.raises(ValueError, match="t_eval"):
        vr.solve(STANDARD, 0.1, 100.0, [1.0, 0.5])
    with pytest.raises(ValueError, match="params"):
        vr.solve({**STANDARD, "eps": 0.03}, 0.1, 100.0, [0.0, 1.0])


# --------------------------------------------------------------------------------------------
# tests/fit_records.py: the records made from this integrator
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def fit_records():
    import fit_records

    return fit_records


@pytest.mark.slow  # draws records with their Cramer-Rao bounds: minutes without numba (CI)
def test_fit_records_drawn_as_documented(fit_records, tmp_path, monkeypatch):
    """Four records (one per group): ranges, noise, reproducible data, converged bound, cache."""
    monkeypatch.setattr(fit_records, "CACHE_ROOT", tmp_path)
    recs = fit_records.draw_records(4, 7)
    assert [r["group"] for r in recs] == ["IIa", "IIb", "IIc", "III"]
    for r in recs:
        p, launch = r["params"], r["launch"]
        assert fit_records._classify_numpy(p["A"] / p["C"], p["eps"] / p["R"]) == r["group"]
        assert 0.005 <= p["m"] <= 0.06 and 0.01 <= p["R"] <= 0.03 and 0.05 <= p["mu"] <= 2
        assert 1.5 <= r["spin_over_n1"] <= 8 and 20 <= r["rate_hz"] <= 500
        assert 0.002 <= r["sigma"] <= 0.03 and 3 <= r["length_s"] <= 20
        if r["upright"]:
            assert launch["theta0"] == 0 and 0.2 <= launch["theta_dot"] <= 2
            assert r["free"] == ("mu", "eps", "spin", "theta_dot")
        else:
            assert 0.02 <= launch["theta0"] <= 0.5 and launch["theta_dot"] == 0
            assert r["free"] == ("mu", "eps", "spin")
        # the clean data are the integrator's, the noise has the stated size
        sol = vr.solve(p, launch["theta0"], launch["spin"], r["ts"], theta_dot=launch["theta_dot"])
        assert np.max(np.abs(sol["theta"] - r["theta_clean"])) < 1e-7
        assert np.all(sol["normal_force"] > 0)
        resid = (r["theta_obs"] - r["theta_clean"])[np.isfinite(r["theta_obs"])]
        assert abs(resid.std() / r["sigma"] - 1) < 5 / np.sqrt(2 * resid.size)
        gap = np.isnan(r["theta_obs"])
        assert (r["gap"] is None) == (not gap.any())
        # the bound: below the cut, and unchanged (0.1%) with 10x smaller difference steps
        assert max(r["crb_rel"][k] for k in ("mu", "eps", "spin")) <= fit_records.MAX_CRB_REL
        _, jac = fit_records.sensitivities(p, launch, r["free"], r["ts"], step_scale=0.1)
        crb = fit_records.cramer_rao(jac, r["sigma"], ~gap)
        np.testing.assert_allclose(crb, [r["crb"][k] for k in r["free"]], rtol=1e-3)
    # cached records come back identical; redrawn, the first records of a seed do not depend on n
    cached = fit_records.draw_records(4, 7)
    again = fit_records.draw_records(2, 7, cache=False)
    assert all(r.get("from_cache") for r in cached)
    for a, b, c in zip(again, cached, recs):
        assert a["params"] == b["params"] == c["params"] and a["crb"] == b["crb"] == c["crb"]
        np.testing.assert_array_equal(a["theta_obs"], c["theta_obs"])
        np.testing.assert_array_equal(b["theta_obs"], c["theta_obs"])
