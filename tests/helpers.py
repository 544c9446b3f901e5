"""Shared test helpers: tree comparison and one top per group."""

import jax
import jax.numpy as jnp

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
