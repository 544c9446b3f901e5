"""Which law does a top obey: `fit` with any law's fields and `compare_laws`.

Records come from `tests/real_top_reference.py` (Newton-Euler in the space frame with its own
friction laws, the Hertz disc by quadrature; no tippejax physics). Both records share one time
grid, one free set per law and the laws' classes, so the fits of the second record reuse the
first one's compilations.
"""

import math

import jax.numpy as jnp
import numpy as np
import pytest
import real_top_reference as rr
from scipy import stats

import tippejax as tj
from tippejax._fit import diagnostics

RATE = 100.0  # Hz: the first frame one sample after the launch, as a camera sees it
LENGTH = 2.0  # s
NOISE = 0.01  # rad
THETA0, SPIN = 0.1, 100.0
TOP = tj.TippeTop(**rr.STANDARD, mu=0.3)
MU_VISCOUS = 0.3  # s/m
MU_COULOMB, PATCH, SLIP = 0.3, 5e-4, 1e-5  # dimensionless, m, m/s
FREE = ("spin",)


def _record(law, mu, seed):
    n = int(LENGTH * RATE)
    out = rr.solve(
        rr.STANDARD,
        law,
        THETA0,
        SPIN,
        (n + 0.5) / RATE,
        mu=mu,
        rho=PATCH,
        delta=SLIP,
        stem=False,
        contact="rigid",
        dt_sample=1.0 / RATE,
        rtol=1e-10,
    )
    t, theta = np.asarray(out["t"]), np.asarray(out["theta"])
    keep = (t > 0.5 / RATE) & (t < (n + 0.25) / RATE)
    ts, clean = t[keep], theta[keep]
    assert ts.size == n and abs(ts[0] - 1.0 / RATE) < 1e-12  # no contact loss, frames 1..n
    return ts, clean, clean + NOISE * np.random.default_rng(seed).standard_normal(n)


def _guesses():
    """The laws' guesses: each some 20-30% off the records' truths."""
    return [tj.Viscous(0.4), tj.CoulombContensou(0.22, 6.5e-4, SLIP)]


@pytest.fixture(scope="module")
def viscous_record():
    ts, clean, obs = _record("viscous", MU_VISCOUS, seed=1)
    y0 = tj.initial_state(TOP, THETA0, SPIN * 1.05)
    return ts, clean, tj.compare_laws(TOP, y0, ts, obs, _guesses(), free=FREE, sigma=NOISE)


@pytest.fixture(scope="module")
def contensou_record():
    ts, clean, obs = _record("hertz", MU_COULOMB, seed=2)
    y0 = tj.initial_state(TOP, THETA0, SPIN * 0.95)
    return ts, clean, tj.compare_laws(TOP, y0, ts, obs, _guesses(), free=FREE, sigma=NOISE)


def _check_fit(res, truth):
    values, errors = np.asarray(res.values), np.asarray(res.std_errors)
    assert bool(res.converged), res.message()
    assert np.all(np.abs(values - truth) / np.abs(truth) < 0.02), values
    assert np.all(np.abs(values - truth) < 3 * errors), (values - truth) / errors


@pytest.mark.slow  # (two law comparisons: about two minutes on 2 cores)
def test_viscous_record_keeps_the_viscous_law(viscous_record):
    """The record of the viscous law does not rule it out; the fit (launched at t = 0, a
    sample before the first frame) recovers its mu and spin."""
    ts, clean, cmp = viscous_record
    print(cmp)
    assert cmp.names == ("Viscous", "CoulombContensou(hertz)")
    res = cmp.fits[0]
    assert type(res.top.friction) is tj.Viscous
    assert res.free == ("spin", "mu")
    _check_fit(res, np.array([SPIN, MU_VISCOUS]))
    assert not cmp.ruled_out[0] and cmp.p_value[0] > cmp.level and cmp.white[0]
    # the chi-square is the residual sum of squares against the given noise
    r = np.asarray(res.residuals)
    assert math.isclose(float(cmp.chi2[0]), float(np.sum(r**2)) / NOISE**2, rel_tol=1e-9)
    assert int(cmp.dof[0]) == ts.size - 2


@pytest.mark.slow  # (two law comparisons: about two minutes on 2 cores)
def test_contensou_record_rules_out_the_viscous_law(contensou_record):
    """A Coulomb-Contensou record, whose best viscous fit is much further than the noise from
    it, rules out the viscous law and prefers Coulomb-Contensou, whose mu (dimensionless) and
    patch radius the fit recovers."""
    ts, clean, cmp = contensou_record
    print(cmp)
    viscous, contensou = cmp.fits
    differs = np.sqrt(np.mean((np.asarray(viscous.theta_fit) - clean) ** 2))
    assert differs > 3 * NOISE  # the laws differ by more than the noise on this record
    assert cmp.ruled_out[0] and not cmp.ruled_out[1]
    assert cmp.preferred_index == 1 and cmp.preferred_name == "CoulombContensou(hertz)"
    assert cmp.ruled_out_names == ("Viscous",)
    assert isinstance(cmp.preferred, tj.CoulombContensou)
    assert contensou.free == ("spin", "mu", "patch_radius")
    _check_fit(contensou, np.array([SPIN, MU_COULOMB, PATCH]))
    assert float(cmp.preferred.patch_radius) == pytest.approx(float(contensou.values[2]))
    # the statistics from their definitions
    n, k = ts.size, np.array([2, 3])
    assert np.allclose(cmp.bic, cmp.chi2 + k * math.log(n))
    assert np.allclose(cmp.aic, cmp.chi2 + 2 * k)
    assert np.allclose(cmp.likelihood_ratio, cmp.chi2 - cmp.chi2.min())
    assert np.allclose(cmp.p_value, stats.chi2.sf(cmp.chi2, n - k), rtol=1e-8, atol=1e-300)
    assert "rules out: Viscous" in str(cmp)


def test_chi2_tail_against_scipy():
    for x, nu in [(0.5, 1), (3.0, 2), (150.0, 197), (260.0, 197), (900.0, 197), (1e-3, 50)]:
        assert diagnostics.chi2_sf(x, nu) == pytest.approx(
            stats.chi2.sf(x, nu), rel=1e-9, abs=1e-300
        )


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda ts, y: tj.compare_laws(TOP, y, ts, ts, [tj.Viscous(0.3)]), "at least two laws"),
        (lambda ts, y: tj.compare_laws(TOP, y, ts, ts, [tj.Viscous(0.3), 0.3]), "friction laws"),
        (lambda ts, y: tj.compare_laws(TOP, y, ts, ts, _guesses(), criterion="hqc"), "criterion"),
        (lambda ts, y: tj.compare_laws(TOP, y, ts, ts, _guesses(), level=1.5), "level"),
        (lambda ts, y: tj.compare_laws(TOP, y, ts, ts, _guesses(), sigma=-1.0), "sigma"),
        (lambda ts, y: tj.compare_laws(TOP, y, ts, ts, _guesses(), trim=True), "trim"),
        (lambda ts, y: tj.compare_laws(TOP, y, ts, np.stack([ts, ts]), _guesses()), "one record"),
        (lambda ts, y: tj.fit(TOP, y, ts, ts, free=("patch_radius",)), "no field 'patch_radius'"),
        (
            lambda ts, y: tj.fit(
                TOP.replace(friction=tj.CoulombContensou(0.3, PATCH, SLIP)),
                y,
                ts,
                ts,
                free=("slip_scale",),
            ),
            "does not determine",
        ),
        (lambda ts, y: tj.fit(TOP, y, ts + 10.0, ts, free=("mu",)), "t0="),
        (lambda ts, y: tj.fit(TOP, y, ts, ts, free=("mu",), t0=0.5), "t0"),
    ],
)
def test_bad_input(call, match):
    ts = np.arange(1, 51) / RATE
    with pytest.raises((ValueError, TypeError), match=match):
        call(ts, tj.initial_state(TOP, THETA0, SPIN))


class _Stop(Exception):
    pass


def test_searches_simulate_a_contensou_law_at_the_search_slip_scale(monkeypatch):
    """The fit's searches (ranking, scans) simulate a Coulomb-Contensou law with its slip scale
    raised to `SEARCH_SLIP_SCALE`, whose motion is that of the law as given to well below the
    noise (the motion converges as the slip scale goes to 0), at a fraction of the steps of a
    top that stops drilling; the stages that fit simulate the law as given, and a law whose
    motion depends on its slip scale (`Coulomb`) is never changed."""
    import equinox as eqx

    from tippejax._fit import problem, setup as fit_setup

    floor = fit_setup.SEARCH_SLIP_SCALE
    law = tj.CoulombContensou(MU_COULOMB, PATCH, SLIP)
    assert float(law._with_slip_floor(floor).slip_scale) == floor
    assert float(law._with_slip_floor(0.0).slip_scale) == SLIP
    coarse = law.replace(slip_scale=3 * floor)
    assert float(coarse._with_slip_floor(floor).slip_scale) == 3 * floor
    for other in (tj.Coulomb(MU_COULOMB, SLIP), tj.Viscous(MU_VISCOUS)):
        assert other._with_slip_floor(floor) is other

    top = TOP.replace(friction=law)
    ts = np.arange(1, 101) / RATE
    y0 = tj.initial_state(top, THETA0, SPIN)
    grabbed = {}

    def grab(self, u0, data):
        grabbed["setup"] = self
        raise _Stop

    monkeypatch.setattr(fit_setup.Setup, "optimise", grab)
    with pytest.raises(_Stop):
        tj.fit(top, y0, ts, np.full(ts.shape, THETA0), free=FREE, strategy="plain")
    setup = grabbed["setup"]
    values = {"spin": jnp.asarray(SPIN)}
    run = eqx.filter_jit(lambda d: problem.simulated(values, d, setup.cfg).theta[: ts.size])
    given, searched = run(setup.data(final=True)), run(setup.data(final=True, search=True))

    def plain(slip):
        sol = tj.simulate(
            top.replace(friction=law.replace(slip_scale=slip)),
            y0,
            ts[-1],
            saveat=ts,
            rtol=setup.rtol,
        )
        return np.asarray(sol.theta)

    theta_given, theta_floor = plain(SLIP), plain(floor)
    np.testing.assert_allclose(given, theta_given, atol=1e-8)
    np.testing.assert_allclose(searched, theta_floor, atol=1e-8)
    assert 1e-6 < np.max(np.abs(theta_floor - theta_given)) < 0.1 * NOISE


class _FakeFit:
    """What `compare_laws` reads of a `FitResult`: residuals, the fitted top and launch."""

    def __init__(self, top, y0, white, level, free):
        n = int(LENGTH * RATE)
        noise = NOISE * np.random.default_rng(len(free)).standard_normal(n)
        # white noise, or a slow wave of `level` on top (not white)
        self.residuals = noise if white else noise + level * np.sin(np.linspace(0, 3, n))
        self.top, self.y0, self.free = top, y0, free
        self.t0, self.converged = 0.0, True
        self.values = self.std_errors = np.ones(len(free))


@pytest.mark.parametrize("right_from_guess", [False, True])
def test_shared_search_spends_the_search_on_one_law_and_restarts_the_others(
    monkeypatch, right_from_guess
):
    """`search="shared"` (default): every law from its guess (strategy "windows"); while none
    passes, the whole strategy on the law with the lowest residual sum of squares, then the
    next; once one passes, every other law once more from that fit's top and launch, and not
    searched. `search="every"`: the whole strategy on each law. (A stand-in for `fit` whose
    right law, CoulombContensou, passes after its search, or from its guess, and whose wrong
    law fits better than it from the guess but never passes.)"""
    from tippejax._fit import compare

    calls = []
    warm = tj.initial_state(TOP, 0.2, SPIN)  # the passing fit's launch

    def fake_fit(top, y0, ts, obs, *, free, strategy="global", **kw):
        law = type(top.friction).__name__
        calls.append((law, strategy, y0 is warm))
        if law == "CoulombContensou":
            white = strategy != "windows" or right_from_guess
            return _FakeFit(top, warm, white, 0.05, free)
        return _FakeFit(top, y0, False, 0.03, free)  # the wrong law: closer, never white

    monkeypatch.setattr(compare, "fit", fake_fit)
    ts = np.arange(1, int(LENGTH * RATE) + 1) / RATE
    y0 = tj.initial_state(TOP, THETA0, SPIN)
    cmp = tj.compare_laws(TOP, y0, ts, np.zeros_like(ts), _guesses(), free=FREE, sigma=NOISE)
    cheap = [("Viscous", "windows", False), ("CoulombContensou", "windows", False)]
    if right_from_guess:  # no search: the wrong law restarts from the right law's fit
        assert calls == [*cheap, ("Viscous", "windows", True)]
        assert not cmp.searched.any()
    else:  # the wrong law (lower loss) is searched first, then the right one
        assert calls == [
            *cheap,
            ("Viscous", "global", False),
            ("CoulombContensou", "global", False),
        ]
        assert cmp.searched.all()
    assert list(cmp.ruled_out) == [True, False] and cmp.preferred_index == 1
    assert ("(not searched)" in str(cmp)) == right_from_guess

    calls.clear()
    cmp = tj.compare_laws(
        TOP, y0, ts, np.zeros_like(ts), _guesses(), free=FREE, sigma=NOISE, search="every"
    )
    assert calls == [("Viscous", "global", False), ("CoulombContensou", "global", False)]
    assert cmp.searched.all()
    with pytest.raises(ValueError, match="search must be one of"):
        tj.compare_laws(TOP, y0, ts, np.zeros_like(ts), _guesses(), search="some")
