"""Derivatives with respect to the parameters of the top."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import GROUP_RATIOS

import internal as ti

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
    print(f"d W''/d eps at theta={theta}, J/J1={j_ratio}: grad vs FD rel diff "
          f"{abs(got - fd) / abs(fd):.2e} (autodiff W''), {abs(got - fd_closed) / abs(fd_closed):.2e} (closed form)")
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
