r"""Independent reference model of a real tippe top: Coulomb-type friction, Contensou drilling, stem.

Written from the physics (Newton-Euler in the space frame), not from tippejax: a test oracle for
the friction laws and the stem (issue 58) and the scipy peer of `benchmarks/real_tops.py`.
Conventions of `euler_reference` / `vector_reference`: unit axis a from the centre of mass O
towards the ball centre, theta = arccos a_z, Z up.

Body: mass m, inertia A = B, C about O; contact spheres on the axis, sphere i with radius r_i and
centre O + d_i a: the ball (r = R, d = eps) and, optionally, the stem tip (r = r2, d = a2 > eps).
State y (14): O = (x, y, z), its velocity v, the axis a, the angular velocity w, and two running
integrals used by the checks (the Jellett source and the friction work, below). For contact i

    rho_i = d_i a - r_i e_z          (from O to the sphere's lowest point Q_i)
    delta_i = r_i - z - d_i a_z      (penetration; > 0 in contact)
    s_i = [v + w x rho_i]_xy         (slip of Q_i), drilling rate w_n = w_z,

the friction law gives a horizontal force R_n,i f(s_i, w_n) and a torque R_n,i m(s_i, w_n) e_z:

    viscous   f = -mu s                                        (mu in s/m)
    coulomb   f = -mu s / sqrt(|s|^2 + delta^2)                 (mu dimensionless)
    ellipse   D = sqrt(|s|^2 + Rb^2 w_n^2 + delta^2), Rb = 3 pi rho / 16,
              f = -mu s / D,  m = -mu Rb^2 w_n / D              (Moeller, Leine & Glocker 2009)
    hertz     Coulomb's law integrated over a Hertz disc of radius rho (`hertz_contensou`).

Equations of motion: m dv/dt = sum_i R_n,i (e_z + f_i) - m g e_z, and with L = I w,
I = A 1 + (C - A) a a^T, dI/dt w = (C - A) n (w x a), n = w . a:

    I dw/dt = sum_i [rho_i x R_n,i (e_z + f_i) + R_n,i m_i e_z] - (C - A) n (w x a),  da/dt = w x a.

Normal forces, two contact models:
- "compliant": Hunt-Crossley, R_n = max(0, k delta^{3/2} (1 + 3/2 c d(delta)/dt)) for delta > 0,
  with Hertz's k = 4/3 E* sqrt(r_i); z is a free coordinate. Elastic energy 2/5 k delta^{5/2}.
- "rigid" (ball only, stem clear): z = R - eps a_z; then dw/dt = R_n w1 + w0 is affine in R_n and
  the vertical Newton equation m d^2z/dt^2 = R_n - m g gives
  R_n = m (g - eps [w0 x a + w x (w x a)]_z) / (1 + m eps [w1 x a]_z).
`solve(contact="rigid-then-compliant")` integrates the rigid model until the stem comes within
`switch_gap` of the table (or the ball would lift off), then continues with compliant contacts,
starting the ball at the penetration that carries the rigid R_n.

Jellett: J = -L . q, q = eps a - R e_z. Since dL/dt = sum of torques about O and
L . (w x a) = 0, dJ/dt = tau . (R e_z - eps a); with the ball alone the force's moment
q x F is orthogonal to q, so dJ/dt = M (R - eps cos theta): J is conserved under any friction
force and changes only through the drilling torque M. y[12] integrates M_ball (R - eps a_z).
Energy: dE/dt = sum_i (F_i . s_i + M_i w_n) - (Hunt-Crossley damping power) <= 0 with
E = m |v|^2/2 + w . L/2 + m g z + sum_i 2/5 k_i delta_i^{5/2}; y[13] integrates the friction
power alone (equal to dE/dt in the rigid model).
"""

from __future__ import annotations

import math
import time

import numpy as np
from scipy.integrate import solve_ivp

try:  # numba is optional: only speed depends on it
    import numba

    def _jit(f):
        return numba.njit(cache=True)(f)

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    HAVE_NUMBA = False

    def _jit(f):
        return f


LAWS = {"viscous": 0, "coulomb": 1, "ellipse": 2, "hertz": 3}
G = 9.81
# the paper's standard top (Ciocci & Langerock) and Leine & Glocker 2003's top with its stem
STANDARD = dict(m=0.02, R=0.025, eps=0.0075, A=4.5e-6, C=5e-6, g=G)
LEINE_GLOCKER = dict(m=6e-3, R=0.015, eps=3e-3, A=8e-7, C=7e-7, g=G, r2=5e-3, a2=0.016)
# fixed quadrature of the Hertz disc: Gauss-Legendre along rays, trapezoid in the angle
N_RAY, N_ANGLE = 24, 64
_GX, _GW = np.polynomial.legendre.leggauss(N_RAY)
_GX, _GW = 0.5 * (_GX + 1.0), 0.5 * _GW


# --------------------------------------------------------------------------------------------
# Friction laws, per unit normal force
# --------------------------------------------------------------------------------------------


@_jit
def _hertz(vx, vy, wn, rho, delta, gx, gw, n_angle, pole_rays=True):
    """(F_x, F_y, M) / (mu R_n) of Coulomb's law over a Hertz disc, by quadrature.

    Pressure 3 R_n/(2 pi rho^2) sqrt(1 - r^2/rho^2); the element at r slides at
    u = v + w_n e_z x r; F = -mu int p u/|u|_delta dA, M = -mu int p (r x u/|u|_delta)_z dA with
    |u|_delta = sqrt(|u|^2 + delta^2). Rays start at the slip pole r* = e_z x v / w_n (u = 0),
    where u = w_n e_z x (r - r*) is smooth along each ray: over all angles if r* is in the disc
    (angles clustered towards the nearest edge), over the disc's aperture if outside. Each ray's
    sqrt edge is removed by a change of variable. With w_n = 0 or pole_rays=False, rays start
    at the centre.
    """
    fx = 0.0
    fy = 0.0
    mz = 0.0
    d2 = delta * delta
    n_ray = gx.shape[0]
    dist = math.sqrt(vx * vx + vy * vy) / abs(wn) if wn != 0.0 else math.inf
    if pole_rays and dist < math.inf:
        px, py = -vy / wn, vx / wn
        c0 = px * px + py * py - rho * rho
        base = math.atan2(py, px)
        if dist < rho:  # all angles; phi = base + q - k sin q clusters towards the near edge
            kappa = dist / rho
            n_phi, span = n_angle, 2.0 * math.pi
        else:  # the aperture |phi - (base + pi)| < asin(rho / dist), Gauss-Legendre
            n_phi, span = gx.shape[0], 2.0 * math.asin(min(rho / dist, 1.0))
        for j in range(n_phi):
            if dist < rho:
                q = (j + 0.5) * span / n_phi
                phi = base + q - kappa * math.sin(q)
                wphi = (1.0 - kappa * math.cos(q)) * span / n_phi
            else:
                phi = base + math.pi + span * (gx[j] - 0.5)
                wphi = span * gw[j]
            ex, ey = math.cos(phi), math.sin(phi)
            b = px * ex + py * ey
            root = math.sqrt(max(b * b - c0, 0.0))
            sp, sm = -b + root, -b - root
            for i in range(n_ray):
                if dist < rho:  # s = s_+ (1 - t^2): sqrt(s_+ - s) = t sqrt(s_+)
                    t = gx[i]
                    s = sp * (1.0 - t * t)
                    pressure = t * math.sqrt(sp * (s - sm))  # sqrt(rho^2 - |r|^2)
                    weight = gw[i] * wphi * 2.0 * sp * t * s * pressure
                else:  # s in (s_-, s_+), s = mid - half cos(gamma)
                    half, gam = 0.5 * (sp - sm), math.pi * gx[i]
                    s = 0.5 * (sp + sm) - half * math.cos(gam)
                    pressure = half * math.sin(gam)
                    weight = math.pi * gw[i] * wphi * half * math.sin(gam) * s * pressure
                rx, ry = px + s * ex, py + s * ey
                ux, uy = -wn * s * ey, wn * s * ex
                inv = weight / math.sqrt(ux * ux + uy * uy + d2)
                fx -= inv * ux
                fy -= inv * uy
                mz -= inv * (rx * uy - ry * ux)
    else:  # rays from the centre, r = rho sin(beta)
        dphi = 2.0 * math.pi / n_angle
        for j in range(n_angle):
            phi = (j + 0.5) * dphi
            ex, ey = math.cos(phi), math.sin(phi)
            for i in range(n_ray):
                beta = 0.5 * math.pi * gx[i]
                sb, cb = math.sin(beta), math.cos(beta)
                weight = 0.5 * math.pi * gw[i] * dphi * rho**3 * sb * cb * cb
                rx, ry = rho * sb * ex, rho * sb * ey
                ux, uy = vx - wn * ry, vy + wn * rx
                inv = weight / math.sqrt(ux * ux + uy * uy + d2)
                fx -= inv * ux
                fy -= inv * uy
                mz -= inv * (rx * uy - ry * ux)
    scale = 3.0 / (2.0 * math.pi * rho**3)
    return scale * fx, scale * fy, scale * mz


@_jit
def _friction(law, vx, vy, wn, mu, rho, delta, gx, gw, n_angle):
    """(f_x, f_y, m) with force R_n (f_x, f_y) and torque R_n m e_z; mu included."""
    if law == 0:
        return -mu * vx, -mu * vy, 0.0
    if law == 1:
        inv = mu / math.sqrt(vx * vx + vy * vy + delta * delta)
        return -inv * vx, -inv * vy, 0.0
    if law == 2:
        rb = 3.0 * math.pi * rho / 16.0
        inv = mu / math.sqrt(vx * vx + vy * vy + (rb * wn) ** 2 + delta * delta)
        return -inv * vx, -inv * vy, -inv * rb * rb * wn
    fx, fy, mz = _hertz(vx, vy, wn, rho, delta, gx, gw, n_angle)
    return mu * fx, mu * fy, mu * mz


def hertz_contensou(v, omega_n, rho, delta, *, n_ray=N_RAY, n_angle=N_ANGLE, pole_rays=True):
    """Coulomb-Contensou friction over a Hertz disc by quadrature, per unit mu R_n.

    **Arguments:** slip velocity v (2,) in m/s, drilling rate omega_n in rad/s, disc radius rho in
    m, slip scale delta in m/s; n_ray, n_angle: nodes along each ray and in the angle;
    pole_rays=False always starts the rays at the centre (a second, slower route for checks).
    **Returns:** (force (2,), torque) with force/(mu R_n) dimensionless and torque/(mu R_n) in m.
    """
    gx, gw = np.polynomial.legendre.leggauss(int(n_ray))
    fx, fy, mz = _hertz(
        float(v[0]),
        float(v[1]),
        float(omega_n),
        float(rho),
        float(delta),
        0.5 * (gx + 1.0),
        0.5 * gw,
        int(n_angle),
        bool(pole_rays),
    )
    return np.array([fx, fy]), mz


def friction(law, v, omega_n, *, mu=1.0, rho=5e-4, delta=1e-6):
    """Friction of `law` per unit normal force: (force (2,), torque about e_z), mu included."""
    fx, fy, mz = _friction(
        LAWS[law],
        float(v[0]),
        float(v[1]),
        float(omega_n),
        float(mu),
        float(rho),
        float(delta),
        _GX,
        _GW,
        N_ANGLE,
    )
    return np.array([fx, fy]), mz


# --------------------------------------------------------------------------------------------
# Vector fields (scalar code: compiled by numba, plain Python without it)
# --------------------------------------------------------------------------------------------
# P = (m, R, eps, A, C, g, mu, law, rho, delta, has_stem, r2, a2, k_ball, k_stem, c)


@_jit
def _axis(y):
    norm = math.sqrt(y[6] * y[6] + y[7] * y[7] + y[8] * y[8])
    return y[6] / norm, y[7] / norm, y[8] / norm


@_jit
def _inv_inertia(A, C, ax, ay, az, tx, ty, tz):
    s = (1.0 / C - 1.0 / A) * (ax * tx + ay * ty + az * tz)
    return tx / A + s * ax, ty / A + s * ay, tz / A + s * az


@_jit
def _rhs_rigid(y, P, out, gx, gw):
    """Ball held on the table (z = R - eps a_z); writes dy/dt, returns R_n."""
    m, R, eps, A, C, g, mu = P[0], P[1], P[2], P[3], P[4], P[5], P[6]
    ax, ay, az = _axis(y)
    wx, wy, wz = y[9], y[10], y[11]
    n = wx * ax + wy * ay + wz * az
    dax, day, daz = wy * az - wz * ay, wz * ax - wx * az, wx * ay - wy * ax
    rx, ry, rz = eps * ax, eps * ay, eps * az - R
    sx = y[3] + wy * rz - wz * ry
    sy = y[4] + wz * rx - wx * rz
    fx, fy, mz = _friction(int(P[7]), sx, sy, wz, mu, P[8], P[9], gx, gw, N_ANGLE)
    t1x, t1y, t1z = ry - rz * fy, rz * fx - rx, rx * fy - ry * fx + mz  # rho x (f, 1) + m e_z
    w1x, w1y, w1z = _inv_inertia(A, C, ax, ay, az, t1x, t1y, t1z)
    k0 = -(C - A) * n / A
    w0x, w0y = k0 * dax, k0 * day
    normal = (
        m
        * (g - eps * (w0x * ay - w0y * ax + wx * day - wy * dax))
        / (1.0 + m * eps * (w1x * ay - w1y * ax))
    )
    out[0], out[1], out[2] = y[3], y[4], y[5]
    out[3], out[4], out[5] = normal * fx / m, normal * fy / m, normal / m - g
    out[6], out[7], out[8] = dax, day, daz
    out[9], out[10], out[11] = normal * w1x + w0x, normal * w1y + w0y, normal * w1z + k0 * daz
    out[12] = normal * mz * (R - eps * az)
    out[13] = normal * (fx * sx + fy * sy + mz * wz)
    return normal


@_jit
def _contact(y, P, radius, offset, k, gx, gw, res):
    """Hunt-Crossley contact of the sphere (radius, offset along a): res = (R_n, F, tau, power)."""
    ax, ay, az = _axis(y)
    wx, wy, wz = y[9], y[10], y[11]
    depth = radius - y[2] - offset * az
    for i in range(8):
        res[i] = 0.0
    if depth <= 0.0:
        return
    rate = -(y[5] + offset * (wx * ay - wy * ax))
    normal = k * depth**1.5 * (1.0 + 1.5 * P[15] * rate)
    if normal <= 0.0:
        return
    rx, ry, rz = offset * ax, offset * ay, offset * az - radius
    sx = y[3] + wy * rz - wz * ry
    sy = y[4] + wz * rx - wx * rz
    fx, fy, mz = _friction(int(P[7]), sx, sy, wz, P[6], P[8], P[9], gx, gw, N_ANGLE)
    Fx, Fy, Fz = normal * fx, normal * fy, normal
    res[0], res[1], res[2] = Fx, Fy, Fz
    res[3] = ry * Fz - rz * Fy
    res[4] = rz * Fx - rx * Fz
    res[5] = rx * Fy - ry * Fx + normal * mz
    res[6] = normal * mz
    res[7] = Fx * sx + Fy * sy + normal * mz * wz


@_jit
def _rhs_compliant(y, P, out, gx, gw, normals):
    """Compliant ball and stem; writes dy/dt and the normal forces (ball, stem)."""
    m, R, eps, A, C, g = P[0], P[1], P[2], P[3], P[4], P[5]
    ax, ay, az = _axis(y)
    wx, wy, wz = y[9], y[10], y[11]
    n = wx * ax + wy * ay + wz * az
    dax, day, daz = wy * az - wz * ay, wz * ax - wx * az, wx * ay - wy * ax
    ball = np.empty(8)
    stem = np.zeros(8)
    _contact(y, P, R, eps, P[13], gx, gw, ball)
    if P[10] > 0.0:
        _contact(y, P, P[11], P[12], P[14], gx, gw, stem)
    normals[0], normals[1] = ball[2], stem[2]
    out[0], out[1], out[2] = y[3], y[4], y[5]
    out[3] = (ball[0] + stem[0]) / m
    out[4] = (ball[1] + stem[1]) / m
    out[5] = (ball[2] + stem[2]) / m - g
    out[6], out[7], out[8] = dax, day, daz
    k0 = -(C - A) * n
    tx, ty, tz = _inv_inertia(
        A,
        C,
        ax,
        ay,
        az,
        ball[3] + stem[3] + k0 * dax,
        ball[4] + stem[4] + k0 * day,
        ball[5] + stem[5] + k0 * daz,
    )
    out[9], out[10], out[11] = tx, ty, tz
    out[12] = ball[6] * (R - eps * az)
    out[13] = ball[7] + stem[7]


@_jit
def _jacobian(rigid, y, P, scale, gx, gw):
    """Forward-difference Jacobian of either vector field (for the implicit solvers)."""
    nd = y.shape[0]
    f0, f1, tmp = np.empty(nd), np.empty(nd), y.copy()
    normals = np.empty(2)
    jac = np.zeros((nd, nd))
    if rigid:
        _rhs_rigid(y, P, f0, gx, gw)
    else:
        _rhs_compliant(y, P, f0, gx, gw, normals)
    for j in range(12):
        h = 1.5e-8 * max(abs(y[j]), scale[j])
        tmp[j] = y[j] + h
        if rigid:
            _rhs_rigid(tmp, P, f1, gx, gw)
        else:
            _rhs_compliant(tmp, P, f1, gx, gw, normals)
        tmp[j] = y[j]
        for i in range(nd):
            jac[i, j] = (f1[i] - f0[i]) / h
    return jac


# --------------------------------------------------------------------------------------------
# Parameters, launch, derived fields
# --------------------------------------------------------------------------------------------

E_STAR = 5e9  # effective modulus of the compliant contacts, Pa
# Hunt-Crossley c in s/m; restitution about 1/(1.5 c v) at impact speed v: 0.08 at 0.04 m/s
DAMPING = 200.0


def make_params(top, law, *, mu, rho=5e-4, delta=1e-6, stem=True, E_star=E_STAR, damping=DAMPING):
    """Parameter vector of the vector fields.

    **Arguments:** top: dict with m, R, eps, A, C, g and (for the stem) r2, a2; law: one of
    `LAWS`; mu: friction coefficient (s/m for "viscous", dimensionless otherwise); rho: contact
    radius in m (Contensou laws); delta: slip scale in m/s; stem: model the stem tip; E_star in Pa
    and damping c in s/m: Hunt-Crossley contacts, k = 4/3 E* sqrt(r).
    **Returns:** a float64 array.
    """
    if law not in LAWS:
        raise ValueError(f"law must be one of {tuple(LAWS)}, got {law!r}")
    m, R, eps, A, C = (float(top[k]) for k in ("m", "R", "eps", "A", "C"))
    g = float(top.get("g", G))
    if not (
        m > 0 and R > 0 and 0 <= eps < R and A > 0 and C > 0 and mu >= 0 and rho > 0 and delta > 0
    ):
        raise ValueError(f"invalid parameters: {top}, mu={mu}, rho={rho}, delta={delta}")
    r2 = float(top.get("r2", 0.0)) if stem else 0.0
    a2 = float(top.get("a2", 0.0)) if stem else 0.0
    if stem and not (r2 > 0 and a2 > eps and a2 + r2 > R and abs(r2 - R) < a2 - eps):
        raise ValueError(
            f"stem needs r2 > 0, a2 > eps, a tip outside the ball that can touch: r2={r2}, a2={a2}"
        )
    k_ball, k_stem = 4.0 / 3.0 * E_star * math.sqrt(R), 4.0 / 3.0 * E_star * math.sqrt(max(r2, 0))
    return np.array(
        [
            m,
            R,
            eps,
            A,
            C,
            g,
            mu,
            LAWS[law],
            rho,
            delta,
            float(stem),
            r2,
            a2,
            k_ball,
            k_stem,
            damping,
        ],
        float,
    )


def stem_touch_angle(top):
    """theta_s of the stem touch with the ball on the table: cos theta_s = (r2 - R)/(a2 - eps)."""
    return math.acos((top["r2"] - top["R"]) / (top["a2"] - top["eps"]))


def initial_state(P, theta0, spin):
    """Launch of `vector_reference.initial_vector` (phi = 0): a = (0, -sin th0, cos th0), w = spin
    a, ball centre at rest on the table (rigid contact: z = R - eps cos th0)."""
    a = np.array([0.0, -math.sin(theta0), math.cos(theta0)])
    y = np.zeros(14)
    y[2] = P[1] - P[2] * a[2]
    y[6:9], y[9:12] = a, spin * a
    return y


def rigid_normal_force(y, P):
    """R_n of the rigid ball contact at state y."""
    return _rhs_rigid(np.asarray(y, float), P, np.empty(14), _GX, _GW)


def _to_compliant(y, P):
    """Same motion, ball pressed in by the depth that carries the rigid R_n (d(delta)/dt = 0)."""
    y = np.array(y, float)
    normal = max(rigid_normal_force(y, P), 0.0)
    a = y[6:9] / np.linalg.norm(y[6:9])
    y[2] = P[1] - P[2] * a[2] - (normal / P[13]) ** (2.0 / 3.0)
    y[5] = -P[2] * np.cross(y[9:12], a)[2]
    return y


def fields(y, P, compliant):
    """theta, Jellett J = -L . q, energy E (elastic included), depths, normal forces at states y."""
    m, R, eps, A, C, g = P[:6]
    y = np.atleast_2d(y)
    a = y[:, 6:9] / np.linalg.norm(y[:, 6:9], axis=1, keepdims=True)
    w, v = y[:, 9:12], y[:, 3:6]
    n = np.sum(w * a, axis=1)
    L = A * w + (C - A) * n[:, None] * a
    depth_ball = R - y[:, 2] - eps * a[:, 2]
    depth_stem = P[11] - y[:, 2] - P[12] * a[:, 2] if P[10] else np.full(len(y), -np.inf)
    compliant = np.broadcast_to(np.asarray(compliant, bool), (len(y),))
    elastic = np.zeros(len(y))
    normals = np.zeros((len(y), 2))
    out = np.empty(14)
    for i, row in enumerate(y):
        if compliant[i]:
            for d, k in ((depth_ball[i], P[13]), (depth_stem[i], P[14])):
                elastic[i] += 0.4 * k * max(d, 0.0) ** 2.5
            _rhs_compliant(row, P, out, _GX, _GW, normals[i])
        else:
            normals[i, 0] = _rhs_rigid(row, P, out, _GX, _GW)
    energy = (
        0.5 * m * np.sum(v * v, axis=1) + 0.5 * np.sum(w * L, axis=1) + m * g * y[:, 2] + elastic
    )
    return {
        "theta": np.arctan2(np.hypot(a[:, 0], a[:, 1]), a[:, 2]),
        "axis": a,
        "omega": w,
        "spin": n,
        "jellett": L[:, 2] * R - eps * C * n,
        "energy": energy,
        "depth_ball": depth_ball,
        "depth_stem": depth_stem,
        "normal_ball": normals[:, 0],
        "normal_stem": normals[:, 1],
        "jellett_source": y[:, 12],
        "friction_work": y[:, 13],
    }


# --------------------------------------------------------------------------------------------
# Integration with events
# --------------------------------------------------------------------------------------------


def _event(fn, direction=0.0, terminal=False):
    fn.direction, fn.terminal = direction, terminal
    return fn


def _phase(
    P,
    rigid,
    y0,
    t0,
    t1,
    t_eval,
    method,
    rtol,
    atol,
    switch_gap,
    max_step=np.inf,
    stop_at_half=False,
):
    """One solve_ivp run of the rigid or the compliant field; returns (sol, event names)."""
    scratch, normals = np.empty(14), np.empty(2)
    scale = np.array(
        [P[1]] * 3 + [0.1] * 3 + [1.0] * 3 + [max(np.abs(y0[9:12]).max(), 1.0)] * 3 + [1.0, 1.0]
    )
    if rigid:

        def f(t, y):
            out = np.empty(14)
            _rhs_rigid(y, P, out, _GX, _GW)
            return out
    else:

        def f(t, y):
            out = np.empty(14)
            _rhs_compliant(y, P, out, _GX, _GW, normals)
            return out

    def jac(t, y):
        return _jacobian(rigid, y, P, scale, _GX, _GW)

    def axis_z(t, y):
        return y[8]

    events, names = [_event(axis_z, -1.0, stop_at_half)], ["theta_pi/2"]
    if rigid:
        events.append(_event(lambda t, y: _rhs_rigid(y, P, scratch, _GX, _GW), -1.0, True))
        names.append("rigid_liftoff")
        if P[10] and switch_gap is not None:
            events.append(_event(lambda t, y: y[2] + P[12] * y[8] - P[11] - switch_gap, -1.0, True))
            names.append("switch")
    else:

        def ball(t, y):
            return P[1] - y[2] - P[2] * y[8]

        def tip(t, y):
            return P[11] - y[2] - P[12] * y[8]

        for fn, (up, down) in (
            (ball, ("ball_touchdown", "ball_liftoff")),
            (tip, ("stem_touch", "stem_liftoff")),
        )[: 1 + int(P[10])]:
            events += [
                _event(lambda t, y, fn=fn: fn(t, y), 1.0),  # one object per direction
                _event(lambda t, y, fn=fn: fn(t, y), -1.0),
            ]
            names += [up, down]
    keep = t_eval[(t_eval > t0) & (t_eval <= t1)]
    kw = {"jac": jac} if method in ("Radau", "BDF", "LSODA") else {}
    sol = solve_ivp(
        f,
        (t0, t1),
        y0,
        method=method,
        t_eval=keep,
        events=events,
        rtol=rtol,
        atol=atol * scale,
        max_step=max_step,
        **kw,
    )
    if sol.status < 0:
        raise RuntimeError(f"solve_ivp ({method}) failed at t = {sol.t[-1]:.6g}: {sol.message}")
    return sol, names


def _event_list(names, sol):
    """[(t, name, theta)] of a solve_ivp solution's events."""
    return [
        (float(tk), name, float(math.acos(np.clip(yk[8] / np.linalg.norm(yk[6:9]), -1, 1))))
        for name, te, ye in zip(names, sol.t_events, sol.y_events)
        for tk, yk in zip(te, ye)
    ]


def solve(
    top,
    law,
    theta0,
    spin,
    t_end,
    *,
    mu,
    rho=5e-4,
    delta=1e-6,
    stem=True,
    contact="rigid-then-compliant",
    E_star=E_STAR,
    damping=DAMPING,
    switch_gap=1e-4,
    dt_sample=1e-3,
    rtol=1e-9,
    atol=1e-12,
    method_rigid=None,
    method_compliant="LSODA",
    max_step=np.inf,
    stop_at_half=False,
):
    """Integrate a launch (`initial_state`) to t_end with events.

    **Arguments:** top, law, mu, rho, delta, stem, E_star, damping as `make_params`; theta0 in rad,
    spin in rad/s; contact: "rigid" (ball held on the table, stem ignored; stops if R_n would
    turn negative), "compliant" (Hunt-Crossley ball and stem from t = 0) or
    "rigid-then-compliant" (rigid until the stem is `switch_gap` metres from the table);
    dt_sample: sampling step; rtol, atol (times each component's scale); method_rigid (default
    DOP853, LSODA for "coulomb", which is stiff below the slip scale), method_compliant and
    max_step (compliant phase: a contact shorter than a step may go unlogged); stop_at_half: end
    where theta first reaches pi/2.
    **Returns:** dict: t, y, compliant (bool per sample) and `fields`; events: list of
    (t, name, theta) with names theta_pi/2, switch, stem_touch, stem_liftoff, ball_liftoff,
    ball_touchdown, rigid_liftoff; t_half (first theta = pi/2), t_stem and theta_stem (first
    stem touch), nfev, wall (seconds).
    """
    if contact not in ("rigid", "compliant", "rigid-then-compliant"):
        raise ValueError(
            f"contact must be 'rigid', 'compliant' or 'rigid-then-compliant', got {contact!r}"
        )
    P = make_params(
        top, law, mu=mu, rho=rho, delta=delta, stem=stem, E_star=E_star, damping=damping
    )
    if contact == "rigid":
        P[10] = 0.0
    method_rigid = method_rigid or ("LSODA" if law == "coulomb" else "DOP853")
    t_eval = np.arange(0.0, t_end + 0.5 * dt_sample, dt_sample)
    start = time.perf_counter()
    y = initial_state(P, theta0, spin)
    ts, ys, flags, events, nfev, t = [np.zeros(1)], [y[None]], [np.zeros(1, bool)], [], 0, 0.0
    if contact == "compliant":
        y = _to_compliant(y, P)
        ys[0], flags[0] = y[None], np.ones(1, bool)
    else:
        sol, names = _phase(
            P,
            True,
            y,
            0.0,
            t_end,
            t_eval,
            method_rigid,
            rtol,
            atol,
            switch_gap if contact == "rigid-then-compliant" else None,
            stop_at_half=stop_at_half,
        )
        nfev += sol.nfev
        ts.append(sol.t), ys.append(sol.y.T), flags.append(np.zeros(sol.t.size, bool))
        events += _event_list(names, sol)
        t = t_end
        hit = [i for i, te in enumerate(sol.t_events) if i > 0 and len(te)]
        if sol.status == 1 and hit and contact == "rigid-then-compliant":
            # the stem is near, or the ball would lift off: continue with compliant contacts
            t, y = float(sol.t_events[hit[0]][0]), _to_compliant(sol.y_events[hit[0]][0], P)
    if t < t_end:
        sol, names = _phase(
            P,
            False,
            y,
            t,
            t_end,
            t_eval,
            method_compliant,
            rtol,
            atol,
            None,
            max_step,
            stop_at_half,
        )
        nfev += sol.nfev
        ts.append(sol.t), ys.append(sol.y.T), flags.append(np.ones(sol.t.size, bool))
        events += _event_list(names, sol)
    wall = time.perf_counter() - start
    events.sort()
    t_all, y_all, comp = np.concatenate(ts), np.concatenate(ys), np.concatenate(flags)
    out = {
        "t": t_all,
        "y": y_all,
        "compliant": comp,
        "events": events,
        "nfev": nfev,
        "wall": wall,
        "params": P,
    }
    out.update(fields(y_all, P, comp))
    first = {}
    for te, name, th in events:
        first.setdefault(name, (te, th))
    out["t_half"] = first.get("theta_pi/2", (math.nan, math.nan))[0]
    out["t_stem"], out["theta_stem"] = first.get("stem_touch", (math.nan, math.nan))
    return out


def theta_at(result, t):
    """theta of a `solve` result at time t (linear between samples)."""
    return float(np.interp(t, result["t"], result["theta"]))
