"""Fitting: recovery from poor guesses, honest standard errors, gradients, robustness, bad input.

Every fit here uses the same record (801 samples over 8 s, free mu, eps, spin), so the
unbatched fit compiles once for the module, and the batched one once.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tippejax as tj
from tippejax import _fit

FREE = ("mu", "eps", "spin")
TS = np.linspace(0.0, 8.0, 801)
NOISE = 0.01


def _record(spin, seed, *, top=None):
    top = tj.default_top() if top is None else top
    sol = tj.simulate(top, tj.initial_state(top, 0.1, spin), 8.0, saveat=TS)
    clean = np.asarray(sol.theta)
    return clean + NOISE * np.random.default_rng(seed).standard_normal(TS.shape), sol


def _guess(mu_factor, eps_factor, spin):
    top = tj.default_top()
    guess = tj.TippeTop(m=top.m, R=top.R, eps=top.eps * eps_factor, A=top.A, C=top.C,
                        mu=top.mu * mu_factor)
    return guess, tj.initial_state(guess, 0.1, spin)


@pytest.fixture(scope="module")
def inverting_fit():
    """Data of the standard top (inverts at 5.70 s) with gaps; guesses 25-30% off."""
    obs, sol = _record(100.0, seed=0)
    assert 5.5 < float(sol.t_invert) < 6.0
    obs[150:170] = np.nan  # a gap of 0.2 s, as when the top leaves the camera's view
    guess, y0 = _guess(1.3, 0.72, 127.0)
    return tj.fit(guess, y0, TS, obs, free=FREE), obs


def test_recovers_parameters_from_poor_guess(inverting_fit):
    res, _ = inverting_fit
    truth = np.array([0.3, float(tj.default_top().eps), 100.0])
    values, errors = np.asarray(res.values), np.asarray(res.std_errors)
    print(res.table())
    rel = np.abs(values - truth) / truth
    assert np.all(rel < 0.02), rel
    assert np.all(np.abs(values - truth) < 3 * errors), (values - truth) / errors
    assert bool(res.converged), res.message
    # The fit reaches the noise floor: rms residual ~ the noise (0.01 rad).
    assert 0.8 * NOISE < float(res.rms) < 1.2 * NOISE
    # The fitted top and launch carry the fitted values.
    assert float(res.top.mu) == pytest.approx(values[0])
    assert float(tj.euler_angles(res.y0)[0]) == pytest.approx(0.1)
    assert float(jnp.sum(res.y0.omega * res.y0.axis)) == pytest.approx(values[2])
    # The whole record is described by the model that made it.
    assert float(res.describes_until) == pytest.approx(8.0)


def test_nan_samples_are_masked(inverting_fit):
    res, obs = inverting_fit
    residuals = np.asarray(res.residuals)
    assert np.all(np.isnan(residuals[150:170]))
    assert np.all(np.isfinite(residuals[np.isfinite(obs)]))
    assert np.all(np.isnan(np.asarray(res.theta_obs)[150:170]))


def test_loss_history_decreases_to_noise_floor(inverting_fit):
    res, obs = inverting_fit
    hist = np.asarray(res.loss_history)
    hist = hist[np.isfinite(hist)]
    assert hist.size == int(res.num_steps)
    last = hist[-1]
    n_used = np.isfinite(obs).sum()
    # 0.5 * sum r^2 with r ~ N(0, 0.01^2) is about 0.5 * N * 1e-4.
    assert last == pytest.approx(0.5 * n_used * NOISE**2, rel=0.2)


def test_standard_errors_match_scatter_of_noisy_fits():
    """Fit 12 noisy copies of one record at once (vmapped over recordings); the scatter of the
    fitted values agrees with the reported standard errors within a factor of 2."""
    copies = 12
    clean = _record(100.0, seed=0)[1].theta
    rng = np.random.default_rng(7)
    obs = np.asarray(clean)[None] + NOISE * rng.standard_normal((copies, TS.size))
    guess, y0 = _guess(1.0, 1.0, 100.0)
    res = _fit.fit(guess, y0, TS, obs, free=FREE, strategy="plain")
    assert np.asarray(res.values).shape == (copies, 3)
    assert np.all(np.asarray(res.converged)), res.message
    scatter = np.std(np.asarray(res.values), axis=0, ddof=1)
    reported = np.median(np.asarray(res.std_errors), axis=0)
    print("scatter", scatter, "reported", reported, "ratio", scatter / reported)
    assert np.all(scatter / reported < 2.0) and np.all(scatter / reported > 0.5)


def test_trial_that_loses_contact_does_not_break_fit():
    """The guess (spin 200) loses contact at about 5.2 s, so the first trials stop early: their
    later save times get the finite failure residual, and the fit recovers the truth."""
    obs, sol = _record(100.0, seed=3)
    guess, y0 = _guess(1.05, 0.95, 200.0)
    first = tj.simulate(guess, y0, 8.0, saveat=TS, throw=False)
    assert int(first.result._value) == int(tj.RESULTS.contact_lost._value)
    res = tj.fit(guess, y0, TS, obs, free=FREE)
    assert np.isfinite(np.asarray(res.loss_history)[0])
    print(res.table())
    truth = np.array([0.3, float(tj.default_top().eps), 100.0])
    assert np.all(np.abs(np.asarray(res.values) - truth) / truth < 0.02)
    assert bool(res.converged), res.message


@pytest.fixture(scope="module")
def short_problem():
    """Every free name at once on 2 s of data (101 samples): residual function and data."""
    top = tj.default_top()
    ts = np.linspace(0.0, 2.0, 101)
    y0 = tj.initial_state(top, 0.3, 80.0, theta_dot=0.5, phi_dot=2.0, vx=0.01, vy=-0.02)
    sol = tj.simulate(top, y0, 2.0, saveat=ts)
    obs = np.asarray(sol.theta) + NOISE * np.random.default_rng(1).standard_normal(ts.shape)
    free = _fit.FREE_NAMES
    guess = tj.TippeTop(m=0.021, R=0.026, eps=0.008, A=top.A * 1.05, C=top.C, g=9.7, mu=0.33)
    y_guess = tj.initial_state(guess, 0.33, 85.0, theta_dot=0.4, phi_dot=2.2, vx=0.012, vy=-0.018)
    captured = {}
    real = _fit._run_stage

    def grab(u0, data, cfg, batched):
        captured.setdefault("stage", (data, cfg))
        raise _Stop

    _fit._run_stage = grab
    try:
        with pytest.raises(_Stop):
            _fit.fit(guess, y_guess, ts, obs, free=free, strategy="plain")
    finally:
        _fit._run_stage = real
    return captured["stage"]


class _Stop(Exception):
    pass


def test_gradient_of_every_free_parameter_matches_finite_differences(short_problem):
    """Forward-mode Jacobian of the residuals (the fit's) against central differences of the
    loss, one parameter at a time in the physical units."""
    data, cfg = short_problem
    p = len(cfg.free)
    value_and_jac = jax.jit(lambda u: _fit._value_and_jacobian(u, data, cfg))
    u_to_p = jax.jit(lambda u: jnp.stack([_fit._physical(u, data.base, cfg.free)[n] for n in cfg.free]))

    def loss_of_values(values):
        vals = dict(zip(cfg.free, values))
        r = _fit._residuals_of_values(vals, data, cfg)[0]
        return 0.5 * jnp.sum(r**2)

    loss_p = jax.jit(loss_of_values)
    u = jnp.zeros(p)
    r, jac_u = value_and_jac(u)
    assert np.all(np.isfinite(np.asarray(jac_u)))
    # d loss / d u = J^T r; to physical: d loss / d p = (du/dp)^T J^T r, du/dp = inverse of dp/du.
    dp_du = jax.jacfwd(u_to_p)(u)
    grad_p = np.linalg.solve(np.asarray(dp_du).T, np.asarray(jac_u.T @ r))
    values = np.asarray(u_to_p(u))
    for i, name in enumerate(cfg.free):
        h = 1e-5 * abs(values[i]) if values[i] != 0 else 1e-6
        up, down = values.copy(), values.copy()
        up[i] += h
        down[i] -= h
        fd = (float(loss_p(jnp.asarray(up))) - float(loss_p(jnp.asarray(down)))) / (2 * h)
        print(f"{name}: autodiff {grad_p[i]:.6e}, FD {fd:.6e}")
        assert grad_p[i] == pytest.approx(fd, rel=2e-4, abs=1e-8 * abs(fd) + 1e-12), name


def test_non_finite_trial_is_a_failed_trial_not_an_error(short_problem):
    """An optimiser step that overflows (nan coordinates) must not reach simulate's state
    checks: every sample gets the finite failure residual."""
    data, cfg = short_problem
    r = jax.jit(lambda u: _fit._residuals(u, data, cfg))(jnp.full(len(cfg.free), jnp.nan))
    theta_part = np.asarray(r)[: data.ts.size]
    used = np.asarray(data.weights) > 0
    assert np.all(np.isfinite(np.asarray(r)))
    np.testing.assert_allclose(theta_part[used], _fit.FAILED_RESIDUAL * np.sqrt(np.asarray(data.weights)[used]))


def test_reparametrisation_keeps_constraints(short_problem):
    data, cfg = short_problem
    physical = jax.jit(lambda u: _fit._physical(u, data.base, cfg.free))
    at_zero = physical(jnp.zeros(len(cfg.free)))
    launch = data.base.launch
    for name in cfg.free:
        expected = data.base.top[name] if name in _fit.TOP_FIELDS else launch[name]
        assert float(at_zero[name]) == pytest.approx(float(expected), rel=1e-12), name
    rng = np.random.default_rng(0)
    for _ in range(50):
        v = physical(jnp.asarray(rng.normal(0.0, 8.0, len(cfg.free))))
        assert all(float(v[n]) > 0 for n in ("m", "R", "g", "mu", "C", "A", "eps"))
        assert float(v["eps"]) < float(v["R"])
        assert float(v["A"]) / float(v["C"]) > 0.5
        assert 0.0 < float(v["theta0"]) < np.pi
        assert np.sign(float(v["spin"])) == np.sign(float(launch["spin"]))
        tj.TippeTop(**{f: float(v[f]) for f in ("m", "R", "eps", "A", "C", "g", "mu")})


def test_covariance_matches_finite_difference_jacobian(short_problem):
    """The Gauss-Newton covariance from the autodiff Jacobian in u, mapped to physical units,
    equals s^2 (J_p^T J_p)^{-1} with J_p by central differences in the physical parameters."""
    data, cfg = short_problem
    free = ("mu", "eps", "spin")
    sub = eqx.tree_at(lambda c: c.free, cfg, free)
    out = jax.jit(lambda u: _fit._finish(u, tj.FIT_RESULTS.successful, data, sub))(jnp.zeros(3))

    def res_p(values):
        return _fit._residuals_of_values(dict(zip(free, values)), data, sub)[0]

    res_p = jax.jit(res_p)
    values = np.asarray(out["values"])
    cols = []
    for i in range(3):
        h = 1e-6 * abs(values[i])
        up, down = values.copy(), values.copy()
        up[i] += h
        down[i] -= h
        cols.append((np.asarray(res_p(jnp.asarray(up))) - np.asarray(res_p(jnp.asarray(down)))) / (2 * h))
    jac = np.stack(cols, 1)
    r = np.asarray(res_p(jnp.asarray(values)))
    n_used = int(np.sum(np.asarray(data.weights) > 0))
    s2 = np.sum(r**2) / (n_used - 3)
    cov_fd = s2 * np.linalg.inv(jac.T @ jac)
    np.testing.assert_allclose(np.asarray(out["covariance"]), cov_fd, rtol=1e-3)
    np.testing.assert_allclose(np.asarray(out["std_errors"]), np.sqrt(np.diag(cov_fd)), rtol=1e-3)


# --------------------------------------------------------------------------------------------
# Bad input: each raises a clear error before anything is compiled.

GOOD_TOP = tj.default_top()
GOOD_Y0 = tj.initial_state(GOOD_TOP, 0.1, 100.0)
GOOD_OBS = np.full(TS.shape, 0.1)


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(theta_obs=GOOD_OBS[:-1]), ValueError, "shape"),
        (dict(ts=TS[::-1]), ValueError, "strictly increasing"),
        (dict(ts=np.where(np.arange(TS.size) == 5, np.nan, TS)), ValueError, "finite times"),
        (dict(theta_obs=np.where(np.arange(TS.size) == 5, np.inf, GOOD_OBS)), ValueError, "inf"),
        (dict(free=("mu", "friction")), ValueError, "Unknown names in free"),
        (dict(free=()), ValueError, "free is empty"),
        (dict(free=("mu", "mu")), ValueError, "twice"),
        (dict(model="gyroscopic"), ValueError, "fit supports model"),
        (dict(method="bfgs"), ValueError, "Unknown method"),
        (dict(strategy="magic"), ValueError, "Unknown strategy"),
        (dict(top_guess="default"), TypeError, "TippeTop"),
        (dict(y0_guess=(0.1, 100.0)), TypeError, "State"),
        (dict(top_guess=eqx.tree_at(lambda t: t.eps, GOOD_TOP, jnp.asarray(0.03))), ValueError, "eps"),
        (dict(top_guess=eqx.tree_at(lambda t: t.A, GOOD_TOP, GOOD_TOP.C * 0.4)), ValueError, "A/C"),
        (dict(y0_guess=tj.initial_state(GOOD_TOP, 0.0, 100.0)), ValueError, "pole"),
        (dict(y0_guess=tj.initial_state(GOOD_TOP, 0.1, 0.0)), ValueError, "zero spin"),
        (dict(theta_obs=np.where(np.arange(TS.size) < 799, np.nan, GOOD_OBS), free=FREE), ValueError,
         "usable samples"),
        (dict(t0=0.5), ValueError, "t0"),
        (dict(weights=-np.ones(TS.size)), ValueError, "weights"),
    ],
)
def test_bad_input_raises(kwargs, error, match):
    args = dict(top_guess=GOOD_TOP, y0_guess=GOOD_Y0, ts=TS, theta_obs=GOOD_OBS)
    args.update({k: kwargs.pop(k) for k in list(kwargs) if k in args})
    with pytest.raises(error, match=match):
        _fit.fit(args["top_guess"], args["y0_guess"], args["ts"], args["theta_obs"], **kwargs)


def test_reports_the_part_of_the_record_the_model_describes():
    """Data the model did not make: after 6.5 s the tilt stops at 2.3 rad, as when a real top's
    stem lands on the table. A fit of the whole record is distorted; `trim` refits on the part
    the model describes, says where that ends, and recovers the top."""
    obs, _ = _record(100.0, seed=11)
    landed = TS >= 6.5
    obs[landed] = 2.3 + NOISE * np.random.default_rng(12).standard_normal(landed.sum())
    guess, y0 = _guess(1.1, 0.9, 110.0)
    whole = tj.fit(guess, y0, TS, obs, free=FREE, trim=False)
    print(whole.table())
    assert float(whole.rms) > 3 * float(whole.noise)  # the whole record is not described
    res = tj.fit(guess, y0, TS, obs, free=FREE)
    print(res.table(), float(res.fitted_until))
    assert 6.0 < float(res.fitted_until) <= 6.5
    assert 6.0 < float(res.describes_until) <= 6.5
    truth = np.array([0.3, float(tj.default_top().eps), 100.0])
    assert np.all(np.abs(np.asarray(res.values) - truth) / truth < 0.02)
    assert float(res.rms) < 1.5 * NOISE  # over the fitted part
    residuals = np.asarray(res.residuals)
    assert np.all(np.isfinite(residuals))  # reported on the whole record
    assert np.mean(np.abs(residuals[TS > 6.8])) > 0.3
