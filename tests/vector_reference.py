r"""Independent reference integrator for the tippe top in vector form, regular at the poles.

Written from first principles (Newton-Euler), not from tippejax and not from `euler_reference`'s
Euler-angle equations: a test oracle and the data source of `tests/fit_records.py`. Unlike the
Euler-angle chart it has no singularity at theta = 0 or pi, so it integrates upright launches.

Model (Ciocci & Langerock, Sec. 2; conventions of `euler_reference`): a sphere of radius R and mass
m whose centre of mass G lies a distance eps from the geometric centre, on the symmetry axis. The
unit axis a points from G towards the geometric centre (towards the stem), so the height of G is
z_G = R - eps a_z and theta = arccos a_z is the tilt (theta = 0: upright, stem up; theta = pi:
inverted). In Euler angles (ZXZ) a = (sin th sin ph, -sin th cos ph, cos th). Inertia about G:
A = B transverse, C axial. Viscous sliding friction F = -mu R_n v_Q at the contact point Q.

State y = (x, y, vx, vy, a_x, a_y, a_z, w_x, w_y, w_z): horizontal position and velocity of G,
the axis a and the angular velocity w, all in the space frame. With e_z vertical,

    r_Q = eps a - R e_z                       (from G to the contact point Q)
    v_G = (vx, vy, -eps (w x a)_z)            (d z_G / dt = -eps da_z/dt)
    v_Q = v_G + w x r_Q                       (its vertical part vanishes identically)
    L   = I w,  I = A 1 + (C - A) a a^T,      n = w . a (the spin)
    da/dt = w x a
    dL/dt = r_Q x (R_n e_z + F)               (torque about G)
    m dv_G/dt = R_n e_z + F - m g e_z.

Since dI/dt w = (C - A) n (w x a), the angular acceleration is affine in R_n:

    dw/dt = R_n w1 + w0,   w1 = I^{-1} [r_Q x (e_z - mu v_Q)],   w0 = -I^{-1} [(C - A) n (w x a)],
    I^{-1} v = v / A + (1/C - 1/A) (a . v) a,

and the holonomic constraint z_G = R - eps a_z differentiated twice,
d^2 z_G/dt^2 = -eps [dw/dt x a + w x (w x a)]_z, turned into the vertical Newton equation gives

    R_n = m (g - eps [w0 x a + w x (w x a)]_z) / (1 + m eps [w1 x a]_z).

Variant "so3" (paper Sec. 2.2, as in `euler_reference`): the horizontal velocity of G is set to
zero inside v_Q (hence in the friction and in R_n), and x, y, vx, vy are frozen. Variant "full":
everything above.

Invariants: the Jellet quantity J = L . (R e_z - eps a) = -L . r_Q (in Euler angles
C n (R cos th - eps) + A phd R sin^2 th) is conserved exactly; the energy
E = m |v_G|^2 / 2 + w . L / 2 + m g z_G (horizontal part of |v_G|^2 dropped for "so3") does not
increase (dE/dt = F . v_Q = -mu R_n |v_Q|^2 <= 0 while R_n >= 0).

Integration: Dormand-Prince 8(5,3) (DOP853) with its 7th-order dense output, a line-by-line port
of `scipy.integrate.solve_ivp(method="DOP853")` (same coefficients, same error norm and step
control) compiled with numba when numba is importable (`backend="numba"`, ~100x faster) and
run as plain Python otherwise; `backend="scipy"` calls `solve_ivp` itself (the check of the port).
The port integrates a batch of K copies (different parameters or launches) with one shared step
sequence, which makes finite differences across the batch smooth (`solve_batch`).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.integrate import solve_ivp
from scipy.integrate._ivp import dop853_coefficients as _dop

try:  # numba is optional: only speed depends on it
    import numba

    def _jit(f):
        return numba.njit(cache=True, fastmath=False)(f)

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only without numba
    HAVE_NUMBA = False

    def _jit(f):
        return f


_KEYS = ("m", "R", "eps", "A", "C", "g", "mu")
_VARIANTS = {"full": 1, "so3": 0}


def params_of(top):
    """Plain-float parameter dict from any object with attributes m, R, eps, A, C, g, mu."""
    return {k: float(getattr(top, k)) for k in _KEYS}


def _param_vector(params):
    missing = [k for k in _KEYS if k not in params]
    if missing:
        raise ValueError(f"params lacks {missing}; needs keys {_KEYS}")
    p = np.array([float(params[k]) for k in _KEYS])
    m, R, eps, A, C, g, mu = p
    if not (m > 0 and R > 0 and 0 <= eps < R and A > 0 and C > 0 and g > 0 and mu >= 0):
        raise ValueError(
            f"invalid params (need m, R, A, C, g > 0, 0 <= eps < R, mu >= 0): {params}"
        )
    return p


# --------------------------------------------------------------------------------------------
# Right-hand side (scalar code: compiles under numba, runs as plain Python without it)
# --------------------------------------------------------------------------------------------


@_jit
def _rhs(y, p, full, out):
    """Write dy/dt into `out`; return the normal force R_n. y: (10,), p: (m, R, eps, A, C, g, mu)."""
    m, R, eps, A, C, g, mu = p[0], p[1], p[2], p[3], p[4], p[5], p[6]
    vx, vy = y[2], y[3]
    norm_a = math.sqrt(y[4] * y[4] + y[5] * y[5] + y[6] * y[6])
    ax, ay, az = y[4] / norm_a, y[5] / norm_a, y[6] / norm_a
    wx, wy, wz = y[7], y[8], y[9]
    n = wx * ax + wy * ay + wz * az
    # da/dt = w x a
    dax = wy * az - wz * ay
    day = wz * ax - wx * az
    daz = wx * ay - wy * ax
    # r_Q = eps a - R e_z; v_Q = v_G + w x r_Q, horizontal part only (vertical part is 0)
    rx, ry, rz = eps * ax, eps * ay, eps * az - R
    if full:
        gx, gy = vx, vy
    else:
        gx, gy = 0.0, 0.0
    vqx = gx + wy * rz - wz * ry
    vqy = gy + wz * rx - wx * rz
    # tau1 = r_Q x (e_z - mu v_Q), the torque per unit R_n; f = (-mu vqx, -mu vqy, 1)
    fx, fy, fz = -mu * vqx, -mu * vqy, 1.0
    t1x = ry * fz - rz * fy
    t1y = rz * fx - rx * fz
    t1z = rx * fy - ry * fx
    # I^{-1} v = v / A + (1/C - 1/A)(a.v) a
    inv_a, dinv = 1.0 / A, 1.0 / C - 1.0 / A
    s1 = dinv * (ax * t1x + ay * t1y + az * t1z)
    w1x, w1y, w1z = inv_a * t1x + s1 * ax, inv_a * t1y + s1 * ay, inv_a * t1z + s1 * az
    # w0 = -I^{-1} (C - A) n (w x a); (w x a) is perpendicular to a, so I^{-1} acts as 1/A on it
    k0 = -(C - A) * n / A
    w0x, w0y, w0z = k0 * dax, k0 * day, k0 * daz
    # [w x (w x a)]_z, [w1 x a]_z, [w0 x a]_z
    wwa_z = wx * day - wy * dax
    w1a_z = w1x * ay - w1y * ax
    w0a_z = w0x * ay - w0y * ax
    normal = m * (g - eps * (w0a_z + wwa_z)) / (1.0 + m * eps * w1a_z)
    if full:
        out[0], out[1] = vx, vy
        out[2], out[3] = normal * fx / m, normal * fy / m
    else:
        out[0], out[1], out[2], out[3] = 0.0, 0.0, 0.0, 0.0
    out[4], out[5], out[6] = dax, day, daz
    out[7] = normal * w1x + w0x
    out[8] = normal * w1y + w0y
    out[9] = normal * w1z + w0z
    return normal


# --------------------------------------------------------------------------------------------
# DOP853 on a batch of copies, ported from scipy.integrate._ivp.rk (same tableau and control)
# --------------------------------------------------------------------------------------------

_NS = _dop.N_STAGES  # 12
_A = np.ascontiguousarray(_dop.A)  # (16, 16), rows 13..15: extra stages of the dense output
_B = np.ascontiguousarray(_dop.B)
_C = np.ascontiguousarray(_dop.C)
_E3 = np.ascontiguousarray(_dop.E3)
_E5 = np.ascontiguousarray(_dop.E5)
_D = np.ascontiguousarray(_dop.D)  # (4, 16)


@_jit
def _eval_batch(t, Y, P, full, out, normals):
    for k in range(Y.shape[0]):
        normals[k] = _rhs(Y[k], P[k], full, out[k])


@_jit
def _dense_coeffs(t_old, h, y_old, y_new, f_new, K, P, full, A, C, D, F, tmp, normals):
    """Fill F (7, K, 10) with the DOP853 interpolant of the step [t_old, t_old + h]."""
    nk, nd = y_old.shape
    for s in range(13, 16):
        for k in range(nk):
            for j in range(nd):
                acc = 0.0
                for r in range(s):
                    acc += A[s, r] * K[r, k, j]
                tmp[k, j] = y_old[k, j] + h * acc
        _eval_batch(t_old + C[s] * h, tmp, P, full, K[s], normals)
    for k in range(nk):
        for j in range(nd):
            dy = y_new[k, j] - y_old[k, j]
            F[0, k, j] = dy
            F[1, k, j] = h * K[0, k, j] - dy
            F[2, k, j] = 2.0 * dy - h * (f_new[k, j] + K[0, k, j])
            for i in range(4):
                acc = 0.0
                for r in range(16):
                    acc += D[i, r] * K[r, k, j]
                F[3 + i, k, j] = h * acc


@_jit
def _dense_eval(x, y_old, F, out):
    """y(t_old + x h) from the interpolant (scipy's Dop853DenseOutput)."""
    nk, nd = y_old.shape
    for k in range(nk):
        for j in range(nd):
            v = 0.0
            for i in range(6, -1, -1):
                v += F[i, k, j]
                if (6 - i) % 2 == 0:
                    v *= x
                else:
                    v *= 1.0 - x
            out[k, j] = v + y_old[k, j]


@_jit
def _dop853(Y0, P, full, t_eval, rtol, atol, max_steps, stop_at_contact, A, B, C, E3, E5, D):
    """Integrate K copies from t = 0 to t_eval[-1]; states sampled at t_eval (increasing, >= 0).

    Returns (Ys (T, K, 10), status, n_steps, n_fev, t_invert (K,), t_contact (K,)):
    status 0 success, 1 stopped at a contact loss (stop_at_contact; later samples nan),
    -1 step size too small, -2 max_steps reached. t_invert: first time a_z
    crosses 0 downwards (theta passes pi/2 upwards); t_contact: first time R_n crosses 0
    downwards (contact lost); nan if none.
    """
    nk, nd = Y0.shape
    nt = t_eval.shape[0]
    Ys = np.full((nt, nk, nd), np.nan)
    t_invert = np.full(nk, np.nan)
    t_contact = np.full(nk, np.nan)
    K = np.zeros((16, nk, nd))
    F = np.zeros((7, nk, nd))
    tmp = np.zeros((nk, nd))
    y = Y0.copy()
    y_new = np.zeros((nk, nd))
    f = np.zeros((nk, nd))
    f_new = np.zeros((nk, nd))
    normals = np.zeros(nk)
    normals_new = np.zeros(nk)
    probe = np.zeros((nk, nd))
    probe_f = np.zeros((nk, nd))
    probe_n = np.zeros(nk)
    t_end = t_eval[-1]
    t = 0.0
    ie = 0
    while ie < nt and t_eval[ie] <= 0.0:
        Ys[ie] = y
        ie += 1
    _eval_batch(t, y, P, full, f, normals)
    nfev = 1
    if t_end <= 0.0:
        return Ys, 0, 0, nfev, t_invert, t_contact
    # initial step (scipy's select_initial_step, order 7)
    d0 = 0.0
    d1 = 0.0
    for k in range(nk):
        for j in range(nd):
            sc = atol + abs(y[k, j]) * rtol
            d0 += (y[k, j] / sc) ** 2
            d1 += (f[k, j] / sc) ** 2
    d0 = math.sqrt(d0 / (nk * nd))
    d1 = math.sqrt(d1 / (nk * nd))
    h0 = 1e-6 if (d0 < 1e-5 or d1 < 1e-5) else 0.01 * d0 / d1
    h0 = min(h0, t_end)
    for k in range(nk):
        for j in range(nd):
            tmp[k, j] = y[k, j] + h0 * f[k, j]
    _eval_batch(t + h0, tmp, P, full, probe_f, probe_n)
    nfev += 1
    d2 = 0.0
    for k in range(nk):
        for j in range(nd):
            sc = atol + abs(y[k, j]) * rtol
            d2 += ((probe_f[k, j] - f[k, j]) / sc) ** 2
    d2 = math.sqrt(d2 / (nk * nd)) / h0
    if d1 <= 1e-15 and d2 <= 1e-15:
        h1 = max(1e-6, h0 * 1e-3)
    else:
        h1 = (0.01 / max(d1, d2)) ** (1.0 / 8.0)
    h_abs = min(100 * h0, h1, t_end)
    exponent = -1.0 / 8.0
    steps = 0
    while t < t_end:
        if steps >= max_steps:
            return Ys, -2, steps, nfev, t_invert, t_contact
        min_step = 10.0 * abs(np.nextafter(t, np.inf) - t)
        if h_abs < min_step:
            h_abs = min_step
        rejected = False
        while True:
            if h_abs < min_step:
                return Ys, -1, steps, nfev, t_invert, t_contact
            t_new = t + h_abs
            if t_new > t_end:
                t_new = t_end
            h = t_new - t
            h_abs = abs(h)
            # stages
            K[0] = f
            for s in range(1, _NS):
                for k in range(nk):
                    for j in range(nd):
                        acc = 0.0
                        for r in range(s):
                            acc += A[s, r] * K[r, k, j]
                        tmp[k, j] = y[k, j] + h * acc
                _eval_batch(t + C[s] * h, tmp, P, full, K[s], probe_n)
            for k in range(nk):
                for j in range(nd):
                    acc = 0.0
                    for r in range(_NS):
                        acc += B[r] * K[r, k, j]
                    y_new[k, j] = y[k, j] + h * acc
            _eval_batch(t_new, y_new, P, full, f_new, normals_new)
            K[_NS] = f_new
            nfev += _NS
            # error norm (scipy's DOP853._estimate_error_norm)
            e5 = 0.0
            e3 = 0.0
            for k in range(nk):
                for j in range(nd):
                    sc = atol + max(abs(y[k, j]), abs(y_new[k, j])) * rtol
                    a5 = 0.0
                    a3 = 0.0
                    for r in range(_NS + 1):
                        a5 += E5[r] * K[r, k, j]
                        a3 += E3[r] * K[r, k, j]
                    e5 += (a5 / sc) ** 2
                    e3 += (a3 / sc) ** 2
            if e5 == 0.0 and e3 == 0.0:
                err = 0.0
            else:
                err = h_abs * e5 / math.sqrt((e5 + 0.01 * e3) * (nk * nd))
            if err < 1.0:
                if err == 0.0:
                    factor = 10.0
                else:
                    factor = min(10.0, 0.9 * err**exponent)
                if rejected:
                    factor = min(1.0, factor)
                h_next = h_abs * factor
                break
            h_abs *= max(0.2, 0.9 * err**exponent)
            rejected = True
        steps += 1
        # dense output over [t, t_new] for samples and events
        need_dense = ie < nt and t_eval[ie] <= t_new
        if not need_dense:
            for k in range(nk):
                if (math.isnan(t_invert[k]) and y[k, 6] > 0.0 and y_new[k, 6] <= 0.0) or (
                    math.isnan(t_contact[k]) and normals[k] > 0.0 and normals_new[k] <= 0.0
                ):
                    need_dense = True
        if need_dense:
            _dense_coeffs(t, h, y, y_new, f_new, K, P, full, A, C, D, F, tmp, probe_n)
            nfev += 3
            while ie < nt and t_eval[ie] <= t_new:
                _dense_eval((t_eval[ie] - t) / h, y, F, probe)
                Ys[ie] = probe
                ie += 1
            for k in range(nk):
                inv = math.isnan(t_invert[k]) and y[k, 6] > 0.0 and y_new[k, 6] <= 0.0
                con = math.isnan(t_contact[k]) and normals[k] > 0.0 and normals_new[k] <= 0.0
                if not (inv or con):
                    continue
                for which in range(2):
                    if which == 0 and not inv:
                        continue
                    if which == 1 and not con:
                        continue
                    lo, hi = 0.0, 1.0
                    for _ in range(60):
                        mid = 0.5 * (lo + hi)
                        _dense_eval(mid, y, F, probe)
                        if which == 0:
                            val = probe[k, 6]
                        else:
                            val = _rhs(probe[k], P[k], full, probe_f[k])
                        if val > 0.0:
                            lo = mid
                        else:
                            hi = mid
                    if which == 0:
                        t_invert[k] = t + 0.5 * (lo + hi) * h
                    else:
                        t_contact[k] = t + 0.5 * (lo + hi) * h
        if stop_at_contact:
            for k in range(nk):
                if not math.isnan(t_contact[k]):
                    return Ys, 1, steps, nfev, t_invert, t_contact
        t = t_new
        y[:] = y_new
        f[:] = f_new
        normals[:] = normals_new
        h_abs = h_next
    return Ys, 0, steps, nfev, t_invert, t_contact


# --------------------------------------------------------------------------------------------
# Launch state and derived fields
# --------------------------------------------------------------------------------------------


def initial_vector(theta0, spin, *, theta_dot=0.0, phi_dot=0.0, phi=0.0, vx=0.0, vy=0.0):
    r"""State y0 of a launch, in `euler_reference.initial_vector`'s convention, valid at the poles.

    Axis a = (sin th0 sin ph, -sin th0 cos ph, cos th0); line of nodes e_N = (cos ph, sin ph, 0);
    w = thd e_N + phd e_z + psd a with psd = spin - phd cos th0, so that w . a = spin.
    At theta0 = 0 this gives a = e_z and da/dt = thd e_N x e_z = thd (sin ph, -cos ph, 0):
    the tilt rate tips the axis towards the azimuth that `phi` names (d a / d theta of the axis
    formula). vx, vy: horizontal velocity of the centre of mass.
    """
    s, c = math.sin(theta0), math.cos(theta0)
    sp, cp = math.sin(phi), math.cos(phi)
    a = np.array([s * sp, -s * cp, c])
    e_n = np.array([cp, sp, 0.0])
    psi_dot = spin - phi_dot * c
    w = theta_dot * e_n + phi_dot * np.array([0.0, 0.0, 1.0]) + psi_dot * a
    return np.concatenate([[0.0, 0.0, vx, vy], a, w])


def fields(y, params, variant="full"):
    """Derived fields of states y[..., 10]: theta, spin, normal force, Jellet J, energy, ..."""
    p = _param_vector(params)
    m, R, eps, A, C, g, mu = p
    full = _VARIANTS[variant]
    y = np.asarray(y, float)
    a = y[..., 4:7] / np.linalg.norm(y[..., 4:7], axis=-1, keepdims=True)
    w = y[..., 7:10]
    rho = np.hypot(a[..., 0], a[..., 1])
    theta = np.arctan2(rho, a[..., 2])
    n = np.sum(w * a, axis=-1)
    adot = np.cross(w, a)
    # theta_dot = d/dt atan2(rho, a_z); at rho = 0 the tilt rate is |da/dt|
    with np.errstate(invalid="ignore", divide="ignore"):
        rhodot = np.where(
            rho > 0,
            (a[..., 0] * adot[..., 0] + a[..., 1] * adot[..., 1]) / rho,
            np.linalg.norm(adot, axis=-1),
        )
    theta_dot = a[..., 2] * rhodot - rho * adot[..., 2]
    L = A * w + (C - A) * n[..., None] * a
    jellet = R * L[..., 2] - eps * C * n
    vz = -eps * adot[..., 2]
    trans = (y[..., 2] ** 2 + y[..., 3] ** 2) if full else 0.0
    energy = (
        0.5 * m * (trans + vz**2) + 0.5 * np.sum(w * L, axis=-1) + m * g * (R - eps * a[..., 2])
    )
    flat = y.reshape(-1, 10)
    out = np.empty(10)
    normal = np.array([_rhs(row, p, full, out) for row in flat]).reshape(y.shape[:-1])
    return {
        "theta": theta,
        "theta_dot": theta_dot,
        "phi": np.arctan2(a[..., 0], -a[..., 1]),
        "spin": n,
        "axis": a,
        "omega": w,
        "x": y[..., 0],
        "y": y[..., 1],
        "vx": y[..., 2],
        "vy": y[..., 3],
        "normal_force": normal,
        "jellet": jellet,
        "energy": energy,
    }


# --------------------------------------------------------------------------------------------
# Public entry points
# --------------------------------------------------------------------------------------------


def _check_t_eval(t_eval):
    t_eval = np.asarray(t_eval, float)
    if t_eval.ndim != 1 or t_eval.size == 0 or t_eval[0] < 0 or np.any(np.diff(t_eval) <= 0):
        raise ValueError("t_eval must be a non-empty, strictly increasing 1-D array with t >= 0")
    return t_eval


def solve_batch(
    params_list,
    y0_list,
    t_eval,
    *,
    variant="full",
    rtol=1e-12,
    atol=1e-12,
    max_steps=10_000_000,
    stop_at_contact_loss=False,
):
    """Integrate K copies (parameter dicts and launch states) with one shared DOP853 step sequence.

    Returns (ys (T, K, 10), info) where info has status (0, or 1: stopped at the first contact
    loss of any copy, samples after it nan), n_steps, nfev, t_invert (K,), t_contact (K,).
    Raises RuntimeError if the integrator fails.
    """
    if variant not in _VARIANTS:
        raise ValueError(f"variant must be 'full' or 'so3', got {variant!r}")
    t_eval = _check_t_eval(t_eval)
    P = np.stack([_param_vector(p) for p in params_list])
    Y0 = np.stack([np.asarray(y0, float) for y0 in y0_list])
    if Y0.shape != (P.shape[0], 10):
        raise ValueError(f"need one 10-vector state per parameter dict, got {Y0.shape}")
    ys, status, steps, nfev, t_inv, t_con = _dop853(
        Y0,
        P,
        _VARIANTS[variant],
        t_eval,
        float(rtol),
        float(atol),
        int(max_steps),
        bool(stop_at_contact_loss),
        _A,
        _B,
        _C,
        _E3,
        _E5,
        _D,
    )
    if status < 0:
        why = "step size too small" if status == -1 else f"more than {max_steps} steps"
        raise RuntimeError(f"DOP853 failed ({why})")
    return ys, {
        "status": status,
        "n_steps": steps,
        "nfev": nfev,
        "t_invert": t_inv,
        "t_contact": t_con,
    }


def _scipy_solve(p, y0, t_eval, full, rtol, atol, stop_at_contact_loss):
    def f(t, y):
        out = np.empty(10)
        _rhs(y, p, full, out)
        return out

    def az(t, y):
        return y[6]

    az.direction = -1

    def rn(t, y):
        return _rhs(y, p, full, np.empty(10))

    rn.direction = -1
    rn.terminal = bool(stop_at_contact_loss)
    sol = solve_ivp(
        f,
        (0.0, float(t_eval[-1])),
        y0,
        method="DOP853",
        t_eval=t_eval,
        rtol=rtol,
        atol=atol,
        events=(az, rn),
    )
    if not sol.success:
        raise RuntimeError(f"solve_ivp failed: {sol.message}")
    first = [ev[0] if len(ev) else np.nan for ev in sol.t_events]
    ys = np.full((t_eval.size, 10), np.nan)
    ys[: sol.y.shape[1]] = sol.y.T
    return ys[:, None, :], {
        "status": int(sol.status == 1),
        "n_steps": None,
        "nfev": sol.nfev,
        "t_invert": np.array([first[0]]),
        "t_contact": np.array([first[1]]),
    }


def solve(
    params,
    theta0,
    spin,
    t_eval,
    *,
    theta_dot=0.0,
    phi_dot=0.0,
    phi=0.0,
    vx=0.0,
    vy=0.0,
    variant="full",
    rtol=1e-12,
    atol=1e-12,
    backend="auto",
    stop_at_contact_loss=False,
):
    """Integrate one launch from t = 0; fields sampled at t_eval (launch as `initial_vector`).

    backend: "numba" (the DOP853 port compiled), "python" (the same port uncompiled, slow),
    "scipy" (solve_ivp's DOP853), "auto" (numba if importable, else scipy).
    stop_at_contact_loss: end the integration where R_n first reaches 0 (samples after it nan;
    past a contact loss the equations describe a top glued to the table and may blow up).

    Returns a dict of arrays: t, theta (atan2 of the axis' horizontal norm and a_z, accurate at
    the poles), theta_dot, phi, spin (w . a), axis (T, 3), omega (T, 3), x, y, vx, vy,
    normal_force, jellet, energy, state (T, 10); scalars t_invert (first upward crossing of
    theta = pi/2, nan if none), t_contact_loss (first R_n = 0, nan if none), contact_lost,
    nfev, n_steps.
    """
    t_eval = _check_t_eval(t_eval)
    if not (0.0 <= theta0 <= math.pi):
        raise ValueError(f"theta0 must lie in [0, pi], got {theta0}")
    p = _param_vector(params)
    y0 = initial_vector(theta0, spin, theta_dot=theta_dot, phi_dot=phi_dot, phi=phi, vx=vx, vy=vy)
    if backend == "auto":
        backend = "numba" if HAVE_NUMBA else "scipy"
    if backend == "scipy":
        if variant not in _VARIANTS:
            raise ValueError(f"variant must be 'full' or 'so3', got {variant!r}")
        ys, info = _scipy_solve(p, y0, t_eval, _VARIANTS[variant], rtol, atol, stop_at_contact_loss)
    elif backend == "numba":
        if not HAVE_NUMBA:
            raise ValueError("backend='numba' needs numba; use 'scipy' or 'python'")
        ys, info = solve_batch(
            [params],
            [y0],
            t_eval,
            variant=variant,
            rtol=rtol,
            atol=atol,
            stop_at_contact_loss=stop_at_contact_loss,
        )
    elif backend == "python":
        fn = getattr(_dop853, "py_func", _dop853)
        ys, status, steps, nfev, t_inv, t_con = fn(
            y0[None],
            p[None],
            _VARIANTS[variant],
            t_eval,
            float(rtol),
            float(atol),
            10_000_000,
            bool(stop_at_contact_loss),
            _A,
            _B,
            _C,
            _E3,
            _E5,
            _D,
        )
        if status < 0:
            raise RuntimeError("DOP853 failed")
        info = {
            "status": status,
            "n_steps": steps,
            "nfev": nfev,
            "t_invert": t_inv,
            "t_contact": t_con,
        }
    else:
        raise ValueError(f"backend must be 'auto', 'numba', 'python' or 'scipy', got {backend!r}")
    y = ys[:, 0, :]
    out = fields(y, params, variant)
    t_con = float(info["t_contact"][0])
    out.update(
        t=t_eval,
        state=y,
        t_invert=float(info["t_invert"][0]),
        t_contact_loss=t_con,
        contact_lost=bool(np.isfinite(t_con) or np.any(out["normal_force"] <= 0)),
        stopped=info["status"] == 1,
        nfev=info["nfev"],
        n_steps=info["n_steps"],
    )
    return out
