"""The result of `tippejax.simulate`: a solution at the save times, with failure codes."""

from __future__ import annotations

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from . import _export

OUTCOMES = ("upright", "inverted", "intermediate", "contact_lost", "failed", "on_stem")
"""Outcome codes of `outcome_map` and `sol.outcome`: `tj.OUTCOMES[int(om.outcome[i, j])]`.
New outcomes are appended, so that the codes of the others keep their values."""


class RESULTS(eqxi.Enumeration):
    """Outcome of a simulation. `successful` is the empty message."""

    successful = ""
    max_steps_reached = (
        "The maximum number of solver steps was reached before t1. Increase `max_steps`, shorten "
        "the run or loosen the tolerances (the steps follow the nutation: their number grows "
        "with spin x (t1 - t0)). An implicit solver (diffrax.Kvaerno5()) helps only when the "
        "friction is stiff, tj.friction_rate(top) above about 1e3/s."
    )
    contact_lost = (
        "The normal force R_n reached 0: the top leaves the table and the contact model no "
        "longer applies (docs/notes.md, 'Contact loss'). Values after `t_contact_loss` are "
        "not physical."
    )
    normal_force_singular = (
        "The denominator of R_n vanished: a Painleve-type singularity of friction proportional "
        "to R_n (docs/notes.md, 'The R_n singularity'). The model has no solution beyond this "
        "time."
    )
    nonfinite = "The solution became NaN or infinite."
    solver_failed = "The ODE solver failed (step size underflow or an internal diffrax error)."
    contact_loss_missed = (
        "R_n was negative at a save time before any contact loss the solver located: a dip of "
        "R_n below 0 too brief for the event watch's quintic over one step to follow went "
        "unseen, so the first loss of contact is somewhere before that save time. Tighten "
        "rtol (shorter steps); values from there on are nan."
    )
    stiff_under_trace = (
        "This top's friction is very stiff (friction_rate > 5e5/s) and simulate ran under "
        "jit/vmap with a traced top, where the default solver must be explicit (Dopri8) and "
        "would not finish. Pass solver=diffrax.Kvaerno5(), or call simulate with a concrete "
        "top so that the default can be chosen per top. The member was not integrated."
    )
    no_gyroscopic_balance = (
        "model='gyroscopic' cannot describe this motion: either the steady-precession "
        "(gyroscopic balance) equation A h Omega^2 - J Omega - m g eps (R cos(theta) - eps) = 0 "
        "has no real root here (the spin is too slow, e.g. |n_pi| < n_* = 2 sqrt(A m g eps)/C "
        "near the inverted position), or the nutation the level averages out has grown past "
        "0.05 rad and is still growing (at fast spins the slow manifold repels during the rise; "
        "a contact loss may follow), or the launch has more than 0.25 rad of nutation (too far "
        "from the slow manifold to project). The run stopped at `t_final` (a launch outside was "
        "not integrated; values from there on are nan). Use model='so3' (or 'routhian', 'full')."
    )


def _is_item(x) -> bool:
    """An item of an equinox enumeration (e.g. `RESULTS.successful`, or `sol.result`)."""
    return hasattr(x, "_enumeration") and hasattr(x, "_value")


def result_message(code, enumeration=None):
    """The message of a result code, or of an array of codes elementwise.

    The one way to read a result in tippejax: `tj.RESULTS.message(x)`, or `x.message()` on a
    `Solution` (single run or batch) and an `OutcomeMap`.

    **Arguments:**

    - `code`: an item of a result enumeration (`sol.result`, scalar or batched), a plain
      integer code or an integer array of codes (`OutcomeMap.result`), or any object with a
      `result` field (a `Solution`, an `OutcomeMap`).
    - `enumeration`: the enumeration whose table reads integer codes (default `RESULTS`). An
      enumeration item always carries its own.

    **Returns:** a `str` for one code, or a numpy array of `str` with the codes' shape. A
    successful code reads `"successful"` (its message in the enumeration is empty).
    """
    if enumeration is None:
        enumeration = RESULTS
    if _is_item(code):
        enumeration = code._enumeration
        code = code._value
    elif not isinstance(code, (int, np.integer, np.ndarray, jax.Array)) and hasattr(code, "result"):
        return result_message(code.result, enumeration)
    if isinstance(code, jax.core.Tracer):
        raise ValueError(
            "result messages are read outside jax.jit/vmap: return the result code from the "
            "jitted function and call tj.RESULTS.message on it afterwards."
        )
    if isinstance(code, bool) or not isinstance(code, (int, np.integer, np.ndarray, jax.Array)):
        raise ValueError(
            "tj.RESULTS.message takes a result code (sol.result, an integer or an integer "
            f"array) or an object with a `result` field, got {type(code).__name__}."
        )
    values = np.asarray(code)
    if not np.issubdtype(values.dtype, np.integer):
        raise ValueError(f"result codes are integers, got an array of dtype {values.dtype}.")
    names = list(enumeration._name_to_item)
    table = [""] * len(names)
    for name, item in enumeration._name_to_item.items():
        index = int(item._value)
        table[index] = enumeration._index_to_message[index] or name
    if np.any(values < 0) or np.any(values >= len(table)):
        raise ValueError(
            f"result codes of {enumeration.__name__} lie in [0, {len(table) - 1}], got "
            f"{values.min()} to {values.max()}."
        )
    if values.ndim == 0:
        return table[int(values)]
    return np.array(table)[values]


def attach_message(enumeration) -> None:
    """Give an enumeration the method `enumeration.message(code)` (`result_message` with its own
    table). Enumerations take no methods in their class body: every name there is an item."""
    type.__setattr__(
        enumeration, "message", classmethod(lambda cls, code: result_message(code, cls))
    )


attach_message(RESULTS)


def _export_name(name: str) -> str:
    return name if name in ("theta0", "top") else f"{name}0"


SAVED_FIELDS = (
    "ts",
    "theta",
    "phi",
    "psi",
    "theta_dot",
    "phi_dot",
    "psi_dot",
    "spin",
    "position",
    "velocity",
    "jellet",
    "energy",
    "normal_force",
    "slip_speed",
)
"""The fields with a save axis (and `states`)."""


def drop_save_axis(sol: Solution, batch_ndim: int) -> Solution:
    """A summary-mode batch with the save axis (of length one, after the batch's axes)
    dropped from every saved field and the states."""

    def squeeze(x):
        return x if x is None else jnp.squeeze(x, axis=batch_ndim)

    names = [k for k in SAVED_FIELDS if getattr(sol, k) is not None]
    sol = eqx.tree_at(
        lambda s: [getattr(s, k) for k in names], sol, [squeeze(getattr(sol, k)) for k in names]
    )
    if sol.states is not None:
        sol = eqx.tree_at(lambda s: s.states, sol, jax.tree_util.tree_map(squeeze, sol.states))
    return sol


class _NotOne(Exception):
    """A solution that is not one concrete run (batched or traced): no summary."""


class Solution(eqx.Module):
    r"""A simulated trajectory, sampled at the save times `ts`.

    Entries at save times after the run stopped (contact loss with `on_contact_loss="stop"`, the
    $R_n$ singularity, a solver failure) are nan; `result` says why it stopped.

    **Fields** (shape `(n_save,)` unless said; leading batch axes under `vmap`):

    - `ts`: save times (s).
    - `theta`, `phi`, `psi`: ZXZ Euler angles (rad); `phi`, `psi` unwrapped. `phi`, `psi` and
      their rates are singular where $\sin\theta = 0$.
    - `theta_dot`, `phi_dot`, `psi_dot`: Euler rates (rad/s); `spin`: $n = \omega\cdot a$.
    - `position`, `velocity`: horizontal centre-of-mass position and velocity, `(n_save, 2)`
      (nan for the SO(3), Routhian and gyroscopic levels, which drop the translation).
    - `jellet`: $J$; `energy`: $E$; `normal_force`: $R_n$; `slip_speed`: $|v_Q|$.
    - `states`: the `State`s at `ts` (in a level's own terms: a level without translation
      keeps the centre of mass at rest there).
    - `model`: the level used (str); "routhian->so3" when a Routhian run left its chart;
      "gyroscopic->full" when a gyroscopic run handed over to the full model (see
      `t_hand_over`); "full->stem" when the run of a top with a stem went on to the stem
      level (two compliant contacts, `docs/friction.md`). From there `energy` includes the contacts' elastic
      energy, `normal_force` is the table's whole normal force (ball and stem) and
      `slip_speed` that of the contact carrying more of it; `states.height` is the height of
      the centre of mass.
      A gyroscopic run that leaves the domain of gyroscopic balance stops there
      (`result == RESULTS.no_gyroscopic_balance`) and stays "gyroscopic".
    - `result`: a `RESULTS` code (`sol.result == tj.RESULTS.successful`); `sol.message()`
      gives its text (an array of texts for a batch).
    - `t_invert`: first upward crossing of $\theta = \pi/2$ (nan if none).
    - `t_contact_loss`: first time $R_n = 0$ (nan if never).
    - `t_chart_switch`: time a run left its level's chart for the level's fallback (nan
      otherwise): a Routhian run near a pole, a gyroscopic run where its chart ends, the full
      level of a top with a stem just before the stem touched (the stem level follows).
    - `t_hand_over` (property): the same time, for a gyroscopic run, read as the hand-over
      from the slow flow (G3) to the full model: the slow flow runs from `t0` to
      `t_hand_over`, the full model from `t_hand_over` (from the state on the slow manifold
      there) to `t_final`, and nothing of the full model runs before it. The level hands
      over where its chart condition falls through zero: the nutation it drops starts to
      grow, $-\sigma/\nu$ below `HAND_OVER_MARGIN` (the slow manifold repels), or the
      gyroscopic balance (G2) loses its real root (`docs/derivations/gyroscopic-averaging.md`).
      `t0` for a launch outside the chart (the full model runs the whole run), nan for a run
      that never hands over (the slow flow runs it all) and for every other level.
    - `t_stem`: the first touch of the stem (`tj.Stem`) on the table (nan if none, and for a
      top without a stem).
    - `t_ball_return`: the first time the ball touches the table again after it left it on
      the stem level (nan if it does not by `t_final`, and for a top without a stem).
    - `t_final`: the time the integration reached (t1 unless it stopped early).
    - `num_steps`, `num_rejected_steps`: solver statistics (all segments together).
    - `outcome`: where the run ended, an index into `tj.OUTCOMES` ("upright", "inverted",
      "intermediate", "contact_lost", "failed", "on_stem"): the stable steady state of the
      launch's Jellet $J$ nearest to the tilt where the run ended, classified as
      `tj.outcome_map` does (`tippejax/_maps.py`); "contact_lost" when $R_n$ reached 0,
      "failed" for any other failure; "on_stem" for a top with a stem that ended tilted past
      `top.stem_angle`, where the stem and not the ball rests on the table (settled within
      0.1 rad of the vertical $\theta = \pi$ on the stem). `tj.OUTCOMES[int(sol.outcome)]` is
      its name.
    - `settled`: the final tilt is within 0.1 rad of that state (`print(sol)` says "on its
      way" for a run that is not). A run still on its way at
      `t1` is classified by the state it is nearest to; only `outcome == inverted` with
      `settled` says that the top turned over and stayed there. (`t_invert`, the first upward
      crossing of $\pi/2$, is no proof of inversion: a Group III top or a top that settles on
      an intermediate state beyond $\pi/2$ crosses it too.)

    A field a level does not model is nan at the save times that level produced, never a
    number (`AbstractLevel.unmodelled`): with `model="gyroscopic"` the others are those of the
    state on the slow manifold (`theta_dot` the slow drift, without the nutation; `phi_dot` the
    balance precession rate; `spin`, `energy` their values there; `jellet` exact), while `psi`,
    `normal_force`, `slip_speed`, `position` and `velocity` are nan until a hand-over to the
    full model (`"gyroscopic->full"`), after which the full model's values follow.
    A batch from `tj.simulate_batch` also keeps its inputs:

    - `inputs`: every member's inputs as arrays of the batch's shape: the launch (`theta0`, and
      `spin0`, `theta_dot0`, `phi_dot0`, `phi0`, `psi0`, `vx0`, `vy0`: the values at $t_0$), the
      top's fields (`m`, `R`, `eps`, `A`, `C`, `g`, and its friction law's: `mu`, ...) and its
      ratios `A_over_C`, `eps_over_R`.
    - `grid`: the names of the batch's grid axes, as given to `simulate_batch` (`("theta0",
      "spin")` by default); `sol.coords()` gives each axis's values.

    In summary mode a batch's fields have the batch's shape (no save axis). Every result
    exports itself: `to_dict()`, `to_csv(path)` (one row per member), `to_npz(path)`, and
    `to_xarray()` (the optional dependency xarray; `pip install xarray`).
    """

    ts: Float[Array, "*batch n"]
    theta: Float[Array, "*batch n"]
    phi: Float[Array, "*batch n"]
    psi: Float[Array, "*batch n"]
    theta_dot: Float[Array, "*batch n"]
    phi_dot: Float[Array, "*batch n"]
    psi_dot: Float[Array, "*batch n"]
    spin: Float[Array, "*batch n"]
    position: Float[Array, "*batch n 2"]
    velocity: Float[Array, "*batch n 2"]
    jellet: Float[Array, "*batch n"]
    energy: Float[Array, "*batch n"]
    normal_force: Float[Array, "*batch n"]
    slip_speed: Float[Array, "*batch n"]
    states: object
    result: RESULTS
    t_invert: Float[Array, "*batch"]
    t_contact_loss: Float[Array, "*batch"]
    t_chart_switch: Float[Array, "*batch"]
    t_final: Float[Array, "*batch"]
    num_steps: Int[Array, "*batch"]
    num_rejected_steps: Int[Array, "*batch"]
    model: str = eqx.field(static=True)
    outcome: Int[Array, "*batch"] | None = None
    settled: Bool[Array, "*batch"] | None = None
    inputs: dict | None = None
    grid: tuple[str, ...] | None = eqx.field(static=True, default=None)
    t_stem: Float[Array, "*batch"] | None = None
    t_ball_return: Float[Array, "*batch"] | None = None

    def message(self):
        """The message of `result`: a `str`, or a numpy array of `str` for a batch
        (`"successful"` where the run succeeded). Same as `tj.RESULTS.message(sol.result)`."""
        return result_message(self.result)

    def __repr__(self) -> str:
        try:
            return self._summary()
        except _NotOne:
            return eqx.tree_pformat(self)

    __str__ = __repr__

    def _summary(self) -> str:
        """One run's summary: the level, the result, its events and where it ended."""
        leaves = [self.t_final, self.t_invert, self.theta]
        if any(isinstance(x, jax.core.Tracer) for x in leaves) or np.ndim(self.t_final) != 0:
            raise _NotOne
        ts, theta = np.asarray(self.ts), np.asarray(self.theta)

        def seconds(x) -> str:
            x = float(x)
            return "nan" if np.isnan(x) else f"{x:.6g} s"

        parts = [
            f"model={self.model!r}",
            f"result={result_message(self.result)!r}",
            f"t_final={seconds(self.t_final)}",
            f"saves={ts.size}",
            f"t_invert={seconds(self.t_invert)}",
            f"t_contact_loss={seconds(self.t_contact_loss)}",
        ]
        if "->stem" in self.model:  # (a top with a stem that reached the stem level)
            parts += [
                f"t_stem={seconds(self.t_stem)}",
                f"t_ball_return={seconds(self.t_ball_return)}",
            ]
        if self.outcome is not None:
            name = OUTCOMES[int(self.outcome)]
            if (
                self.settled is not None
                and not bool(self.settled)
                and name in ("upright", "inverted", "intermediate")
            ):
                name += " (on its way: not settled by t_final)"
            parts.append(f"outcome={name!r}")
        finite = np.isfinite(theta)
        if finite.any():
            parts.append(f"theta_end={float(theta[finite][-1]):.6g} rad")
        parts.append(f"steps={int(self.num_steps)}")
        return "Solution(" + ", ".join(parts) + ")"

    def coords(self) -> dict[str, np.ndarray]:
        """The values along each grid axis of a batch (`grid`): `{name: 1-d array}`; for a
        grid axis of tops (`"top"`), the member index."""
        if self.grid is None or self.inputs is None:
            raise ValueError(
                "coords() needs a batch from tj.simulate_batch; a single run or a batch made "
                "with jax.vmap has no grid (sol.grid is None)."
            )
        out = {}
        for axis, name in enumerate(self.grid):
            if name == "top":
                out[name] = np.arange(np.shape(self.t_final)[axis])
                continue
            values = np.asarray(self.inputs[_export_name(name)])
            index = tuple(slice(None) if i == axis else 0 for i in range(values.ndim))
            out[name] = values[index]
        return out

    def to_dict(self) -> dict[str, np.ndarray]:
        """The result as numpy arrays: every field (series with their save axis; `position`,
        `velocity` with a trailing axis of 2), the outcome's name, the result's message, and
        for a batch its `inputs` under their names (see the class docstring)."""
        return _export.solution_dict(self, result_message(self.result), OUTCOMES)

    def to_csv(self, path) -> None:
        """Write one row per member (one row for a single run) to `path`: the inputs of a
        batch, the event times, the outcome and whether it `settled`, the result, the step
        counts, and each series' value at the last save time (columns `theta_end`, ...). The
        whole series are in `to_npz` and `to_xarray`."""
        _export.write_csv(self.to_dict(), path, batch_ndim=np.ndim(self.t_final))

    def to_npz(self, path) -> None:
        """Write every array of `to_dict()` to `path` with `numpy.savez_compressed`
        (`np.load(path)` reads it), with the grid's names and the level under `grid`,
        `model`."""
        _export.write_npz(self.to_dict(), path, grid=self.grid, model=self.model)

    def to_xarray(self):
        """The result as an `xarray.Dataset`: dimensions named by the grid (`theta0`, `spin`
        for the default grid, with their values as coordinates; `member_k` where there is no
        grid), `time` for the save times and `xy` for `position`, `velocity`; the inputs as
        coordinates over the batch's dimensions. Needs xarray (`pip install xarray`)."""
        return _export.to_xarray(
            self.to_dict(), batch_shape=np.shape(self.t_final), grid=self.grid, model=self.model
        )

    @property
    def t_hand_over(self):
        """The time a gyroscopic run handed over from the slow flow to the full model (nan
        where none; see the class docstring). Leading batch axes as `t_final`."""
        if self.model.startswith("gyroscopic"):
            return self.t_chart_switch
        return jnp.full_like(self.t_chart_switch, jnp.nan)

    @property
    def succeeded(self):
        """Boolean array: True where the run reached t1 without a reported failure."""
        return self.result == RESULTS.successful
