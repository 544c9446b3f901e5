"""What is drawn at each frame: the frame times and the top's geometry resampled to them."""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import numpy as np

from .._solution import RESULTS, Solution
from .._top import TippeTop

STEM_LENGTH = 0.55  # drawn stem beyond the sphere, in units of R


STEM_RIM = math.radians(38.0)  # polar angle (from +a) of the drawn rim of the flat face


_SHORT_REASON = {
    "contact_lost": "contact lost (R_n = 0)",
    "normal_force_singular": "R_n singular",
    "max_steps_reached": "max_steps reached",
    "nonfinite": "non-finite values",
    "solver_failed": "solver failed",
    "contact_loss_missed": "contact lost (between save times)",
    "stiff_under_trace": "not integrated",
    "no_gyroscopic_balance": "gyroscopic balance lost",
}


class FrameGeometry(NamedTuple):
    """What is drawn at each frame time (numpy arrays, leading axis: frames; lengths in m).

    - `t`: the frame times (s).
    - `axis`, `body`: the symmetry axis $a$ and the body-fixed vector perpendicular to it.
    - `theta`: tilt $\\arccos a_Z$ (rad).
    - `centre`: centre of the sphere (height $R$); `centre_of_mass`: $\\mathcal C - \\epsilon a$.
    - `contact`: contact point $Q = \\mathcal C - R e_Z$ (on the table).
    - `stem`: `(frames, 2, 3)`, the drawn stem from the sphere's surface outwards along $+a$,
      clipped at the table; for a top with a `tj.Stem`, the rod from the rim's plane of the
      flat face to the centre of the tip's sphere.
    - `stem_tip`: `(frames, 3)`, the centre $O + a_2 a$ of the tip's sphere (a top with a
      `tj.Stem`; nan without one).
    """

    t: np.ndarray
    axis: np.ndarray
    body: np.ndarray
    theta: np.ndarray
    centre: np.ndarray
    centre_of_mass: np.ndarray
    contact: np.ndarray
    stem: np.ndarray
    stem_tip: np.ndarray


def _numpy_member(sol: Solution, index) -> Solution:
    """`sol` with numpy leaves, one member of a batch if `index` is given."""
    batched = np.ndim(sol.theta) > 1
    if index is None and batched:
        raise ValueError(
            f"animate draws one trajectory, but this solution is batched (theta has shape "
            f"{np.shape(sol.theta)}). Pass index=i (or a tuple for several batch axes) to pick a "
            f"member."
        )
    if index is not None and not batched:
        raise ValueError("index= is for batched solutions; this solution holds one trajectory.")
    if index is not None:
        sol = jax.tree_util.tree_map(lambda x: x[index], sol)
    return jax.tree_util.tree_map(np.asarray, sol)


def _valid_count(sol: Solution) -> int:
    """Number of leading save times with a finite state (the rest is a nan tail)."""
    finite = np.isfinite(sol.theta) & np.all(np.isfinite(sol.states.axis), axis=-1)
    finite &= np.all(np.isfinite(sol.states.body), axis=-1)
    finite &= np.all(np.isfinite(sol.states.omega), axis=-1)
    bad = np.flatnonzero(~finite)
    return int(bad[0]) if bad.size else int(finite.size)


def _end_reason(sol: Solution, n_valid: int) -> str | None:
    """Why the solution ends before its last save time (None if it does not)."""
    names = {int(item._value): name for name, item in RESULTS._name_to_item.items()}
    code = int(np.asarray(sol.result._value))
    if n_valid == np.size(sol.ts) and code == 0:
        return None
    reason = _SHORT_REASON.get(names.get(code, ""), names.get(code, "failure"))
    if code == 0:
        reason = "non-finite values"
    return f"run ends at t = {float(sol.ts[n_valid - 1]):.3g} s: {reason}"


def frame_times(
    t_first: float,
    t_last: float,
    *,
    fps: float,
    speed: float | None = None,
    duration: float | None = None,
    frames: int | None = None,
) -> np.ndarray:
    r"""Times (s of the simulation) of the frames of an animation of `[t_first, t_last]`.

    One frame every `speed / fps` seconds of simulation (`speed` = seconds of simulation per
    second of animation; default 1, real time) from `t_first`, the last one at or before `t_last`.
    `duration` (s of animation) sets `speed = (t_last - t_first) / duration`; `frames` gives
    exactly that many frames evenly from `t_first` to `t_last`. Give at most one of the three.
    """
    given = [
        name
        for name, v in (("speed", speed), ("duration", duration), ("frames", frames))
        if v is not None
    ]
    if len(given) > 1:
        raise ValueError(
            f"give at most one of speed, duration and frames (got {', '.join(given)})."
        )
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps!r}.")
    span = float(t_last) - float(t_first)
    if not span >= 0:
        raise ValueError(f"the animated time span is empty: [{t_first}, {t_last}].")
    if frames is not None:
        if not (isinstance(frames, (int, np.integer)) and frames >= 1):
            raise ValueError(f"frames must be a positive integer, got {frames!r}.")
        return np.linspace(t_first, t_last, int(frames)) if frames > 1 else np.array([t_first])
    if duration is not None:
        if not duration > 0:
            raise ValueError(f"duration must be positive, got {duration!r}.")
        speed = span / duration
        if speed == 0:
            return np.full(max(1, round(duration * fps)), float(t_first))
    speed = 1.0 if speed is None else float(speed)
    if not speed > 0:
        raise ValueError(f"speed must be positive, got {speed!r}.")
    step = speed / fps
    count = int(math.floor(span / step * (1 + 1e-12))) + 1
    return t_first + step * np.arange(count)


def _rotate(vectors: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues: rotate each row of `vectors` by the rotation vector in the same row."""
    angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    safe = np.where(angle > 0, angle, 1.0)
    k = rotvec / safe
    cos, sin = np.cos(angle), np.sin(angle)
    k_dot_v = np.sum(k * vectors, axis=-1, keepdims=True)
    return vectors * cos + np.cross(k, vectors) * sin + k * k_dot_v * (1 - cos)


def frame_geometry(sol: Solution, top: TippeTop, t) -> FrameGeometry:
    r"""The drawn geometry of one (unbatched) solution at times `t` (within its valid range).

    The orientation at `t` is that of the nearest save time $t_k$, turned by
    $\omega_k (t - t_k)$ (exact for constant $\omega$; the spin, the fast part, is then right
    between coarse save times); the centre-of-mass position is interpolated linearly.
    """
    sol = jax.tree_util.tree_map(np.asarray, sol)
    n_valid = _valid_count(sol)
    ts = sol.ts[:n_valid]
    t = np.atleast_1d(np.asarray(t, dtype=float))
    upper = np.clip(np.searchsorted(ts, t), 0, n_valid - 1)
    lower = np.maximum(upper - 1, 0)
    k = np.where(np.abs(t - ts[lower]) <= np.abs(ts[upper] - t), lower, upper)
    turn = sol.states.omega[k] * (t - ts[k])[:, None]
    axis = _rotate(sol.states.axis[k], turn)
    body = _rotate(sol.states.body[k], turn)
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    body -= np.sum(body * axis, -1, keepdims=True) * axis
    body /= np.linalg.norm(body, axis=-1, keepdims=True)
    R, eps = float(top.R), float(top.eps)
    position = np.stack([np.interp(t, ts, _centre_xy(sol)[:n_valid, i]) for i in range(2)], axis=-1)
    height = R - eps * axis[:, 2]
    if sol.states.height is not None:  # (a top with a stem: its height is a state)
        height = np.interp(t, ts, sol.states.height[:n_valid])
    cm = np.concatenate([position, height[:, None]], axis=-1)
    centre = cm + eps * axis
    contact = centre.copy()
    contact[:, 2] -= R
    stem_tip = np.full_like(cm, np.nan)
    if top.stem is None:
        base = centre + R * axis
        tip = centre + (1 + STEM_LENGTH) * R * axis
        # Clip the stem at the table (z = 0); the base is at height R (1 + a_Z) >= 0.
        drop = base[:, 2] - tip[:, 2]
        frac = np.where(tip[:, 2] < 0, base[:, 2] / np.where(drop > 0, drop, 1.0), 1.0)
        tip = base + np.clip(frac, 0.0, 1.0)[:, None] * (tip - base)
    else:  # the modelled stem: from the flat face's plane to the centre of its tip's sphere
        stem_tip = cm + float(top.stem.offset) * axis
        base = centre + R * math.cos(STEM_RIM) * axis
        tip = stem_tip
    theta = np.arccos(np.clip(axis[:, 2], -1.0, 1.0))
    return FrameGeometry(
        t, axis, body, theta, centre, cm, contact, np.stack([base, tip], 1), stem_tip
    )


def _centre_xy(sol) -> np.ndarray:
    """The centre of mass's horizontal position: the run's, or the state's for a level that
    does not model the translation (its `sol.position` is nan; the centre stays put)."""
    position = np.asarray(sol.position)
    return np.where(np.isfinite(position), position, np.asarray(sol.states.position))
