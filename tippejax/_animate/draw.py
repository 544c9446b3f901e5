"""The animation drawn with matplotlib and written to GIF or MP4."""

from __future__ import annotations

import math
import os
import shutil

import numpy as np

from .._solution import Solution
from .._top import TippeTop
from .frames import (
    STEM_LENGTH,
    STEM_RIM,
    _centre_xy,
    _end_reason,
    _numpy_member,
    _valid_count,
    frame_geometry,
    frame_times,
)


def _wireframe(n_lat: int = 5, n_lon: int = 12, samples: int = 49):
    """Polylines of a unit sphere in body coordinates (e1 = body, e2 = a x body, e3 = a).

    Returns `(lines, meridian, rim)`: the latitude circles and meridians (the meridian through
    `body`, which shows the spin, is `meridian`) and the rim of the flat face around the stem.
    """
    s = np.linspace(0.0, 2 * np.pi, samples)
    lines = []
    for polar in np.linspace(0, np.pi, n_lat + 2)[1:-1]:
        lines.append(
            np.stack(
                [
                    np.sin(polar) * np.cos(s),
                    np.sin(polar) * np.sin(s),
                    np.full_like(s, np.cos(polar)),
                ],
                -1,
            )
        )
    half = np.linspace(0.0, np.pi, samples // 2 + 1)
    for lon in np.linspace(0, 2 * np.pi, n_lon, endpoint=False)[1:]:
        lines.append(
            np.stack([np.sin(half) * np.cos(lon), np.sin(half) * np.sin(lon), np.cos(half)], -1)
        )
    meridian = np.stack([np.sin(half), np.zeros_like(half), np.cos(half)], -1)
    rim = np.stack(
        [
            np.sin(STEM_RIM) * np.cos(s),
            np.sin(STEM_RIM) * np.sin(s),
            np.full_like(s, np.cos(STEM_RIM)),
        ],
        -1,
    )
    return lines, meridian, rim


def _to_space(points, centre, axis, body, R):
    """Body-frame unit-sphere points to space, for one frame."""
    e2 = np.cross(axis, body)
    return centre + R * (points[:, :1] * body + points[:, 1:2] * e2 + points[:, 2:] * axis)


def _split(points, centre, view):
    """`(front, back)` copies of a polyline with the hidden / visible part set to nan."""
    facing = (points - centre) @ view >= 0
    # Keep one shared point at each boundary so the two halves join.
    grown = facing | np.roll(facing, 1) | np.roll(facing, -1)
    front, back = points.copy(), points.copy()
    front[~grown] = np.nan
    back[facing & np.roll(facing, 1) & np.roll(facing, -1)] = np.nan
    return front, back


def _writer(path: str, fps: float):
    from matplotlib import animation

    ext = os.path.splitext(path)[1].lower()
    if ext == ".gif":
        return animation.PillowWriter(fps=fps)
    if ext == ".mp4":
        if not animation.FFMpegWriter.isAvailable():
            raise RuntimeError(
                f"writing {path!r} needs ffmpeg, which was not found on PATH (matplotlib "
                f"rcParams['animation.ffmpeg_path'] = {shutil.which('ffmpeg')!r}). Write a .gif "
                f"instead, or install ffmpeg (e.g. apt-get install ffmpeg, conda install ffmpeg)."
            )
        return animation.FFMpegWriter(fps=fps, codec="h264", extra_args=["-pix_fmt", "yuv420p"])
    raise ValueError(f"unknown animation format {ext or '(none)'!r} in {path!r}: use .gif or .mp4.")


def animate(
    sol: Solution,
    top: TippeTop,
    path: str,
    *,
    fps: float = 20.0,
    speed: float | None = None,
    duration: float | None = None,
    frames: int | None = None,
    t_start: float | None = None,
    t_end: float | None = None,
    index: int | tuple[int, ...] | None = None,
    dpi: float = 80.0,
    figsize: tuple[float, float] = (5.0, 5.0),
    elev: float = 22.0,
    azim: float = -60.0,
    follow: bool = False,
    trace: bool = True,
    title: str | None = None,
    progress: bool = False,
) -> str:
    r"""Render a simulated top as a 3-D animation and write it to `path` (`.gif` or `.mp4`).

    Draws the sphere of radius $R$ (a wireframe fixed in the body, so the spin $\dot\psi$ turns
    it; the red meridian through the body vector marks the spin) centred at
    $\mathcal C = (x + \epsilon a_x, y + \epsilon a_y, R)$, the stem along $+a$ (the side away
    from the centre of mass: up at $\theta = 0$, down at $\theta = \pi$; without a `tj.Stem` the
    model is an eccentric sphere, so it is only a marker, clipped at the table; with one it is
    the modelled rod and the outline of its tip's sphere, and the top rises onto it), the rim of the flat
    face around it, the centre of mass $O = \mathcal C - \epsilon a$ (black dot), the contact point
    $Q = \mathcal C - R e_Z$ and its trace on the table, and a title with $t$, $\theta$ and the
    model. The solution's save times are resampled to the frame times (`frame_geometry`).

    **Aliasing.** A frame is shown every `speed / fps` s of simulation, in which the spin $n$
    turns the body by $n \cdot$ `speed / fps` rad. Above about $\pi/2$ per frame the eye sees a
    stroboscopic (wrong, even backwards) spin: a top at $n = 100$ rad/s in real time at 20 fps
    turns 5 rad per frame. Use slow motion (`speed` < 1, e.g. `speed=0.2` for 1 rad per frame)
    to see the spin; the rise of $\theta$ (seconds) reads well in real time. The save times
    must resolve the precession and nutation (the orientation between save times is the
    nearest saved one turned by its $\omega$).

    A solution with a nan tail (contact loss, a stopped run) is drawn up to its last finite save
    time, and the title says why it ends.

    **Arguments:**

    - `sol`: a `Solution` of `simulate` (any level; the SO(3), Routhian and gyroscopic levels
      have no translation, so their centre of mass stays at the origin).
    - `top`: the `TippeTop` that was simulated (for $R$ and $\epsilon$).
    - `path`: output file, `.gif` (Pillow) or `.mp4` (needs ffmpeg).
    - `fps`: frames per second of the animation.
    - `speed`: seconds of simulation per second of animation (default 1: real time).
      Or `duration`: seconds of animation for the whole span; or `frames`: number of frames,
      evenly over the span (at most one of the three).
    - `t_start`, `t_end`: the animated span (default: the first save time to the last finite one).
    - `index`: the member of a batched solution to draw (int or tuple); required for a batch.
    - `dpi`, `figsize`: size of the frames (pixels = dpi x figsize).
    - `elev`, `azim`: viewing angles (degrees, as `Axes3D.view_init`).
    - `follow`: keep the sphere in the middle of the view (default: a fixed view of the table
      covering the whole trace).
    - `trace`: draw the trace of the contact point.
    - `title`: a first title line (default "tippejax: {model} model").
    - `progress`: print a line per 10 % of frames.

    **Returns:** `path`.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    writer = _writer(path, fps)
    sol = _numpy_member(sol, index)
    n_valid = _valid_count(sol)
    if n_valid == 0:
        raise ValueError("the solution has no finite state to draw (its first save is nan).")
    reason = _end_reason(sol, n_valid)
    t_first_valid, t_last_valid = float(sol.ts[0]), float(sol.ts[n_valid - 1])
    t0 = t_first_valid if t_start is None else float(t_start)
    t1 = t_last_valid if t_end is None else float(t_end)
    if not t_first_valid <= t0 <= t1 <= t_last_valid:
        raise ValueError(
            f"t_start = {t0:g}, t_end = {t1:g} must satisfy {t_first_valid:g} <= t_start <= "
            f"t_end <= {t_last_valid:g} (the solution's finite range)."
        )
    times = frame_times(t0, t1, fps=fps, speed=speed, duration=duration, frames=frames)
    geom = frame_geometry(sol, top, times)
    shown_speed = (times[-1] - times[0]) / (len(times) - 1) * fps if len(times) > 1 else 1.0
    R = float(top.R)

    # Contact-point trace at the (dense) save times, cut at each frame time.
    valid_ts = sol.ts[:n_valid]
    trace_xy = _centre_xy(sol)[:n_valid] + float(top.eps) * sol.states.axis[:n_valid, :2]
    if follow:
        half = 3.0 * R
    else:
        inside = (valid_ts >= t0) & (valid_ts <= t1)
        xy = np.concatenate([trace_xy[inside], geom.centre[:, :2]])
        lo, hi = xy.min(0) - 1.7 * R, xy.max(0) + 1.7 * R
        middle, half = (lo + hi) / 2, max(float(np.max(hi - lo)) / 2, 2.2 * R)
    height = (2 + STEM_LENGTH) * R + 0.1 * R

    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="3d", computed_zorder=False)
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.9)
    ax.view_init(elev=elev, azim=azim)
    ax.set_box_aspect((1, 1, height / (2 * half)), zoom=1.25)
    ax.set_zlim(0, height)
    ax.set_axis_off()
    view = np.array(
        [
            math.cos(math.radians(elev)) * math.cos(math.radians(azim)),
            math.cos(math.radians(elev)) * math.sin(math.radians(azim)),
            math.sin(math.radians(elev)),
        ]
    )

    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    def table_square(mid):
        x0, y0 = mid - half
        x1, y1 = mid + half
        return [[(x0, y0, 0), (x1, y0, 0), (x1, y1, 0), (x0, y1, 0)]]

    table = Poly3DCollection(
        table_square(geom.centre[0, :2] if follow else middle),
        facecolor="0.9",
        edgecolor="0.6",
        zorder=0,
    )
    ax.add_collection3d(table)
    (trace_line,) = ax.plot([], [], [], color="tab:blue", lw=0.6, alpha=0.8, zorder=1)
    lines, meridian, rim = _wireframe()
    back_lines = [ax.plot([], [], [], color="0.55", lw=0.5, alpha=0.35, zorder=2)[0] for _ in lines]
    (back_meridian,) = ax.plot([], [], [], color="tab:red", lw=0.8, alpha=0.35, zorder=2)
    (back_rim,) = ax.plot([], [], [], color="tab:green", lw=0.9, alpha=0.35, zorder=2)
    (stem_back,) = ax.plot(
        [], [], [], color="tab:green", lw=4, alpha=0.45, zorder=2.5, solid_capstyle="round"
    )
    disk = Poly3DCollection(
        [np.zeros((3, 3))],
        facecolor=(0.93, 0.88, 0.78, 0.75),
        edgecolor="0.3",
        linewidth=0.6,
        zorder=3,
    )
    ax.add_collection3d(disk)
    front_lines = [ax.plot([], [], [], color="0.25", lw=0.7, zorder=4)[0] for _ in lines]
    (front_meridian,) = ax.plot([], [], [], color="tab:red", lw=1.8, zorder=4.5)
    (front_rim,) = ax.plot([], [], [], color="tab:green", lw=1.4, zorder=4.5)
    (stem_front,) = ax.plot([], [], [], color="tab:green", lw=4, zorder=5, solid_capstyle="round")
    # the stem's tip, a sphere of radius r2 (its outline), for a top with a modelled stem
    (stem_tip,) = ax.plot([], [], [], color="tab:green", lw=1.6, zorder=5, gid="stem_tip")
    (cm_dot,) = ax.plot([], [], [], "o", color="k", ms=3, zorder=6)
    (contact_dot,) = ax.plot([], [], [], "o", color="tab:blue", ms=3.5, zorder=6)
    heading = title if title is not None else f"tippejax: {sol.model} model"
    text = fig.suptitle("", fontsize=9, y=0.985)

    # Silhouette circle in the plane perpendicular to the view direction.
    u = np.cross(view, [0.0, 0.0, 1.0])
    u /= np.linalg.norm(u)
    w = np.cross(view, u)
    s = np.linspace(0, 2 * np.pi, 61)
    circle = np.cos(s)[:, None] * u + np.sin(s)[:, None] * w

    def draw(i):
        centre, a, b = geom.centre[i], geom.axis[i], geom.body[i]
        if follow:
            mid = centre[:2]
            table.set_verts(table_square(mid))
        else:
            mid = middle
        ax.set_xlim(mid[0] - half, mid[0] + half)
        ax.set_ylim(mid[1] - half, mid[1] + half)
        if trace:
            shown = (valid_ts >= times[0]) & (valid_ts <= geom.t[i])
            pts = np.concatenate([trace_xy[shown], geom.contact[i : i + 1, :2]])
            if follow:  # only the part over the table in view
                pts = np.where(np.all(np.abs(pts - mid) <= half, -1)[:, None], pts, np.nan)
            trace_line.set_data_3d(pts[:, 0], pts[:, 1], np.zeros(len(pts)))
        for poly, front, back in zip(lines, front_lines, back_lines):
            f, bk = _split(_to_space(poly, centre, a, b, R), centre, view)
            front.set_data_3d(*f.T)
            back.set_data_3d(*bk.T)
        for poly, front, back in (
            (meridian, front_meridian, back_meridian),
            (rim, front_rim, back_rim),
        ):
            f, bk = _split(_to_space(poly, centre, a, b, R), centre, view)
            front.set_data_3d(*f.T)
            back.set_data_3d(*bk.T)
        disk.set_verts([centre + R * circle])
        stem = geom.stem[i].T
        facing = a @ view >= -0.35  # the stem's base seen beside or in front of the sphere
        stem_front.set_data_3d(*(stem if facing else np.full((3, 2), np.nan)))
        stem_back.set_data_3d(*(np.full((3, 2), np.nan) if facing else stem))
        if top.stem is not None:
            stem_tip.set_data_3d(*(geom.stem_tip[i] + float(top.stem.radius) * circle).T)
        cm_dot.set_data_3d(*geom.centre_of_mass[i : i + 1].T)
        contact_dot.set_data_3d(*geom.contact[i : i + 1].T)
        theta = geom.theta[i]
        lines_text = [
            heading,
            f"t = {geom.t[i]:6.2f} s   theta = {theta:5.3f} rad ({math.degrees(theta):5.1f} deg)"
            + ("" if abs(shown_speed - 1) < 1e-3 else f"   (x{shown_speed:.2g} speed)"),
        ]
        if reason is not None:
            lines_text.append(reason)
        text.set_text("\n".join(lines_text))

    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with writer.saving(fig, path, dpi):
        for i in range(len(times)):
            draw(i)
            writer.grab_frame()
            if progress and (i + 1) % max(1, len(times) // 10) == 0:
                print(f"animate: frame {i + 1}/{len(times)}")
    return path
