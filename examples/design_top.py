r"""Design a tippe top: the eccentricity and inertia ratio that make it turn over fastest, or at
the lowest spin, by gradient descent on `tj.inversion_time`.

The maker's top: a sphere of mass m = 20 g, radius R = 25 mm, viscous friction mu = 0.3 s/m,
axial moment C = 0.4 m R^2 (kept), launched at theta0 = 0.1 rad. Free: the eccentricity
e = eps/R and the inertia ratio a = A/C, within what a maker could build:

- e in [0.05, 0.5]: the centre of mass moves off the centre of the sphere by lightening the
  stem half (a truncated sphere, a hollow); past ~R/2 there is no room left;
- a in [0.55, 1.2]: no rigid body has a < 1/2; with all the mass inside the ball,
  $A + m\epsilon^2 - C/2 = \int z^2 dm \le mR^2 - C$ gives $a \le 2 - 2.5 e^2$ (>= 1.375 on the
  box), and a stem long enough for a > 1.2 no longer fits a tippe top;
- the top must stay in Group II ($|a - 1| < e$), the tops that can turn over (Group I keeps
  theta = 0 stable at every spin, Group III stops at the intermediate angle theta_c). The
  parametrisation keeps $|a - 1| \le 0.9 e$, off the group boundaries where $n_1$ or $n_2$
  blow up.

Bounded reparametrisation (sigmoid $\sigma$), unconstrained $u \in \mathbb R^2$:
$e = 0.05 + 0.45\,\sigma(u_0)$, $a = a_-(e) + (a_+(e) - a_-(e))\,\sigma(u_1)$ with
$a_\mp(e) = \max/\min(0.55 \text{ or } 1.2,\ 1 \mp 0.9 e)$.

Turning over means two things: crossing theta = pi/2 (`tj.inversion_time`) and ending upside
down. The second needs the launch's Jellet integral $J = C n (R\cos\theta_0 - \epsilon)$
(conserved) above $J_2 = C(R+\epsilon) n_2$, i.e. a spin above
$n_{full} = J_2 / (C(R\cos\theta_0 - \epsilon))$ (closed form, `tj.thresholds`); below it the
top stops on an intermediate state, which may lie past pi/2. A first run that only asked for
the fastest crossing found such a top: it crossed at 3.1 s and stayed at theta ~ 2.2 rad.

Both objectives use the nutation-averaged inversion time, `tj.inversion_time(...,
model="gyroscopic")`: the full model's $t^*$ is a staircase in every parameter (one step per
nutation cycle), whose local gradient is not the trend. The table and curves report the full
model's $t^*$ of the designs beside it.

Objective 1: the inversion time $t^*$ at the launch spin 100 rad/s, differentiated through the
solve (`jax.grad` of `tj.inversion_time`), plus a quadratic penalty where the launch is less
than 5% above $n_{full}$.

Objective 2: the lowest launch spin at which the top turns over, $n_{min} =
\max(n_{full}, n_{cross})$ with $t^*(n_{cross}) = 8$ s (it crosses pi/2 within 8 s). Not the
linear threshold $n_1$: above it the upright top is unstable, but it may rise only to an
intermediate angle, and slowly. $n_{cross}$ is found by bisection on the spin (no gradient)
and differentiated by the implicit function theorem,
$dn_{cross}/dp = -(\partial t^*/\partial p)/(\partial t^*/\partial n)$.

Both with optax's Adam, its rate decaying from 0.25 (cosine) over 40 steps. Writes `examples/figures/design_top.png` (the optimiser's paths on the
group map of `tippejax._plot.group_map`, theta(t) before and after) and prints a table.

    python examples/design_top.py
"""

import pathlib
import time

import matplotlib

matplotlib.use("Agg")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

import tippejax as tj  # noqa: E402
from tippejax._plot import group_map  # noqa: E402

M, R, MU = 0.02, 0.025, 0.3  # kg, m, s/m
THETA0 = 0.1  # rad
SPIN = 100.0  # rad/s, the launch of objective 1
T1 = 12.0  # s, how long objective 1 looks for the inversion
T_LIMIT = 8.0  # s, objective 2: turn over within this time
E_BOUNDS = (0.05, 0.5)
A_BOUNDS = (0.55, 1.2)
GROUP_MARGIN = 0.9  # |a - 1| <= 0.9 e
SPIN_BRACKET = (10.0, 150.0)  # rad/s, bisection bracket of objective 2
BISECTIONS = 22  # on log(spin): relative width 2.7 / 2^22 < 1e-6
STEPS = 40
LEARNING_RATE = 0.25
SOLVE = dict(rtol=1e-8, atol=1e-10)
# The design quantity: the nutation-averaged inversion time of the gyroscopic level (chaining to
# the full model where the slow manifold repels). The full model's t* is a staircase in every
# parameter (one step of about a nutation period per nutation cycle): its exact local gradient
# is the slope of one stair, not the trend, while the gyroscopic t*'s gradient is the trend
# (see `tj.inversion_time`).
DESIGN = dict(SOLVE, model="gyroscopic")
PENALTY = 0.02  # s / (rad/s)^2, objective 1's penalty on a launch below the full-turn spin


def ratios(u):
    """(A/C, eps/R) of the unconstrained parameters u (shape (2,))."""
    e = E_BOUNDS[0] + (E_BOUNDS[1] - E_BOUNDS[0]) * jax.nn.sigmoid(u[0])
    a_lo = jnp.maximum(A_BOUNDS[0], 1 - GROUP_MARGIN * e)
    a_hi = jnp.minimum(A_BOUNDS[1], 1 + GROUP_MARGIN * e)
    return a_lo + (a_hi - a_lo) * jax.nn.sigmoid(u[1]), e


def parameters_of(a, e):
    """The inverse of `ratios` (a must lie inside its bounds for e)."""
    s0 = (e - E_BOUNDS[0]) / (E_BOUNDS[1] - E_BOUNDS[0])
    a_lo = max(A_BOUNDS[0], 1 - GROUP_MARGIN * e)
    a_hi = min(A_BOUNDS[1], 1 + GROUP_MARGIN * e)
    s1 = (a - a_lo) / (a_hi - a_lo)
    return jnp.log(jnp.array([s0, s1]) / (1 - jnp.array([s0, s1])))


def top_of(u):
    a, e = ratios(u)
    return tj.TippeTop.from_ratios(a, e, m=M, R=R, mu=MU)


def inversion_time(u, spin, t1):
    top = top_of(u)
    # throw=False: a launch that fails before turning over (contact loss) is nan, handled below.
    return tj.inversion_time(top, tj.initial_state(top, THETA0, spin), t1=t1, throw=False, **DESIGN)


def full_turn_spin(u):
    r"""The launch spin above which the top ends upside down, $n_J = J_2 / (C (R\cos\theta_0 -
    \epsilon))$: the launch's Jellet integral $J = C n (R\cos\theta_0 - \epsilon)$ (conserved)
    must exceed $J_2 = C (R + \epsilon) n_2$, else the top stops on an intermediate state (which
    may lie past pi/2: crossing pi/2 is not yet turning over)."""
    top = top_of(u)
    return tj.thresholds(top).J2 / (top.C * (top.R * jnp.cos(THETA0) - top.eps))


def fastest(u):
    """Objective 1: t* at the launch spin (s), plus a penalty unless the launch is at least 5%
    above the full-turn spin."""
    excess = jax.nn.relu(full_turn_spin(u) - SPIN / 1.05)
    return inversion_time(u, SPIN, T1) + PENALTY * excess**2


def lowest_spin(u):
    """Objective 2: the lowest spin (rad/s) at which the top turns over completely and crosses
    pi/2 within T_LIMIT: the larger of the full-turn spin and `crossing_spin`."""
    return jnp.maximum(full_turn_spin(u), crossing_spin(u))


def crossing_spin(u):
    """The lowest spin (rad/s) with t* <= T_LIMIT, differentiable in u."""
    fixed = jax.lax.stop_gradient(u)

    def halve(_, bracket):
        lo, hi = bracket
        mid = jnp.sqrt(lo * hi)
        too_slow = ~(inversion_time(fixed, mid, T_LIMIT) <= T_LIMIT)  # later, or never (nan)
        return jnp.where(too_slow, mid, lo), jnp.where(too_slow, hi, mid)

    bracket = tuple(jnp.asarray(x) for x in SPIN_BRACKET)
    _, n_star = jax.lax.fori_loop(0, BISECTIONS, halve, bracket)  # turns over at n_star
    # Implicit function theorem: t*(n_min(u), u) = T_LIMIT. The value is n_star; the gradient
    # is -(dt*/du) / (dt*/dn).
    dt_dn = jax.grad(inversion_time, argnums=1)(fixed, n_star, T_LIMIT)
    t = inversion_time(u, n_star, T_LIMIT)
    return n_star - (t - jax.lax.stop_gradient(t)) / dt_dn


def optimise(name, objective, u0):
    value_and_grad = jax.jit(jax.value_and_grad(objective))
    # Decaying step: both optima sit on a kink (the penalty's edge, the max of two spins),
    # where Adam at a constant rate circles.
    optimiser = optax.adam(optax.cosine_decay_schedule(LEARNING_RATE, STEPS, alpha=0.02))
    state = optimiser.init(u0)
    u, path, values = u0, [], []
    start = time.perf_counter()
    for step in range(STEPS + 1):
        value, grad = value_and_grad(u)
        a, e = (float(x) for x in ratios(u))
        path.append((a, e))
        values.append(float(value))
        if step == 0:
            compiled = time.perf_counter() - start
        if not (np.isfinite(float(value)) and np.all(np.isfinite(np.asarray(grad)))):
            print(f"  {name}: step {step} left the region where the objective is defined; stop")
            break
        if step == STEPS:
            break
        updates, state = optimiser.update(grad, state)
        u = optax.apply_updates(u, updates)
    wall = time.perf_counter() - start
    groups = sorted(set(tj.classify(tj.TippeTop.from_ratios(a, e)) for a, e in path))
    print(
        f"  {name}: {len(path) - 1} Adam steps, {wall:.1f} s ({compiled:.1f} s for the first, "
        f"compilation included); groups visited: {', '.join(groups)}"
    )
    for k in range(0, len(path), 8):
        print(
            f"    step {k:3d}: A/C = {path[k][0]:.4f}, eps/R = {path[k][1]:.4f}, "
            f"objective = {values[k]:.4f}"
        )
    return u, np.array(path), values


_inversion_time = jax.jit(inversion_time)


@jax.jit
def _full_inversion_time(u, spin, t1):
    """The full model's t* (with its nutation), for the table."""
    top = top_of(u)
    return tj.inversion_time(top, tj.initial_state(top, THETA0, spin), t1=t1, throw=False, **SOLVE)


_crossing_spin = jax.jit(crossing_spin)
_lowest_spin = jax.jit(lowest_spin)


def describe(label, u):
    a, e = (float(x) for x in ratios(u))
    top = top_of(u)
    th = tj.thresholds(top)
    return dict(
        label=label,
        a=a,
        e=e,
        group=tj.classify(top),
        n1=float(th.n1),
        n2=float(th.n2),
        n_full=float(full_turn_spin(u)),
        t_star=float(_inversion_time(u, SPIN, T1)),
        t_star_full=float(_full_inversion_time(u, SPIN, T1)),
        n_cross=float(_crossing_spin(u)),
        n_min=float(_lowest_spin(u)),
    )


def theta_curve(u, spin, t1):
    top = top_of(u)
    ts = np.linspace(0.0, t1, 801)
    sol = tj.simulate(top, tj.initial_state(top, THETA0, spin), t1, saveat=ts, throw=False, **SOLVE)
    return ts, np.asarray(sol.theta)


def main():
    here = pathlib.Path(__file__).parent
    (here / "figures").mkdir(exist_ok=True)
    start_all = time.perf_counter()
    u0 = parameters_of(0.9, 0.3)  # the standard top (tj.default_top())
    print(f"start: the standard top, A/C = 0.9, eps/R = 0.3; launch theta0 = {THETA0} rad\n")
    print(f"objective 1: turn over fastest at spin {SPIN:g} rad/s")
    u_fast, path_fast, _ = optimise("fastest", fastest, u0)
    print(f"\nobjective 2: turn over within {T_LIMIT:g} s at the lowest spin")
    u_low, path_low, _ = optimise("lowest spin", lowest_spin, u0)

    rows = [
        describe("standard (before)", u0),
        describe("fastest (after 1)", u_fast),
        describe("lowest spin (after 2)", u_low),
    ]
    print(
        f"\n{'top':22s} {'A/C':>7s} {'eps/R':>7s} {'group':>6s} {'n1':>7s} {'n2':>7s} "
        f"{'n_full':>7s} {'t* at ' + format(SPIN, 'g'):>10s} {'(full)':>8s} {'n_cross':>8s} "
        f"{'n_min':>8s}"
    )
    print(
        f"{'':22s} {'':>7s} {'':>7s} {'':>6s} {'rad/s':>7s} {'rad/s':>7s} {'rad/s':>7s} "
        f"{'s':>10s} {'s':>8s} {'rad/s':>8s} {'rad/s':>8s}"
    )
    for r in rows:
        print(
            f"{r['label']:22s} {r['a']:7.4f} {r['e']:7.4f} {r['group']:>6s} {r['n1']:7.2f} "
            f"{r['n2']:7.2f} {r['n_full']:7.2f} {r['t_star']:10.4f} {r['t_star_full']:8.4f} "
            f"{r['n_cross']:8.2f} "
            f"{r['n_min']:8.2f}"
        )
    print(
        "t*: nutation-averaged inversion time (gyroscopic level, the design quantity); "
        "(full): the full model's, with its nutation"
    )
    print(
        f"n_full: launch spin above which the top ends upside down (J > J2); n_cross: lowest "
        f"spin crossing pi/2 within {T_LIMIT:g} s; n_min = max(n_full, n_cross)"
    )

    fig = plt.figure(figsize=(13, 8.5), layout="constrained")
    grid = fig.add_gridspec(2, 2, width_ratios=(1.1, 1))
    ax_map = fig.add_subplot(grid[:, 0])
    group_map(n=300, ax=ax_map, inset=False, points={"standard": (0.9, 0.3)})
    e_line = np.linspace(*E_BOUNDS, 200)
    a_lo = np.maximum(A_BOUNDS[0], 1 - GROUP_MARGIN * e_line)
    a_hi = np.minimum(A_BOUNDS[1], 1 + GROUP_MARGIN * e_line)
    ax_map.fill(
        np.concatenate([a_lo, a_hi[::-1]]),
        np.concatenate([e_line, e_line[::-1]]),
        facecolor="none",
        edgecolor="black",
        linewidth=1.5,
        linestyle=":",
        label="design region",
    )
    for path, colour, label in (
        (path_fast, "crimson", f"fastest at {SPIN:g} rad/s"),
        (path_low, "navy", f"lowest spin (within {T_LIMIT:g} s)"),
    ):
        ax_map.plot(
            path[:, 0],
            path[:, 1],
            "o-",
            color=colour,
            markersize=3,
            linewidth=1.2,
            label=f"Adam path: {label}",
        )
        ax_map.plot(path[-1, 0], path[-1, 1], "s", color=colour, markersize=8)
    ax_map.set_xlim(0.5, 1.4)
    ax_map.set_ylim(0.0, 0.6)
    ax_map.set_title("Design region and the optimiser's paths on the group map")
    groups = ax_map.get_legend()  # group_map's legend: the group colours and boundaries
    handles, labels = ax_map.get_legend_handles_labels()
    ax_map.legend(
        list(groups.legend_handles) + handles,
        [t.get_text() for t in groups.get_texts()] + labels,
        loc="upper left",
        fontsize=8,
        framealpha=0.95,
        ncols=2,
    )

    ax1 = fig.add_subplot(grid[0, 1])
    for u, style, label in ((u0, "--", "standard"), (u_fast, "-", "designed (objective 1)")):
        ts, theta = theta_curve(u, SPIN, T1)
        t_star = float(_inversion_time(u, SPIN, T1))
        ax1.plot(ts, theta, style, label=f"{label}: t* = {t_star:.2f} s")
    ax1.set_title(f"Objective 1: turn over fastest at n = {SPIN:g} rad/s")
    n_low = rows[2]["n_min"]
    ax2 = fig.add_subplot(grid[1, 1])
    for u, style, label in ((u0, "--", "standard"), (u_low, "-", "designed (objective 2)")):
        ts, theta = theta_curve(u, n_low, T_LIMIT + 4)
        ax2.plot(ts, theta, style, label=label)
    ax2.axvline(T_LIMIT, color="grey", linewidth=0.8)
    ax2.set_title(f"Objective 2: both launched at the designed top's n_min = {n_low:.1f} rad/s")
    for ax in (ax1, ax2):
        ax.axhline(np.pi / 2, color="grey", linewidth=0.8, linestyle=":")
        ax.set_xlabel("t (s)")
        ax.set_ylabel(r"$\theta$ (rad)")
        ax.set_yticks([0, np.pi / 2, np.pi], ["0", r"$\pi/2$", r"$\pi$"])
        ax.legend(loc="lower right", fontsize=9)
    out = here / "figures" / "design_top.png"
    fig.savefig(out, dpi=110)
    print(f"\nwrote {out} ({time.perf_counter() - start_all:.0f} s in all)")


if __name__ == "__main__":
    main()
