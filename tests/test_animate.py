"""The animation: geometry of the drawn top, resampling to frame times, files written, errors."""

import contextlib

import matplotlib

matplotlib.use("Agg")

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from PIL import Image  # noqa: E402

import tippejax as tj  # noqa: E402
from tippejax._animate.frames import (  # noqa: E402
    STEM_LENGTH,
    _end_reason,
    _valid_count,
    frame_geometry,
    frame_times,
)
from tippejax._cli import main  # noqa: E402

T1 = 0.25  # the CLI test simulates the same launch and save grid (one compilation)
N_SAVE = 51


def _fake_solution(ts, axis, body, omega, position=None, model="full", height=None):
    """A `Solution` holding the given orientation (other fields zero), no simulation."""
    ts = jnp.asarray(ts, dtype=float)
    n = ts.shape[0]
    zeros = jnp.zeros(n)
    position = jnp.zeros((n, 2)) if position is None else jnp.asarray(position, dtype=float)
    states = tj.State(
        position=position,
        velocity=jnp.zeros((n, 2)),
        axis=jnp.asarray(axis),
        omega=jnp.asarray(omega),
        body=jnp.asarray(body),
        height=None if height is None else jnp.asarray(height, dtype=float),
        height_rate=None if height is None else zeros,
    )
    theta = jnp.arccos(jnp.clip(states.axis[:, 2], -1, 1))
    scalar = jnp.asarray(jnp.nan)
    return tj.Solution(
        ts=ts,
        theta=theta,
        phi=zeros,
        psi=zeros,
        theta_dot=zeros,
        phi_dot=zeros,
        psi_dot=zeros,
        spin=zeros,
        position=position,
        velocity=jnp.zeros((n, 2)),
        jellet=zeros,
        energy=zeros,
        normal_force=zeros,
        slip_speed=zeros,
        states=states,
        result=tj.RESULTS.successful,
        t_invert=scalar,
        t_contact_loss=scalar,
        t_chart_switch=scalar,
        t_final=ts[-1],
        num_steps=jnp.asarray(0),
        num_rejected_steps=jnp.asarray(0),
        model=model,
    )


@pytest.fixture(scope="module")
def top():
    return tj.default_top()


@pytest.fixture(scope="module")
def sol(top):
    y0 = tj.initial_state(top, 0.1, 99.0, vx=0.05)
    return tj.simulate(top, y0, T1, saveat=np.linspace(0.0, T1, N_SAVE), throw=False)


@pytest.mark.parametrize("theta", [0.0, 0.7, np.pi / 2, 2.5, np.pi])
def test_geometry_stem_sphere_contact(top, theta):
    y = tj.state_from_euler(theta, 0.3, 0.2, 0.0, 0.0, 0.0)
    n = 3
    sol = _fake_solution(
        np.arange(n) * 0.1,
        np.tile(y.axis, (n, 1)),
        np.tile(y.body, (n, 1)),
        np.zeros((n, 3)),
        position=np.tile([0.01, -0.02], (n, 1)),
    )
    g = frame_geometry(sol, top, [0.05])
    R, eps = float(top.R), float(top.eps)
    a = np.asarray(y.axis)
    np.testing.assert_allclose(g.theta, theta, atol=1e-7)
    # Centre of the sphere at height R, contact point on the table right below it.
    np.testing.assert_allclose(g.centre[0, 2], R)
    np.testing.assert_allclose(g.contact[0], g.centre[0] - [0, 0, R])
    # Centre of mass eps from the centre, opposite the stem; at the saved position.
    np.testing.assert_allclose(g.centre_of_mass[0], g.centre[0] - eps * a, atol=1e-15)
    np.testing.assert_allclose(g.centre_of_mass[0, :2], [0.01, -0.02])
    np.testing.assert_allclose(g.centre_of_mass[0, 2], R - eps * np.cos(theta), atol=1e-15)
    # The stem starts on the sphere along +a and never goes below the table.
    base, tip = g.stem[0]
    np.testing.assert_allclose(base, g.centre[0] + R * a, atol=1e-15)
    assert tip[2] >= -1e-15
    if theta == 0.0:  # stem up, centre of mass below the centre
        np.testing.assert_allclose(tip, g.centre[0] + [0, 0, (1 + STEM_LENGTH) * R])
        assert g.centre_of_mass[0, 2] < g.centre[0, 2]
    if theta == np.pi:  # inverted: stem down (clipped to nothing at the table), CM above
        np.testing.assert_allclose(base[2], 0.0, atol=1e-15)
        np.testing.assert_allclose(tip, base, atol=1e-15)
        assert g.centre_of_mass[0, 2] > g.centre[0, 2]


def test_modelled_stem_is_drawn_and_moves_with_the_axis(tmp_path, monkeypatch):
    """A top with a `tj.Stem`: the rod runs along the axis to the tip's centre O + a2 a, the
    tip's outline (an artist of its own) is drawn there at each frame, of radius r2, and the
    centre of mass is at the height the states carry."""
    import tippejax._animate.draw as animate_module

    top = tj.TippeTop(m=0.006, R=0.015, eps=0.003, A=8e-7, C=7e-7, stem=tj.Stem(0.005, 0.016))
    thetas = np.array([0.3, 1.2, 2.3])
    ys = [tj.state_from_euler(th, 0.4 * k, 0.0, 0.0, 0.0, 0.0) for k, th in enumerate(thetas)]
    axis = np.stack([np.asarray(y.axis) for y in ys])
    height = 0.015 - 0.003 * np.cos(thetas) + [0.0, 1e-3, 2e-3]
    sol = _fake_solution(
        np.arange(3) * 0.1,
        axis,
        np.stack([np.asarray(y.body) for y in ys]),
        np.zeros((3, 3)),
        height=height,
    )
    g = frame_geometry(sol, top, [0.0, 0.1, 0.2])
    np.testing.assert_allclose(g.centre_of_mass[:, 2], height, atol=1e-15)
    np.testing.assert_allclose(g.stem_tip, g.centre_of_mass + 0.016 * axis, atol=1e-15)
    np.testing.assert_allclose(g.stem[:, 1], g.stem_tip, atol=1e-15)
    rod = g.stem[:, 1] - g.stem[:, 0]  # along the axis, outwards
    np.testing.assert_allclose(rod / np.linalg.norm(rod, axis=-1, keepdims=True), axis, atol=1e-12)

    drawn = []  # the tip's outline at each frame, as the animation draws it

    class Writer:
        def saving(self, fig, path, dpi):
            self.fig = fig
            return contextlib.nullcontext()

        def grab_frame(self):
            (line,) = [ln for ln in self.fig.axes[0].lines if ln.get_gid() == "stem_tip"]
            drawn.append(np.stack(line.get_data_3d(), axis=-1))

    monkeypatch.setattr(animate_module, "_writer", lambda path, fps: Writer())
    tj.animate(sol, top, str(tmp_path / "stem.gif"), frames=3, dpi=20)
    assert len(drawn) == 3
    for outline, centre in zip(drawn, g.stem_tip):
        np.testing.assert_allclose(np.linalg.norm(outline - centre, axis=-1), 0.005, rtol=1e-9)
    assert np.linalg.norm(drawn[2].mean(0) - drawn[0].mean(0)) > 0.01  # it moved


def test_geometry_matches_simulation(top, sol):
    n = _valid_count(sol)
    assert n == N_SAVE
    g = frame_geometry(sol, top, np.asarray(sol.ts))
    np.testing.assert_allclose(g.centre_of_mass[:, :2], np.asarray(sol.position), atol=1e-14)
    np.testing.assert_allclose(g.theta, np.asarray(sol.theta), atol=1e-9)
    np.testing.assert_allclose(g.axis, np.asarray(sol.states.axis), atol=1e-12)
    assert np.all(g.contact[:, 2] == 0) and np.all(g.centre[:, 2] > g.contact[:, 2])
    # The launch has vx = 0.05 m/s: the centre of mass moves (friction turns its path).
    assert np.max(np.linalg.norm(g.centre_of_mass[:, :2], axis=-1)) > 0.002


def test_resampling_between_coarse_saves(top):
    # Steady spin about the vertical at n = 40 rad/s, saved every 0.1 s (4 rad per interval):
    # a frame between saves turns the body by omega (t - t_k), not by a chord between saves.
    n_spin, ts = 40.0, np.arange(6) * 0.1
    body = np.stack([np.cos(n_spin * ts), np.sin(n_spin * ts), 0 * ts], -1)
    axis = np.tile([0.0, 0.0, 1.0], (6, 1))
    omega = np.tile([0.0, 0.0, n_spin], (6, 1))
    position = np.stack([ts, 2 * ts], -1) * 0.01
    sol = _fake_solution(ts, axis, body, omega, position)
    t = np.array([0.0, 0.033, 0.07, 0.26, 0.5])
    g = frame_geometry(sol, top, t)
    np.testing.assert_allclose(g.body[:, 0], np.cos(n_spin * t), atol=1e-12)
    np.testing.assert_allclose(g.body[:, 1], np.sin(n_spin * t), atol=1e-12)
    np.testing.assert_allclose(g.centre_of_mass[:, :2], np.stack([t, 2 * t], -1) * 0.01)


def test_frame_times():
    np.testing.assert_allclose(frame_times(0.0, 1.0, fps=10), np.linspace(0, 1, 11))
    # Slow motion: 0.5 s of simulation per second shown, one frame per 0.05 s.
    np.testing.assert_allclose(frame_times(1.0, 2.0, fps=10, speed=0.5), 1.0 + 0.05 * np.arange(21))
    np.testing.assert_allclose(frame_times(0.0, 3.0, fps=10, duration=2.0), np.linspace(0, 3, 21))
    np.testing.assert_allclose(frame_times(0.0, 3.0, fps=10, frames=4), [0, 1, 2, 3])
    assert frame_times(0.0, 1.0, fps=10, speed=0.3)[-1] <= 1.0
    with pytest.raises(ValueError, match="at most one"):
        frame_times(0.0, 1.0, fps=10, speed=1.0, frames=3)
    with pytest.raises(ValueError, match="speed must be positive"):
        frame_times(0.0, 1.0, fps=10, speed=-1.0)


def _frames(path):
    with Image.open(path) as image:
        return image.n_frames, image.size


def test_gif_has_the_frames_asked(top, sol, tmp_path):
    path = tj.animate(sol, top, str(tmp_path / "top.gif"), frames=4, dpi=40, fps=10)
    assert path == str(tmp_path / "top.gif")
    assert _frames(path) == (4, (200, 200))
    # Slow motion at fps 20 over 0.1 s of simulation at speed 0.25: 0.1 / (0.25 / 20) + 1 frames.
    path = tj.animate(
        sol,
        top,
        str(tmp_path / "slow.gif"),
        fps=20,
        speed=0.25,
        t_start=0.1,
        t_end=0.2,
        dpi=30,
        follow=True,
    )
    assert _frames(path)[0] == 9


def _with_nan_tail(sol, first_nan):
    n = sol.ts.shape[0]

    def cut(x):
        x = jnp.asarray(x)
        if x.ndim >= 1 and x.shape[0] == n and jnp.issubdtype(x.dtype, jnp.floating):
            return x.at[first_nan:].set(jnp.nan)
        return x

    sol = eqx.tree_at(lambda s: s.result, sol, tj.RESULTS.contact_lost)
    ts = sol.ts
    return eqx.tree_at(lambda s: s.ts, jax.tree_util.tree_map(cut, sol), ts)


def test_nan_tail_renders_to_last_valid_time(top, sol, tmp_path):
    cut = _with_nan_tail(sol, 30)
    assert _valid_count(cut) == 30
    last = float(sol.ts[29])
    assert _end_reason(cut, 30) == f"run ends at t = {last:.3g} s: contact lost (R_n = 0)"
    assert _end_reason(sol, N_SAVE) is None
    path = tj.animate(cut, top, str(tmp_path / "cut.gif"), frames=3, dpi=30)
    assert _frames(path)[0] == 3
    with pytest.raises(ValueError, match="finite range"):
        tj.animate(cut, top, str(tmp_path / "x.gif"), t_end=float(sol.ts[40]), dpi=30)


def test_errors(top, sol, tmp_path, monkeypatch):
    batch = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), sol, sol)
    with pytest.raises(ValueError, match="index="):
        tj.animate(batch, top, str(tmp_path / "b.gif"), frames=2)
    path = tj.animate(batch, top, str(tmp_path / "b.gif"), frames=2, index=1, dpi=30)
    assert _frames(path)[0] == 2
    with pytest.raises(ValueError, match="index= is for batched"):
        tj.animate(sol, top, str(tmp_path / "c.gif"), frames=2, index=0)
    with pytest.raises(ValueError, match=r"\.gif or \.mp4"):
        tj.animate(sol, top, str(tmp_path / "top.png"), frames=2)
    from matplotlib import animation

    monkeypatch.setattr(animation.FFMpegWriter, "isAvailable", classmethod(lambda cls: False))
    with pytest.raises(RuntimeError, match="ffmpeg"):
        tj.animate(sol, top, str(tmp_path / "top.mp4"), frames=2)
    assert not (tmp_path / "top.mp4").exists()


def test_cli_end_to_end(sol, tmp_path, capsys):
    # The default launch (the demo's), simulated to T1 with the fixture's save grid.
    out = tmp_path / "cli.gif"
    args = ["animate", "--t1", str(T1), "--frames", "3", "--dpi", "30", "--out", str(out)]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "spin = 99 rad/s" in text and f"wrote {out}" in text
    assert _frames(out)[0] == 3
    assert main(["animate", "--t1", str(T1), "--out", str(tmp_path / "a.png")]) == 2
    assert ".gif or .mp4" in capsys.readouterr().err
