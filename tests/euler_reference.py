r"""Independent reference integrator for the tippe top: the paper's Euler-angle equations, plain numpy.

Written from the paper (Ciocci & Langerock, Sec. 2), not from tippejax: a test oracle and the
speed baseline "scipy.integrate.solve_ivp on the textbook equations". Conventions as in the paper
and ERRATA.md: ZXZ Euler angles (phi, theta, psi), axis a = (s sin ph, -s cos ph, c),
s = sin th, c = cos th, spin n = psid + phid c, height h = R - eps c, h' = eps s, h'' = eps c.

Coordinates q = (x, y, th, ph, ps); state z = (x, y, th, ph, ps, xd, yd, thd, phd, psd).
Lagrangian  L = 1/2 (m (xd^2 + yd^2) + (A + m h'^2) thd^2 + A s^2 phd^2 + C n^2) - m g h.
Lagrange's equations d/dt dL/dqd - dL/dq = Q_i, written out (derived by hand, checked with sympy):

    x:   m xdd                                       = Q_x
    y:   m ydd                                       = Q_y
    th:  (A + m h'^2) thdd + m h' h'' thd^2 - A s c phd^2 + C n s phd + m g h'      = Q_th
    ph:  (A s^2 + C c^2) phdd + C c psdd + 2 A s c thd phd - C n s thd - C c s thd phd = Q_ph
    ps:  C c phdd + C psdd - C s thd phd             = Q_ps        (i.e. C ndot = Q_ps)

Friction R_f = -mu R_n v_Q (eq. viscfric), generalized forces as printed in the paper, Q_i = R_n k_i,
with w = s (R psd + eps phd):

    k_x  = -mu (xd - sin ph thd h + cos ph w)        k_y = -mu (yd + cos ph thd h + sin ph w)
    k_th = -mu h (cos ph yd - sin ph xd + h thd)
    k_ph = -mu eps s (cos ph xd + sin ph yd + w)     k_ps = -mu R s (cos ph xd + sin ph yd + w)

R_n from the vertical Newton equation m zdd = R_n - m g with z = h(th):

    -m h' thdd + R_n = m (g + h'' thd^2).

Since Q depends on R_n, the five accelerations and R_n are solved together as one 6x6 linear system
M u = b, u = (xdd, ydd, thdd, phdd, psdd, R_n) (numpy.linalg.solve). Its R_n coincides with the
paper's closed form (eq. reactie); tests/test_reference.py checks that.

Variant "so3" (paper Sec. 2.2): xd = yd = 0 inside every k_i and in R_n; x, y, xd, yd are kept in
the state with zero derivative (frozen). Variant "full": everything above.

Jellet J = C n (R c - eps) + A phd R s^2 = R p_ph - eps p_ps is conserved exactly (R k_ph = eps k_ps).

Valid only away from the poles: the Euler chart is singular at sin th = 0 (the ph and ps rows of
M degenerate). `solve` stops and raises if theta comes within 0.05 rad of 0 or pi. It does not
stop at R_n <= 0 (contact loss); check `normal_force` in the output.
"""

import math

import numpy as np
from scipy.integrate import solve_ivp

POLE_MARGIN = 0.05
_KEYS = ("m", "R", "eps", "A", "C", "g", "mu")


def params_of(top):
    """Plain-float parameter dict from any object with attributes m, R, eps, A, C, g, mu."""
    return {k: float(getattr(top, k)) for k in _KEYS}


def _accelerations(z, p, variant):
    """(xdd, ydd, thdd, phdd, psdd, R_n) at state z (sequence of 10 floats), parameter dict p."""
    m, R, eps, A, C, g, mu = p["m"], p["R"], p["eps"], p["A"], p["C"], p["g"], p["mu"]
    _, _, th, ph, _, xd, yd, thd, phd, psd = z
    if variant == "so3":
        xd = yd = 0.0
    elif variant != "full":
        raise ValueError(f"variant must be 'full' or 'so3', got {variant!r}")
    s, c = math.sin(th), math.cos(th)
    sp, cp = math.sin(ph), math.cos(ph)
    h, hp, hpp = R - eps * c, eps * s, eps * c
    n = psd + phd * c
    w = s * (R * psd + eps * phd)
    u = cp * xd + sp * yd + w
    kx = -mu * (xd - sp * thd * h + cp * w)
    ky = -mu * (yd + cp * thd * h + sp * w)
    kth = -mu * h * (cp * yd - sp * xd + h * thd)
    kph = -mu * eps * s * u
    kps = -mu * R * s * u
    Cc = C * c
    M = np.array(
        [
            [m, 0.0, 0.0, 0.0, 0.0, -kx],
            [0.0, m, 0.0, 0.0, 0.0, -ky],
            [0.0, 0.0, A + m * hp * hp, 0.0, 0.0, -kth],
            [0.0, 0.0, 0.0, A * s * s + Cc * c, Cc, -kph],
            [0.0, 0.0, 0.0, Cc, C, -kps],
            [0.0, 0.0, -m * hp, 0.0, 0.0, 1.0],
        ]
    )
    b = np.array(
        [
            0.0,
            0.0,
            -m * hp * hpp * thd * thd + A * s * c * phd * phd - C * n * s * phd - m * g * hp,
            (-2.0 * A * s * c * phd + C * n * s + Cc * s * phd) * thd,
            C * s * thd * phd,
            m * (g + hpp * thd * thd),
        ]
    )
    return np.linalg.solve(M, b)


def rhs(t, z, params, variant):
    """d z / dt for solve_ivp, z = (x, y, th, ph, ps, xd, yd, thd, phd, psd)."""
    zl = z.tolist()
    acc = _accelerations(zl, params, variant)
    if variant == "so3":
        return np.array([0.0, 0.0, zl[7], zl[8], zl[9], 0.0, 0.0, acc[2], acc[3], acc[4]])
    return np.array([zl[5], zl[6], zl[7], zl[8], zl[9], acc[0], acc[1], acc[2], acc[3], acc[4]])


def normal_force(z, params, variant):
    """Normal force R_n of the table at state z (solved with the accelerations)."""
    return float(_accelerations(np.asarray(z, float).tolist(), params, variant)[5])


def jellet(z, params):
    """J = C n (R cos th - eps) + A phd R sin^2 th (eq. jello). Works on arrays z[..., 10]."""
    z = np.asarray(z, float)
    th, phd, psd = z[..., 2], z[..., 8], z[..., 9]
    s, c = np.sin(th), np.cos(th)
    n = psd + phd * c
    return (
        params["C"] * n * (params["R"] * c - params["eps"]) + params["A"] * phd * params["R"] * s**2
    )


def energy(z, params, variant="full"):
    """E = T + m g h; for "so3" without the horizontal translation (E' of L'). Arrays z[..., 10]."""
    p = params
    z = np.asarray(z, float)
    th, xd, yd, thd, phd, psd = z[..., 2], z[..., 5], z[..., 6], z[..., 7], z[..., 8], z[..., 9]
    s, c = np.sin(th), np.cos(th)
    n = psd + phd * c
    trans = 0.0 if variant == "so3" else p["m"] * (xd**2 + yd**2)
    T = 0.5 * (
        trans
        + (p["A"] + p["m"] * (p["eps"] * s) ** 2) * thd**2
        + p["A"] * s**2 * phd**2
        + p["C"] * n**2
    )
    return T + p["m"] * p["g"] * (p["R"] - p["eps"] * c)


def _pole_event(t, z, params, variant):
    th = z[2]
    return min(th, math.pi - th) - POLE_MARGIN


_pole_event.terminal = True
_pole_event.direction = -1


def initial_vector(theta0, spin, *, theta_dot=0.0, phi_dot=0.0, phi=0.0, psi=0.0, vx=0.0, vy=0.0):
    """State z0 of a launch as tippejax.initial_state defines it: psid0 = spin - phid0 cos th0."""
    psi_dot = spin - phi_dot * math.cos(theta0)
    return np.array([0.0, 0.0, theta0, phi, psi, vx, vy, theta_dot, phi_dot, psi_dot], float)


def solve(
    params,
    theta0,
    spin,
    t_eval,
    *,
    theta_dot=0.0,
    phi_dot=0.0,
    phi=0.0,
    psi=0.0,
    vx=0.0,
    vy=0.0,
    variant="full",
    rtol=1e-12,
    atol=1e-12,
):
    """Integrate a launch with DOP853 from t = 0 to t_eval[-1]; fields sampled at t_eval.

    Returns a dict of arrays (t, theta, phi, psi, theta_dot, phi_dot, psi_dot, spin, x, y, vx, vy,
    normal_force, jellet, energy, z) plus nfev and success. Raises RuntimeError if theta comes
    within 0.05 rad of 0 or pi (Euler chart singular) or if the solver fails.
    """
    t_eval = np.asarray(t_eval, float)
    if min(theta0, math.pi - theta0) <= POLE_MARGIN:
        raise RuntimeError(f"theta0={theta0} is within {POLE_MARGIN} rad of a pole")
    z0 = initial_vector(
        theta0, spin, theta_dot=theta_dot, phi_dot=phi_dot, phi=phi, psi=psi, vx=vx, vy=vy
    )
    sol = solve_ivp(
        rhs,
        (0.0, float(t_eval[-1])),
        z0,
        method="DOP853",
        t_eval=t_eval,
        args=(params, variant),
        rtol=rtol,
        atol=atol,
        events=_pole_event,
    )
    if sol.status == 1:
        raise RuntimeError(
            f"theta came within {POLE_MARGIN} rad of a pole at t = {sol.t_events[0][0]:.6g} s: "
            "the Euler-angle chart is singular there; use tippejax's vector form instead."
        )
    if not sol.success:
        raise RuntimeError(f"solve_ivp failed: {sol.message}")
    z = sol.y.T
    th, phd, psd = z[:, 2], z[:, 8], z[:, 9]
    return {
        "t": sol.t,
        "z": z,
        "theta": th,
        "phi": z[:, 3],
        "psi": z[:, 4],
        "theta_dot": z[:, 7],
        "phi_dot": phd,
        "psi_dot": psd,
        "spin": psd + phd * np.cos(th),
        "x": z[:, 0],
        "y": z[:, 1],
        "vx": z[:, 5],
        "vy": z[:, 6],
        "normal_force": np.array([normal_force(zi, params, variant) for zi in z]),
        "jellet": jellet(z, params),
        "energy": energy(z, params, variant),
        "nfev": sol.nfev,
        "success": sol.success,
    }
