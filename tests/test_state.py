"""Vector state <-> ZXZ Euler angles, and initial_state."""

import re
import warnings

import equinox as eqx
import internal as ti
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tippejax as tj

N_SAMPLES = 50


def _wrap(x):
    """Angle difference mapped to (-pi, pi]."""
    return np.angle(np.exp(1j * np.asarray(x)))


def _rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _d_rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[-s, -c, 0.0], [c, -s, 0.0], [0.0, 0.0, 0.0]])


def _d_rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[0.0, 0.0, 0.0], [0.0, -s, -c], [0.0, c, -s]])


def _reference_state(theta, phi, psi, thd, phid, psid):
    """Axis, body vector and angular velocity from the ZXZ rotation matrix Rz(phi) Rx(theta) Rz(psi).

    Independent of the package: omega is read off the skew matrix dR/dt R^T.
    """
    rot = _rot_z(phi) @ _rot_x(theta) @ _rot_z(psi)
    rot_dot = (
        _d_rot_z(phi) @ _rot_x(theta) @ _rot_z(psi) * phid
        + _rot_z(phi) @ _d_rot_x(theta) @ _rot_z(psi) * thd
        + _rot_z(phi) @ _rot_x(theta) @ _d_rot_z(psi) * psid
    )
    skew = rot_dot @ rot.T
    omega = np.array([skew[2, 1], skew[0, 2], skew[1, 0]])
    return rot[:, 2], rot[:, 0], omega


@pytest.fixture(scope="module")
def samples():
    rng = np.random.default_rng(1234)
    theta = rng.uniform(0.05, np.pi - 0.05, N_SAMPLES)
    phi = rng.uniform(-np.pi + 1e-3, np.pi - 1e-3, N_SAMPLES)
    psi = rng.uniform(-np.pi + 1e-3, np.pi - 1e-3, N_SAMPLES)
    rates = rng.normal(scale=[5.0, 20.0, 60.0], size=(N_SAMPLES, 3))
    return theta, phi, psi, rates[:, 0], rates[:, 1], rates[:, 2]


def test_state_from_euler_matches_rotation_matrix(samples):
    y = tj.state_from_euler(*samples)
    for i in range(N_SAMPLES):
        axis, body, omega = _reference_state(*(s[i] for s in samples))
        np.testing.assert_allclose(np.asarray(y.axis[i]), axis, rtol=0, atol=1e-14)
        np.testing.assert_allclose(np.asarray(y.body[i]), body, rtol=0, atol=1e-14)
        scale = np.linalg.norm(omega)
        np.testing.assert_allclose(np.asarray(y.omega[i]), omega, rtol=0, atol=1e-13 * scale)


def test_unit_axis_and_perpendicular_body(samples):
    y = tj.state_from_euler(*samples)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(y.axis), axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(y.body), axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(np.sum(np.asarray(y.axis * y.body), -1), 0.0, atol=1e-15)
    np.testing.assert_array_equal(np.asarray(y.position), 0.0)
    np.testing.assert_array_equal(np.asarray(y.velocity), 0.0)


def test_angles_round_trip(samples):
    theta, phi, psi = samples[:3]
    y = tj.state_from_euler(*samples)
    theta2, phi2, psi2 = tj.euler_angles(y)
    np.testing.assert_allclose(np.asarray(theta2), theta, rtol=0, atol=1e-12)
    np.testing.assert_allclose(_wrap(np.asarray(phi2) - phi), 0.0, atol=1e-12)
    np.testing.assert_allclose(_wrap(np.asarray(psi2) - psi), 0.0, atol=1e-12)
    # Angles outside (-pi, pi] come back wrapped.
    y = tj.state_from_euler(theta, phi + 4 * np.pi, psi - 2 * np.pi, *samples[3:])
    _, phi3, psi3 = tj.euler_angles(y)
    np.testing.assert_allclose(_wrap(np.asarray(phi3) - phi), 0.0, atol=1e-11)
    np.testing.assert_allclose(_wrap(np.asarray(psi3) - psi), 0.0, atol=1e-11)
    assert np.all(np.abs(np.asarray(phi3)) <= np.pi)


def test_rates_round_trip(samples):
    theta, _, _, thd, phid, psid = samples
    y = tj.state_from_euler(*samples)
    thd2, phid2, psid2 = tj.euler_rates(y)
    scale = np.abs(thd) + np.abs(phid) + np.abs(psid)
    # phid is omega.M / sin(theta): its round-off grows like 1/sin(theta).
    tol = 1e-13 * scale / np.sin(theta)
    assert np.all(np.abs(np.asarray(thd2) - thd) <= tol)
    assert np.all(np.abs(np.asarray(phid2) - phid) <= tol)
    assert np.all(np.abs(np.asarray(psid2) - psid) <= tol)
    n = psid + phid * np.cos(theta)
    np.testing.assert_allclose(np.asarray(ti.spin(y)), n, rtol=0, atol=1e-13 * scale.max())


def test_vector_to_euler_to_vector(samples):
    """Starting from the vector form: a random rotation and angular velocity."""
    rng = np.random.default_rng(7)
    y = tj.state_from_euler(*samples)
    omega = rng.normal(scale=30.0, size=(N_SAMPLES, 3))
    y = eqx.tree_at(lambda s: s.omega, y, jnp.asarray(omega))
    angles = tj.euler_angles(y)
    rates = tj.euler_rates(y)
    y2 = tj.state_from_euler(*angles, *rates)
    np.testing.assert_allclose(np.asarray(y2.axis), np.asarray(y.axis), atol=1e-14)
    np.testing.assert_allclose(np.asarray(y2.body), np.asarray(y.body), atol=1e-14)
    np.testing.assert_allclose(np.asarray(y2.omega), omega, rtol=0, atol=1e-12 * 30)


def test_initial_state():
    top = tj.default_top()
    y = tj.initial_state(
        top, 0.4, 75.0, theta_dot=1.5, phi_dot=-3.0, phi=0.7, psi=-1.1, vx=0.2, vy=-0.05
    )
    np.testing.assert_allclose(float(ti.spin(y)), 75.0, rtol=1e-15)
    np.testing.assert_allclose(float(jnp.dot(y.omega, y.axis)), 75.0, rtol=1e-15)
    np.testing.assert_array_equal(np.asarray(y.position), [0.0, 0.0])
    np.testing.assert_array_equal(np.asarray(y.velocity), [0.2, -0.05])
    theta, phi, psi = tj.euler_angles(y)
    np.testing.assert_allclose([float(theta), float(phi), float(psi)], [0.4, 0.7, -1.1], atol=1e-14)
    thd, phid, psid = tj.euler_rates(y)
    np.testing.assert_allclose(
        [float(thd), float(phid), float(psid)], [1.5, -3.0, 75.0 + 3.0 * np.cos(0.4)], rtol=1e-13
    )
    # Independent: omega from the rotation matrix.
    axis, body, omega = _reference_state(0.4, 0.7, -1.1, 1.5, -3.0, 75.0 + 3.0 * np.cos(0.4))
    np.testing.assert_allclose(np.asarray(y.axis), axis, atol=1e-15)
    np.testing.assert_allclose(np.asarray(y.omega), omega, atol=1e-12)


def test_initial_state_defaults_and_poles():
    top = tj.default_top()
    y = tj.initial_state(top, 0.0, 50.0)
    np.testing.assert_allclose(np.asarray(y.axis), [0.0, 0.0, 1.0], atol=0)
    np.testing.assert_allclose(np.asarray(y.omega), [0.0, 0.0, 50.0], atol=1e-14)
    np.testing.assert_array_equal(np.asarray(y.velocity), [0.0, 0.0])
    y = tj.initial_state(top, np.pi, 50.0)
    np.testing.assert_allclose(np.asarray(y.axis), [0.0, 0.0, -1.0], atol=1e-15)
    np.testing.assert_allclose(float(ti.spin(y)), 50.0, rtol=1e-15)


def test_initial_state_broadcasts():
    top = tj.default_top()
    theta = jnp.array([0.1, 0.5, 2.0])
    y = tj.initial_state(top, theta, 30.0, vx=jnp.array([0.0, 0.1, 0.2]))
    assert y.axis.shape == (3, 3) and y.velocity.shape == (3, 2)
    np.testing.assert_allclose(np.asarray(ti.spin(y)), 30.0, rtol=1e-15)
    np.testing.assert_allclose(np.asarray(y.velocity[:, 0]), [0.0, 0.1, 0.2], rtol=0)
    np.testing.assert_allclose(np.asarray(tj.euler_angles(y)[0]), np.asarray(theta), atol=1e-14)


_initial_state_jit = eqx.filter_jit(tj.initial_state)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(theta=0.1, spin=float("nan")), "spin must be finite"),
        (dict(theta=0.1, spin=float("inf")), "spin must be finite"),
        (dict(theta=float("nan"), spin=10.0), "theta must be finite"),
        (dict(theta=-0.1, spin=10.0), "theta must lie in [0, pi]"),
        (dict(theta=3.2, spin=10.0), "theta must lie in [0, pi]"),
    ],
)
def test_initial_state_rejects(kwargs, message):
    top = tj.default_top()
    with pytest.raises(Exception, match=re.escape(message)):
        jax.block_until_ready(tj.initial_state(top, **kwargs))
    with pytest.raises(Exception, match=re.escape(message)):
        jax.block_until_ready(
            _initial_state_jit(top, jnp.asarray(kwargs["theta"]), jnp.asarray(kwargs["spin"]))
        )


# Poles: rates from the state's own motion, never from the sign of a zero.


def _pole_state(axis_z, zero_x, zero_y, omega):
    return tj.State(
        position=jnp.zeros(2),
        velocity=jnp.zeros(2),
        axis=jnp.array([zero_x, zero_y, axis_z]),
        omega=jnp.asarray(omega, float),
        body=jnp.array([1.0, 0.0, 0.0]),
    )


@pytest.mark.parametrize("axis_z", [1.0, -1.0])
@pytest.mark.parametrize("zero_x, zero_y", [(0.0, 0.0), (-0.0, 0.0), (0.0, -0.0), (-0.0, -0.0)])
@pytest.mark.parametrize(
    "omega", [[1.0, 0.0, 50.0], [-0.0, 2.0, -3.0], [0.3, -0.4, 7.0], [0.0, -0.0, 3.0]]
)
def test_euler_rates_at_the_poles(axis_z, zero_x, zero_y, omega):
    y = _pole_state(axis_z, zero_x, zero_y, omega)
    theta, phi, psi = (np.asarray(v) for v in tj.euler_angles(y))
    thd, phid, psid = (np.asarray(v) for v in tj.euler_rates(y))
    assert np.all(np.isfinite([theta, phi, psi, thd, phid, psid]))
    np.testing.assert_allclose(theta, 0.0 if axis_z > 0 else np.pi, atol=0)
    # |theta_dot| is the speed of the axis, |omega x a|; theta can only grow from 0, fall from pi.
    speed = np.hypot(omega[0], omega[1])
    np.testing.assert_allclose(thd, speed if axis_z > 0 else -speed, rtol=1e-15, atol=0)
    np.testing.assert_allclose(
        psid - phid * np.cos(theta), np.dot(omega, [0, 0, axis_z]), rtol=1e-15
    )
    # The angles and rates rebuild the state (independent check: the rotation matrix).
    axis, body, omega_ref = _reference_state(theta, phi, psi, thd, phid, psid)
    np.testing.assert_allclose(axis, [0.0, 0.0, axis_z], atol=1e-15)
    np.testing.assert_allclose(body, [1.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(omega_ref, omega, atol=1e-14)
    # The same answer whatever the signs of the zeros.
    ref = [
        np.asarray(v)
        for v in (
            *tj.euler_angles(_pole_state(axis_z, 0.0, 0.0, omega)),
            *tj.euler_rates(_pole_state(axis_z, 0.0, 0.0, omega)),
        )
    ]
    np.testing.assert_array_equal(_wrap(np.array([theta, phi, psi, thd, phid, psid]) - ref), 0.0)


@pytest.mark.parametrize("axis_z", [1.0, -1.0])
def test_pole_angles_are_the_limit_along_the_motion(axis_z):
    """phi and theta_dot at the pole equal their values a moment later (axis moved by omega x a)."""
    omega = np.array([0.7, -1.9, 40.0])
    y = _pole_state(axis_z, 0.0, 0.0, omega)
    _, phi0, _ = tj.euler_angles(y)
    thd0, _, _ = tj.euler_rates(y)
    for dt in (1e-4, 1e-6):
        a = np.array([0.0, 0.0, axis_z])
        a = a + dt * np.cross(omega, a)
        a = a / np.linalg.norm(a)
        body = np.cross(a, [0.0, 1.0, 0.0])
        body /= np.linalg.norm(body)
        y_later = eqx.tree_at(lambda s: (s.axis, s.body), y, (jnp.asarray(a), jnp.asarray(body)))
        _, phi1, _ = tj.euler_angles(y_later)
        thd1, _, _ = tj.euler_rates(y_later)
        np.testing.assert_allclose(_wrap(float(phi1) - float(phi0)), 0.0, atol=1e-12)
        np.testing.assert_allclose(float(thd1), float(thd0), rtol=1e-6)


def test_initial_state_at_pole_round_trips_theta_dot():
    top = tj.default_top()
    for theta, thd in ((0.0, 1.0), (np.pi, -1.0)):
        y = tj.initial_state(top, theta, 100.0, theta_dot=thd)
        got = [float(v) for v in tj.euler_rates(y)]
        np.testing.assert_allclose(got, [thd, 0.0, 100.0], rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("theta", [5.7, 90.0, [0.1, 30.0]])
def test_initial_state_in_degrees_is_a_value_error(theta):
    """Concrete values are checked in Python: a ValueError naming radians, not a jit error."""
    with pytest.raises(ValueError, match=r"theta must lie in \[0, pi\].*radians.*np\.deg2rad"):
        tj.initial_state(tj.default_top(), theta, 100.0)


def test_implausible_spin_warns_with_the_rpm_hint_and_still_runs():
    top = tj.default_top()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tj.initial_state(top, 0.1, 600.0)  # fast, but a real top's spin: no warning
        tj.initial_state(top, 0.1, -600.0)
    with pytest.warns(UserWarning, match=r"rpm, pass 3000 \* 2 \* pi / 60 = 314\.159 rad/s"):
        y0 = tj.initial_state(top, 0.1, 3000.0)
    assert float(tj.euler_rates(y0)[2]) == pytest.approx(3000.0)  # warned, not refused
    with pytest.warns(UserWarning, match="spin of 3000"):
        tj.initial_state(top, [0.1, 0.2], [100.0, 3000.0])


@pytest.mark.parametrize(
    "fields, match",
    [
        (dict(m=20.0), "mean density"),  # kilograms for a 25 mm ball
        (dict(R=25.0, eps=7.5), "mean density"),  # millimetres as metres
        (dict(g=981.0), "g = 981"),
        (dict(C=5e-2, A=4.5e-2), "exceeds m R"),
    ],
)
def test_implausible_tops_warn(fields, match):
    from tippejax._plausibility import warn_if_implausible_top

    values = dict(m=0.02, R=0.025, eps=0.0075, A=4.5e-6, C=5e-6, g=9.81) | fields
    with pytest.warns(UserWarning, match=match):
        warn_if_implausible_top(**values)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_if_implausible_top(m=0.02, R=0.025, eps=0.0075, A=4.5e-6, C=5e-6, g=9.81)
        warn_if_implausible_top(m=0.006, R=0.015, eps=0.003, A=8e-7, C=7e-7, g=9.81)  # LG 2003
