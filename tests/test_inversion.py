"""`inversion_time`: its value, its gradient against finite differences, nan and failures.

The standard top launched at theta0 = 0.1 with spin 100 (inverts at about 5.70 s), t1 = 6.5 s,
rtol 1e-12, atol 1e-14. Compilations are the cost of this file (10-20 s each on a small CPU),
so there are three: one batched value function (`jax.vmap`) that runs every finite-difference
perturbation, the vmap and nan checks at once, one gradient (reverse mode) with respect to the
top, the launch (theta0, spin through `initial_state`) and every field of the `State`, and one
forward-mode derivative (`diffrax.ForwardMode`, `jax.jvp`) along one direction.
"""

import math
import time

import diffrax
import equinox as eqx
import euler_reference as ref
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import tippejax as tj

FIELDS = ("m", "R", "eps", "A", "C", "g", "mu")
STATE_FIELDS = ("position", "velocity", "axis", "omega", "body")
SOLVE = dict(rtol=1e-12, atol=1e-14)
T1 = 6.5
THETA0, SPIN = 0.1, 100.0
SLOW_SPIN = 80.0  # inverts later, still before T1
BELOW_N1 = 20.0  # below n1 = 26.9 rad/s: theta = 0 is stable, no inversion
# Central differences. Top fields and the launch: relative step 1e-6 (as tests/test_grad.py,
# which measured the truncation and round-off of t_invert there). State fields: absolute steps;
# the axis step keeps |axis| within simulate's unit-vector check (1e-6).
REL_STEP = 1e-6
STATE_STEP = dict(position=1e-6, velocity=1e-6, axis=2e-7, omega=1e-5, body=2e-7)
FD_RTOL = 1e-5


def _time(top, y0):
    return tj.inversion_time(top, y0, t1=T1, **SOLVE)


def _add(y0, dy):
    return jax.tree_util.tree_map(jnp.add, y0, dy)


def _launch_time(top, theta0, spin, dy):
    """t* as a function of the top, the launch and a perturbation of the launch state."""
    return _time(top, _add(tj.initial_state(top, theta0, spin), dy))


def _zero_state(y0):
    return jax.tree_util.tree_map(jnp.zeros_like, y0)


def _timed(label, fn, *args):
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    print(f"[{label}: {time.perf_counter() - start:.1f} s, compilation included]")
    return out


def _perturbations(top):
    """[(name, step, (top, y0) plus, (top, y0) minus)] for every field of the top, the launch
    and every component of the launch state."""
    y0 = tj.initial_state(top, THETA0, SPIN)
    out = []
    for f in FIELDS:
        x = getattr(top, f)
        h = REL_STEP * abs(float(x))
        xp, xm = x + h, x - h
        out.append(
            (
                f,
                float(xp - xm),
                (eqx.tree_at(lambda t: getattr(t, f), top, xp), y0),
                (eqx.tree_at(lambda t: getattr(t, f), top, xm), y0),
            )
        )
    for name, theta0, spin in (("theta0", 1, 0), ("spin", 0, 1)):
        h = REL_STEP * (THETA0 if theta0 else SPIN)
        plus = tj.initial_state(top, THETA0 + h * theta0, SPIN + h * spin)
        minus = tj.initial_state(top, THETA0 - h * theta0, SPIN - h * spin)
        out.append((name, 2 * h, (top, plus), (top, minus)))
    for f in STATE_FIELDS:
        value = getattr(y0, f)
        for i in range(value.shape[0]):
            h = STATE_STEP[f]
            plus = eqx.tree_at(lambda s: getattr(s, f), y0, value.at[i].add(h))
            minus = eqx.tree_at(lambda s: getattr(s, f), y0, value.at[i].add(-h))
            out.append((f"{f}[{i}]", 2 * h, (top, plus), (top, minus)))
    return out


def _stack(pairs):
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *pairs)


@pytest.fixture(scope="module")
def batched():
    return jax.jit(jax.vmap(_time))


@pytest.fixture(scope="module")
def runs(batched):
    """One batch: the launch, a slower one, one below n1, then every +/- perturbation."""
    top = tj.default_top()
    perturbations = _perturbations(top)
    pairs = [(top, tj.initial_state(top, THETA0, s)) for s in (SPIN, SLOW_SPIN, BELOW_N1)]
    for _, _, plus, minus in perturbations:
        pairs += [plus, minus]
    times = np.asarray(_timed(f"vmap over {len(pairs)} runs", batched, *_stack(pairs)))
    fd, steps = {}, {}
    for k, (name, step, _, _) in enumerate(perturbations):
        fd[name] = (times[3 + 2 * k] - times[4 + 2 * k]) / step
        steps[name] = step
    return dict(t=times[0], t_slow=times[1], t_below=times[2], fd=fd, steps=steps, pairs=pairs)


@pytest.fixture(scope="module")
def gradient():
    """(t*, its gradient), unbatched."""
    return jax.jit(jax.value_and_grad(_launch_time, argnums=(0, 1, 2, 3)))


def _by_name(grads):
    d_top, d_theta0, d_spin, d_state = grads
    out = {f: float(getattr(d_top, f)) for f in FIELDS}
    out["theta0"], out["spin"] = float(d_theta0), float(d_spin)
    for f in STATE_FIELDS:
        for i, v in enumerate(np.asarray(getattr(d_state, f))):
            out[f"{f}[{i}]"] = float(v)
    return out


@pytest.fixture(scope="module")
def reverse(gradient):
    top = tj.default_top()
    y0 = tj.initial_state(top, THETA0, SPIN)
    value, grads = _timed("jax.value_and_grad", gradient, top, THETA0, SPIN, _zero_state(y0))
    return dict(_by_name(grads), value=float(value))


def _crossing_on_save_grid(top, spin, n=13001):
    """t* where theta on a fine save grid first crosses pi/2 upwards, by Hermite cubic
    interpolation between the two save times around it (theta and theta_dot at both) and
    bisection: the event machinery of the engine plays no part."""
    ts = np.linspace(0.0, T1, n)
    sol = tj.simulate(top, tj.initial_state(top, THETA0, spin), T1, saveat=ts, **SOLVE)
    theta, theta_dot = np.asarray(sol.theta), np.asarray(sol.theta_dot)
    k = int(np.argmax((theta[:-1] < np.pi / 2) & (theta[1:] >= np.pi / 2)))
    h = ts[k + 1] - ts[k]

    def cubic(t):
        s = (t - ts[k]) / h
        h00, h10, h01, h11 = (
            2 * s**3 - 3 * s**2 + 1,
            s**3 - 2 * s**2 + s,
            -2 * s**3 + 3 * s**2,
            s**3 - s**2,
        )
        return (
            h00 * theta[k]
            + h10 * h * theta_dot[k]
            + h01 * theta[k + 1]
            + h11 * h * theta_dot[k + 1]
        ) - np.pi / 2

    lo, hi = ts[k], ts[k + 1]
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if cubic(mid) < 0 else (lo, mid)
    return 0.5 * (lo + hi)


def test_value_against_save_grid(runs):
    top = tj.default_top()
    for spin, got in ((SPIN, runs["t"]), (SLOW_SPIN, runs["t_slow"])):
        want = _crossing_on_save_grid(top, spin)
        print(f"spin {spin}: t* = {got:.12f} (inversion_time), {want:.12f} (save grid)")
        np.testing.assert_allclose(got, want, rtol=1e-10)
    assert 5.6 < runs["t"] < 5.8
    assert runs["t"] < runs["t_slow"] < T1


@pytest.mark.slow
def test_value_against_euler_reference(runs):
    """t* from the paper's Euler-angle equations (tests/euler_reference.py) with scipy's
    DOP853 and its event location: no tippejax code. Pure-Python right-hand side: 1.5-6 min."""
    top = tj.default_top()
    params = ref.params_of(top)

    def crossing(t, z, params, variant):
        return z[2] - math.pi / 2

    crossing.terminal = True
    crossing.direction = 1
    z0 = ref.initial_vector(THETA0, SPIN)
    sol = solve_ivp(
        ref.rhs,
        (0.0, T1),
        z0,
        method="DOP853",
        args=(params, "full"),
        rtol=1e-12,
        atol=1e-12,
        events=crossing,
    )
    assert sol.status == 1, sol.message
    want = float(sol.t_events[0][0])
    print(f"t* = {runs['t']:.12f} (inversion_time), {want:.12f} (scipy, Euler angles)")
    np.testing.assert_allclose(runs["t"], want, rtol=1e-8)


@pytest.mark.slow
def test_vmap_matches_single_run(runs, reverse):
    """Slow: vmap against a loop (plumbing); the value is checked against the save grid."""
    np.testing.assert_allclose(reverse["value"], runs["t"], rtol=1e-12)


def test_gradient_matches_finite_differences(runs, reverse):
    fd = runs["fd"]
    assert set(fd) == set(reverse) - {"value"}
    print(f"\nd t*/d p at theta0={THETA0}, spin={SPIN}: reverse mode vs central differences")
    print(f"{'p':>10} {'grad':>16} {'central diff':>16} {'rel. error':>11}")
    for name, want in fd.items():
        got = reverse[name]
        assert np.isfinite(got), name
        if name.startswith(("position", "body")):
            # Neither enters the dynamics: the derivative is exactly zero. The difference is
            # round-off (the step-size controller's error norm sees these components): t*
            # moved by less than 1e-11 s.
            print(f"{name:>10} {got:>16.9e} {want:>16.9e} {'(zero)':>11}")
            assert got == 0.0 and abs(want * runs["steps"][name]) < 1e-11, name
            continue
        error = abs(got - want) / abs(want)
        print(f"{name:>10} {got:>16.9e} {want:>16.9e} {error:>11.2e}")
        assert error < FD_RTOL, name


def test_gradient_signs(reverse):
    # More friction, faster rise; a larger spin, a faster rise (above n1, at this launch);
    # starting more tilted, less far to go.
    assert reverse["mu"] < 0
    assert reverse["spin"] < 0
    assert reverse["theta0"] < 0


def test_forward_mode_matches_reverse(reverse):
    top = tj.default_top()
    y0 = tj.initial_state(top, THETA0, SPIN)
    direction = (
        jax.tree_util.tree_map(lambda x: 1e-3 * x, top),  # 0.1% of every field
        0.01,
        -1.0,
        _zero_state(y0),
    )

    def fn(top, theta0, spin, dy):
        y = _add(tj.initial_state(top, theta0, spin), dy)
        return tj.inversion_time(top, y, t1=T1, adjoint=diffrax.ForwardMode(), **SOLVE)

    jvp = jax.jit(lambda *p: jax.jvp(fn, p, direction))
    value, tangent = _timed("jax.jvp, ForwardMode", jvp, top, THETA0, SPIN, _zero_state(y0))
    want = sum(1e-3 * float(getattr(top, f)) * reverse[f] for f in FIELDS)
    want += 0.01 * reverse["theta0"] - reverse["spin"]
    np.testing.assert_allclose(float(tangent), want, rtol=1e-9)


def test_no_inversion_is_nan_with_zero_gradient(runs, gradient):
    assert np.isnan(runs["t_below"])
    top = tj.default_top()
    y0 = tj.initial_state(top, THETA0, BELOW_N1)
    value, grads = gradient(top, THETA0, BELOW_N1, _zero_state(y0))
    assert np.isnan(float(value))
    grads = _by_name(grads)
    assert all(v == 0.0 for v in grads.values()), grads


def test_failure_before_crossing_raises_under_jit(batched, runs):
    # A friction so stiff that, traced, the default solver refuses it (RESULTS.stiff_under_trace):
    # it fails before any crossing, and one failing member raises for the batch.
    pairs = list(runs["pairs"])
    stiff = eqx.tree_at(lambda t: t.mu, pairs[0][0], jnp.asarray(2e4))
    pairs[0] = (stiff, pairs[0][1])
    with pytest.raises(Exception, match="friction is very stiff"):
        jax.block_until_ready(batched(*_stack(pairs)))


def test_failure_before_and_after_crossing():
    top = tj.default_top()
    # At rtol 1e-8 the launch at spin 100 takes ~990 steps to pass its inversion (5.8 s) and
    # ~1800 to reach t = 60; the one below n1 takes ~1360 to reach t = 60 (and never inverts).
    # (Counts since the SO(3)/full levels carry the body vector as a slow frame; before, ~930,
    # ~5100 and ~1950.) A limit between them fails one after its crossing, the other before.
    max_steps = 1200
    y0 = tj.initial_state(top, THETA0, SPIN)
    options = dict(t1=60.0, max_steps=max_steps)
    sol = tj.simulate(top, y0, 60.0, summary=True, throw=False, max_steps=max_steps)
    assert sol.result == tj.RESULTS.max_steps_reached
    # Failed after the crossing: the crossing stands, with or without throw.
    t = float(tj.inversion_time(top, y0, **options))
    np.testing.assert_allclose(t, float(sol.t_invert), rtol=0)
    assert 5.6 < t < 5.8
    # Failed before any crossing (below n1, no crossing ever): raises, or nan with throw=False.
    y_slow = tj.initial_state(top, THETA0, BELOW_N1)
    with pytest.raises(RuntimeError, match="maximum number of solver steps"):
        tj.inversion_time(top, y_slow, **options)
    assert np.isnan(float(tj.inversion_time(top, y_slow, throw=False, **options)))


def test_bad_input():
    top = tj.default_top()
    y0 = tj.initial_state(top, THETA0, SPIN)
    with pytest.raises(ValueError, match="Unknown model"):
        tj.inversion_time(top, y0, t1=T1, model="euler")
    with pytest.raises(TypeError, match="State"):
        tj.inversion_time(top, (THETA0, SPIN), t1=T1)
    with pytest.raises(TypeError, match="TippeTop"):
        tj.inversion_time("top", y0, t1=T1)
    tops = jax.vmap(lambda e: tj.TippeTop.from_ratios(0.9, e))(jnp.array([0.2, 0.3]))
    with pytest.raises(ValueError, match="jax.vmap"):
        tj.inversion_time(tops, y0, t1=T1)
    with pytest.raises(ValueError, match="t1 must be greater than t0"):
        tj.inversion_time(top, y0, t1=0.0)
    with pytest.raises(ValueError, match="rtol"):
        tj.inversion_time(top, y0, t1=T1, rtol=-1.0)
    with pytest.raises(TypeError):
        tj.inversion_time(top, y0, T1)  # t1 is keyword-only


@pytest.mark.slow  # compiling the reverse pass through the launch's projection and the
# chain takes minutes on a CPU
def test_gyroscopic_gradient_is_the_secular_slope():
    """The design quantity: the gyroscopic t* (nutation averaged) has the gradient of its trend
    over +-1% of mu and A, where the full model's t* is a staircase whose local gradient is
    not (standard top, theta0 = 0.1, n0 = 100)."""
    top = tj.default_top()

    def t_star(mu, A):
        t = eqx.tree_at(lambda x: (x.mu, x.A), top, (mu, A))
        return tj.inversion_time(
            t, tj.initial_state(t, THETA0, SPIN), t1=T1, model="gyroscopic", throw=False
        )

    value = jax.jit(t_star)
    grad = jax.jit(jax.grad(t_star, argnums=(0, 1)))
    mu, A = top.mu, top.A
    g_mu, g_A = (float(x) for x in grad(mu, A))
    s_mu = float(value(1.01 * mu, A) - value(0.99 * mu, A)) / (0.02 * float(mu))
    s_A = float(value(mu, 1.01 * A) - value(mu, 0.99 * A)) / (0.02 * float(A))
    print(
        f"gyroscopic t* = {float(value(mu, A)):.4f} s: dt*/dmu {g_mu:.4f} (secular {s_mu:.4f}),"
        f" dt*/dA {g_A:.5g} (secular {s_A:.5g})"
    )
    assert np.isfinite(float(value(mu, A)))
    assert abs(g_mu - s_mu) < 0.01 * abs(s_mu)
    assert abs(g_A - s_A) < 0.01 * abs(s_A)
