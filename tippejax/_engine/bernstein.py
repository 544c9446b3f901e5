"""The event watch's sign test: a condition's quintic over a step and the signs of its Bernstein
coefficients (derivation: `docs/derivations/event-watch.md`)."""

from __future__ import annotations

import functools
import math
from fractions import Fraction

import jax.numpy as jnp
import numpy as np


def _hermite_to_power() -> list[list[Fraction]]:
    r"""The exact matrix that maps the Hermite data of a condition over a step,
    $(c_0, h\dot c_0, c_{1/2}, h\dot c_{1/2}, c_1, h\dot c_1)$, to the power coefficients
    $a_0, \dots, a_5$ of its quintic interpolant $p(s) = \sum_j a_j s^j$, $s\in[0, 1]$: the
    inverse of the Hermite conditions, by Gauss-Jordan elimination in rationals (so that the
    weights that are zero are exactly zero)."""
    half = Fraction(1, 2)
    rows = []
    for s in (Fraction(0), half, Fraction(1)):
        rows.append([s**j for j in range(6)])
        rows.append([j * s ** (j - 1) if j else Fraction(0) for j in range(6)])
    n = 6
    aug = [row + [Fraction(int(i == k)) for k in range(n)] for i, row in enumerate(rows)]
    for col in range(n):
        pivot = next(r for r in range(col, n) if aug[r][col] != 0)
        aug[col], aug[pivot] = aug[pivot], aug[col]
        aug[col] = [x / aug[col][col] for x in aug[col]]
        for r in range(n):
            if r != col and aug[r][col] != 0:
                aug[r] = [x - aug[r][col] * y for x, y in zip(aug[r], aug[col])]
    return [row[n:] for row in aug]


def _matmul(a, b):
    return [[sum(x * b[k][j] for k, x in enumerate(row)) for j in range(len(b[0]))] for row in a]


def _quintic_samples(samples: int) -> np.ndarray:
    r"""The matrix that maps the Hermite data of a condition over a step (`_hermite_to_power`)
    to the values of its quintic interpolant at $s = k/$`samples`, $k = 1, \dots,$
    `samples` $- 1$: a check by sampling, to compare the Bernstein test with."""
    s = [[Fraction(k, samples) ** j for j in range(6)] for k in range(1, samples)]
    return np.array(_matmul(s, _hermite_to_power()), dtype=float)


@functools.cache
def _bernstein_polygon(pieces: int) -> np.ndarray:
    r"""The matrix that maps the Hermite data of a condition over a step (`_hermite_to_power`)
    to the Bernstein coefficients of its quintic on each of `pieces` equal parts of the step,
    in order, each part's last coefficient (its end value, the next part's first) once: shape
    `(5 * pieces + 1, 6)`, exact in rationals before it is rounded to floats.

    On part $k$, $s = (k + u)/P$, the quintic is $q(u) = \sum_i b_i \binom5i u^i(1-u)^{5-i}$
    with $q(u) = \sum_i c_i u^i$, $c_i = \sum_{j\ge i} a_j \binom ji k^{j-i}/P^j$ and
    $b_i = \sum_{l\le i} \binom il c_l / \binom5l$. The sign changes of the whole sequence bound
    the crossings of the quintic in the step from above (`docs/derivations/event-watch.md`)."""
    to_bernstein = [
        [Fraction(math.comb(i, j), math.comb(5, j)) if j <= i else Fraction(0) for j in range(6)]
        for i in range(6)
    ]
    rows = []
    for k in range(pieces):
        shift = [
            [
                Fraction(math.comb(j, i) * k ** (j - i), pieces**j) if j >= i else Fraction(0)
                for j in range(6)
            ]
            for i in range(6)
        ]
        part = _matmul(_matmul(to_bernstein, shift), _hermite_to_power())
        rows.extend(part if k == pieces - 1 else part[:-1])
    return np.array(rows, dtype=float)


def bernstein_signs(previous, previous_rate, mid, mid_rate, end, end_rate, h, pieces: int):
    """Whether each Bernstein coefficient of each condition's quintic over the step is
    positive (`_bernstein_polygon`, on `pieces` parts of the step): shape
    `(5 * pieces + 1,) + end.shape` (the conditions on the last axis, any leading axes
    before). The first row is the sign at the start of the step, the last at its end."""
    coefficients = bernstein_coefficients(
        previous, previous_rate, mid, mid_rate, end, end_rate, h, pieces
    )
    return coefficients > 0


def bernstein_coefficients(previous, previous_rate, mid, mid_rate, end, end_rate, h, pieces):
    """The Bernstein coefficients of each condition's quintic over the step, shaped as
    `bernstein_signs`' signs."""
    h = h.astype(end.dtype)
    data = (previous, h * previous_rate, mid, h * mid_rate, end, h * end_rate)
    weights = _bernstein_polygon(pieces).astype(np.dtype(end.dtype))
    # Each coefficient a sum of scaled data, the zero weights left out (the end coefficients
    # are the end values, the next ones two terms): XLA fuses these; as a matrix product
    # they ran as a small batched dot per member of a batch.
    rows = []
    for row in weights:
        terms = [w * x for w, x in zip(row, data) if w != 0.0]
        rows.append(sum(terms[1:], terms[0]))
    return jnp.stack(rows)


def settled_signs(positive, significant):
    """`positive` (`bernstein_signs`) with each coefficient inside its condition's rounding
    floor (`significant` False) given the sign of the nearest significant one before it (after
    it, before the first): a condition at zero to rounding changes sign only where it leaves
    that band. A condition with no significant coefficient stays at zero to rounding all
    along the step: it keeps its first sign, and changes none."""
    rows = positive.shape[0]
    first = positive[rows - 1]  # the first significant sign, from the end backwards
    for k in range(rows - 2, -1, -1):
        first = jnp.where(significant[k], positive[k], first)
    filled, last = [], first
    for k in range(rows):
        last = jnp.where(significant[k], positive[k], last)
        filled.append(last)
    held = jnp.broadcast_to(positive[0], positive.shape)
    return jnp.where(jnp.any(significant, axis=0), jnp.stack(filled), held)


def hidden_crossing(positive, watched=None):
    """Whether some condition's coefficients (`bernstein_signs`) change sign more than once:
    the step may hide a crossing and its way back. Shape `positive.shape[1:-1]`.

    `watched`: which conditions count, broadcast against `positive.shape[1:]` (default all):
    an observed event already recorded has no crossing left to find, and its later crossings,
    however close (a compliant contact's chatter), must not hold the steps back."""
    many = jnp.sum(positive[1:] != positive[:-1], axis=0) > 1
    if watched is not None:
        many = many & watched
    return jnp.any(many, axis=-1)


def fell(positive, columns):
    """Whether each of the conditions `columns` fell through zero along the step: one of its
    coefficients (`bernstein_signs`) is positive and the next is not. Shape
    `positive.shape[1:-1] + (len(columns),)`."""
    columns = jnp.asarray(columns, int)
    return jnp.any(positive[:-1][..., columns] & ~positive[1:][..., columns], axis=0)
