"""One test (or a few) per numbered point of /work/shared/paper/ERRATA.md, pinned with our code.

Each test states what the paper prints, what is true, and checks it numerically.
"""

from __future__ import annotations

import diffrax
import internal as ti
import jax
import jax.numpy as jnp
import numpy as np
import sympy as sp
from helpers import match_max_rel

import tippejax as tj

GROUP_RATIOS = {
    "Ia": (0.9, 0.03),
    "Ib": (0.6, 0.3),
    "IIa": (0.8, 0.3),
    "IIb": (0.9, 0.3),
    "IIc": (0.97, 0.05),
    "III": (1.5, 0.3),
}


def _params(top):
    return {k: float(getattr(top, k)) for k in ("m", "R", "eps", "A", "C", "g", "mu")}


def _branch_thetas(top):
    """Five angles inside the domain of intermediate states (eq. Exist), 0.03 rad off theta_b."""
    p = _params(top)
    a, e = p["A"] / p["C"], p["eps"] / p["R"]
    lo, hi = 0.0, np.pi
    if a - 1 < -e:
        lo = np.arccos(e / (1 - a))
    elif a - 1 > e:
        hi = np.arccos(e / (1 - a))
    th = lo + (hi - lo) * np.array([0.1, 0.3, 0.5, 0.7, 0.9])
    theta_b = float(tj.thresholds(top).theta_b)
    if np.isfinite(theta_b):
        close = np.abs(th - theta_b) < 0.03
        th = np.where(close, theta_b + np.where(th > theta_b, 0.03, -0.03), th)
    return th


# --------------------------------------------------------------------------------------------
# 1. Factor 2 in the linearised equations
# --------------------------------------------------------------------------------------------


def _printed_polynomial():
    """The characteristic cubic of Sec. 4 / App. B built from the printed T2, T1, W (sympy).

    Returns a numpy function (theta, J, m, g, eps, A, C, R, mu, factor) -> [1, c2, c1, c0], where
    the inertia coefficients are `factor` times the printed T_thth, T_pbpb (factor 1 = literal).
    """
    th, J, m, g, eps, A, C, R, mu, k = sp.symbols("theta J m g epsilon A C R mu k", positive=True)
    D = R**2 * A * sp.sin(th) ** 2 + C * (R * sp.cos(th) - eps) ** 2
    T_thth = k * sp.Rational(1, 2) * (eps**2 * m * sp.sin(th) ** 2 + A)
    T_pbpb = k * sp.Rational(1, 2) * A * C * sp.sin(th) ** 2 / D
    T1_coeff = (
        J
        / (R**2 + eps**2)
        * (R * eps * A * sp.sin(th) ** 2 + C * (R + eps * sp.cos(th)) * (R * sp.cos(th) - eps))
        / D
    )
    W = J**2 / (2 * D) - m * g * eps * sp.cos(th)
    W2 = sp.diff(W, th, 2)
    dT1 = sp.diff(T1_coeff, th)
    h = R - eps * sp.cos(th)
    c2 = mu * m * g * (h**2 / T_thth + sp.sin(th) ** 2 / T_pbpb)
    c1 = ((mu * m * g * h * sp.sin(th)) ** 2 + dT1**2) / (T_thth * T_pbpb) + W2 / T_thth
    c0 = mu * m * g * sp.sin(th) ** 2 * W2 / (T_thth * T_pbpb)
    fn = sp.lambdify((th, J, m, g, eps, A, C, R, mu, k), [c2, c1, c0], "numpy")

    def coeffs(top, theta, Jv, factor):
        p = _params(top)
        c = fn(theta, Jv, p["m"], p["g"], p["eps"], p["A"], p["C"], p["R"], p["mu"], factor)
        return np.array([1.0] + [float(v) for v in c])

    return coeffs


@jax.jit
def _eigen_routes(top, theta, J):
    def one(th, j):
        return (
            ti.reduced_jacobian_eigenvalues(top, th, j),
            ti.vector_field_eigenvalues(top, th, j, model="so3"),
            ti.polynomial_eigenvalues(top, th, j, corrected=True),
            ti.polynomial_eigenvalues(top, th, j, corrected=False),
            ti.characteristic_polynomial(top, th, j, corrected=True),
            ti.characteristic_polynomial(top, th, j, corrected=False),
            ti.effective_potential_d2_closed_form(top, th, j),
        )

    return jax.vmap(one)(theta, J)


def test_1_factor_two_in_linearised_equations():
    printed = _printed_polynomial()
    worst_coeff = worst_corrected = 0.0
    best_literal = np.inf
    n_states = 0
    for group, (a, e) in GROUP_RATIOS.items():
        top = tj.TippeTop.from_ratios(a, e)
        thetas = _branch_thetas(top)
        J = ti.branch_jellet(top, jnp.asarray(thetas))
        red, so3, corr, lit, c_corr, c_lit, d2w = map(
            np.asarray, _eigen_routes(top, jnp.asarray(thetas), J)
        )
        for k, theta in enumerate(thetas):
            n_states += 1
            Jk = float(J[k])
            # The package's literal/corrected polynomials are the printed one with T and 2T.
            for factor, ours in ((1.0, c_lit[k]), (2.0, c_corr[k])):
                ref = printed(top, theta, Jk, factor)
                worst_coeff = max(worst_coeff, float(np.max(np.abs(ours - ref) / np.abs(ref))))
            # True eigenvalues: the reduced Jacobian and the SO(3) model agree with each other...
            assert match_max_rel(red[k], so3[k]) < 1e-8
            # ... and with the corrected polynomial, never with the printed one.
            worst_corrected = max(worst_corrected, match_max_rel(red[k], corr[k]))
            best_literal = min(best_literal, match_max_rel(red[k], lit[k]))
            # The stability criterion W'' > 0 is the same for both (Hurwitz, App. B).
            stable = d2w[k] > 0
            assert (np.max(np.real(lit[k])) < 0) == stable
            assert (np.max(np.real(corr[k])) < 0) == stable
            assert (np.max(np.real(red[k])) < 0) == stable
    assert n_states == 30
    assert worst_coeff < 1e-9, worst_coeff
    assert worst_corrected < 1e-8, worst_corrected
    assert best_literal > 1e-2, best_literal


# --------------------------------------------------------------------------------------------
# 2. "g is strictly increasing"
# --------------------------------------------------------------------------------------------


def _np_g(a, e, x):
    b = (a - 1) * x + e
    return (a - 1) + 4 * b**2 / (a * (1 - x**2) + (x - e) ** 2)


def test_2_g_is_not_monotone_in_general():
    x = np.linspace(-1.0, 1.0, 4001)[1:-1]
    non_monotone = []  # on the branch of intermediate states
    non_monotone_all = []  # on the whole of (-1, 1)
    not_increasing_in_theta = 0
    total = 0
    for a in np.linspace(0.5, 2.0, 31):
        for e in np.linspace(0.02, 0.98, 25):
            top = tj.TippeTop.from_ratios(a, e)
            gx = np.asarray(ti.stability_function(top, jnp.asarray(x)))
            np.testing.assert_allclose(gx, _np_g(a, e, x), rtol=1e-12, atol=1e-12)
            d_all = np.diff(gx)
            if (d_all > 0).any() and (d_all < 0).any():
                non_monotone_all.append((a, e))
            # Restrict to the branch of intermediate states, where g matters.
            on_branch = (a - 1) * x + e > 0
            d = np.diff(gx[on_branch])
            total += 1
            if (d > 0).any() and (d < 0).any():
                non_monotone.append((a, e))
            # "strictly increasing in theta" = strictly decreasing in x = cos(theta).
            if not np.all(d < 0):
                not_increasing_in_theta += 1
    assert len(non_monotone_all) > total // 4  # 328 of 775 on this grid
    assert len(non_monotone) > 0  # 1 of 775: (A/C, eps/R) = (0.75, 0.5)
    # The paper's claim (g strictly increasing in theta on the branch) fails on most of the grid
    # (648 of 775 here; ERRATA: about 3/4).
    assert not_increasing_in_theta > total // 2
    # A concrete point: up and down along its branch.
    a, e = non_monotone[0]
    top = tj.TippeTop.from_ratios(a, e)
    gx = np.asarray(ti.stability_function(top, jnp.asarray(x)))[(a - 1) * x + e > 0]
    assert np.max(np.diff(gx)) > 0 > np.min(np.diff(gx))


def test_2_partial2_f_on_branch_is_g_J2_over_K_and_decreasing():
    d2f = jax.vmap(
        jax.grad(lambda top, J, x: ti.intermediate_condition(top, J, x), argnums=2),
        in_axes=(None, 0, 0),
    )
    tops = [tj.TippeTop.from_ratios(a, e) for a, e in GROUP_RATIOS.values()]
    tops += [
        tj.TippeTop.from_ratios(a, e) for a, e in ((0.55, 0.5), (1.2, 0.4), (0.7, 0.2), (1.0, 0.6))
    ]
    worst = 0.0
    for top in tops:
        p = _params(top)
        K = p["m"] * p["g"] * p["eps"] * p["R"] ** 2 * p["C"]
        lo, hi = 0.0, np.pi
        a, e = p["A"] / p["C"], p["eps"] / p["R"]
        if a - 1 < -e:
            lo = np.arccos(e / (1 - a))
        elif a - 1 > e:
            hi = np.arccos(e / (1 - a))
        theta = np.linspace(lo, hi, 402)[1:-1]
        x = np.cos(theta)
        J = np.asarray(ti.branch_jellet(top, jnp.asarray(theta)))
        assert np.all(np.isfinite(J))
        ad = np.asarray(d2f(top, jnp.asarray(J), jnp.asarray(x)))
        # Independent: the paper's formula for partial_2 f (numpy).
        b = (a - 1) * x + e
        P = a * (1 - x**2) + (x - e) ** 2
        formula = J**2 / K * (a - 1) + 4 * b * P  # as printed in Sec. 4
        np.testing.assert_allclose(ad, formula, rtol=1e-9, atol=1e-12 * np.max(np.abs(formula)))
        g_branch = np.asarray(ti.stability_function(top, jnp.asarray(x)))
        target = g_branch * J**2 / K
        scale = np.max(np.abs(target))
        worst = max(worst, float(np.max(np.abs(ad - target)) / scale))
        # Strictly decreasing in x along the branch (x decreasing with theta: increasing in theta).
        order = np.argsort(x)
        assert np.all(np.diff(ad[order]) < 0)
    assert worst < 1e-10, worst


def test_2_g_for_A_equal_C():
    theta = np.linspace(0.0, np.pi, 201)
    for e in (0.1, 0.3, 0.6, 0.9):
        top = tj.TippeTop.from_ratios(1.0, e)
        g = np.asarray(ti.stability_function(top, jnp.asarray(np.cos(theta))))
        ref = 4 * e**2 / (1 + e**2 - 2 * e * np.cos(theta))
        np.testing.assert_allclose(g, ref, rtol=1e-13)
        assert np.all(np.diff(g) < 0)  # strictly decreasing in theta, contrary to the paper


# --------------------------------------------------------------------------------------------
# 3. Footnote on n2/n1
# --------------------------------------------------------------------------------------------


def test_3_footnote_n2_over_n1_and_jellet_thresholds():
    a = np.linspace(0.5, 2.0, 301)
    e = np.linspace(0.0, 1.0, 302)[1:-1]
    A, E = np.meshgrid(a, e, indexing="ij")
    tops = tj.TippeTop.from_ratios(A, E)
    group = np.array(tj.GROUPS)[np.asarray(ti.group_index(tops))]
    th = tj.thresholds(tops)
    n1, n2, J1, J2 = (np.asarray(v) for v in (th.n1, th.n2, th.J1, th.J2))
    iib = group == "IIb"
    iic = group == "IIc"
    assert iib.sum() > 10000 and iic.sum() > 10
    # The footnote as printed fails on part of IIb ...
    counterexamples = iib & (n2**2 / n1**2 < 1)
    assert counterexamples.sum() > 0
    # e.g. this one, checked from the closed forms of eqs. n1, n2 in numpy:
    i, j = np.argwhere(counterexamples)[0]
    ai, ei = A[i, j], E[i, j]
    ratio = (1 + ei) ** 2 * (ai - 1 + ei) / ((1 - ei) ** 2 * (1 + ei - ai))
    assert ratio < 1
    np.testing.assert_allclose(n2[i, j] ** 2 / n1[i, j] ** 2, ratio, rtol=1e-12)
    # ... while the Jellet statement holds everywhere.
    assert np.all(J2[iib] > J1[iib])
    assert np.all(J2[iic] < J1[iic])
    assert np.all(n2[iic] < n1[iic])  # the IIc half of the footnote holds
    # J1, J2 are the branch ends, independently of the threshold formulas.
    ends = [np.asarray(ti.branch_jellet(tops, jnp.full(A.shape, t))) for t in (1e-8, np.pi - 1e-8)]
    ii = iib | iic
    np.testing.assert_allclose(ends[0][ii], J1[ii], rtol=1e-10)
    np.testing.assert_allclose(ends[1][ii], J2[ii], rtol=1e-10)


# --------------------------------------------------------------------------------------------
# 4. Vertical states in the reduced chart
# --------------------------------------------------------------------------------------------


def test_4_pole_eigenvalues_need_a_regular_chart():
    top = tj.default_top()
    assert tj.classify(top) == "IIb"
    p = _params(top)
    n0 = 60.0
    J = p["C"] * (p["R"] - p["eps"]) * n0
    true = np.sort_complex(
        np.asarray(ti.vector_field_eigenvalues(top, 0.0, J, model="so3", pole=True))
    )
    printed_true = np.sort_complex(
        np.array([-4.77 - 4.64j, -4.77 + 4.64j, 0.76 - 71.3j, 0.76 + 71.3j])
    )
    assert true.shape == (4,)
    # To the printed precision (2 decimals, 3 significant digits for 71.3).
    np.testing.assert_allclose(true.real, printed_true.real, atol=0.005)
    np.testing.assert_allclose(true.imag, printed_true.imag, atol=0.05)
    np.testing.assert_allclose(np.abs(true.imag[:2]), 4.64, atol=0.005)
    # The paper's (corrected) polynomial as theta0 -> 0 has a finite limit ...
    limits = [
        np.sort_complex(np.asarray(ti.polynomial_eigenvalues(top, t, J)))
        for t in (1e-4, 1e-5, 1e-6)
    ]
    np.testing.assert_allclose(limits[1], limits[2], rtol=1e-8)
    limit = limits[2]
    printed_limit = np.sort_complex(np.array([-4.28 - 98.3j, -4.28 + 98.3j, 0.54]))
    np.testing.assert_allclose(limit.real, printed_limit.real, atol=0.005)
    np.testing.assert_allclose(np.abs(limit.imag), np.abs(printed_limit.imag), atol=0.05)
    # ... which is not the true spectrum at the pole (3 roots + the removed 0 versus 4 values).
    full_limit = np.concatenate([limit, [0.0]])
    assert match_max_rel(true, full_limit) > 0.2
    # The full model with translation, also in a regular chart, agrees with SO(3) on the unstable
    # pair and has an extra stable pair.
    full = np.asarray(ti.vector_field_eigenvalues(top, 0.0, J, model="full", pole=True))
    assert full.shape == (6,)
    unstable = full[np.real(full) > 0]
    assert len(unstable) == 2 and np.allclose(np.abs(unstable.imag), 71.3, atol=0.1)
    # The polynomial limit does reproduce the threshold n1 (stability verdict), as the paper says.
    n1 = float(tj.thresholds(top).n1)
    for factor, expect_stable in ((0.999, True), (1.001, False)):
        Jn = p["C"] * (p["R"] - p["eps"]) * n1 * factor
        poly = np.asarray(ti.polynomial_eigenvalues(top, 1e-6, Jn))
        so3 = np.asarray(ti.vector_field_eigenvalues(top, 0.0, Jn, model="so3", pole=True))
        assert (np.max(poly.real) < 0) == expect_stable
        assert (np.max(so3.real) < 0) == expect_stable


# --------------------------------------------------------------------------------------------
# 5. R'_n can vanish
# --------------------------------------------------------------------------------------------


def test_5_normal_force_denominator_vanishes():
    top = tj.default_top()
    p = _params(top)

    def closed_form(theta, thd):
        h = p["R"] - p["eps"] * np.cos(theta)
        hp = p["eps"] * np.sin(theta)
        return 1 / p["m"] + hp * (hp + p["mu"] * h**2 * thd) / p["A"]

    rng = np.random.default_rng(0)
    for theta in (0.4, 1.0, 2.0, 2.8):
        h = p["R"] - p["eps"] * np.cos(theta)
        hp = p["eps"] * np.sin(theta)
        thd_star = -(p["A"] / p["m"] + hp**2) / (p["mu"] * h**2 * hp)
        assert abs(closed_form(theta, thd_star)) < 1e-9 / p["m"]
        values = []
        for factor in (0.99, 0.999, 1.001, 1.01):
            spin, phid = rng.uniform(-100, 100, 2)
            y = tj.initial_state(
                top, theta=theta, spin=spin, theta_dot=factor * thd_star, phi_dot=phid
            )
            den = float(tj.normal_force_denominator(top, y, model="so3"))
            ref = closed_form(theta, factor * thd_star)
            assert abs(den - ref) <= 1e-10 / p["m"], (theta, factor, den, ref)
            values.append(den)
        # Positive before the threshold, negative beyond it (thd more negative).
        assert values[0] > 0 and values[1] > 0 and values[2] < 0 and values[3] < 0
        # Across the zero, R'_n = numerator / denominator jumps by orders of magnitude.
        rn = [
            float(
                tj.normal_force(
                    top,
                    tj.initial_state(top, theta=theta, spin=0.0, theta_dot=f * thd_star),
                    model="so3",
                )
            )
            for f in (0.9999, 1.0001)
        ]
        assert abs(rn[0]) > 100 * p["m"] * p["g"] and abs(rn[1]) > 100 * p["m"] * p["g"]
        assert np.sign(rn[0]) != np.sign(rn[1])


# --------------------------------------------------------------------------------------------
# 6. R_n < 0 happens
# --------------------------------------------------------------------------------------------


def test_6_normal_force_becomes_negative_during_the_rise():
    top = tj.default_top()
    p = _params(top)
    y0 = tj.initial_state(top, theta=0.1, spin=200.0)
    ts = jnp.linspace(0.0, 6.0, 12001)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(ti.full_vector_field),
        diffrax.Tsit5(),
        t0=0.0,
        t1=6.0,
        dt0=None,
        y0=y0,
        args=top,
        stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-10),
        saveat=diffrax.SaveAt(ts=ts),
        max_steps=200_000,
    )
    assert sol.result == diffrax.RESULTS.successful
    t = np.asarray(ts)
    rn = np.asarray(tj.normal_force(top, sol.ys))
    below = np.nonzero(rn < 0)[0]
    assert len(below) > 0
    k = below[0]
    t_cross = t[k - 1] + (t[k] - t[k - 1]) * rn[k - 1] / (rn[k - 1] - rn[k])
    assert abs(t_cross - 5.19) < 0.05, t_cross
    assert np.all(rn[t < 5.0] > 0)
    # R_n is the vertical Newton force: m h'' = R_n - m g, with h = R - eps a_Z (finite
    # differences on the saved trajectory, independent of the closed form).
    h = p["R"] - p["eps"] * np.asarray(sol.ys.axis)[:, 2]
    dt = t[1] - t[0]
    hdd = (h[2:] - 2 * h[1:-1] + h[:-2]) / dt**2
    newton = p["m"] * (hdd + p["g"])
    smooth = t[1:-1] < 5.0
    err = np.abs(newton - rn[1:-1])[smooth]
    assert np.max(err) < 2e-3 * p["m"] * p["g"], np.max(err)
    # Jellet is conserved along the way (sanity of the integration).
    J = np.asarray(tj.jellet(top, sol.ys))
    np.testing.assert_allclose(J, J[0], rtol=1e-8)
