"""tippejax against an independent reference: the paper's Euler-angle equations in numpy + DOP853.

`euler_reference` is written from the paper alone (no tippejax physics). Here it is first checked on
its own (R_n against eq. reactie, the generalized forces against the vector form of the friction
law, Jellet conservation, energy decay), then used as an oracle for `tj.simulate` at the levels
"full" (reference variant "full") and "so3", "routhian" (reference variant "so3").

Every tippejax call uses the same save grid, t1 and tolerances, so each level compiles once.
Run with `pytest -s` to see the largest disagreement of every comparison.
"""

import math

import euler_reference as er
import numpy as np
import pytest

import tippejax as tj

T1 = 1.0
TS = np.linspace(0.0, T1, 201)
RTOL, ATOL = 1e-11, 1e-13  # tippejax tolerances (one configuration for every call)
TOL = 1e-7  # absolute agreement asked of angles (rad), rates (rad/s) and R_n (N)
# Fields whose natural size is far from 1 get a tolerance on their own scale: J ~ 1e-5 kg m^2/s
# (compared relative to |J(0)|), position ~ 1e-3 m, velocity ~ 1e-2 m/s.
TOLS = dict(
    theta=TOL,
    theta_dot=TOL,
    phi_dot=TOL,
    spin=TOL,
    normal_force=TOL,
    jellet_rel=1e-9,
    position=1e-9,
    velocity=1e-8,
)
THETA_MARGIN = 0.1  # launches must keep theta in [0.1, pi - 0.1] over [0, T1]
N_LAUNCHES = 4  # per top

TOPS = {
    "standard": lambda: tj.default_top(),
    "Ib": lambda: tj.TippeTop.from_ratios(0.6, 0.1, m=0.05, R=0.03, mu=0.8),
}
LEVEL_VARIANT = {"full": "full", "so3": "so3", "routhian": "so3"}


def random_params(rng):
    R = rng.uniform(0.01, 0.05)
    m = rng.uniform(0.01, 0.3)
    C = rng.uniform(0.3, 0.5) * m * R**2
    return dict(
        m=m,
        R=R,
        eps=rng.uniform(0.05, 0.6) * R,
        A=rng.uniform(0.55, 1.6) * C,
        C=C,
        g=rng.uniform(9.7, 9.9),
        mu=rng.uniform(0.0, 1.5),
    )


def random_state(rng):
    return np.array(
        [
            rng.uniform(-0.1, 0.1),
            rng.uniform(-0.1, 0.1),
            rng.uniform(0.2, math.pi - 0.2),
            rng.uniform(-math.pi, math.pi),
            rng.uniform(-math.pi, math.pi),
            rng.uniform(-0.2, 0.2),
            rng.uniform(-0.2, 0.2),
            rng.uniform(-3, 3),
            rng.uniform(-10, 10),
            rng.uniform(-150, 150),
        ]
    )


def reactie(z, p, variant):
    """The paper's closed form eq. reactie for R_n (xd = yd = 0 for the SO(3) variant: R'_n)."""
    m, R, eps, A, C, g, mu = (p[k] for k in ("m", "R", "eps", "A", "C", "g", "mu"))
    _, _, th, ph, _, xd, yd, thd, phd, psd = z
    if variant == "so3":
        xd = yd = 0.0
    s, c = math.sin(th), math.cos(th)
    h, hp, hpp = R - eps * c, eps * s, eps * c
    num = g + thd**2 * hpp + hp * phd * s * (phd * c - C * (psd + phd * c) / A)
    den = 1 / m + hp / A * (-h * mu * (math.sin(ph) * xd - math.cos(ph) * yd - thd * h) + hp)
    return num / den


def contact_velocity(z, p, variant):
    """v_Q = v_O + omega x q from the vectors (ERRATA.md conventions), not from the paper's Q_i."""
    _, _, th, ph, _, xd, yd, thd, phd, psd = z
    if variant == "so3":
        xd = yd = 0.0
    s, c, sp, cp = math.sin(th), math.cos(th), math.sin(ph), math.cos(ph)
    a = np.array([s * sp, -s * cp, c])
    nodes = np.array([cp, sp, 0.0])
    e_z = np.array([0.0, 0.0, 1.0])
    omega = phd * e_z + thd * nodes + psd * a
    q = p["eps"] * a - p["R"] * e_z
    v_o = np.array([xd, yd, p["eps"] * s * thd])
    return v_o + np.cross(omega, q)


# --------------------------------------------------------------- the reference on its own


@pytest.mark.parametrize("variant", ["full", "so3"])
def test_normal_force_is_eq_reactie(variant):
    rng = np.random.default_rng(1)
    worst = 0.0
    for _ in range(400):
        p, z = random_params(rng), random_state(rng)
        ours, paper = er.normal_force(z, p, variant), reactie(z, p, variant)
        worst = max(worst, abs(ours - paper) / abs(paper))
    print(f"\n[{variant}] R_n vs eq. reactie, max relative difference {worst:.2e}")
    assert worst < 1e-12


def energy_rate_terms(z, f, p, variant):
    """The terms of dE/dt = dE/dz . f (E of euler_reference.energy, differentiated by hand)."""
    m, R, eps, A, C, g = (p[k] for k in ("m", "R", "eps", "A", "C", "g"))
    _, _, th, _, _, xd, yd, thd, phd, psd = z
    s, c = math.sin(th), math.cos(th)
    n = psd + phd * c
    dE_dth = m * eps**2 * s * c * thd**2 + A * s * c * phd**2 - C * n * phd * s + m * g * eps * s
    terms = [
        dE_dth * thd,
        (A + m * eps**2 * s**2) * thd * f[7],
        (A * s**2 * phd + C * n * c) * f[8],
        C * n * f[9],
    ]
    if variant == "full":
        terms += [m * xd * f[5], m * yd * f[6]]
    return np.array(terms)


@pytest.mark.parametrize("variant", ["full", "so3"])
def test_energy_rate_is_friction_power(variant):
    """dE/dt along rhs equals R_f . v_Q = -mu R_n |v_Q|^2 (eq. derE), v_Q from the vectors: checks
    the paper's Q_i and the accelerations together."""
    rng = np.random.default_rng(2)
    worst = 0.0
    for _ in range(400):
        p, z = random_params(rng), random_state(rng)
        v_q = contact_velocity(z, p, variant)
        assert abs(v_q[2]) < 1e-14 * (
            1 + np.abs(v_q).max()
        )  # the contact point slides horizontally
        power = -p["mu"] * er.normal_force(z, p, variant) * (v_q @ v_q)
        terms = energy_rate_terms(z, er.rhs(0.0, z, p, variant), p, variant)
        worst = max(worst, abs(terms.sum() - power) / np.abs(terms).sum())
    print(f"\n[{variant}] dE/dt vs -mu R_n |v_Q|^2, max difference / size of terms {worst:.2e}")
    assert worst < 1e-12


@pytest.fixture(scope="module")
def launches():
    """N_LAUNCHES random launches per top that keep theta in [0.1, pi - 0.1] and R_n > 0 (both
    reference variants, checked here) over [0, T1]; fixed seed, so always the same."""
    rng = np.random.default_rng(20240611)
    out = {}
    for name, make in TOPS.items():
        p = er.params_of(make())
        chosen, tried = [], 0
        while len(chosen) < N_LAUNCHES:
            tried += 1
            assert tried < 20 * N_LAUNCHES, "too few admissible launches"
            kw = dict(
                theta0=rng.uniform(0.6, 2.4),
                spin=rng.uniform(20, 120),
                theta_dot=rng.uniform(-2, 2),
                phi_dot=rng.uniform(-5, 5),
                vx=rng.uniform(-0.1, 0.1),
                vy=rng.uniform(-0.1, 0.1),
            )
            try:
                refs = {v: er.solve(p, t_eval=TS, variant=v, **kw) for v in ("full", "so3")}
            except RuntimeError:  # came within 0.05 rad of a pole
                continue
            if all(
                r["theta"].min() > THETA_MARGIN
                and r["theta"].max() < math.pi - THETA_MARGIN
                and r["normal_force"].min() > 0
                for r in refs.values()
            ):
                chosen.append((kw, refs))
        out[name] = chosen
    return out


@pytest.mark.parametrize("variant", ["full", "so3"])
def test_reference_conserves_jellet(launches, variant):
    worst = 0.0
    for chosen in launches.values():
        for _, refs in chosen:
            J = refs[variant]["jellet"]
            worst = max(worst, np.abs(J - J[0]).max() / abs(J[0]))
    print(f"\n[{variant}] reference Jellet drift, max relative {worst:.2e}")
    assert worst < 1e-10


@pytest.mark.parametrize("variant", ["full", "so3"])
def test_reference_energy_never_increases(launches, variant):
    worst = -np.inf
    for chosen in launches.values():
        for _, refs in chosen:
            E = refs[variant]["energy"]
            worst = max(worst, np.diff(E).max() / abs(E[0]))
            assert E[-1] < E[0]
    print(f"\n[{variant}] reference energy, largest relative step {worst:.2e} (must be <= ~0)")
    assert worst < 1e-12


# --------------------------------------------------------------- tippejax against the reference


@pytest.fixture(scope="module")
def tippejax_runs():
    cache = {}

    def get(top_name, index, level, launches):
        key = (top_name, index, level)
        if key not in cache:
            top = TOPS[top_name]()
            kw = launches[top_name][index][0]
            y0 = tj.initial_state(
                top,
                kw["theta0"],
                kw["spin"],
                theta_dot=kw["theta_dot"],
                phi_dot=kw["phi_dot"],
                vx=kw["vx"],
                vy=kw["vy"],
            )
            cache[key] = tj.simulate(top, y0, T1, model=level, saveat=TS, rtol=RTOL, atol=ATOL)
        return cache[key]

    return get


def disagreements(sol, ref, level):
    d = {
        name: float(np.max(np.abs(np.asarray(getattr(sol, name)) - ref[name])))
        for name in ("theta", "theta_dot", "phi_dot", "spin", "normal_force")
    }
    d["jellet_rel"] = float(
        np.max(np.abs(np.asarray(sol.jellet) - ref["jellet"])) / abs(ref["jellet"][0])
    )
    if level == "full":
        d["position"] = float(
            np.max(np.abs(np.asarray(sol.position) - np.stack([ref["x"], ref["y"]], -1)))
        )
        d["velocity"] = float(
            np.max(np.abs(np.asarray(sol.velocity) - np.stack([ref["vx"], ref["vy"]], -1)))
        )
    return d


@pytest.mark.parametrize("index", range(N_LAUNCHES))
@pytest.mark.parametrize("top_name", list(TOPS))
@pytest.mark.parametrize("level", ["full", "so3", "routhian"])
def test_simulate_matches_reference(launches, tippejax_runs, level, top_name, index):
    kw, refs = launches[top_name][index]
    ref = refs[LEVEL_VARIANT[level]]
    sol = tippejax_runs(top_name, index, level, launches)
    theta = np.asarray(sol.theta)
    assert np.all(np.isfinite(theta))
    assert theta.min() > THETA_MARGIN and theta.max() < math.pi - THETA_MARGIN
    d = disagreements(sol, ref, level)
    print(
        f"\n[{level} ({sol.model}), {top_name} #{index}: th0={kw['theta0']:.3f} "
        f"n0={kw['spin']:.1f}] max abs diff: " + ", ".join(f"{k} {v:.1e}" for k, v in d.items())
    )
    bad = {k: (v, TOLS[k]) for k, v in d.items() if not v < TOLS[k]}
    assert not bad, f"level {level!r}, top {top_name}, launch {index}: (diff, tol) {bad}"


@pytest.mark.parametrize("factor", [1.1, 1.001])
def test_comparison_is_sensitive(launches, tippejax_runs, factor):
    """A reference with mu off by a factor must disagree with tippejax by more than TOL."""
    top_name, index = "standard", 0
    kw, _ = launches[top_name][index]
    p = er.params_of(TOPS[top_name]())
    p["mu"] *= factor
    ref = er.solve(p, t_eval=TS, variant="full", **kw)
    d = disagreements(tippejax_runs(top_name, index, "full", launches), ref, "full")
    print(f"\n[mu x {factor}] max abs diff: " + ", ".join(f"{k} {v:.1e}" for k, v in d.items()))
    assert (
        d["theta"] > 10 * TOL and d["spin"] > 100 * TOL and d["position"] > 100 * TOLS["position"]
    )
