"""TippeTop: construction, from_ratios, and every invalid input, eagerly and under jit."""

import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tippejax as tj

FIELDS = ("m", "R", "eps", "A", "C", "g", "mu")
M, RADIUS = 0.02, 0.025
C0 = 0.4 * M * RADIUS**2
VALID = dict(m=M, R=RADIUS, eps=0.3 * RADIUS, A=0.9 * C0, C=C0, g=9.81, mu=0.3)

# (field overrides, fragment that the error message must contain).
BAD = [
    (dict(eps=0.0), "TippeTop.eps"),
    (dict(eps=-1e-3), "TippeTop.eps"),
    (dict(eps=RADIUS), "TippeTop.eps"),
    (dict(eps=2 * RADIUS), "TippeTop.eps"),
    (dict(m=0.0), "TippeTop.m (mass) must be > 0"),
    (dict(m=-0.01), "TippeTop.m (mass) must be > 0"),
    (dict(R=0.0, eps=-1e-3), "TippeTop.R (radius of the sphere) must be > 0"),
    (dict(R=-0.025), "TippeTop.R (radius of the sphere) must be > 0"),
    (dict(A=0.0), "TippeTop.A (transverse moment of inertia) must be > 0"),
    (dict(A=-C0), "TippeTop.A (transverse moment of inertia) must be > 0"),
    (dict(C=0.0), "TippeTop.C (axial moment of inertia) must be > 0"),
    (dict(C=-C0), "TippeTop.C (axial moment of inertia) must be > 0"),
    (dict(A=0.49 * C0), "A/C must be >= 1/2"),
    (dict(C=2.2 * VALID["A"]), "A/C must be >= 1/2"),
    (dict(mu=-0.1), "TippeTop.mu (viscous friction coefficient, s/m) must be >= 0"),
    (dict(g=0.0), "TippeTop.g (gravitational acceleration) must be > 0"),
    (dict(g=-9.81), "TippeTop.g (gravitational acceleration) must be > 0"),
]
for _name in FIELDS:
    BAD.append(({_name: float("nan")}, f"TippeTop.{_name} must be finite"))
    BAD.append(({_name: float("inf")}, f"TippeTop.{_name} must be finite"))
    BAD.append(({_name: -float("inf")}, f"TippeTop.{_name} must be finite"))
BAD_IDS = [",".join(f"{k}={v:g}" for k, v in kw.items()) for kw, _ in BAD]


def _values(**overrides):
    kw = dict(VALID, **overrides)
    return tuple(kw[f] for f in FIELDS)


@pytest.fixture(scope="module")
def build_jit():
    # One compilation for all scalar cases (every argument a float64 scalar).
    return eqx.filter_jit(lambda *v: tj.TippeTop(*v))


@pytest.fixture(scope="module")
def build_jax_jit():
    return jax.jit(lambda *v: tj.TippeTop(*v))


def test_construction_stores_fields_as_float64_arrays():
    top = tj.TippeTop(**VALID)
    for f in FIELDS:
        value = getattr(top, f)
        assert isinstance(value, jax.Array)
        assert value.dtype == jnp.float64
        assert float(value) == VALID[f]
    # Integer inputs become floats.
    top = tj.TippeTop(m=1, R=2, eps=1, A=3, C=4, g=10, mu=0)
    assert all(getattr(top, f).dtype == jnp.float64 for f in FIELDS)
    # Defaults g = 9.81 and mu = 0.3.
    top = tj.TippeTop(m=M, R=RADIUS, eps=0.3 * RADIUS, A=0.9 * C0, C=C0)
    assert float(top.g) == 9.81 and float(top.mu) == 0.3


def test_boundary_values_are_accepted():
    # A/C = 1/2 exactly (a thin disc) and mu = 0 (no friction) are allowed.
    tj.TippeTop(**dict(VALID, A=0.5 * C0))
    tj.TippeTop(**dict(VALID, mu=0.0))


def test_from_ratios_defaults():
    top = tj.TippeTop.from_ratios(0.9, 0.3)
    m, R = 0.02, 0.025
    C = 0.4 * m * R**2
    np.testing.assert_allclose(float(top.m), m, rtol=0)
    np.testing.assert_allclose(float(top.R), R, rtol=0)
    np.testing.assert_allclose(float(top.C), C, rtol=1e-15)
    np.testing.assert_allclose(float(top.A), 0.9 * C, rtol=1e-15)
    np.testing.assert_allclose(float(top.eps), 0.3 * R, rtol=1e-15)
    np.testing.assert_allclose(float(top.mu), 0.3, rtol=0)
    np.testing.assert_allclose(float(top.g), 9.81, rtol=0)
    np.testing.assert_allclose(float(top.A_over_C), 0.9, rtol=1e-15)
    np.testing.assert_allclose(float(top.eps_over_R), 0.3, rtol=1e-15)


def test_from_ratios_custom():
    top = tj.TippeTop.from_ratios(1.3, 0.6, m=0.1, R=0.04, mu=0.05, g=9.0)
    C = 0.4 * 0.1 * 0.04**2
    np.testing.assert_allclose(float(top.C), C, rtol=1e-15)
    np.testing.assert_allclose(float(top.A), 1.3 * C, rtol=1e-15)
    np.testing.assert_allclose(float(top.eps), 0.6 * 0.04, rtol=1e-15)
    assert float(top.mu) == 0.05 and float(top.g) == 9.0 and float(top.m) == 0.1
    top = tj.TippeTop.from_ratios(0.8, 0.2, C=3e-6)
    np.testing.assert_allclose(float(top.C), 3e-6, rtol=0)
    np.testing.assert_allclose(float(top.A), 0.8 * 3e-6, rtol=1e-15)


def test_from_ratios_array_ratios_make_a_batch():
    ratios = jnp.array([0.6, 0.9, 1.5])
    eps = jnp.array([0.1, 0.3, 0.5])
    top = tj.TippeTop.from_ratios(ratios, eps)
    assert top.A.shape == (3,) and top.eps.shape == (3,)
    np.testing.assert_allclose(np.asarray(top.A_over_C), np.asarray(ratios), rtol=1e-15)
    np.testing.assert_allclose(np.asarray(top.eps_over_R), np.asarray(eps), rtol=1e-15)


@pytest.mark.parametrize("overrides, message", BAD, ids=BAD_IDS)
def test_bad_input_raises_value_error(overrides, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        tj.TippeTop(*_values(**overrides))


@pytest.mark.parametrize("overrides, message", BAD, ids=BAD_IDS)
def test_bad_input_raises_under_filter_jit(build_jit, overrides, message):
    values = [jnp.asarray(v, dtype=jnp.float64) for v in _values(**overrides)]
    with pytest.raises(Exception, match=re.escape(message)):
        top = build_jit(*values)
        jax.block_until_ready(top)


@pytest.mark.parametrize(
    "overrides, message",
    [(dict(eps=0.0), "TippeTop.eps"), (dict(mu=float("nan")), "TippeTop.mu must be finite")],
)
def test_bad_input_raises_under_jax_jit(build_jax_jit, overrides, message):
    values = [jnp.asarray(v, dtype=jnp.float64) for v in _values(**overrides)]
    with pytest.raises(Exception, match=re.escape(message)):
        jax.block_until_ready(build_jax_jit(*values))


def test_valid_top_under_jit_passes_and_matches(build_jit):
    values = [jnp.asarray(v, dtype=jnp.float64) for v in _values()]
    top = build_jit(*values)
    for f in FIELDS:
        assert float(getattr(top, f)) == VALID[f]


def test_check_survives_when_only_one_field_is_used(build_jit):
    # The check must not be dropped when the jitted computation only uses one field.
    @eqx.filter_jit
    def uses_mass(*v):
        return tj.TippeTop(*v).m * 2.0

    values = [jnp.asarray(v, dtype=jnp.float64) for v in _values(eps=0.0)]
    with pytest.raises(Exception, match=re.escape("TippeTop.eps")):
        jax.block_until_ready(uses_mass(*values))


def test_from_ratios_bad_ratios():
    with pytest.raises(ValueError, match=re.escape("A/C must be >= 1/2")):
        tj.TippeTop.from_ratios(0.4, 0.3)
    with pytest.raises(ValueError, match=re.escape("TippeTop.eps")):
        tj.TippeTop.from_ratios(0.9, 1.0)
    with pytest.raises(ValueError, match=re.escape("TippeTop.eps")):
        tj.TippeTop.from_ratios(0.9, 0.0)
    with pytest.raises(ValueError, match=re.escape("TippeTop.A")):
        tj.TippeTop.from_ratios(float("nan"), 0.3)


def test_from_ratios_bad_ratio_under_jit():
    build = eqx.filter_jit(lambda a, e: tj.TippeTop.from_ratios(a, e))
    jax.block_until_ready(build(jnp.asarray(0.9), jnp.asarray(0.3)))
    with pytest.raises(Exception, match=re.escape("TippeTop.eps")):
        jax.block_until_ready(build(jnp.asarray(0.9), jnp.asarray(1.2)))
    with pytest.raises(Exception, match=re.escape("A/C must be >= 1/2")):
        jax.block_until_ready(build(jnp.asarray(0.3), jnp.asarray(0.3)))


def test_batch_with_one_bad_member_raises():
    ratios = np.array([0.6, 0.9, 0.45, 1.5])  # the third has A/C < 1/2
    eps = np.array([0.1, 0.3, 0.3, 0.5])
    with pytest.raises(ValueError, match=re.escape("A/C must be >= 1/2")):
        tj.TippeTop.from_ratios(ratios, eps)
    eps_bad = np.array([0.1, 0.3, 1.0, 0.5])  # the third has eps = R
    with pytest.raises(ValueError, match=re.escape("TippeTop.eps")):
        tj.TippeTop.from_ratios(np.array([0.6, 0.9, 1.0, 1.5]), eps_bad)
    mu = np.array([0.3, 0.3, np.nan, 0.3])
    with pytest.raises(ValueError, match=re.escape("TippeTop.mu must be finite")):
        tj.TippeTop.from_ratios(np.array([0.6, 0.9, 1.0, 1.5]), eps, mu=mu)
    # The good batch is fine.
    tj.TippeTop.from_ratios(np.array([0.6, 0.9, 1.0, 1.5]), eps)


def test_batch_with_one_bad_member_raises_under_jit():
    build = eqx.filter_jit(lambda a, e: tj.TippeTop.from_ratios(a, e))
    eps = jnp.array([0.1, 0.3, 0.3, 0.5])
    jax.block_until_ready(build(jnp.array([0.6, 0.9, 1.0, 1.5]), eps))
    with pytest.raises(Exception, match=re.escape("A/C must be >= 1/2")):
        jax.block_until_ready(build(jnp.array([0.6, 0.9, 0.45, 1.5]), eps))


def test_astype_float32():
    top = tj.TippeTop(**VALID)
    top32 = top.astype(jnp.float32)
    for f in FIELDS:
        value = getattr(top32, f)
        assert value.dtype == jnp.float32
        np.testing.assert_allclose(float(value), VALID[f], rtol=1e-7)
    back = top32.astype(jnp.float64)
    assert all(getattr(back, f).dtype == jnp.float64 for f in FIELDS)


def test_default_top():
    top = tj.default_top()
    np.testing.assert_allclose(float(top.A_over_C), 0.9, rtol=1e-15)
    np.testing.assert_allclose(float(top.eps_over_R), 0.3, rtol=1e-15)
    assert float(top.m) == 0.02 and float(top.R) == 0.025 and float(top.mu) == 0.3


# replace, repr, batches from one swept field


def test_replace_changes_one_field_and_checks_it():
    top = tj.default_top()
    new = top.replace(mu=0.1)
    assert float(new.mu) == 0.1
    for k in ("m", "R", "eps", "A", "C", "g"):
        assert float(getattr(new, k)) == float(getattr(top, k))
    assert float(top.mu) == 0.3  # the original is unchanged
    with pytest.raises(ValueError, match="mu"):
        top.replace(mu=-1.0)
    with pytest.raises(ValueError, match="unknown field"):
        top.replace(Mu=1.0)
    with pytest.raises(ValueError, match="not both"):
        top.replace(A=1e-6, A_over_C=1.0)


def test_replace_with_ratios_keeps_C_and_R():
    top = tj.default_top()
    new = top.replace(A_over_C=1.2, eps_over_R=0.1)
    np.testing.assert_allclose(float(new.A_over_C), 1.2, rtol=1e-15)
    np.testing.assert_allclose(float(new.eps_over_R), 0.1, rtol=1e-15)
    assert float(new.C) == float(top.C) and float(new.R) == float(top.R)
    with pytest.raises(ValueError, match="A/C must be >= 1/2"):
        top.replace(A_over_C=0.4)


def test_sweeping_one_field_makes_a_batch():
    top = tj.default_top()
    mus = np.linspace(0.1, 1.0, 4)
    tops = top.replace(mu=mus)
    assert tops.batch_shape == (4,)
    for k in ("m", "R", "eps", "A", "C", "g", "mu"):
        assert getattr(tops, k).shape == (4,)
    np.testing.assert_array_equal(np.asarray(tops.mu), mus)
    np.testing.assert_array_equal(np.asarray(tops.A), float(top.A))
    # jax.vmap over the batch sees one top per member
    rates = jax.vmap(tj.friction_rate)(tops)
    np.testing.assert_allclose(
        np.asarray(rates), [float(tj.friction_rate(top.replace(mu=m))) for m in mus], rtol=1e-15
    )
    with pytest.raises(ValueError, match="do not broadcast"):
        tj.TippeTop(m=[0.02, 0.03], R=0.025, eps=0.0075, A=4.5e-6, C=5e-6, mu=[0.1, 0.2, 0.3])


def test_repr_shows_values():
    top = tj.default_top()
    text = repr(top)
    assert text == "TippeTop(m=0.02, R=0.025, eps=0.0075, A=4.5e-06, C=5e-06, g=9.81, mu=0.3)"
    assert "f64[]" not in text
    batch = repr(top.replace(mu=[0.1, 0.2]))
    assert "batch_shape=(2,)" in batch and "mu=[0.1 0.2]" in batch and "m=0.02" in batch


def test_a_batch_with_invalid_members_names_them_briefly():
    """One bad corner of a large sweep: the message names the members and stays short."""
    top = tj.default_top()
    ratios = np.linspace(0.3, 2.0, 171)[:, None] * np.ones((1, 97))
    ratios[100, 7] = 0.9 * 0.5 + 1e-17  # noise-level values print as numbers, not 17 digits
    with pytest.raises(ValueError) as info:
        top.replace(A_over_C=ratios)
    message = str(info.value)
    assert len(message) < 1000
    bad = np.argwhere(ratios < 0.5)
    assert f"{len(bad)} of the batch's {ratios.size} " in message
    assert f"[{bad[0][0]}, {bad[0][1]}]" in message and "more" in message
    assert "4.500000000000001" not in message
    one = np.full(5, 0.9)
    one[3] = 0.4
    with pytest.raises(ValueError, match=r"1 of the batch's 5 .* at index \[3\]: .*A=2e-06"):
        top.replace(A_over_C=one)
