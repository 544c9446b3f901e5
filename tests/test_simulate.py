"""Integration tests for `tj.simulate`: invariants, agreement between levels, chart switching,
attractors against the analysis level, contact loss, stiffness, vmap, float32, convergence and
failure reporting.

Every `simulate` call with a new (model, tolerances, saveat length, max_steps, on_contact_loss,
solver, dtype, batching) compiles anew (5-30 s on a small CPU), so all runs share one save-grid
length `N` and a handful of tolerance settings, and the expensive runs are module-scoped fixtures.
"""

import diffrax
import internal as ti
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tippejax as tj

N = 301  # one save-grid length for every run (the save-grid shape is static under jit)
TIGHT = dict(rtol=1e-12, atol=1e-14)  # reference runs of the full model
VECTOR = dict(rtol=1e-12, atol=1e-14)  # so3 / routhian runs (Dopri8: J drifts ~20 rtol over 3 s)
DEFAULT = dict(rtol=1e-8, atol=1e-10)  # long runs (attractors, contact loss, vmap)


def grid(t1):
    return jnp.linspace(0.0, t1, N)


def _np(x):
    return np.asarray(x, dtype=np.float64)


def is_ok(sol):
    return bool(np.all(np.asarray(sol.result == tj.RESULTS.successful)))


def same_result(sol, code):
    return bool(np.all(np.asarray(sol.result == code)))


def check_invariants(sol, *, j_rtol=1e-10, e_slack=1e-12):
    """J constant to `j_rtol` relative; E non-increasing up to `e_slack * |E|` of round-off."""
    valid = np.isfinite(_np(sol.theta))
    J, E = _np(sol.jellet)[valid], _np(sol.energy)[valid]
    assert valid.sum() > 10
    j_err = np.max(np.abs(J / J[0] - 1.0))
    e_rise = np.max(np.diff(E) / np.abs(E[1:]))
    assert j_err < j_rtol, j_err
    assert e_rise <= e_slack, e_rise
    # and it actually dissipates: E falls by more than round-off over the run
    assert E[-1] < E[0] * (1 - 1e-9)
    return j_err, e_rise


def releq_launch(top, theta_eq):
    """Rates of the relative equilibrium on the intermediate branch at `theta_eq` (ERRATA,
    'Useful facts'): phid = R J / D, psid = -eps J / D; returns (spin n, phi_dot)."""
    m, R, eps, A, C = (float(getattr(top, k)) for k in ("m", "R", "eps", "A", "C"))
    J = float(ti.branch_jellet(top, theta_eq))
    D = R**2 * A * np.sin(theta_eq) ** 2 + C * (R * np.cos(theta_eq) - eps) ** 2
    phid, psid = R * J / D, -eps * J / D
    return psid + phid * np.cos(theta_eq), phid


# ------------------------------------------------------------------------------------------------
# Module-scoped runs


@pytest.fixture(scope="module")
def top():
    return tj.default_top()


@pytest.fixture(scope="module")
def y_std(top):
    return tj.initial_state(top, 0.1, 100.0)


@pytest.fixture(scope="module")
def full_ref(top, y_std):
    """Full model, theta0 = 0.1, n = 100 rad/s, 3 s, rtol 1e-12: invariants and reference."""
    return tj.simulate(top, y_std, 3.0, model="full", saveat=grid(3.0), **TIGHT)


@pytest.fixture(scope="module")
def full_default(top, y_std):
    return tj.simulate(top, y_std, 3.0, model="full", saveat=grid(3.0), **DEFAULT)


# Launches that stay away from the poles: near a relative equilibrium of the intermediate branch.
AWAY_LAUNCHES = [(1.0, 0.8), (1.2, 0.9)]  # (theta of the relative equilibrium, theta0)


@pytest.fixture(scope="module")
def so3_routhian_pairs(top):
    out = []
    for theta_eq, theta0 in AWAY_LAUNCHES:
        n, phid = releq_launch(top, theta_eq)
        y0 = tj.initial_state(top, theta0, n, phi_dot=phid)
        s = tj.simulate(top, y0, 3.0, model="so3", saveat=grid(3.0), **VECTOR)
        r = tj.simulate(top, y0, 3.0, model="routhian", saveat=grid(3.0), **VECTOR)
        out.append((s, r))
    # a plain launch with moderate spin that later falls towards theta = 0 (leaves the chart)
    y0 = tj.initial_state(top, 0.8, 50.0, phi_dot=10.0)
    s = tj.simulate(top, y0, 3.0, model="so3", saveat=grid(3.0), **VECTOR)
    r = tj.simulate(top, y0, 3.0, model="routhian", saveat=grid(3.0), **VECTOR)
    out.append((s, r))
    return out


@pytest.fixture(scope="module")
def chart_pair(top):
    """theta0 = 0.3 thrown towards the pole: theta passes ~0.01 rad from theta = 0."""
    y0 = tj.initial_state(top, 0.3, 30.0, theta_dot=-4.0)
    s = tj.simulate(top, y0, 2.0, model="so3", saveat=grid(2.0), **VECTOR)
    r = tj.simulate(top, y0, 2.0, model="routhian", saveat=grid(2.0), **VECTOR)
    return s, r


@pytest.fixture(scope="module")
def contact_stop(top):
    y0 = tj.initial_state(top, 0.1, 200.0)
    return tj.simulate(top, y0, 7.0, model="full", saveat=grid(7.0), throw=False, **DEFAULT)


# ------------------------------------------------------------------------------------------------
# Invariants


def test_invariants_full(full_ref):
    assert is_ok(full_ref) and full_ref.model == "full"
    j_err, e_rise = check_invariants(full_ref)
    print(f"full: max |J/J0 - 1| = {j_err:.2e}, max dE/|E| = {e_rise:.2e}")


def test_invariants_so3_and_routhian(so3_routhian_pairs, chart_pair):
    for s, r in [*so3_routhian_pairs, chart_pair]:
        assert is_ok(s) and is_ok(r)
        assert s.model == "so3" and r.model in ("routhian", "routhian->so3")
        for sol in (s, r):
            j_err, e_rise = check_invariants(sol)
            print(f"{sol.model}: max |J/J0 - 1| = {j_err:.2e}, max dE/|E| = {e_rise:.2e}")


# ------------------------------------------------------------------------------------------------
# SO(3) vs Routhian


def test_so3_and_routhian_agree_away_from_poles(so3_routhian_pairs):
    worst = 0.0
    for k, (s, r) in enumerate(so3_routhian_pairs):
        th_s, th_r = _np(s.theta), _np(r.theta)
        ts = _np(s.ts)
        t_switch = float(r.t_chart_switch)
        mask = (np.sin(th_s) > 0.1) & ~(ts >= t_switch)  # nan t_switch -> whole run
        # until the first time sin(theta) drops below 0.1
        first_bad = np.argmin(mask) if not mask.all() else len(mask)
        mask[first_bad:] = False
        assert mask.sum() > 20
        if k < len(AWAY_LAUNCHES):  # the near-equilibrium launches stay in the chart all along
            assert r.model == "routhian" and np.isnan(t_switch) and mask.all()
        d = np.max(np.abs(th_s[mask] - th_r[mask]))
        worst = max(worst, d)
        assert d < 1e-8, (k, d)
        # it is not trivially constant: theta moves by much more than the bound
        assert np.ptp(th_s[mask]) > 0.1
    print(f"so3 vs routhian away from poles: max |dtheta| = {worst:.2e} rad")


def test_routhian_leaves_chart_through_pole(chart_pair):
    s, r = chart_pair
    assert r.model == "routhian->so3"
    t_switch = float(r.t_chart_switch)
    assert np.isfinite(t_switch) and 0.0 < t_switch < 2.0
    th_s, th_r = _np(s.theta), _np(r.theta)
    assert np.min(th_s) < 0.05  # the run really goes through the region sin(theta) < 0.05
    # at the switch time sin(theta) = CHART_SIN_MIN on the SO(3) run (interpolated on the grid)
    assert abs(np.sin(np.interp(t_switch, _np(s.ts), th_s)) - tj.CHART_SIN_MIN) < 5e-3
    assert np.all(np.isfinite(th_r))
    d = np.max(np.abs(th_s - th_r))
    print(
        f"routhian->so3 vs so3 over the whole run: max |dtheta| = {d:.2e} rad, "
        f"t_chart_switch = {t_switch:.4f} s, min theta = {np.min(th_s):.4f}"
    )
    assert d < 1e-7


# ------------------------------------------------------------------------------------------------
# Attractors against the analysis level


def test_default_top_inverts(top):
    assert tj.classify(top) == "IIb"
    y0 = tj.initial_state(top, 0.1, 100.0)
    sol = tj.simulate(top, y0, 20.0, model="full", saveat=grid(20.0), **DEFAULT)
    ss = tj.steady_states(top, sol.jellet[0])
    assert bool(ss.vertical_stable[1]) and not bool(ss.vertical_stable[0])
    th = _np(sol.theta)
    print(
        f"inversion: pi - theta(20 s) = {np.pi - th[-1]:.2e}, t_invert = {float(sol.t_invert):.4f}"
    )
    assert abs(np.pi - th[-1]) < 1e-3
    assert np.all(np.abs(np.pi - th[-N // 20 :]) < 1e-3)
    # ERRATA, useful facts: first time theta > pi/2 is 5.70 s with translation
    assert np.isfinite(float(sol.t_invert))
    assert abs(float(sol.t_invert) - 5.70) < 0.02
    # the refined crossing lies between the bracketing save points
    k = np.argmax(th > np.pi / 2)
    assert float(sol.ts[k - 1]) <= float(sol.t_invert) <= float(sol.ts[k])
    assert tj.OUTCOMES[int(sol.outcome)] == "inverted" and bool(sol.settled)


def test_intermediate_state_attractor(top):
    th = tj.thresholds(top)
    J1, J2 = float(th.J1), float(th.J2)
    C, R, eps = float(top.C), float(top.R), float(top.eps)
    J_target = 5e-6
    assert J1 < J_target < J2
    theta0 = 0.1
    n = J_target / (C * (R * np.cos(theta0) - eps))  # phi_dot = 0: J = C n (R cos th - eps)
    y0 = tj.initial_state(top, theta0, n)
    sol = tj.simulate(top, y0, 30.0, model="full", saveat=grid(30.0), **DEFAULT)
    J = float(sol.jellet[0])
    assert J1 < J < J2
    ss = tj.steady_states(top, J)
    states = ss.intermediate
    stable = [t for t, s in states if s]
    assert len(stable) == 1
    theta_i = stable[0]
    assert not bool(ss.vertical_stable[0]) and not bool(ss.vertical_stable[1])
    tail = _np(sol.theta)[-N // 30 :]  # the last second
    dev = np.max(np.abs(tail - theta_i))
    print(f"intermediate: predicted {theta_i:.6f}, max |theta - theta_i| over last 1 s = {dev:.2e}")
    assert dev < 1e-2
    assert _np(sol.theta)[-1] > 0.5  # it did rise from 0.1
    assert tj.OUTCOMES[int(sol.outcome)] == "intermediate" and bool(sol.settled)


def test_fall_back_from_near_pi(top):
    spin = 5.0  # |n_pi| ~ 5 rad/s, far below n2 (35 rad/s) and |J| < J1: theta = 0 stable
    y0 = tj.initial_state(top, np.pi - 0.1, spin)
    th = tj.thresholds(top)
    J = float(tj.jellet(top, y0))
    assert abs(J) < float(th.J1) and spin < 0.5 * float(th.n2)
    ss = tj.steady_states(top, J)
    assert bool(ss.vertical_stable[0]) and not bool(ss.vertical_stable[1])
    assert not np.any(np.asarray(ss.intermediate_valid))
    sol = tj.simulate(top, y0, 20.0, model="full", saveat=grid(20.0), **DEFAULT)
    theta = _np(sol.theta)
    print(f"fall back: theta(20 s) = {theta[-1]:.2e}")
    assert theta[-1] < np.pi / 2
    assert theta[-1] < 0.05
    assert np.isnan(float(sol.t_invert))  # launched beyond pi/2 and never crosses upwards
    assert tj.OUTCOMES[int(sol.outcome)] == "upright" and bool(sol.settled)


def test_crossing_pi_over_2_is_not_an_inversion():
    """A Group III top crosses pi/2 (finite t_invert) and settles on its intermediate state
    beyond pi/2: sol.outcome says "intermediate", the state the analysis level predicts."""
    top = tj.TippeTop.from_ratios(1.5, 0.3)
    assert tj.classify(top) == "III"
    sol = tj.simulate(
        top, tj.initial_state(top, 0.1, 100.0), 20.0, model="full", saveat=grid(20.0), **DEFAULT
    )
    assert np.isfinite(float(sol.t_invert))
    assert tj.OUTCOMES[int(sol.outcome)] == "intermediate" and bool(sol.settled)
    ss = tj.steady_states(top, sol.jellet[0])
    stable = [t for t, ok in ss.intermediate if ok]
    assert len(stable) == 1 and np.pi / 2 < stable[0] < np.pi
    assert abs(float(sol.theta[-1]) - stable[0]) < 0.1
    assert not bool(ss.vertical_stable[1])  # theta = pi is unstable: no inversion to reach


# ------------------------------------------------------------------------------------------------
# Contact loss


def test_contact_loss_stop(contact_stop):
    sol = contact_stop
    assert same_result(sol, tj.RESULTS.contact_lost)
    t_loss = float(sol.t_contact_loss)
    print(f"t_contact_loss = {t_loss:.4f} s (ERRATA: 5.19 s)")
    assert abs(t_loss - 5.19) < 0.02
    assert abs(float(sol.t_final) - t_loss) < 1e-9
    assert tj.OUTCOMES[int(sol.outcome)] == "contact_lost" and not bool(sol.settled)
    ts = _np(sol.ts)
    after = ts > t_loss
    assert after.any() and (~after).any()
    for name in ("theta", "jellet", "energy", "normal_force", "spin"):
        v = _np(getattr(sol, name))
        assert np.all(np.isnan(v[after])), name
        assert np.all(np.isfinite(v[~after])), name
    rn = _np(sol.normal_force)[~after]
    assert np.all(rn > 0)


def test_contact_loss_throw(top):
    y0 = tj.initial_state(top, 0.1, 200.0)
    with pytest.raises(RuntimeError, match="(?i)normal force"):
        tj.simulate(top, y0, 7.0, model="full", saveat=grid(7.0), **DEFAULT)


def test_contact_loss_continue(top, contact_stop):
    y0 = tj.initial_state(top, 0.1, 200.0)
    sol = tj.simulate(
        top, y0, 7.0, model="full", saveat=grid(7.0), on_contact_loss="continue", **DEFAULT
    )  # does not raise with throw=True
    assert same_result(sol, tj.RESULTS.contact_lost)
    assert float(sol.t_final) == pytest.approx(7.0)
    assert abs(float(sol.t_contact_loss) - float(contact_stop.t_contact_loss)) < 1e-9
    assert np.all(np.isfinite(_np(sol.theta)))
    after = _np(sol.ts) > float(sol.t_contact_loss)
    assert np.any(_np(sol.normal_force)[after] < 0)
    # same trajectory as the stopped run before the loss
    before = ~after
    assert np.max(np.abs(_np(sol.theta)[before] - _np(contact_stop.theta)[before])) < 1e-12


def test_steps_run_out_past_a_contact_loss_says_so(top, contact_stop):
    """A run that goes on past its contact loss and then runs out of steps is told why (the
    model feeds energy into the top past the loss, docs/notes.md), not only to raise
    max_steps; a run out of steps with no loss keeps the friction hint."""
    import equinox as eqx

    lost = eqx.tree_at(lambda s: s.result, contact_stop, tj.RESULTS.max_steps_reached)
    t_loss = float(contact_stop.t_contact_loss)
    with pytest.raises(RuntimeError, match=f"lost contact .* t = {t_loss:.6g} s") as info:
        ti.raise_if_failed(lost, "continue", top)
    assert "on_contact_loss='stop'" in str(info.value)
    never_lost = eqx.tree_at(lambda s: s.t_contact_loss, lost, jnp.asarray(jnp.nan))
    with pytest.raises(RuntimeError, match="friction is not stiff") as info:
        ti.raise_if_failed(never_lost, "continue", top)
    assert "lost contact" not in str(info.value)


def test_contact_loss_located_by_every_solver(contact_stop):
    """The located loss does not depend on the solver: Tsit5 at rtol 1e-8 (steps ~10x shorter
    than Dopri8's) finds it at the time the default Dopri8 does."""
    y0 = tj.initial_state(tj.default_top(), 0.1, 200.0)
    sol = tj.simulate(
        tj.default_top(),
        y0,
        7.0,
        model="full",
        saveat=grid(7.0),
        throw=False,
        solver=diffrax.Tsit5(),
        **DEFAULT,
    )
    assert same_result(sol, tj.RESULTS.contact_lost)
    d = abs(float(sol.t_contact_loss) - float(contact_stop.t_contact_loss))
    print(
        f"t_contact_loss Tsit5 - Dopri8 = {d:.1e} s ({int(sol.num_steps)} vs "
        f"{int(contact_stop.num_steps)} steps)"
    )
    assert d < 1e-5


def test_contact_loss_too_brief_for_the_watch_is_reported(monkeypatch):
    """The safety net behind the event watch: a dip of R_n below 0 that the watch did not see
    but a save time did must be reported, not the later loss as the first. The watch no longer
    misses the first brief dip of this run (its Bernstein check bounds the quintic's crossings),
    so it is blinded here to the ends of each step (`event_pieces=7` only keys this program,
    kept out of the store of traced programs): Dopri8's long steps at rtol 1e-5 then go over
    the dip, which the 1.3 ms save grid sees."""
    from tippejax._cache import stored as _cache
    from tippejax._engine import bernstein as watch

    monkeypatch.setattr(_cache, "EXPORT_DIR", None)

    bernstein = watch._bernstein_polygon
    ends_only = np.array([[1.0, 0, 0, 0, 0, 0], [0, 0, 0, 0, 1.0, 0]])
    monkeypatch.setattr(
        watch, "_bernstein_polygon", lambda pieces: ends_only if pieces == 7 else bernstein(pieces)
    )
    top = tj.default_top()
    y0 = tj.initial_state(top, 0.1, 200.0)
    ts = jnp.linspace(4.9, 5.3, N)
    opts = dict(
        model="full", saveat=ts, rtol=1e-5, atol=1e-7, solver=diffrax.Dopri8(), event_pieces=7
    )
    sol = tj.simulate(top, y0, 5.3, throw=False, **opts)
    assert same_result(sol, tj.RESULTS.contact_loss_missed)
    assert np.isnan(float(sol.t_contact_loss))
    theta = _np(sol.theta)
    # nothing is returned from the first save time with R_n < 0 on; before it, all is finite
    first_nan = np.argmax(np.isnan(theta))
    assert 0 < first_nan and np.all(np.isnan(theta[first_nan:]))
    assert np.all(np.isfinite(theta[:first_nan])) and np.all(_np(sol.normal_force)[:first_nan] >= 0)
    # the true first loss (5.1865 s) lies before the first nan
    assert float(sol.ts[first_nan]) > 5.1865
    with pytest.raises(RuntimeError, match="went unseen"):
        tj.simulate(top, y0, 5.3, **opts)


# ------------------------------------------------------------------------------------------------
# Stiff friction


def test_stiff_friction_default_solver():
    top = tj.TippeTop.from_ratios(0.9, 0.3, m=0.02, R=0.025, mu=300.0)
    assert float(tj.friction_rate(top)) > 1000.0
    # Choices follow benchmarks/RESULTS.md: under stiff friction Tsit5 beat Dopri8 and Kvaerno5.
    assert isinstance(tj.default_solver(top), diffrax.Tsit5)
    assert isinstance(tj.default_solver(tj.default_top()), diffrax.Dopri8)
    very_stiff = tj.TippeTop.from_ratios(0.9, 0.3, mu=3.0e4)
    assert isinstance(tj.default_solver(very_stiff), diffrax.Kvaerno5)
    y0 = tj.initial_state(top, 0.1, 100.0)
    sol = tj.simulate(top, y0, 1.0, model="full", saveat=grid(1.0), **DEFAULT)
    assert is_ok(sol)
    # rtol = 1e-8 here (an implicit solve at 1e-10 costs ~3x): J drifts ~1e-10 relative
    j_err, e_rise = check_invariants(sol, j_rtol=1e-9)
    print(
        f"stiff mu=300: {int(sol.num_steps)} steps, max |J/J0 - 1| = {j_err:.2e}, "
        f"max dE/|E| = {e_rise:.2e}"
    )
    # Very stiff friction: the implicit default (Kvaerno5) finishes where Tsit5 needs > 1e6
    # steps per second of motion.
    y0 = tj.initial_state(very_stiff, 0.1, 100.0)
    sol = tj.simulate(very_stiff, y0, 0.2, model="full", saveat=grid(0.2), **DEFAULT)
    assert is_ok(sol)
    check_invariants(sol, j_rtol=1e-9)


# ------------------------------------------------------------------------------------------------
# vmap

SPINS = np.linspace(20.0, 200.0, 32)


@pytest.mark.slow
def test_vmap_over_spins_matches_loop(top):
    ts = grid(3.0)

    def one(n):
        y0 = tj.initial_state(top, 0.1, n)
        sol = tj.simulate(top, y0, 3.0, model="full", saveat=ts, throw=False, **DEFAULT)
        return sol.theta, sol.result == tj.RESULTS.successful

    theta_b, res_b = jax.vmap(one)(jnp.asarray(SPINS))
    assert theta_b.shape == (32, N)
    assert np.all(np.asarray(res_b))
    worst = 0.0
    for i in (0, 11, 22, 31):
        y0 = tj.initial_state(top, 0.1, SPINS[i])
        s = tj.simulate(top, y0, 3.0, model="full", saveat=ts, **DEFAULT)
        worst = max(worst, np.max(np.abs(_np(s.theta) - _np(theta_b[i]))))
    print(f"vmap over spins vs loop: max |dtheta| = {worst:.2e}")
    assert worst < 1e-8
    # different spins give different trajectories
    assert np.max(np.abs(_np(theta_b[0]) - _np(theta_b[31]))) > 1e-2


def test_jit_with_default_solver(top, full_ref):
    """Under jit (spin traced) the default solver still meets the tolerance: against the
    rtol-1e-12 reference, theta agrees to what rtol 1e-8 gives (see the convergence test)."""

    def one(n):
        y0 = tj.initial_state(top, 0.1, n)
        sol = tj.simulate(top, y0, 3.0, model="full", saveat=grid(3.0), throw=False, **DEFAULT)
        return sol.theta, sol.result == tj.RESULTS.successful

    theta, ok = jax.jit(one)(100.0)
    err = np.max(np.abs(_np(theta) - _np(full_ref.theta)))
    print(f"jit, default solver vs tight reference: max |dtheta| = {err:.2e} rad")
    assert bool(ok) and err < 1e-5


def test_jit_with_every_input_a_concrete_array(top):
    """`simulate` inside a caller's `jit` whose inputs are all concrete arrays closed over (no
    traced argument at all) is traced into the caller's program, and agrees with the call
    outside it. (It raised before: the concrete inputs sent it to the path of a top-level
    call, whose compile options JAX refuses on a nested `jit`.)"""
    y0 = tj.initial_state(top, 0.1, 100.0)
    t0, t1, rtol, atol = (jnp.asarray(v) for v in (0.0, 1.0, DEFAULT["rtol"], DEFAULT["atol"]))

    def run():
        sol = tj.simulate(top, y0, t1, t0=t0, model="full", summary=True, rtol=rtol, atol=atol)
        return sol.states.omega[-1], sol.num_steps

    omega, steps = jax.jit(run)()
    omega_eager, steps_eager = run()
    # (two compilations of one solve: they may round differently, which can move a step, but
    # agree to well within the solve's rtol)
    assert int(steps_eager) > 10 and abs(int(steps) - int(steps_eager)) <= 2
    np.testing.assert_allclose(_np(omega), _np(omega_eager), rtol=1e-9, atol=1e-9)


def test_an_eager_vmap_compiles_with_tippejaxs_options(top, monkeypatch):
    """An eager `jax.vmap` of `simulate` runs the batched solve as a top-level program, so
    it is compiled with tippejax's options, as a concrete call is (an unknown option raising
    proves they reach XLA); `test_vmap_over_spins_matches_loop` checks its numbers."""
    import tippejax._simulate.single as simulate_module

    bad = {"not_an_xla_option": 1}
    monkeypatch.setattr(simulate_module, "own_compiler_options", lambda: bad)

    def one(n):
        y0 = tj.initial_state(top, 0.1, n)
        return tj.simulate(top, y0, 0.5, model="full", summary=True, throw=False).t_final

    with pytest.raises(Exception, match="not_an_xla_option"):
        jax.vmap(one)(jnp.array([100.0, 120.0]))


def _four_tops():
    ratios = [(0.9, 0.3, 0.3), (0.8, 0.2, 0.5), (0.95, 0.4, 0.2), (1.2, 0.1, 1.0)]
    return [tj.TippeTop.from_ratios(a, e, m=0.02, R=0.025, mu=mu) for a, e, mu in ratios]


def _stack(tops):
    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *tops)


@pytest.mark.slow
def test_vmap_over_tops_explicit_solver():
    tops = _four_tops()
    ts = grid(3.0)

    def one(tp):
        y0 = tj.initial_state(tp, 0.1, 80.0)
        sol = tj.simulate(
            tp, y0, 3.0, model="full", saveat=ts, throw=False, solver=diffrax.Tsit5(), **DEFAULT
        )
        return sol.theta, sol.result == tj.RESULTS.successful

    theta_b, res_b = jax.vmap(one)(_stack(tops))
    assert np.all(np.asarray(res_b))
    worst = 0.0
    for i, tp in enumerate(tops):
        s = tj.simulate(
            tp,
            tj.initial_state(tp, 0.1, 80.0),
            3.0,
            model="full",
            saveat=ts,
            solver=diffrax.Tsit5(),
            **DEFAULT,
        )
        worst = max(worst, np.max(np.abs(_np(s.theta) - _np(theta_b[i]))))
    print(f"vmap over tops vs loop: max |dtheta| = {worst:.2e}")
    assert worst < 1e-8


def test_vmap_over_a_stiff_and_a_soft_top_says_so():
    """Under vmap over tops the stiffness cannot pick the solver per member: the soft member is
    integrated (and agrees with its own eager run, which picks its solver itself), the very
    stiff one (friction rate > 5e5/s, where an explicit solver cannot finish) is reported at
    once as `stiff_under_trace` instead of holding the batch up until max_steps."""
    soft = tj.default_top()
    stiff = tj.TippeTop.from_ratios(0.9, 0.3, m=0.02, R=0.025, mu=3.0e4)
    assert float(tj.friction_rate(stiff)) > 5e5 > float(tj.friction_rate(soft))
    ts = grid(1.0)

    def one(tp):
        y0 = tj.initial_state(tp, 0.1, 80.0)
        sol = tj.simulate(tp, y0, 1.0, model="full", saveat=ts, throw=False, **DEFAULT)
        ok = sol.result == tj.RESULTS.successful
        return sol.theta, ok, sol.result == tj.RESULTS.stiff_under_trace, sol.num_steps

    theta_b, ok_b, stiff_b, steps_b = jax.vmap(one)(_stack([soft, stiff]))
    assert bool(ok_b[0]) and not bool(stiff_b[0])
    assert bool(stiff_b[1]) and not bool(ok_b[1])
    assert int(steps_b[1]) == 0 and np.all(np.isnan(_np(theta_b[1])[1:]))
    eager = tj.simulate(
        soft, tj.initial_state(soft, 0.1, 80.0), 1.0, model="full", saveat=ts, **DEFAULT
    )
    d = np.max(np.abs(_np(eager.theta) - _np(theta_b[0])))
    print(f"vmap soft member vs eager: {d:.2e} rad")
    assert d < 1e-8
    # With an implicit solver passed explicitly, the stiff member is integrated too.
    with pytest.raises(RuntimeError, match="very stiff"):
        jax.jit(
            lambda tp: (
                tj.simulate(tp, tj.initial_state(tp, 0.1, 80.0), 1.0, saveat=ts, **DEFAULT).theta
            )
        )(stiff)


# ------------------------------------------------------------------------------------------------
# float32


def _float32_run():
    top32 = tj.default_top().astype(jnp.float32)
    y0 = tj.initial_state(top32, 0.1, 100.0)
    y0 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), y0)
    return tj.simulate(
        top32, y0, 3.0, model="full", saveat=grid(3.0).astype(jnp.float32), throw=False, **DEFAULT
    )


@pytest.mark.slow
def test_float32_with_x64_disabled(full_ref):
    """Slow: `tests/test_float32.py` runs float32 with x64 off in a process of its own."""
    with jax.enable_x64(False):
        sol = _float32_run()
        assert sol.theta.dtype == jnp.float32
        assert sol.jellet.dtype == jnp.float32
        assert is_ok(sol)
        theta32 = _np(sol.theta)
    err = np.max(np.abs(theta32 - _np(full_ref.theta)))
    print(f"float32 vs float64: max |dtheta| over 3 s = {err:.2e} rad")
    # float32 runs at rtol >= 1e-5 over ~50 nutation periods: allow 100x amplification.
    assert err < 1e-3


def test_float32_with_x64_enabled(full_ref):
    assert jax.config.jax_enable_x64
    sol = _float32_run()
    assert sol.theta.dtype == jnp.float32 and is_ok(sol)


# ------------------------------------------------------------------------------------------------
# Convergence


def test_convergence_in_rtol(top, y_std, full_ref, full_default):
    ref = _np(full_ref.theta)
    errors = []
    for rtol in (1e-4, 1e-6):
        s = tj.simulate(
            top, y_std, 3.0, model="full", saveat=grid(3.0), rtol=rtol, atol=rtol * 1e-2
        )
        errors.append(np.max(np.abs(_np(s.theta) - ref)))
    errors.append(np.max(np.abs(_np(full_default.theta) - ref)))  # rtol 1e-8, atol 1e-10
    print(
        "convergence (rtol 1e-4, 1e-6, 1e-8): max |dtheta| = "
        + ", ".join(f"{e:.2e}" for e in errors)
    )
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 1e-5
    assert errors[0] > 10 * errors[2]  # a real decrease, not noise


# ------------------------------------------------------------------------------------------------
# Save grids share compilations by bucket


def test_save_grid_lengths_in_one_bucket_compile_once(top, y_std):
    from tippejax._bucket import bucket as save_bucket
    from tippejax._simulate.programs import _run

    assert [save_bucket(n) for n in (1, 16, 17, 32, 33, 1001)] == [16, 16, 32, 32, 64, 1024]
    ts = np.linspace(0.0, 0.5, 21)
    a = tj.simulate(top, y_std, 0.5, saveat=ts, **DEFAULT)
    before = _run._cached._cache_size()
    b = tj.simulate(top, y_std, 0.5, saveat=ts[:17], **DEFAULT)  # 17 and 21: bucket 32
    assert _run._cached._cache_size() == before
    assert b.theta.shape == (17,) and b.states.axis.shape == (17, 3) and b.ts.shape == (17,)
    np.testing.assert_allclose(_np(b.theta), _np(a.theta)[:17], rtol=0, atol=1e-14)
    np.testing.assert_allclose(_np(b.ts), ts[:17], rtol=0, atol=0)
    assert float(b.t_invert) == float(a.t_invert) or np.isnan(float(a.t_invert))


# ------------------------------------------------------------------------------------------------
# Rates at the pole


@pytest.mark.parametrize("theta0, theta_dot", [(0.0, 1.0), (np.pi, -1.0)])
def test_theta_dot_at_the_pole_follows_theta(top, theta0, theta_dot):
    """Launched from a pole with a tilt rate: sol.theta_dot[0] is that rate (theta leaves 0
    upwards, pi downwards), and agrees with finite differences of theta a moment later."""
    y0 = tj.initial_state(top, theta0, 100.0, theta_dot=abs(theta_dot))
    t1 = 0.03
    sol = tj.simulate(top, y0, t1, model="full", saveat=grid(t1), **DEFAULT)
    theta, thd = _np(sol.theta), _np(sol.theta_dot)
    assert thd[0] == theta_dot
    h = t1 / (N - 1)
    for k in (2, 10, 50):
        central = (theta[k + 1] - theta[k - 1]) / (2 * h)
        np.testing.assert_allclose(thd[k], central, rtol=1e-3)
    assert np.sign(theta[1] - theta[0]) == np.sign(theta_dot)


# ------------------------------------------------------------------------------------------------
# Failures


def test_max_steps_reached(top, y_std):
    sol = tj.simulate(
        top, y_std, 3.0, model="full", saveat=grid(3.0), max_steps=16, throw=False, **DEFAULT
    )
    assert same_result(sol, tj.RESULTS.max_steps_reached)
    assert float(sol.t_final) < 3.0
    assert "maximum number of solver steps" in sol.message()
    # mu = 0.3 is not stiff friction: the error must not send the user to an implicit solver.
    with pytest.raises(RuntimeError, match="maximum number of solver steps") as info:
        tj.simulate(top, y_std, 3.0, model="full", saveat=grid(3.0), max_steps=16, **DEFAULT)
    text = str(info.value)
    assert "not stiff" in text and "would not help" in text
    assert f"{float(tj.friction_rate(top)):.3g}/s" in text
    # A stiff top's message does point to an implicit solver.
    from tippejax._simulate.single import _max_steps_hint

    stiff = top.replace(mu=3000.0)
    assert float(tj.friction_rate(stiff)) > 1e3
    assert "Kvaerno5" in _max_steps_hint(stiff) and "not stiff" not in _max_steps_hint(stiff)


def test_bad_arguments(top, y_std):
    with pytest.raises(ValueError):
        tj.simulate(top, y_std, 1.0, model="euler")
    for t0, t1 in [(0.0, 0.0), (0.0, -1.0), (2.0, 1.0)]:
        with pytest.raises(ValueError):
            tj.simulate(top, y_std, t1, t0=t0)


FIELDS = (
    "theta",
    "phi",
    "psi",
    "theta_dot",
    "spin",
    "position",
    "velocity",
    "jellet",
    "energy",
    "normal_force",
    "slip_speed",
)


def test_successful_runs_are_finite(full_ref, full_default, so3_routhian_pairs, chart_pair):
    sols = [full_ref, full_default, *[x for p in so3_routhian_pairs for x in p], *chart_pair]
    for sol in sols:
        assert is_ok(sol)
        for name in FIELDS:
            value = _np(getattr(sol, name))
            if name in ("position", "velocity") and not sol.model.startswith("full"):
                # (the SO(3) and Routhian levels drop the translation: not computed, nan)
                assert np.all(np.isnan(value)), (sol.model, name)
            else:
                assert np.all(np.isfinite(value)), (sol.model, name)
        assert float(sol.t_final) == pytest.approx(float(sol.ts[-1]))


# --- the R_n singularity (ERRATA, point 5) -------------------------------------------------------

MU_SING = 20.0  # friction_rate ~ 920/s < 1000/s: Tsit5, the same compiled so3 solve as above
THETA_SING = 1.0


def _singular_setup():
    top = tj.TippeTop.from_ratios(0.9, 0.3, m=0.02, R=0.025, mu=MU_SING)
    m, R, eps, A = (float(getattr(top, k)) for k in ("m", "R", "eps", "A"))
    h = R - eps * np.cos(THETA_SING)
    hp = eps * np.sin(THETA_SING)
    bound = -(A / m + hp**2) / (MU_SING * h**2 * hp)
    return top, (m, A, h, hp), bound


def test_normal_force_denominator_matches_errata():
    top, (m, A, h, hp), bound = _singular_setup()
    for fac in (0.0, 0.5, 0.95, 1.05, 2.0):
        thd = fac * bound
        y0 = tj.initial_state(top, THETA_SING, 50.0, theta_dot=thd)
        den = float(tj.normal_force_denominator(top, y0, model="so3"))
        expected = 1 / m + hp * (hp + MU_SING * h**2 * thd) / A
        assert den == pytest.approx(expected, rel=1e-10, abs=1e-10)
        assert (den > 0) == (fac < 1)


def test_dynamics_stay_away_from_singularity():
    """Launched at 0.95 of the bound (denominator 5% of its thd = 0 value), the flow moves away
    from the singular surface: the run succeeds and the denominator stays positive."""
    top, _, bound = _singular_setup()
    y0 = tj.initial_state(top, THETA_SING, 50.0, theta_dot=0.95 * bound)
    sol = tj.simulate(top, y0, 1.0, model="so3", saveat=grid(1.0), throw=False, **VECTOR)
    assert is_ok(sol)
    den = _np(tj.normal_force_denominator(top, sol.states, model="so3"))
    print(f"singularity: min denominator along the run = {np.min(den):.3g} (at t0 {den[0]:.3g})")
    assert np.all(den > 0)


def test_state_beyond_singularity_is_not_a_success():
    top, _, bound = _singular_setup()
    y0 = tj.initial_state(top, THETA_SING, 50.0, theta_dot=1.05 * bound)
    assert float(tj.normal_force_denominator(top, y0, model="so3")) < 0
    sol = tj.simulate(top, y0, 1.0, model="so3", saveat=grid(1.0), throw=False, **VECTOR)
    print(f"beyond the singularity at t0: result = {sol.result!r}")
    assert not is_ok(sol)
    with pytest.raises(RuntimeError):
        tj.simulate(top, y0, 1.0, model="so3", saveat=grid(1.0), **VECTOR)


def test_state_beyond_singularity_reported_as_singular():
    top, _, bound = _singular_setup()
    y0 = tj.initial_state(top, THETA_SING, 50.0, theta_dot=1.05 * bound)
    sol = tj.simulate(top, y0, 1.0, model="so3", saveat=grid(1.0), throw=False, **VECTOR)
    assert same_result(sol, tj.RESULTS.normal_force_singular)
