"""Spun launches (omega = n a): the gyroscopic level's launch projections against SO(3).

For omega = n a launches (theta_dot = phi_dot = 0), t_invert of the slow flow alone
(`GyroscopicLevel(hand_over=False)`, Dopri5, rtol 1e-8, summary mode) with each projection
(`projection="averaged"`, the default; `"fibre"`; `"linear"`) against the SO(3) model
(rtol 1e-10), and against the slow flow launched from the slow state the SO(3) transient really
leaves (followed for 1 s and 1.5 s, projected linearly there, the slow flow run back to t = 0,
the small drift with the settle time extrapolated to zero): that "exact slow state" column is
the slow flow's own error, and the differences from it are the projections' own. The standard
top at theta0 = 0.1 over the spins (with the full model's own difference and what
`model="gyroscopic"` reports), then theta0 = 0.05, 0.2 and tops of groups III and IIa; fitted
power laws of |error| in n0; the projections' cost (jitted `from_state` on a batch of 256
launches) and a 20 s run against the full model. Rewrites the "Spun launches" section of
benchmarks/LEVELS.md:

    python benchmarks/levels.py --spun     (or python benchmarks/levels_spun.py)
"""

from __future__ import annotations

import platform
import statistics
import time

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from levels import GYRO_THETA0, SPEED_REPEATS, SPEED_T1, gyro_speed, power_law, write_section

import tippejax as tj
from tippejax._models.gyroscopic import (
    PROJECTIONS,
    GyroscopicLevel,
    GyroscopicLevelState,
    _linear_state as linear_state,
)
from tippejax._models.so3 import SO3Level
from tippejax._simulate import _run

SPUN_SPINS = (100.0, 125.0, 150.0, 175.0, 200.0, 225.0, 250.0, 300.0)
OTHER_SPINS = (100.0, 150.0, 225.0, 300.0)
OTHER_LAUNCHES = (  # (label, A/C, eps/R, theta0)
    ("IIb (standard)", 0.9, 0.3, 0.05),
    ("IIb (standard)", 0.9, 0.3, 0.2),
    ("III", 1.5, 0.2, 0.1),
    ("IIa", 0.8, 0.3, 0.1),
)
SETTLE = (1.0, 1.5)
COST_BATCH = 256
T1 = 20.0
SPUN_MARK = "## Spun launches (omega = n a): the launch projection"


def slow_alone(top, y0, *, projection):
    """t_invert of the slow flow alone (no hand-over), Dopri5 at rtol 1e-8, summary mode."""
    f = lambda x: jnp.asarray(x, jnp.float64)  # noqa: E731
    out = _run(top, y0, None, f(0.0), f(T1), f(1e-8), f(1e-10),
               level=GyroscopicLevel(hand_over=False, projection=projection),
               solver=diffrax.Dopri5(), guard_stiff=False, stop_on_contact=True,
               max_steps=200_000, adjoint=diffrax.RecursiveCheckpointAdjoint(), progress=False,
               pieces=1)
    return float(out["t_invert"])


def _solve(field, y0, t0, t1, norm):
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field), diffrax.Dopri8(), t0, t1, None, y0,
        stepsize_controller=diffrax.PIDController(rtol=1e-11, atol=1e-13, norm=norm),
        saveat=diffrax.SaveAt(t1=True), max_steps=100_000)
    return jax.tree_util.tree_map(lambda v: v[-1], sol.ys)


@eqx.filter_jit
def _settled(top, state, settle):
    """The launch followed in SO(3) for `settle` s, projected linearly, the slow flow run back
    to t = 0: u = ln tan(theta_s/2)."""
    so3, level = SO3Level(), GyroscopicLevel()
    end = _solve(lambda t, y, a: so3.vector_field(t, y, top), so3.from_state(top, state), 0.0,
                 settle, so3.error_norm)
    settled = linear_state(top, so3.to_state(top, end))
    settled = eqx.tree_at(lambda y: y.jellet, settled, tj.jellet(top, state))
    back = _solve(lambda t, y, a: level.vector_field(t, y, top), settled, settle, 0.0,
                  level.error_norm)
    return back.log_tan_half_theta


def exact_slow_state(top, y0):
    """The state on the slow manifold that the SO(3) transient of `y0` leaves (see the module
    docstring), for the slow flow to be launched from."""
    u = [float(_settled(top, y0, jnp.asarray(s))) for s in SETTLE]
    u0 = u[0] - (u[1] - u[0]) * SETTLE[0] / (SETTLE[1] - SETTLE[0])
    theta = float(2 * np.arctan(np.exp(u0)))
    state = GyroscopicLevelState.from_theta(theta, 0.0, 0.0, -30.0, tj.jellet(top, y0))
    return GyroscopicLevel().to_state(top, state)


def launch_row(top, theta0, n0):
    y0 = tj.initial_state(top, theta0, n0)
    so3 = tj.simulate(top, y0, T1, model="so3", summary=True, throw=False, rtol=1e-10,
                      atol=1e-12)
    row = dict(n0=n0, theta0=theta0, so3=float(so3.t_invert),
               exact=slow_alone(top, exact_slow_state(top, y0), projection="linear"))
    for p in PROJECTIONS:
        row[p] = slow_alone(top, y0, projection=p)
    return y0, row


def spun_launches():
    """The standard top at theta0 = 0.1 over the spins, with the full model's own difference
    and what `model="gyroscopic"` (chaining to the full model) reports."""
    top = tj.default_top()
    rows = []
    for n0 in SPUN_SPINS:
        y0, row = launch_row(top, GYRO_THETA0, n0)
        full = tj.simulate(top, y0, T1, model="full", summary=True, throw=False,
                           on_contact_loss="continue")
        chained = tj.simulate(top, y0, T1, model="gyroscopic", summary=True, throw=False,
                              on_contact_loss="continue")
        row.update(full=float(full.t_invert), full_loss=float(full.t_contact_loss),
                   chained_model=chained.model, chained_switch=float(chained.t_chart_switch),
                   chained_loss=float(chained.t_contact_loss),
                   chained_invert=float(chained.t_invert))
        rows.append(row)
        print("spun", row, flush=True)
    return rows


def other_launches():
    rows = []
    for label, a, e, theta0 in OTHER_LAUNCHES:
        top = tj.TippeTop.from_ratios(a, e)
        for n0 in OTHER_SPINS:
            _, row = launch_row(top, theta0, n0)
            row["top"] = f"{label}, A/C {a}, eps/R {e}"
            rows.append(row)
            print("other", row, flush=True)
    return rows


def projection_cost():
    """Median wall time of a jitted `from_state` of each projection on a batch of 256 launches
    (theta0 in [0.02, 0.2], n0 in [80, 300] rad/s) and on one launch."""
    top = tj.default_top()
    rng = np.random.default_rng(0)
    batch = tj.initial_state(top, jnp.asarray(rng.uniform(0.02, 0.2, COST_BATCH)),
                             jnp.asarray(rng.uniform(80.0, 300.0, COST_BATCH)))
    one = jax.tree_util.tree_map(lambda x: x[0], batch)
    out = {}
    for p in PROJECTIONS:
        level = GyroscopicLevel(projection=p)
        timings = []
        for fn, y in ((jax.jit(jax.vmap(lambda s, lv=level: lv.from_state(top, s))), batch),
                      (jax.jit(lambda s, lv=level: lv.from_state(top, s)), one)):
            jax.block_until_ready(fn(y))
            times = []
            for _ in range(SPEED_REPEATS):
                start = time.perf_counter()
                jax.block_until_ready(fn(y))
                times.append(time.perf_counter() - start)
            timings.append(statistics.median(times))
        out[p] = tuple(timings)
    print("projection cost", out, flush=True)
    return out


def _pct(x, ref):
    return "n/a" if not (np.isfinite(x) and np.isfinite(ref)) else f"{100 * (x - ref) / ref:+.3f}%"


def _own(r, p):
    """A projection's own error: its t_invert against the slow flow from the exact slow state."""
    if not all(np.isfinite(r[k]) for k in (p, "exact", "so3")):
        return "n/a"
    return f"{100 * (r[p] - r['exact']) / r['so3']:+.3f}%"


def _rates(rows):
    n0 = [r["n0"] for r in rows]
    total = {k: power_law(n0, [(r[k] - r["so3"]) / r["so3"] for r in rows])
             for k in (*PROJECTIONS, "exact")}
    own = {k: power_law(n0, [(r[k] - r["exact"]) / r["so3"] for r in rows])
           for k in PROJECTIONS}
    return total, own


def spun_section(rows, others, cost, speed):
    total, own = _rates(rows)
    lines = [
        SPUN_MARK,
        "",
        "Made by `python benchmarks/levels.py --spun` (`benchmarks/levels_spun.py`; rewrites this "
        f"section only), {platform.processor() or platform.machine()}. omega = n a launches "
        "(theta_dot = phi_dot = 0). t_invert of the slow flow alone "
        "(`GyroscopicLevel(hand_over=False)`, Dopri5, rtol 1e-8) against the SO(3) model (rtol "
        "1e-10), with the averaged projection (`average_launch`, the default: first-order "
        "averaging over the nutation, no solve), the fibre projection (`settle_launch`: the "
        "launch followed in SO(3) until its nutation has decayed to 0.01 rad, projected there, "
        "the slow flow run back to t = 0) and the linear projection (`project_launch`). "
        "\"Exact slow state\": the slow flow launched from the slow state the SO(3) transient "
        "really leaves (followed for 1 s and 1.5 s at rtol 1e-11, projected there, the slow "
        "flow run back, extrapolated to zero settle time): the slow flow's own error. In "
        "brackets, each projection's own error, its t_invert minus that of the exact slow "
        "state (relative to SO(3)'s).",
        "",
        f"Standard top, theta0 = {GYRO_THETA0}; the full model's own difference from SO(3) "
        "beside them, and what `model=\"gyroscopic\"` reports (the averaged projection; it "
        "hands over to the full model where the slow manifold repels):",
        "",
        "| n0 (rad/s) | SO(3) t_invert (s) | exact slow state | averaged | fibre | linear "
        "| full - SO(3) | `model=\"gyroscopic\"` |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if np.isfinite(r["full"]):
            full = _pct(r["full"], r["so3"])
        else:
            full = f"contact lost at {r['full_loss']:.2f} s"
        if np.isfinite(r["chained_switch"]):
            chained = f"{r['chained_model']}, hand-over at {r['chained_switch']:.2f} s"
            if np.isfinite(r["chained_loss"]):
                chained += f", contact lost at {r['chained_loss']:.2f} s"
            else:
                chained += f", t_invert {_pct(r['chained_invert'], r['so3'])}"
        else:
            chained = f"{r['chained_model']}, t_invert {_pct(r['chained_invert'], r['so3'])}"
        cells = " | ".join(f"{_pct(r[p], r['so3'])} ({_own(r, p)})" for p in PROJECTIONS)
        lines.append(f"| {r['n0']:g} | {r['so3']:.4f} | {_pct(r['exact'], r['so3'])} | {cells} "
                     f"| {full} | {chained} |")
    lines += [
        "",
        "Fitted power law of |error| in n0 (all spins above): t_invert against SO(3): averaged "
        f"n0^{total['averaged']:+.2f}, fibre n0^{total['fibre']:+.2f}, linear "
        f"n0^{total['linear']:+.2f}, exact slow state n0^{total['exact']:+.2f}; the "
        f"projections' own errors: averaged n0^{own['averaged']:+.2f}, fibre "
        f"n0^{own['fibre']:+.2f}, linear n0^{own['linear']:+.2f}.",
        "",
        "Other tilts and groups (same columns):",
        "",
        "| top | theta0 | n0 (rad/s) | SO(3) t_invert (s) | exact slow state | averaged | fibre "
        "| linear |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in others:
        cells = " | ".join(f"{_pct(r[p], r['so3'])} ({_own(r, p)})" for p in PROJECTIONS)
        lines.append(f"| {r['top']} | {r['theta0']:g} | {r['n0']:g} | {r['so3']:.4f} | "
                     f"{_pct(r['exact'], r['so3'])} | {cells} |")
    (g20, s20), (f20, n20) = speed[SPEED_T1]["gyroscopic"], speed[SPEED_T1]["full"]
    g0, f0 = speed[0.01]["gyroscopic"][0], speed[0.01]["full"][0]
    costs = ", ".join(f"{p} {1e3 * cost[p][0]:.2f} ms ({1e3 * cost[p][1]:.3f} ms for one)"
                      for p in PROJECTIONS)
    lines += [
        "",
        f"Cost of the projection (jitted `from_state`, median of {SPEED_REPEATS}, a batch of "
        f"{COST_BATCH} launches with theta0 in [0.02, 0.2] and n0 in [80, 300] rad/s): {costs}.",
        "",
        f"Cost of a run with the default (averaged) projection (median of {SPEED_REPEATS} "
        f"interleaved jitted summary runs, theta0 = {GYRO_THETA0}, n0 = 100, rtol 1e-8): "
        f"{SPEED_T1:g} s run {1e3 * g20:.2f} ms ({s20} slow steps) against {1e3 * f20:.2f} ms for "
        f"the full model ({n20} steps): {f20 / g20:.0f}x; a 0.01 s run (the fixed cost) "
        f"{1e3 * g0:.2f} ms against {1e3 * f0:.2f} ms.",
        "",
    ]
    return lines


def write_spun_section():
    rows, others = spun_launches(), other_launches()
    speed = gyro_speed()  # before the fibre projection's batch, which slows what follows it
    lines = spun_section(rows, others, projection_cost(), speed)
    write_section(SPUN_MARK, lines)


if __name__ == "__main__":
    write_spun_section()
