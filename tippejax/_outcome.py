"""Where a run ends: its final tilt classified against the stable steady states of its Jellet."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ._analysis.branch import branch_pieces, find_branch_root
from ._analysis.potential import effective_potential_d2_closed_form
from ._solution import OUTCOMES, RESULTS
from ._top import TippeTop

UPRIGHT, INVERTED, INTERMEDIATE, CONTACT_LOST, FAILED, ON_STEM = range(len(OUTCOMES))

SETTLE_TOL = 0.1
"""Tilt distance (rad) within which a run's end counts as `settled` on its outcome."""

_CONTACT_CODES = ("contact_lost", "contact_loss_missed")


def stable_states(top: TippeTop, J) -> tuple[Float[Array, "4"], Bool[Array, "4"], Int[Array, "4"]]:
    r"""The steady states of `top` at Jellet `J` and whether each is stable ($W'' > 0$).

    The lean part of `steady_states` that a map needs (no eigenvalues): four slots, the
    vertical states $\theta = 0$ and $\pi$ and the two intermediate slots (roots of eq.
    (Exist) on the two monotone pieces of the branch).

    **Returns:** `(theta, stable, kind)`: tilts (nan for an empty slot), stability (False for an
    empty slot), and the outcome code of each slot (`UPRIGHT`, `INVERTED`, `INTERMEDIATE`).
    """
    dtype = jnp.result_type(top.m)
    J = jnp.asarray(J, dtype)
    roots = [find_branch_root(top, J, lo, hi) for lo, hi in branch_pieces(top)]
    theta = jnp.stack([jnp.zeros((), dtype), jnp.asarray(jnp.pi, dtype)] + [r[0] for r in roots])
    exists = jnp.stack([jnp.array(True), jnp.array(True)] + [r[1] for r in roots])
    safe = jnp.where(exists, theta, 1.0)
    d2w = effective_potential_d2_closed_form(top, safe, J)
    stable = exists & (d2w > 0)
    kind = jnp.array([UPRIGHT, INVERTED, INTERMEDIATE, INTERMEDIATE])
    return jnp.where(exists, theta, jnp.nan), stable, kind


def classify_end(top: TippeTop, J, theta_final, result, *, settle_tol):
    r"""Outcome code, settled flag and expected tilt of one run.

    The outcome is the stable state of the launch's Jellet $J$ (`stable_states`) nearest to
    the final tilt `theta_final`; `CONTACT_LOST` where the run ended on a contact loss
    (`result` `contact_lost` or `contact_loss_missed`), `FAILED` for any other failure and
    for a $J$ with no stable state. Settled: the final tilt is within `settle_tol` of that
    state.

    **Returns:** `(outcome, settled, expected)`: the code (int8, an index into `OUTCOMES`),
    the settled flag, and the tilt of the stable state (nan where there is none).

    A top with a stem (`tj.Stem`) that ended tilted past `top.stem_angle` rests on its stem,
    not on the ball: `ON_STEM`, settled within `settle_tol` of the vertical on the stem,
    $\theta = \pi$ (the steady states above are the ball's).
    """
    theta, stable, kind = stable_states(top, J)
    distance = jnp.where(stable, jnp.abs(theta_final - theta), jnp.inf)
    nearest = jnp.argmin(distance)
    any_stable = jnp.any(stable)
    outcome = jnp.where(any_stable, kind[nearest], FAILED)
    expected = jnp.where(any_stable, theta[nearest], jnp.nan)
    settled = any_stable & (distance[nearest] <= settle_tol)
    contact = jnp.zeros((), bool)
    for code in _CONTACT_CODES:
        contact = contact | (result == getattr(RESULTS, code))
    ok = (result == RESULTS.successful) & jnp.isfinite(theta_final)
    if top.stem is not None:  # (the stem, not the ball, on the table: the stem's outcome)
        on_stem = theta_final > top.stem_angle
        outcome = jnp.where(on_stem, ON_STEM, outcome)
        expected = jnp.where(on_stem, jnp.pi, expected)
        settled = jnp.where(on_stem, jnp.abs(theta_final - jnp.pi) <= settle_tol, settled)
    outcome = jnp.where(contact, CONTACT_LOST, jnp.where(ok, outcome, FAILED))
    return outcome.astype(jnp.int8), settled & ok, jnp.where(ok, expected, jnp.nan)


def classify(top: TippeTop, J, theta_end, result):
    """`sol.outcome` and `sol.settled` of one run: `classify_end` with `SETTLE_TOL`."""
    outcome, settled, _ = classify_end(top, J, theta_end, result, settle_tol=SETTLE_TOL)
    return outcome, settled


classify_program = eqx.filter_jit(classify)
"""`classify` as a program of its own (an eager `jax.grad` of `simulate` compiles it apart
from the differentiated solve)."""
