"""Derivatives with respect to the parameters of the top."""

import functools
import time

import diffrax
import equinox as eqx
import internal as ti
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import GROUP_RATIOS

import tippejax as tj

FIELDS = ("m", "R", "eps", "A", "C", "g", "mu")


def _build(**overrides):
    """A top with the standard values, any field replaceable by a (possibly traced) value."""
    base = tj.default_top()
    kw = {f: getattr(base, f) for f in FIELDS}
    kw.update(overrides)
    return tj.TippeTop(**kw)


def _central_difference(fn, x, rel_step=1e-4):
    h = rel_step * abs(x)
    return (fn(x + h) - fn(x - h)) / (2 * h)


CASES = [(0.3, 1.0), (1.2, 2.0), (2.5, 1.5), (0.0, 1.2), (np.pi, 0.7)]  # (theta, J / J1)


@pytest.fixture(scope="module")
def d2w_of_eps():
    def fn(eps, theta, J):
        return tj.effective_potential_derivative(_build(eps=eps), theta, J, order=2)

    return jax.jit(fn), jax.jit(jax.grad(fn))


@pytest.mark.parametrize("theta, j_ratio", CASES)
def test_grad_d2w_wrt_eps(d2w_of_eps, theta, j_ratio):
    value, grad = d2w_of_eps
    top = tj.default_top()
    eps0 = float(top.eps)
    J = j_ratio * float(tj.thresholds(top).J1)
    got = float(grad(eps0, theta, J))
    # Finite differences of the autodiff W'' and of the closed form (eq. stabilityba).
    fd = _central_difference(lambda e: float(value(e, theta, J)), eps0)
    fd_closed = _central_difference(
        lambda e: float(ti.effective_potential_d2_closed_form(_build(eps=e), theta, J)), eps0
    )
    print(
        f"d W''/d eps at theta={theta}, J/J1={j_ratio}: grad vs FD rel diff "
        f"{abs(got - fd) / abs(fd):.2e} (autodiff W''), {abs(got - fd_closed) / abs(fd_closed):.2e} (closed form)"
    )
    np.testing.assert_allclose(got, fd, rtol=1e-6)
    np.testing.assert_allclose(got, fd_closed, rtol=1e-6)
    assert abs(got) > 0


def test_grad_d2w_wrt_eps_via_tree_at():
    top = tj.default_top()
    theta, J = 1.2, 2.0 * float(tj.thresholds(top).J1)

    def fn(eps):
        return tj.effective_potential_derivative(
            eqx.tree_at(lambda t: t.eps, top, eps), theta, J, order=2
        )

    got = float(jax.grad(fn)(top.eps))
    fd = _central_difference(lambda e: float(fn(jnp.asarray(e))), float(top.eps))
    np.testing.assert_allclose(got, fd, rtol=1e-6)


@pytest.mark.parametrize("group", ["IIa", "IIb", "III"])
def test_grad_n1_wrt_A(group):
    base = tj.TippeTop.from_ratios(*GROUP_RATIOS[group])
    m, R, eps, C, g = (float(getattr(base, f)) for f in ("m", "R", "eps", "C", "g"))

    def n1(A):
        return tj.thresholds(_build(m=m, R=R, eps=eps, A=A, C=C, g=g)).n1

    A0 = float(base.A)
    got = float(jax.grad(n1)(A0))
    fd = _central_difference(lambda a: float(n1(a)), A0, rel_step=1e-5)
    # d/dA of n1 = sqrt(m g eps / (C (A/C - 1 + e))) (1 - e), e = eps/R.
    e = eps / R
    d = A0 / C - 1 + e
    closed = (1 - e) * np.sqrt(m * g * eps / C) * (-0.5) * d**-1.5 / C
    np.testing.assert_allclose(float(n1(A0)), (1 - e) * np.sqrt(m * g * eps / (C * d)), rtol=1e-14)
    np.testing.assert_allclose(got, closed, rtol=1e-12)
    np.testing.assert_allclose(got, fd, rtol=1e-6)


@pytest.mark.parametrize("theta", [0.0, 0.7, 2.0, np.pi])
def test_grad_d2w_wrt_every_field_is_finite(theta):
    top = tj.default_top()
    J = 1.5 * float(tj.thresholds(top).J1)
    grads = jax.grad(lambda t: tj.effective_potential_derivative(t, theta, J, order=2))(top)
    for f in FIELDS:
        assert np.isfinite(float(getattr(grads, f))), f
    # W'' does not depend on mu; it does depend on every other field.
    assert float(grads.mu) == 0.0
    for f in ("m", "eps", "g", "A", "C", "R"):
        assert float(getattr(grads, f)) != 0.0, f


def test_grad_through_traced_construction_matches_tree_at():
    """Building the top from traced values (checks active) gives the same gradient."""
    theta, J = 0.9, 1e-5
    top = tj.default_top()

    def via_build(values):
        return tj.effective_potential_derivative(tj.TippeTop(*values), theta, J, order=2)

    values = tuple(getattr(top, f) for f in FIELDS)
    g_build = jax.grad(via_build)(values)
    g_tree = jax.grad(lambda t: tj.effective_potential_derivative(t, theta, J, order=2))(top)
    for f, gb in zip(FIELDS, g_build):
        np.testing.assert_allclose(float(gb), float(getattr(g_tree, f)), rtol=1e-14, atol=0)


# --- Gradients through `simulate`: reverse mode, forward mode and finite differences ---------
#
# The standard top launched at theta0 = 0.1 with spin 100, run to t1 = 6.5 s in summary mode
# (it inverts at about 5.70 s). Four outputs, each differentiated with respect to every field
# of the top and the launch (theta0, spin):
#
# - `t_invert`, the first upward crossing of theta = pi/2 (a root find on the dense output,
#   differentiated through the implicit function theorem);
# - theta, theta_dot and the energy of the final state, at t1 (trajectory functionals).
#
# Everything runs at rtol 1e-12, atol 1e-14, so that the derivative of the discrete solve and
# the finite differences both sit close to the exact derivative. Each derivative is one
# function of the whole top (a pytree) and the launch, compiled once per module; all finite
# differences reuse one compiled forward function (the perturbed top is an argument). Each
# distinct derivative costs 10-25 s of compilation on a small CPU, which is why there is one
# run only (theta at save times of a separate short run agreed as well, to < 5e-7 against
# central differences of step 1e-5, but cost another 40 s).

SOLVE = dict(rtol=1e-12, atol=1e-14)
LAUNCH = (0.1, 100.0)  # theta0, spin
LAUNCH_FIELDS = ("theta0", "spin")
T1 = 6.5
OUTPUTS = ("t_invert", "theta(t1)", "theta_dot(t1)", "energy(t1)")
# Central differences of relative step 1e-6: t_invert is strongly curved in A and C (at a
# step of 1e-5 the O(h^2) error is 1e-4); at 1e-6 the measured disagreements are at most
# ~1.5e-6 (truncation for A and C, round-off elsewhere). Printed with `pytest -s`.
REL_STEP = 1e-6
FD_RTOL = 1e-5
MODES_RTOL = 1e-9  # reverse and forward mode differentiate the same discrete solve (~1e-12)


def _outputs(top, launch, adjoint=None):
    y0 = tj.initial_state(top, launch[0], launch[1])
    sol = tj.simulate(top, y0, T1, summary=True, adjoint=adjoint, **SOLVE)
    return jnp.stack([sol.t_invert, sol.theta[0], sol.theta_dot[0], sol.energy[0]])


def _by_name(jacobian):
    """{field or launch name: d outputs / d it} from a (TippeTop, launch) pair."""
    d_top, d_launch = jacobian
    out = {f: np.asarray(getattr(d_top, f)) for f in FIELDS}
    for i, name in enumerate(LAUNCH_FIELDS):
        out[name] = np.asarray(d_launch)[:, i]
    return out


def _central_differences(value, top, launch, rel_step):
    """{field or launch name: central difference of `value(top, launch)`}."""

    def difference(plus, minus, step):
        return (np.asarray(value(*plus)) - np.asarray(value(*minus))) / step

    out = {}
    for f in FIELDS:
        x = getattr(top, f)
        h = rel_step * abs(float(x))
        xp, xm = x + h, x - h
        plus = (eqx.tree_at(lambda t: getattr(t, f), top, xp), launch)
        minus = (eqx.tree_at(lambda t: getattr(t, f), top, xm), launch)
        out[f] = difference(plus, minus, float(xp - xm))
    for i, name in enumerate(LAUNCH_FIELDS):
        h = rel_step * abs(float(launch[i]))
        lp, lm = launch.at[i].add(h), launch.at[i].add(-h)
        out[name] = difference((top, lp), (top, lm), float(lp[i] - lm[i]))
    return out


def _disagreement(got, want):
    """|got - want| / |want| per output; where `want` is exactly 0, |got| (absolute)."""
    scale = np.where(want == 0, 1.0, np.abs(want))
    return np.abs(got - want) / scale


def _report(title, got, want):
    """Print the disagreement per parameter and output; return the largest."""
    print(f"\n{title}: relative disagreement")
    print("        " + "".join(f"{o:>15}" for o in OUTPUTS))
    worst = 0.0
    for k in want:
        e = _disagreement(got[k], want[k])
        print(f"{k:>6}  " + "".join(f"{x:>15.2e}" for x in e))
        worst = max(worst, float(np.max(e)))
    return worst


def _timed(label, fn, *args):
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    print(f"\n[{label}: {time.perf_counter() - start:.1f} s, compilation included]")
    return out


@pytest.fixture(scope="module")
def problem():
    return tj.default_top(), jnp.asarray(LAUNCH)


@pytest.fixture(scope="module")
def reverse(problem):
    """Reverse mode with the default adjoint (the transposed forward sensitivities)."""
    jac = jax.jit(jax.jacrev(_outputs, argnums=(0, 1)))
    return _by_name(_timed("jax.jacrev, default adjoint", jac, *problem))


@pytest.fixture(scope="module")
def reverse_through_solve(problem):
    """Reverse mode through the solve's steps (diffrax's checkpointed adjoint): independent
    of forward mode."""
    fn = functools.partial(_outputs, adjoint=diffrax.RecursiveCheckpointAdjoint())
    jac = jax.jit(jax.jacrev(fn, argnums=(0, 1)))
    return _by_name(_timed("jax.jacrev, RecursiveCheckpointAdjoint", jac, *problem))


@pytest.fixture(scope="module")
def forward(problem):
    fn = functools.partial(_outputs, adjoint=diffrax.ForwardMode())
    jac = jax.jit(jax.jacfwd(fn, argnums=(0, 1)))
    return _by_name(_timed("jax.jacfwd, ForwardMode", jac, *problem))


@pytest.fixture(scope="module")
def finite_differences(problem):
    value = jax.jit(_outputs)
    top, launch = problem
    values = np.asarray(_timed("value", value, top, launch))
    start = time.perf_counter()
    fd = _central_differences(value, top, launch, REL_STEP)
    print(f"[central differences: {time.perf_counter() - start:.1f} s]")
    return values, fd


def _check_complete(derivatives):
    assert set(derivatives) == set(FIELDS + LAUNCH_FIELDS)
    for k, v in derivatives.items():
        assert v.shape == (len(OUTPUTS),), k
        assert np.all(np.isfinite(v)), k


def test_simulate_values_for_gradients(finite_differences):
    values, _ = finite_differences
    print("\n" + ", ".join(f"{o} = {v:.10g}" for o, v in zip(OUTPUTS, values)))
    assert abs(values[0] - 5.70) < 0.02  # inverts before t1 ...
    assert values[1] > np.pi / 2  # ... and is still inverted at t1


def test_grad_simulate_reverse_matches_forward(reverse, forward):
    _check_complete(reverse)
    _check_complete(forward)
    assert _report("jax.jacrev vs jax.jacfwd", reverse, forward) < MODES_RTOL


@pytest.mark.slow
def test_grad_simulate_reverse_matches_reverse_through_the_steps(reverse, reverse_through_solve):
    """The default's reverse mode against reverse mode through the solve's steps (a route
    that does not go through forward mode; central differences check both by default)."""
    _check_complete(reverse_through_solve)
    assert (
        _report("jax.jacrev: default vs RecursiveCheckpointAdjoint", reverse, reverse_through_solve)
        < MODES_RTOL
    )


@pytest.mark.slow
def test_default_adjoint_takes_forward_mode_too(problem, forward):
    """`jax.jacfwd` with the default adjoint (diffrax's checkpointed adjoint refuses it)."""
    top, launch = problem
    d_mu = jax.jit(jax.jacfwd(lambda mu: _outputs(top.replace(mu=mu), launch)))(top.mu)
    np.testing.assert_allclose(np.asarray(d_mu), forward["mu"], rtol=MODES_RTOL)


def test_forward_sensitivities_on_a_closed_form():
    """`forward_sensitivities` on f(x, y, n) = (x^2 sin y, x y, n + 1): jax.grad, jax.jacfwd
    and jax.jacrev against the closed form, an integer output with no derivative, and only
    the differentiated inputs carried with tangents into the forward function."""
    from tippejax._engine.sensitivity import forward_sensitivities

    traced = []

    def f(x, y, n):
        return dict(a=x**2 * jnp.sin(y), b=x * y, count=n + 1)

    def forward(x, y, n):
        traced.append((isinstance(x, jax.core.Tracer), isinstance(y, jax.core.Tracer)))
        return f(x, y, n)

    g = forward_sensitivities(f, forward)
    x, y, n = jnp.array([0.3, -1.2, 2.0]), jnp.asarray(0.7), jnp.asarray(3)
    weights = jnp.array([1.0, 2.0, 3.0])

    def loss(x, y):
        out = g(x, y, n)
        return jnp.sum(out["a"] * weights) + jnp.sum(out["b"])

    want_x = 2 * x * jnp.sin(y) * weights + y
    want_y = jnp.sum(x**2 * jnp.cos(y) * weights) + jnp.sum(x)
    got_x, got_y = jax.grad(loss, argnums=(0, 1))(x, y)
    np.testing.assert_allclose(got_x, want_x, rtol=1e-12)
    np.testing.assert_allclose(got_y, want_y, rtol=1e-12)
    np.testing.assert_allclose(jax.jacfwd(loss)(x, y), want_x, rtol=1e-12)
    np.testing.assert_allclose(jax.jit(jax.jacrev(loss, argnums=1))(x, y), want_y, rtol=1e-12)
    np.testing.assert_allclose(jax.jacfwd(lambda y: g(x, y, n)["b"])(y), x, rtol=1e-12)
    assert int(g(x, y, n)["count"]) == 4
    _, tangent = jax.jvp(lambda x: g(x, y, n), (x,), (jnp.ones(3),))
    assert tangent["count"].dtype == jax.dtypes.float0
    traced.clear()
    jax.grad(lambda x: loss(x, y))(x)
    jax.grad(lambda y: loss(x, y))(y)
    assert traced == [(True, False), (False, True)]


def test_grad_simulate_matches_finite_differences(reverse, forward, finite_differences):
    _, fd = finite_differences
    # Every output depends on every field and on the launch: all relative checks.
    for k, v in fd.items():
        assert np.all(v != 0), k
    worst_reverse = _report(f"jax.jacrev vs central differences (step {REL_STEP:g})", reverse, fd)
    worst_forward = _report("jax.jacfwd vs central differences", forward, fd)
    assert worst_reverse < FD_RTOL
    assert worst_forward < FD_RTOL


def test_eager_jacrev_is_a_program_of_its_own_and_agrees(problem, reverse, monkeypatch):
    """An eager `jax.jacrev` (no `jit` of the caller) runs the Jacobian of the solve as a
    top-level program of its own (`_run_jacobian`, compiled with tippejax's options and
    stored), not inside the program JAX derives from `_run`. Its derivatives agree with the
    `jit`-ed route, which differentiates `_run` as one program."""
    import tippejax._simulate.programs as simulate_module

    lives = []
    call = simulate_module.cached_call

    def spy(fn, *args, **kwargs):
        if fn is simulate_module._run_jacobian:
            lives.append(kwargs["live"])
        return call(fn, *args, **kwargs)

    monkeypatch.setattr(simulate_module, "cached_call", spy)
    got = _by_name(_timed("jax.jacrev, eager", jax.jacrev(_outputs, argnums=(0, 1)), *problem))
    # one Jacobian, in the top's seven fields and the launch state's leaves that depend on
    # (theta0, spin)
    assert len(lives) == 1 and len(lives[0]) >= len(FIELDS)
    _check_complete(got)
    assert _report("jax.jacrev eager vs jit", got, reverse) < MODES_RTOL


def test_only_an_eager_derivative_takes_its_own_program():
    """`_differentiated_eagerly`: true under an eager `jax.grad`, `jax.jacfwd` or `jax.jvp`,
    false for concrete inputs, under `jax.vmap`, `jax.jit`, and `jax.grad` inside either
    (where the rule's inputs are not concrete: one program, `_run`)."""
    from tippejax._simulate.single import _differentiated_eagerly

    seen = []

    def record(x, y=1.0):
        seen.append(_differentiated_eagerly((x, y)))
        return x * y

    jax.grad(record)(2.0)
    jax.jacfwd(record)(2.0)
    jax.jvp(record, (2.0,), (1.0,))
    assert seen == [True, True, True]
    seen.clear()
    record(2.0)
    jax.vmap(record)(jnp.ones(2))
    jax.jit(record)(2.0)
    jax.jit(jax.grad(record))(2.0)
    jax.vmap(jax.grad(record))(jnp.ones(2))
    jax.vmap(lambda y: jax.grad(lambda x: record(x, y))(2.0))(jnp.ones(2))  # (y batched)
    assert seen == [False] * 6


def test_grad_t_invert_wrt_mu_sign_and_size(reverse):
    # More friction, faster rise, earlier inversion. The rise is set by the friction, so the
    # elasticity of t_invert in mu is of order one: |d t_invert/d mu| * mu of order seconds.
    d_mu = float(reverse["mu"][0])
    mu = float(tj.default_top().mu)
    print(f"\nd t_invert / d mu = {d_mu:.4f} s^2/m; times mu: {d_mu * mu:.3f} s")
    assert d_mu < 0
    assert 1.0 < abs(d_mu) * mu < 20.0


def test_grad_and_jacfwd_trace_the_solve_once(monkeypatch):
    """`simulate`'s value and its Jacobian (`forward_sensitivities`) are one staged solve:
    under `jax.grad` and `jax.jacfwd` the solve's Python is traced once, not once for the
    value and again for the Jacobian (a gradient's first call is mostly this tracing,
    `benchmarks/gradients.py`)."""
    import tippejax._simulate.programs as simulate_module

    calls = []
    run_chain = simulate_module.run_chain
    monkeypatch.setattr(
        simulate_module,
        "run_chain",
        lambda *a, **k: calls.append(type(k["adjoint"]).__name__) or run_chain(*a, **k),
    )

    def t_invert(top):
        y0 = tj.initial_state(top, 0.1, 150.0)
        return tj.simulate(top, y0, 1.0, summary=True, throw=False).theta[-1]

    jax.clear_caches()  # (a trace cached by an earlier test would hide the count)
    jax.jit(jax.grad(t_invert)).trace(tj.default_top())
    assert calls == ["ForwardMode"]
    # jacfwd's Jacobian rule is the same staged solve: its trace is found in JAX's cache
    jax.jit(jax.jacfwd(t_invert)).trace(tj.default_top())
    assert calls == ["ForwardMode"]
