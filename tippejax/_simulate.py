r"""Integration of the models with diffrax: solver choice, events, chart switching, failures.

The physics lives in `tippejax._models`; this module only wires it to `diffrax.diffeqsolve`.

Events (one diffrax `Event` per segment, located by bisection on the step's dense output):

- contact loss: the numerator of $R_n$ reaches 0 while its denominator is positive;
- the $R_n$ singularity: the denominator of $R_n$ reaches 0 (ERRATA.md, 5);
- (Routhian level) the chart boundary $\sin\theta = $ `CHART_SIN_MIN`, where the run continues in
  the SO(3) vector form, which is regular at the poles.

The first upward crossing of $\theta = \pi/2$ and, when the run goes on after contact loss, the first
zero of $R_n$, are bracketed on the save grid and then located by re-integrating that one save
interval with a terminating event.

Every condition is positive before its event and decreases through zero. The conditions of a
segment are combined into one scalar, their minimum, so that the event time can be found by
bisection inside the step where the sign changed (Newton's method, the usual choice, failed to
converge on some Dopri8 steps near contact loss); which condition fired is read off at the event.
"""

from __future__ import annotations

import functools
from typing import Literal

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import ArrayLike

from ._invariants import energy, jellet, normal_force, slip_velocity
from ._models._rigid_body import rigid_body_dynamics
from ._models.full import full_vector_field
from ._models.routhian import (
    RouthianState,
    routhian_from_state,
    routhian_normal_force,
    routhian_rates,
    routhian_vector_field,
    state_from_routhian,
)
from ._models.so3 import so3_vector_field
from ._solution import RESULTS, Solution
from ._state import State, euler_angles, euler_rates, spin
from ._top import TippeTop

LEVELS = ("full", "so3", "routhian", "gyroscopic", "auto")
CHART_SIN_MIN = 0.05
"""A Routhian run leaves its chart (for the SO(3) vector form) when $\\sin\\theta$ falls below this."""

STIFF_RATE = 1000.0
"""Friction damping rate (1/s) that separates the "stiff" regime of the level table."""

IMPLICIT_RATE = 5.0e5
"""Friction damping rate (1/s) above which the default solver is implicit (Kvaerno5)."""


def friction_rate(top: TippeTop):
    r"""Damping rate of sliding, $\mu g\, m (R+\epsilon)^2/A$ (1/s): the stiffness of the friction."""
    return top.mu * top.g * top.m * (top.R + top.eps) ** 2 / top.A


def default_solver(top: TippeTop) -> diffrax.AbstractSolver:
    """Tsit5, or Kvaerno5 when the friction is very stiff (`friction_rate` > `IMPLICIT_RATE`).

    From benchmarks/RESULTS.md: at mu = 300 s/m Tsit5 was 8-40x faster than Kvaerno5 (the spin must
    be resolved anyway); Kvaerno5 only wins near mu ~ 3e4 s/m for the standard top. Dopri8 takes
    0.3-0.5x Tsit5's time at rtol 1e-8..1e-10 and finds the same events there
    (`benchmarks/dopri8_events.py`), but its long steps at rtol 1e-6 stepped over the first zero
    of $R_n$ (events are seen from the signs at step ends), so it is not the default: pass
    `solver=diffrax.Dopri8()` with rtol <= 1e-8 for speed.

    Needs concrete parameters; for traced tops (e.g. `vmap` over tops) it returns Tsit5.
    """
    rate = friction_rate(top)
    if isinstance(rate, jax.core.Tracer):
        return diffrax.Tsit5()
    rate = float(np.max(np.asarray(rate)))
    return diffrax.Kvaerno5() if rate > IMPLICIT_RATE else diffrax.Tsit5()


def _event_dtype(x):
    # diffrax compares an event condition with a Python 0.0 in `lax.cond`: both branches must
    # have the default float dtype, also for a float32 top in a float64 process.
    return jnp.asarray(x, dtype=jnp.result_type(float))


def _vector_rn_parts(top, y: State, model):
    velocity = y.velocity if model == "full" else jnp.zeros_like(y.velocity)
    rn, _, _, den = rigid_body_dynamics(top, y.axis, y.omega, velocity)
    return _event_dtype(rn * den), _event_dtype(den)


def _routhian_rn_parts(top, r: RouthianState, J):
    _, phi_dot, _, n = routhian_rates(top, r.theta, r.phibar_dot, J)
    rn, den = routhian_normal_force(top, r.theta, r.theta_dot, phi_dot, n)
    return _event_dtype(rn * den), _event_dtype(den)


def _vector_field(model):
    return full_vector_field if model == "full" else so3_vector_field


def _solve(term, solver, t0, t1, y0, args, ts, rtol, atol, max_steps, event, meter):
    return diffrax.diffeqsolve(
        term,
        solver,
        t0,
        t1,
        None,
        y0,
        args,
        saveat=diffrax.SaveAt(subs=[diffrax.SubSaveAt(ts=ts), diffrax.SubSaveAt(t1=True)]),
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
        event=event,
        max_steps=max_steps,
        throw=False,
        progress_meter=meter,
    )


class _EventBisection(optx.Bisection):
    """Bisection for event times, which stops on the width of the bracket alone.

    `optx.Bisection` also asks for |condition| < atol, which a condition of size O(10) with a
    steep slope cannot meet in floating point. The bracket is the step in which the sign changed,
    so it always holds a root; `flip=True` because every condition here decreases through zero.
    """

    def terminate(self, fn, y, args, options, state, tags):
        del fn, args, options, tags
        width = jnp.abs(state.lower - state.upper)
        return width < self.atol + self.rtol * jnp.abs(y), optx.RESULTS.successful


def _root_finder(dtype):
    tol = 1e-12 if dtype == jnp.float64 else 1e-5
    return _EventBisection(rtol=tol, atol=tol, flip=True)


def _first_of(conds):
    """One condition that reaches zero when the first of `conds` does: their minimum."""

    def cond(t, y, args, **kwargs):
        return functools.reduce(jnp.minimum, [c(t, y, args, **kwargs) for c in conds])

    return cond


def _fired(sol, conds, args):
    """For each condition combined by `_first_of`: did the run stop on it?

    At the located event the condition that fired is (to the root finder's tolerance) zero and
    the others are positive, so it is the smallest.
    """
    if sol.event_mask is None:
        return [jnp.array(False)] * len(conds)
    t_end = sol.ts[1][-1]
    y_end = jax.tree_util.tree_map(lambda x: x[-1], sol.ys[1])
    values = jnp.stack([c(t_end, y_end, args) for c in conds])
    first = jnp.argmin(values)
    return [sol.event_mask & (first == i) for i in range(len(conds))]


def _event_time(sol, fired, dtype):
    """Time at which the run stopped if `fired` (else nan)."""
    return jnp.where(fired, sol.ts[1][-1], jnp.nan).astype(dtype), fired


def _refine_crossing(model, top, ts, states, valid, cond, direction, rtol, atol, solver):
    """First save interval where `cond` changes sign (in `direction`), then its exact time."""
    values = jax.vmap(lambda y: cond(0.0, y, top))(states)
    before, after = values[:-1], values[1:]
    if direction is False:
        crossing = (before > 0) & (after <= 0)
    else:
        crossing = (before < 0) & (after >= 0)
    crossing = crossing & valid[:-1] & valid[1:]
    has = jnp.any(crossing)
    k = jnp.argmax(crossing)
    y_a = jax.tree_util.tree_map(lambda x: x[k], states)
    t_a = ts[k]
    t_b = jnp.where(has, ts[k + 1], ts[k] + 1.0)
    event = diffrax.Event(
        lambda t, y, args, **kw: _event_dtype(cond(t, y, args)), _root_finder(ts.dtype)
    )
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(_vector_field(model)),
        solver,
        t_a,
        t_b,
        None,
        y_a,
        top,
        saveat=diffrax.SaveAt(t1=True),
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
        event=event,
        max_steps=4096,
        throw=False,
    )
    found = has & jnp.any(jnp.asarray(jax.tree_util.tree_leaves(sol.event_mask)))
    return jnp.where(found, sol.ts[-1], jnp.nan)


def _where_valid(valid, x):
    shape = valid.shape + (1,) * (x.ndim - valid.ndim)
    return jnp.where(valid.reshape(shape), x, jnp.nan)


def _code(sol, fired_singular, fired_contact, stop_on_contact):
    """Our RESULTS value for one diffrax segment (`fired_*` from `_fired`, or None)."""
    res = jnp.array(RESULTS.successful._value)
    if stop_on_contact and fired_contact is not None:
        res = jnp.where(fired_contact, RESULTS.contact_lost._value, res)
    res = jnp.where(fired_singular, RESULTS.normal_force_singular._value, res)
    ok = (sol.result == diffrax.RESULTS.successful) | (
        sol.result == diffrax.RESULTS.event_occurred
    )
    res = jnp.where(ok, res, RESULTS.solver_failed._value)
    return jnp.where(
        sol.result == diffrax.RESULTS.max_steps_reached, RESULTS.max_steps_reached._value, res
    )


def _merge(ts, states, new_states, t_start):
    """Take `new_states` at the save times from `t_start` on (both agree at `t_start`)."""
    later = ts >= t_start
    return jax.tree_util.tree_map(
        lambda a, b: jnp.where(later.reshape((-1,) + (1,) * (a.ndim - 1)), b, a),
        states,
        new_states,
    )


@eqx.filter_jit
def _simulate(top, y0, ts, t0, t1, *, model, solver, rtol, atol, max_steps, on_contact_loss, progress):
    dtype = jnp.result_type(top.m)
    meter = diffrax.TqdmProgressMeter() if progress else diffrax.NoProgressMeter()
    stop_on_contact = on_contact_loss == "stop"
    finder = _root_finder(dtype)
    nan = jnp.array(jnp.nan, dtype)
    steps = jnp.array(0)
    rejected = jnp.array(0)
    result_value = jnp.array(0)
    t_contact_loss = nan
    t_chart_switch = nan
    vector_model = "full" if model == "full" else "so3"
    # R_n <= 0, or its denominator <= 0, already at t0: no sign change for an event to see,
    # and nothing to integrate.
    numerator0, denominator0 = _vector_rn_parts(top, y0, vector_model)
    singular0 = denominator0 <= 0
    lost0 = (numerator0 <= 0) & ~singular0
    dead0 = singular0 | (lost0 & stop_on_contact)

    # --- Routhian segment: from t0 until the chart ends (or t1, or a failure). ---------------
    if model == "routhian":
        J = jellet(top, y0)
        r0, _ = routhian_from_state(top, y0)
        start_in_chart = jnp.abs(jnp.sin(r0.theta)) > CHART_SIN_MIN

        def cond_chart(t, y, args, **kw):
            return _event_dtype(jnp.abs(jnp.sin(y.theta)) - CHART_SIN_MIN)

        def cond_singular(t, y, args, **kw):
            return _routhian_rn_parts(args[0], y, args[1])[1]

        def cond_contact(t, y, args, **kw):
            return _routhian_rn_parts(args[0], y, args[1])[0]

        conds = [cond_chart, cond_singular, cond_contact]
        event = diffrax.Event(_first_of(conds), finder)
        # Outside the chart at t0: a zero-length first segment; the SO(3) form does the rest.
        t1_first = jnp.where(start_in_chart & ~dead0, t1, t0)
        r0 = jax.tree_util.tree_map(lambda x: jnp.where(start_in_chart, x, jnp.ones_like(x)), r0)
        sol = _solve(
            diffrax.ODETerm(routhian_vector_field), solver, t0, t1_first, r0, (top, J),
            jnp.clip(ts, t0, t1_first), rtol, atol, max_steps, event, meter,
        )
        steps, rejected = steps + sol.stats["num_steps"], rejected + sol.stats["num_rejected_steps"]
        fired = _fired(sol, conds, (top, J))
        result_value = _code(sol, fired[1], fired[2], stop_on_contact)
        t_contact, contact_fired = _event_time(sol, fired[2], dtype)
        t_contact_loss = t_contact
        left_chart = fired[0] | contact_fired | ~start_in_chart
        t_end = sol.ts[1][-1]
        t_chart_switch = jnp.where(left_chart & (result_value == 0), t_end, nan)
        states = jax.vmap(lambda r: state_from_routhian(top, r, J))(sol.ys[0])
        y_end = state_from_routhian(top, jax.tree_util.tree_map(lambda x: x[-1], sol.ys[1]), J)
        y_end = jax.tree_util.tree_map(lambda a, b: jnp.where(start_in_chart, a, b), y_end, y0)
        t_start = jnp.where(left_chart & (result_value == 0), t_end, t1)
    else:
        states = None
        y_end, t_start = y0, jnp.asarray(t0, dtype)
    t_start = jnp.where(dead0, t1, t_start)

    # --- Vector-form segments: until contact loss, then (if asked) on to t1 without it. -------
    def cond_singular_v(t, y, args, **kw):
        return _vector_rn_parts(args, y, vector_model)[1]

    def cond_contact_v(t, y, args, **kw):
        return _vector_rn_parts(args, y, vector_model)[0]

    term = diffrax.ODETerm(_vector_field(vector_model))
    already_lost = jnp.isfinite(t_contact_loss)
    with_contact = [cond_singular_v] if (not stop_on_contact and model == "routhian") else [
        cond_singular_v, cond_contact_v
    ]
    sol = _solve(
        term, solver, t_start, t1, y_end, top, jnp.clip(ts, t_start, t1), rtol, atol,
        max_steps, diffrax.Event(_first_of(with_contact), finder), meter,
    )
    steps, rejected = steps + sol.stats["num_steps"], rejected + sol.stats["num_rejected_steps"]
    has_contact_event = len(with_contact) == 2
    fired = _fired(sol, with_contact, top)
    code = _code(sol, fired[0], fired[1] if has_contact_event else None, stop_on_contact)
    result_value = jnp.where(result_value != 0, result_value, code)
    states = sol.ys[0] if states is None else _merge(ts, states, sol.ys[0], t_start)
    t_final = sol.ts[1][-1]
    if has_contact_event:
        t_contact, contact_fired = _event_time(sol, fired[1], dtype)
        t_contact_loss = jnp.where(already_lost, t_contact_loss, t_contact)
    if not stop_on_contact and has_contact_event:
        # Go on past the contact loss, flagged, without the contact event.
        t_start2 = jnp.where(contact_fired & (result_value == 0), t_final, t1)
        y_start2 = jax.tree_util.tree_map(lambda x: x[-1], sol.ys[1])
        sol = _solve(
            term, solver, t_start2, t1, y_start2, top, jnp.clip(ts, t_start2, t1), rtol, atol,
            max_steps, diffrax.Event(cond_singular_v, finder), meter,
        )
        steps, rejected = steps + sol.stats["num_steps"], rejected + sol.stats["num_rejected_steps"]
        fired = _fired(sol, [cond_singular_v], top)
        result_value = jnp.where(result_value != 0, result_value, _code(sol, fired[0], None, False))
        states = _merge(ts, states, sol.ys[0], t_start2)
        t_final = jnp.where(t_start2 < t1, sol.ts[1][-1], t_final)
    if not stop_on_contact:
        result_value = jnp.where(
            (result_value == 0) & jnp.isfinite(t_contact_loss),
            RESULTS.contact_lost._value,
            result_value,
        )
    result_value = jnp.where(singular0, RESULTS.normal_force_singular._value, result_value)
    result_value = jnp.where((result_value == 0) & lost0, RESULTS.contact_lost._value, result_value)
    t_contact_loss = jnp.where(lost0, jnp.asarray(t0, dtype), t_contact_loss)
    t_final = jnp.where(singular0, jnp.asarray(t0, dtype), t_final)
    if stop_on_contact:
        t_final = jnp.where(lost0, jnp.asarray(t0, dtype), t_final)

    # --- Quantities at the save times. --------------------------------------------------------
    valid = (ts <= t_final) & jnp.all(jnp.isfinite(states.axis), axis=-1)
    theta, phi, psi = euler_angles(states)
    theta_dot, phi_dot, psi_dot = euler_rates(states)
    fields = dict(
        theta=theta,
        phi=jnp.unwrap(jnp.where(valid, phi, 0.0)),
        psi=jnp.unwrap(jnp.where(valid, psi, 0.0)),
        theta_dot=theta_dot, phi_dot=phi_dot, psi_dot=psi_dot, spin=spin(states),
        position=states.position, velocity=states.velocity,
        jellet=jellet(top, states),
        energy=energy(top, states, model=vector_model),
        normal_force=normal_force(top, states, model=vector_model),
        slip_speed=jnp.linalg.norm(slip_velocity(top, states, model=vector_model), axis=-1),
    )
    nonfinite = jnp.any(
        jnp.stack(
            [jnp.any(valid & ~jnp.isfinite(fields[k])) for k in ("theta", "jellet", "energy")]
        )
    )
    result_value = jnp.where((result_value == 0) & nonfinite, RESULTS.nonfinite._value, result_value)
    # A contact loss the event did not see: R_n < 0 at a save time before any located loss means
    # the solver stepped over a brief dip (events are seen from signs at step ends). Report it,
    # and return nothing from that save time on, nor a later loss time as if it were the first.
    missed_at = valid & (fields["normal_force"] < 0) & ~(ts >= t_contact_loss)
    missed = jnp.any(missed_at)
    t_missed = jnp.min(jnp.where(missed_at, ts, jnp.inf))
    result_value = jnp.where(
        missed & ((result_value == 0) | (result_value == RESULTS.contact_lost._value)),
        RESULTS.contact_loss_missed._value,
        result_value,
    )
    t_contact_loss = jnp.where(missed, nan, t_contact_loss)
    valid = valid & (ts < t_missed)
    fields = {k: _where_valid(valid, v) for k, v in fields.items()}  # the one masking of fields
    states = jax.tree_util.tree_map(lambda x: _where_valid(valid, x), states)
    t_invert = _refine_crossing(
        vector_model, top, ts, states, valid, lambda t, y, args: y.axis[2], False, rtol, atol,
        solver,
    )
    return dict(
        ts=ts, states=states, result_value=result_value, t_invert=t_invert,
        t_contact_loss=t_contact_loss, t_chart_switch=t_chart_switch, t_final=t_final,
        num_steps=steps, num_rejected_steps=rejected, **fields,
    )


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def simulate(
    top: TippeTop,
    y0: State,
    t1: float,
    *,
    model: Literal["full", "so3", "routhian", "gyroscopic", "auto"] = "full",
    saveat: ArrayLike | None = None,
    t0: float = 0.0,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    solver: diffrax.AbstractSolver | None = None,
    max_steps: int = 200_000,
    throw: bool = True,
    progress: bool = False,
    on_contact_loss: Literal["stop", "continue"] = "stop",
    tolerance: float | None = None,
) -> Solution:
    r"""Integrate the motion of `top` from `y0` at `t0` to `t1` with the chosen level of model.

    **Arguments:**

    - `top`: a `TippeTop` (single; use `jax.vmap` or `simulate_batch` for batches).
    - `y0`: the initial `State` (see `initial_state`).
    - `t1`: final time (s).
    - `model`: `"full"` (translation included), `"so3"` (translation dropped in the friction),
      `"routhian"` (reduced system with $J$ fixed; leaves the chart for the SO(3) form when
      $\sin\theta <$ `CHART_SIN_MIN`, reported as `"routhian->so3"`), `"auto"` (the cheapest
      level whose measured error is below `tolerance`, see `choose_model`), or `"gyroscopic"`
      (not yet available).
    - `saveat`: save times (default: 1001 points from `t0` to `t1`). The inversion time is
      bracketed on this grid, so it should resolve the nutation.
      Events (contact loss, the $R_n$ singularity, the chart edge) are seen from the sign of
      their condition at the ends of each solver step and then located inside that step: a zero
      crossed and recrossed within one step is missed, which loose tolerances make likely
      (keep rtol <= 1e-8 when contact loss matters).
    - `rtol`, `atol`: tolerances of the PID step-size controller. In float32 `rtol` is raised
      to at least `1e-5` and `atol` to `1e-7`.
    - `solver`: any diffrax solver with an error estimate; default `default_solver(top)`:
      Tsit5, or Kvaerno5 under very stiff friction.
    - `max_steps`: maximum number of steps per segment.
    - `throw`: raise on failure (contact loss with `on_contact_loss="stop"`, the $R_n$
      singularity, max steps, NaN). With `False` the failure is in `sol.result`.
    - `progress`: show diffrax's tqdm progress meter.
    - `on_contact_loss`: `"stop"` ends the run at $R_n = 0$ (a failure); `"continue"` goes on,
      flags `result = contact_lost` and does not raise for it.
    - `tolerance`: for `model="auto"`, the largest acceptable error in $\theta(t)$ (rad).

    **Returns:** a `Solution`.
    """
    if model not in LEVELS:
        raise ValueError(f"Unknown model {model!r}; choose one of {LEVELS}.")
    if on_contact_loss not in ("stop", "continue"):
        raise ValueError(f"on_contact_loss must be 'stop' or 'continue', got {on_contact_loss!r}.")
    if model == "gyroscopic":
        raise NotImplementedError(
            "model='gyroscopic' is not yet available; use 'routhian', 'so3' or 'full'."
        )
    if not isinstance(y0, State):
        raise TypeError(f"y0 must be a tippejax.State (see tj.initial_state), got {type(y0)}.")
    if max_steps <= 0:
        raise ValueError(f"max_steps must be positive, got {max_steps}.")
    if _is_concrete(t1) and _is_concrete(t0) and not float(t1) > float(t0):
        raise ValueError(f"t1 must be greater than t0, got t0={t0}, t1={t1}.")
    if model == "auto":
        from ._levels import choose_model

        model = choose_model(top, y0, tolerance=tolerance)
    dtype = jnp.result_type(top.m)
    if dtype != jnp.float64:
        rtol, atol = max(rtol, 1e-5), max(atol, 1e-7)
    if saveat is None:
        ts = jnp.linspace(t0, t1, 1001, dtype=dtype)
    else:
        ts = jnp.asarray(saveat, dtype=dtype)
        if ts.ndim != 1 or ts.shape[0] < 2:
            raise ValueError("saveat must be a 1-d array of at least two times.")
    if solver is None:
        solver = default_solver(top)
    y0 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), y0)
    out = _simulate(
        top, y0, ts, jnp.asarray(t0, dtype), jnp.asarray(t1, dtype), model=model, solver=solver,
        rtol=rtol, atol=atol, max_steps=max_steps, on_contact_loss=on_contact_loss,
        progress=progress,
    )
    value = out.pop("result_value")
    result = RESULTS.where(value == 0, RESULTS.successful, RESULTS.successful)
    result = eqx.tree_at(lambda r: r._value, result, value)
    name = model
    if model == "routhian":
        switch = out["t_chart_switch"]
        if _is_concrete(switch):
            name = "routhian->so3" if bool(np.any(np.isfinite(np.asarray(switch)))) else "routhian"
        else:
            name = "routhian(->so3 where t_chart_switch is finite)"
    sol = Solution(model=name, result=result, **out)
    if throw:
        sol = _raise_if_failed(sol, on_contact_loss)
    return sol


def _raise_if_failed(sol: Solution, on_contact_loss: str) -> Solution:
    value = sol.result._value
    tolerated = (value == RESULTS.contact_lost._value) if on_contact_loss == "continue" else False
    failed = (value != 0) & ~tolerated
    if _is_concrete(value):
        if bool(np.any(np.asarray(failed))):
            index = int(np.asarray(value).ravel()[np.argmax(np.asarray(failed).ravel())])
            message = RESULTS._index_to_message[index]
            raise RuntimeError(
                f"tippejax.simulate failed: {message} "
                "(pass throw=False to get the flagged solution instead)."
            )
        return sol
    messages = tuple(RESULTS._index_to_message)
    ts = eqx.branched_error_if(sol.ts, jnp.any(failed), jnp.max(value), messages)
    return eqx.tree_at(lambda s: s.ts, sol, ts)


__all__ = ["simulate", "default_solver", "friction_rate", "LEVELS", "CHART_SIN_MIN"]
