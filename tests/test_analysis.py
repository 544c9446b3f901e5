"""Cross-checks of the steady-state and stability analysis (paper Sec. 3-5 and App. B).

Every check compares two routes that share as little code as possible: autodiff against the
closed form, sympy against the closed form, closed-form thresholds against root finding on the
potential and against the linearised vector fields, the package classifier against a
re-implementation of the paper's inequalities, and the five eigenvalue routes against each other.
"""

from __future__ import annotations

import internal as ti
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize
import sympy as sp
from helpers import GROUP_RATIOS, match_max_rel

import tippejax as tj


def _top(group):
    a, e = GROUP_RATIOS[group]
    return tj.TippeTop.from_ratios(a, e)


# --------------------------------------------------------------------------------------------
# Independent re-implementations (numpy, from the paper's text)
# --------------------------------------------------------------------------------------------


def paper_group(a, e):
    """Group of a top from the inequalities of Sec. 5 ("Tippe Top Classification"), in numpy."""
    a = np.asarray(a, dtype=float)
    e = np.asarray(e, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        x_b = (e - np.sqrt(3.0) / 3.0 * np.sqrt(a) * np.sqrt(1.0 - a - e**2)) / (1.0 - a)
    out = np.full(a.shape, "", dtype=object)
    g1 = a - 1.0 < -e
    g3 = a - 1.0 > e
    g2 = ~g1 & ~g3
    out[g1 & (x_b < -1)] = "Ia"
    out[g1 & (x_b > -1)] = "Ib"
    out[g3] = "III"
    cond = (a - 1.0) < -(e**2)
    iia = g2 & cond & (np.abs(x_b) < 1)
    iic = g2 & cond & (x_b < -1)
    out[iia] = "IIa"
    out[iic] = "IIc"
    out[g2 & ~iia & ~iic] = "IIb"
    return out


def _params(top):
    return {k: float(getattr(top, k)) for k in ("m", "R", "eps", "A", "C", "g", "mu")}


def np_f(p, J, x):
    """f(J^2, x) of eq. define_intstates, numpy."""
    a, e = p["A"] / p["C"], p["eps"] / p["R"]
    K = p["m"] * p["g"] * p["C"] * p["R"] ** 2 * p["eps"]
    return J**2 / K * ((a - 1) * x + e) - (a * (1 - x**2) + (x - e) ** 2) ** 2


def np_d(p, theta):
    return (
        p["R"] ** 2 * p["A"] * np.sin(theta) ** 2
        + p["C"] * (p["R"] * np.cos(theta) - p["eps"]) ** 2
    )


def branch_domain(top):
    """(lo, hi): theta-interval where intermediate states exist (eq. Exist), from the paper."""
    p = _params(top)
    a, e = p["A"] / p["C"], p["eps"] / p["R"]
    if a - 1 < -e:  # Group I: theta > theta_c
        return float(np.arccos(e / (1 - a))), float(np.pi)
    if a - 1 > e:  # Group III: theta < theta_c
        return 0.0, float(np.arccos(e / (1 - a)))
    return 0.0, float(np.pi)


def paper_stable(group, theta, theta_b):
    """Stability of the intermediate state at theta predicted by the group (Sec. 5)."""
    if group in ("IIb", "III"):
        return True
    if group in ("Ia", "IIc"):
        return False
    return theta > theta_b  # IIa, Ib


FRACTIONS = (0.08, 0.25, 0.45, 0.62, 0.8, 0.93)


def branch_thetas(top):
    """Six angles inside the branch domain, kept 0.03 rad away from the bifurcation angle."""
    lo, hi = branch_domain(top)
    th = lo + (hi - lo) * np.asarray(FRACTIONS)
    theta_b = float(tj.thresholds(top).theta_b)
    if np.isfinite(theta_b):
        close = np.abs(th - theta_b) < 0.03
        th = np.where(close, theta_b + np.where(th > theta_b, 0.03, -0.03), th)
    return th


# --------------------------------------------------------------------------------------------
# Group points
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("group", tj.GROUPS)
def test_group_points_classified(group):
    a, e = GROUP_RATIOS[group]
    top = _top(group)
    assert paper_group(a, e) == group
    assert tj.classify(top) == group
    assert tj.GROUPS[int(ti.group_index(top))] == group


# --------------------------------------------------------------------------------------------
# W'': autodiff, closed form, sympy
# --------------------------------------------------------------------------------------------

_THETA_GRID = np.linspace(0.0, np.pi, 62)[1:-1]


@pytest.mark.parametrize("group", tj.GROUPS)
def test_d2W_autodiff_equals_closed_form(group):
    top = _top(group)
    p = _params(top)
    theta = jnp.asarray(_THETA_GRID)
    j_scale = p["C"] * p["R"] * np.sqrt(p["m"] * p["g"] * p["eps"] / p["C"])
    worst = 0.0
    for j in (0.0, 0.3, 1.0, 2.0, 7.0):
        J = j * j_scale
        ad = np.asarray(tj.effective_potential_derivative(top, theta, J, order=2))
        cf = np.asarray(ti.effective_potential_d2_closed_form(top, theta, J))
        # Scale of the individual terms (W'' itself crosses zero on the grid).
        d = np_d(p, _THETA_GRID)
        scale = p["m"] * p["g"] * p["eps"] + J**2 * p["R"] ** 2 * p["C"] / d**2
        scale = np.maximum(np.abs(cf), scale)
        rel = np.abs(ad - cf) / scale
        worst = max(worst, float(rel.max()))
        assert np.all(np.isfinite(ad)) and np.all(np.isfinite(cf))
    print(f"W'' autodiff vs closed form [{group}]: max rel diff = {worst:.2e}")
    assert worst < 1e-10, worst


def test_d2W_sympy_matches_closed_form():
    th, J, m, g, eps, A, C, R = sp.symbols("theta J m g epsilon A C R", positive=True)
    D = R**2 * A * sp.sin(th) ** 2 + C * (R * sp.cos(th) - eps) ** 2
    W = J**2 / (2 * D) - m * g * eps * sp.cos(th)
    W2 = sp.diff(W, th, 2)
    # eq. stabilityba of the paper, transcribed.
    B = (A - C) * sp.cos(th) + C * eps / R
    closed = m * g * eps * sp.cos(th) - J**2 * R**2 * C / D**2 * (
        -(A / C - 1) * sp.sin(th) ** 2
        + B / C * sp.cos(th)
        - 4
        * B**2
        / C**2
        * sp.sin(th) ** 2
        / ((A / C) * sp.sin(th) ** 2 + (sp.cos(th) - eps / R) ** 2)
    )
    # Exact identity: write in s = sin, c = cos and reduce modulo s^2 + c^2 - 1.
    s, c = sp.symbols("s c")
    diff = sp.together((W2 - closed).subs({sp.sin(th): s, sp.cos(th): c}))
    num = sp.expand(sp.numer(diff))
    reduced = sp.reduced(num, [s**2 + c**2 - 1], s, c)[1]
    assert sp.expand(reduced) == 0
    # And the package closed form against the sympy-derived W'' (float64).
    fn = sp.lambdify((th, J, m, g, eps, A, C, R), W2, "numpy")
    worst = 0.0
    for group in tj.GROUPS:
        top = _top(group)
        p = _params(top)
        j0 = p["C"] * p["R"] * np.sqrt(p["m"] * p["g"] * p["eps"] / p["C"])
        for J_ in (0.5 * j0, 3.0 * j0):
            ref = fn(_THETA_GRID, J_, p["m"], p["g"], p["eps"], p["A"], p["C"], p["R"])
            got = np.asarray(
                ti.effective_potential_d2_closed_form(top, jnp.asarray(_THETA_GRID), J_)
            )
            scale = (
                p["m"] * p["g"] * p["eps"]
                + J_**2 * p["R"] ** 2 * p["C"] / np_d(p, _THETA_GRID) ** 2
            )
            worst = max(worst, float(np.max(np.abs(ref - got) / scale)))
    assert worst < 1e-12, worst


# --------------------------------------------------------------------------------------------
# Thresholds n1, n2, J1, J2
# --------------------------------------------------------------------------------------------


@jax.jit
def _d2W_autodiff(top, theta, J):
    return tj.effective_potential_derivative(top, theta, J, order=2)


def _pole_d2W(top, pole, n):
    """W''(0) or W''(pi) (autodiff) for the spin n at that pole."""
    p = _params(top)
    lever = p["R"] - p["eps"] if pole == "north" else p["R"] + p["eps"]
    theta = 0.0 if pole == "north" else np.pi
    return float(_d2W_autodiff(top, jnp.asarray(theta), jnp.asarray(p["C"] * lever * n)))


@pytest.mark.parametrize("group", tj.GROUPS)
def test_thresholds_are_sign_changes_of_pole_d2W(group):
    top = _top(group)
    p = _params(top)
    th = tj.thresholds(top)
    scale = np.sqrt(p["m"] * p["g"] * p["eps"] / p["C"])
    spins = scale * np.logspace(-2, 3, 41)
    for pole, value in (("north", float(th.n1)), ("south", float(th.n2))):
        w = np.array([_pole_d2W(top, pole, n) for n in spins])
        changes = np.nonzero(np.sign(w[1:]) != np.sign(w[:-1]))[0]
        if not np.isfinite(value):
            assert len(changes) == 0
            # Group I: north always stable; Group III: south always unstable.
            assert (
                group.startswith("I")
                and not group.startswith("II")
                and pole == "north"
                and np.all(w > 0)
            ) or (group == "III" and pole == "south" and np.all(w < 0))
            continue
        assert len(changes) == 1
        k = changes[0]
        root = scipy.optimize.brentq(
            lambda n: _pole_d2W(top, pole, n), spins[k], spins[k + 1], xtol=1e-15, rtol=1e-15
        )
        assert abs(root - value) <= 1e-8 * value, (pole, root, value)
        # Stable side: below n1 at the north pole, above n2 at the south pole.
        if pole == "north":
            assert w[0] > 0 and w[-1] < 0
        else:
            assert w[0] < 0 and w[-1] > 0
    # Which thresholds exist (eqs. n1, n2).
    assert np.isfinite(th.n1) == (group not in ("Ia", "Ib"))
    assert np.isfinite(th.n2) == (group != "III")


@pytest.mark.parametrize("group", tj.GROUPS)
def test_pole_threshold_from_vector_fields(group):
    top = _top(group)
    th = tj.thresholds(top)
    for pole, value in (("north", float(th.n1)), ("south", float(th.n2))):
        for model in ("so3", "full"):
            got = float(ti.pole_threshold(top, pole=pole, model=model))
            if np.isfinite(value):
                print(
                    f"[{group}] {pole} threshold from the {model} field: rel diff "
                    f"{abs(got - value) / value:.2e}"
                )
                assert abs(got - value) <= 1e-8 * value, (pole, model, got, value)
            else:
                assert np.isnan(got), (pole, model, got)


@pytest.mark.parametrize("group", tj.GROUPS)
def test_jellet_thresholds_are_branch_ends(group):
    top = _top(group)
    p = _params(top)
    th = tj.thresholds(top)
    J1 = p["C"] * (p["R"] - p["eps"]) * float(th.n1)
    J2 = p["C"] * (p["R"] + p["eps"]) * float(th.n2)
    np.testing.assert_allclose(float(th.J1), J1, rtol=1e-14)
    np.testing.assert_allclose(float(th.J2), J2, rtol=1e-14)
    ends = np.asarray(ti.branch_jellet(top, jnp.array([1e-6, np.pi - 1e-6])))
    for end, ref in zip(ends, (J1, J2)):
        if np.isfinite(ref):
            assert abs(end - ref) <= 1e-9 * ref, (end, ref)
        else:
            assert np.isnan(end)
    # Independent: J^2 on the branch from f(J^2, x) = 0 solved for J^2 (numpy) at x = +-1.
    for x, ref in ((1.0, J1), (-1.0, J2)):
        a, e = p["A"] / p["C"], p["eps"] / p["R"]
        b = (a - 1) * x + e
        if b > 0:
            K = p["m"] * p["g"] * p["C"] * p["R"] ** 2 * p["eps"]
            j2 = K * (x - e) ** 4 / b
            assert abs(np.sqrt(j2) - ref) <= 1e-12 * ref
        else:
            assert np.isnan(ref)


def test_n2_at_least_n_star_on_grid():
    a = np.linspace(0.5, 2.0, 60)
    e = np.linspace(0.0, 1.0, 62)[1:-1]
    A, E = np.meshgrid(a, e, indexing="ij")
    top = tj.TippeTop.from_ratios(A, E)
    th = tj.thresholds(top)
    n2 = np.asarray(th.n2)
    n_star = 2 * np.sqrt(np.asarray(top.A * top.m * top.g * top.eps)) / np.asarray(top.C)
    ok = np.isfinite(n2)
    assert ok.sum() > 100
    assert np.all(n2[ok] ** 2 >= n_star[ok] ** 2 * (1 - 1e-12))


# --------------------------------------------------------------------------------------------
# Classification
# --------------------------------------------------------------------------------------------


def test_group_index_matches_paper_inequalities_on_grid():
    a = np.linspace(0.5, 2.0, 60)
    e = np.linspace(0.0, 1.0, 62)[1:-1]
    A, E = np.meshgrid(a, e, indexing="ij")
    ref = paper_group(A, E)
    got = np.array(tj.GROUPS)[np.asarray(ti.group_index(tj.TippeTop.from_ratios(A, E)))]
    assert got.shape == (60, 60)
    mismatch = np.argwhere(got != ref)
    assert len(mismatch) == 0, [(A[i, j], E[i, j], got[i, j], ref[i, j]) for i, j in mismatch[:5]]
    # The grid visits every group (Ia and IIc are small regions near A/C ~ 0.9, eps/R < 0.07).
    present = set(ref.ravel())
    assert present >= {"Ib", "IIa", "IIb", "III"}
    # classify on a batch agrees with group_index.
    np.testing.assert_array_equal(tj.classify(tj.TippeTop.from_ratios(A, E)), got)
    # Refined grid for the two small groups.
    a2 = np.linspace(0.75, 0.999, 60)
    e2 = np.linspace(0.0, 0.08, 62)[1:-1]
    A2, E2 = np.meshgrid(a2, e2, indexing="ij")
    ref2 = paper_group(A2, E2)
    got2 = np.array(tj.GROUPS)[np.asarray(ti.group_index(tj.TippeTop.from_ratios(A2, E2)))]
    np.testing.assert_array_equal(got2, ref2)
    assert {"Ia", "IIc"} <= set(ref2.ravel())


def _fine_root_count(top, J, n=20011):
    """Number of sign changes of f(J^2, cos theta) on a fine grid of the branch domain (numpy)."""
    lo, hi = branch_domain(top)
    theta = np.linspace(lo, hi, n)[1:-1]
    f = np_f(_params(top), J, np.cos(theta))
    positive = f > 0
    return int(np.sum(positive[1:] != positive[:-1]))


def _j_values(top):
    th = tj.thresholds(top)
    js = list(np.asarray(ti.branch_jellet(top, jnp.asarray(branch_thetas(top)))))
    for ref in (float(th.J1), float(th.J2)):
        if np.isfinite(ref):
            js += [ref * (1 - 1e-3), ref * (1 + 1e-3)]
    js += [0.1 * min(js), 2 * max(js)]
    return [float(j) for j in js]


@pytest.mark.parametrize("group", tj.GROUPS)
def test_steady_states_agree_with_group(group):
    top = _top(group)
    p = _params(top)
    th = tj.thresholds(top)
    n1, n2 = float(th.n1), float(th.n2)
    theta_b = float(th.theta_b)
    lo, hi = branch_domain(top)
    branch_th = branch_thetas(top)
    branch_j = np.asarray(ti.branch_jellet(top, jnp.asarray(branch_th)))
    n_two = 0
    mixed = 0
    for J in _j_values(top):
        ss = tj.steady_states(top, J)
        states = ss.intermediate
        # Count agrees with an independent sign-change count of f.
        assert len(states) == _fine_root_count(top, J), (J, states)
        n_two += len(states) == 2
        if len(states) == 2 and states[0][1] != states[1][1]:
            mixed += 1
            stable = [t for t, s in states if s]
            unstable = [t for t, s in states if not s]
            assert unstable[0] < theta_b < stable[0]
        for theta, stable in states:
            assert lo < theta < hi, (group, theta, lo, hi)  # none on the wrong side of theta_c
            assert stable == paper_stable(group, theta, theta_b), (group, theta, stable)
            # A critical point of W, and f = 0 there.
            w1 = float(tj.effective_potential_derivative(top, theta, J, order=1))
            assert abs(w1) <= 1e-9 * p["m"] * p["g"] * p["eps"], w1
            x = np.cos(theta)
            f = float(ti.intermediate_condition(top, J, x))
            a, e = p["A"] / p["C"], p["eps"] / p["R"]
            assert abs(f) <= 1e-10 * (a * (1 - x**2) + (x - e) ** 2) ** 2, f
            assert abs(f - np_f(p, J, x)) <= 1e-12 * (a * (1 - x**2) + (x - e) ** 2) ** 2
            # The stored W'' and g agree with their definitions.
            k = int(np.nanargmin(np.abs(np.asarray(ss.intermediate_theta) - theta)))
            assert bool(ss.intermediate_valid[k])
            np.testing.assert_allclose(
                float(ss.intermediate_g[k]), float(ti.stability_function(top, x)), rtol=1e-12
            )
            assert (float(ss.intermediate_d2W[k]) > 0) == stable
        # If J is a branch value, its state is found.
        for t_i, j_i in zip(branch_th, branch_j):
            if J == float(j_i):
                assert min(abs(t - t_i) for t, _ in states) < 1e-8
        # Vertical states.
        n0 = J / (p["C"] * (p["R"] - p["eps"]))
        npi = -J / (p["C"] * (p["R"] + p["eps"]))
        np.testing.assert_allclose(np.asarray(ss.vertical_spin), [n0, npi], rtol=1e-14)
        north = bool(ss.vertical_stable[0])
        south = bool(ss.vertical_stable[1])
        assert north == (True if np.isnan(n1) else abs(n0) < n1), (J, n0, n1)
        assert south == (False if np.isnan(n2) else abs(npi) > n2), (J, npi, n2)
        # The regular-chart linearisations at the poles agree (ERRATA 4: chart regular there).
        for k, flag in enumerate((north, south)):
            for ev in (ss.vertical_eigenvalues_so3[k], ss.vertical_eigenvalues_full[k]):
                assert (float(np.max(np.real(np.asarray(ev)))) < 0) == flag
    if group in ("IIa", "Ib"):
        assert mixed >= 1  # a stable and an unstable state for one J, on either side of theta_b
    if group in ("Ia", "III", "IIb", "IIc"):
        assert n_two == 0  # monotone branch: at most one state per J


def test_two_states_in_bifurcating_groups():
    for group in ("IIa", "Ib"):
        top = _top(group)
        theta_b = float(tj.thresholds(top).theta_b)
        lo, hi = branch_domain(top)
        # J on the stable piece, close enough to J(theta_b) to be below both branch ends.
        J = float(ti.branch_jellet(top, theta_b + 0.3 * (hi - theta_b)))
        states = tj.steady_states(top, J).intermediate
        assert len(states) == 2, (group, states)
        (t0, s0), (t1, s1) = sorted(states)
        assert t0 < theta_b < t1 and not s0 and s1


# --------------------------------------------------------------------------------------------
# Stability routes
# --------------------------------------------------------------------------------------------


@jax.jit
def _routes(top, theta, J):
    def one(th, j):
        return dict(
            reduced=ti.reduced_jacobian_eigenvalues(top, th, j),
            poly=ti.polynomial_eigenvalues(top, th, j, corrected=True),
            literal=ti.polynomial_eigenvalues(top, th, j, corrected=False),
            so3=ti.vector_field_eigenvalues(top, th, j, model="so3"),
            full=ti.vector_field_eigenvalues(top, th, j, model="full"),
            d2W=ti.effective_potential_d2_closed_form(top, th, j),
            g=ti.stability_function(top, jnp.cos(th)),
        )

    return jax.vmap(one)(theta, J)


def _route_data(group):
    top = _top(group)
    thetas = branch_thetas(top)
    J = ti.branch_jellet(top, jnp.asarray(thetas))
    out = jax.tree_util.tree_map(np.asarray, _routes(top, jnp.asarray(thetas), J))
    return top, thetas, out


@pytest.mark.parametrize("group", tj.GROUPS)
def test_stability_routes_agree(group):
    top, thetas, r = _route_data(group)
    th = tj.thresholds(top)
    worst_poly = worst_so3 = 0.0
    best_literal = np.inf
    for k, theta in enumerate(thetas):
        red = r["reduced"][k]
        assert red.shape == (3,) and r["so3"][k].shape == (3,) and r["full"][k].shape == (5,)
        worst_poly = max(worst_poly, match_max_rel(red, r["poly"][k]))
        worst_so3 = max(worst_so3, match_max_rel(red, r["so3"][k]))
        best_literal = min(best_literal, match_max_rel(red, r["literal"][k]))
        stable_g = r["g"][k] > 0
        assert (r["d2W"][k] > 0) == stable_g
        for key in ("reduced", "poly", "so3", "full"):
            assert (np.max(np.real(r[key][k])) < 0) == stable_g, (group, theta, key)
        # The printed polynomial is wrong, but its stability verdict is the same (Hurwitz).
        assert (np.max(np.real(r["literal"][k])) < 0) == stable_g
        assert stable_g == paper_stable(group, theta, float(th.theta_b))
    print(
        f"[{group}] reduced Jacobian vs corrected cubic: {worst_poly:.2e}; vs SO(3) co-rotating: "
        f"{worst_so3:.2e}; vs printed cubic (closest): {best_literal:.2e}"
    )
    assert worst_poly < 1e-8, worst_poly
    assert worst_so3 < 1e-8, worst_so3
    assert best_literal > 1e-2, best_literal


# Regression: steady_states once dropped states at large J (Bisection's |f| < atol test
# could not be met for f ~ J^2); it now bisects the normalised f / (k + P^2).
def test_steady_states_large_jellet_near_theta_c():
    top = tj.TippeTop.from_ratios(1.5, 0.3)  # Group III: exactly one state for every J > J1
    p = _params(top)
    lo, hi = branch_domain(top)
    missed = []
    for J in np.linspace(1.0e-4, 2.0e-4, 21):  # n0 = J / (C (R - eps)) ~ 1100-2300 rad/s
        root = scipy.optimize.brentq(lambda t: np_f(p, J, np.cos(t)), 1e-9, hi - 1e-15, xtol=1e-15)
        assert hi - root > 1e-4  # inside the branch domain, not at theta_c
        states = tj.steady_states(top, float(J)).intermediate
        if len(states) != 1 or abs(states[0][0] - root) > 1e-9:
            missed.append((float(J), root, states))
    assert not missed, missed


# --------------------------------------------------------------------------------------------
# SteadyStates as a researcher reads it: a table, rows, and the spin of each state
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("group", ["IIb", "III"])
def test_steady_states_table_rows_and_spin(group):
    """`rows()` gives each state's spin, and it is the spin of a relative equilibrium of that J.

    Independent check of the spin: on a relative equilibrium (rolling without slipping)
    $\\dot\\varphi = RJ/D$, so with the row's spin $n$ the Jellet formula
    $J = Cn(R\\cos\\theta - \\epsilon) + A\\dot\\varphi R\\sin^2\\theta$ (eq. Jellet) must give
    back the J the states were found for; at the poles $J = Cn(R\\cos\\theta - \\epsilon)$."""
    top = _top(group)
    p = _params(top)
    m, R, eps, A, C, g = (p[k] for k in ("m", "R", "eps", "A", "C", "g"))
    y0 = tj.initial_state(top, 0.1, 100.0)
    J = float(tj.jellet(top, y0))
    ss = tj.steady_states(top, J)
    rows = ss.rows()
    assert [r["state"] for r in rows[:2]] == ["vertical", "vertical"]
    assert len(rows) == 2 + len(ss.intermediate)
    for r in rows:
        x = np.cos(r["theta"])
        D = R**2 * A * (1 - x**2) + C * (R * x - eps) ** 2
        phi_dot = R * J / D if r["state"] == "intermediate" else 0.0
        J_back = C * r["spin"] * (R * x - eps) + A * phi_dot * R * (1 - x**2)
        assert J_back == pytest.approx(J, rel=1e-12)
        # W'' > 0 and a linearly stable vector field go together (Sec. 4, App. B)
        assert r["routes_agree"], r
        assert (r["max_real_so3"] < 0) == r["stable"]
    for r in rows[2:]:
        assert r["route_spread"] < 1e-8 * np.max(np.abs(r["eigenvalues_so3"]))
    text = repr(ss)
    assert text == ss.table() == str(ss)
    for r in rows:
        assert f"{r['theta']:.6g}" in text and f"{r['spin']:.6g}" in text
    assert text.count("unstable") == sum(not r["stable"] for r in rows)
    # a batch prints its shapes, and rows() says why it cannot make a table
    batch = jax.vmap(lambda j: tj.steady_states(top, j))(jnp.array([0.5 * J, J]))
    assert "f64[2" in repr(batch) or "f32[2" in repr(batch)
    with pytest.raises(ValueError, match="one top"):
        batch.rows()


def test_steady_states_document_their_fields():
    doc = tj.SteadyStates.__doc__
    for name in ("intermediate", "vertical_d2W", "intermediate_spin", "table()"):
        assert name in doc
