"""Shared test helpers: tree comparison and one top per group."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize

import tippejax as tj

# (A/C, eps/R) well inside each group (checked against the paper's inequalities in
# tests/test_analysis.py, which re-implements the classification independently).
GROUP_RATIOS = {
    "Ia": (0.9, 0.02),
    "Ib": (0.6, 0.1),
    "IIa": (0.55, 0.5),
    "IIb": (0.9, 0.3),
    "IIc": (0.95, 0.06),
    "III": (1.5, 0.2),
}

STANDARD = dict(A_over_C=0.9, eps_over_R=0.3, m=0.02, R=0.025, mu=0.3)


def tree_allclose(x, y, *, rtol=1e-5, atol=1e-8):
    same = jax.tree_util.tree_structure(x) == jax.tree_util.tree_structure(y)
    return same and all(
        bool(jnp.allclose(a, b, rtol=rtol, atol=atol))
        for a, b in zip(jax.tree_util.tree_leaves(x), jax.tree_util.tree_leaves(y))
    )


def mixed_tops():
    """Four tops of different groups, sizes, masses, g and mu (one not a homogeneous sphere)."""
    C = 0.4 * 0.3 * 0.05**2
    a_iia, e_iia = GROUP_RATIOS["IIa"]
    return [
        tj.TippeTop.from_ratios(*GROUP_RATIOS["IIb"]),  # the standard top
        tj.TippeTop.from_ratios(*GROUP_RATIOS["Ib"], m=0.05, R=0.03, mu=0.8),
        tj.TippeTop.from_ratios(*GROUP_RATIOS["III"], m=0.01, R=0.02, mu=0.1),
        # Not a homogeneous sphere (C != 0.4 m R^2), other g.
        tj.TippeTop(m=0.3, R=0.05, eps=e_iia * 0.05, A=a_iia * 0.9 * C, C=0.9 * C, g=9.7, mu=1.5),
    ]


MIXED_TOP_IDS = ["IIb-standard", "Ib", "III", "IIa-custom"]


def match_max_rel(ev_a, ev_b):
    """Largest |a_i - b_pi(i)| / max|a| over the optimal pairing of two eigenvalue sets."""
    ev_a = np.asarray(ev_a, dtype=complex)
    ev_b = np.asarray(ev_b, dtype=complex)
    cost = np.abs(ev_a[:, None] - ev_b[None, :])
    rows, cols = scipy.optimize.linear_sum_assignment(cost)
    return float(np.max(cost[rows, cols]) / np.max(np.abs(ev_a)))


def host_devices_env(n: int, **extra) -> dict:
    """The environment for a test's new process with `n` CPU devices: the pytest process's
    `XLA_FLAGS` (the suite's compile options, `conftest.TEST_XLA_FLAGS`) without its device
    count (tippejax sets one per core at import), and `n` host devices."""
    count = "--xla_force_host_platform_device_count"
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split() if not f.startswith(count)]
    return dict(os.environ, XLA_FLAGS=" ".join([f"{count}={n}", *flags]), **extra)
