"""The plots: stable pieces solid and unstable pieces dashed, as the package's stability says."""

import math

import matplotlib

matplotlib.use("Agg")

import internal as ti  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import tippejax as tj  # noqa: E402
from tippejax._cli import REPRESENTATIVES  # noqa: E402
from tippejax._plot import (  # noqa: E402
    bifurcation_diagram,
    bifurcation_diagrams,
    group_map,
    jellet_scale,
)

# Which kinds of branch piece each group has (paper, Sec. 5).
EXPECTED_BRANCH = {
    "Ia": {"branch-unstable"},
    "Ib": {"branch-unstable", "branch-stable"},
    "IIa": {"branch-unstable", "branch-stable"},
    "IIb": {"branch-stable"},
    "IIc": {"branch-unstable"},
    "III": {"branch-stable"},
}


def _tops():
    return {name: tj.TippeTop.from_ratios(a, e) for name, (a, e) in REPRESENTATIVES.items()}


_PAD = 4096


@jax.jit
def _on_branch(top, theta):
    return ti.stability_function(top, jnp.cos(theta)), ti.branch_jellet(top, theta) ** 2


def _stability_and_j2(top, theta):
    """g(cos theta) and J^2 on the branch, jitted on one padded shape (fast in a loop)."""
    padded = np.zeros(_PAD)
    padded[: len(theta)] = theta
    g, j2 = _on_branch(top, padded)
    return np.asarray(g)[: len(theta)], np.asarray(j2)[: len(theta)]


_d2w_at_pole = jax.jit(ti.effective_potential_d2_closed_form)


def _lines(ax, prefix):
    return [line for line in ax.get_lines() if (line.get_gid() or "").startswith(prefix)]


@pytest.mark.parametrize("name", tj.GROUPS)
def test_representatives_are_in_their_group(name):
    a, e = REPRESENTATIVES[name]
    assert tj.classify(tj.TippeTop.from_ratios(a, e)) == name


@pytest.mark.parametrize("name", tj.GROUPS)
def test_branch_style_matches_stability_function(name):
    top = tj.TippeTop.from_ratios(*REPRESENTATIVES[name])
    ax = bifurcation_diagram(top)
    scale = jellet_scale(top)
    lines = _lines(ax, "branch-")
    assert {line.get_gid() for line in lines} == EXPECTED_BRANCH[name]
    for line in lines:
        theta = np.asarray(line.get_xdata())
        y = np.asarray(line.get_ydata())
        stable = line.get_gid() == "branch-stable"
        assert line.get_linestyle() == ("-" if stable else "--")
        # Interior points (the end points may be the shared fold, where g = 0).
        inner = slice(1, -1)
        g, j2 = _stability_and_j2(top, theta[inner])
        assert np.all((g > 0) == stable)
        # The curve is the package's branch J^2 (up to the clipping far above the axes).
        j2 = j2 / scale
        visible = j2 < ax.get_ylim()[1]
        np.testing.assert_allclose(y[inner][visible], j2[visible], rtol=1e-12)
    # The fold is at theta_b where the stability changes.
    if EXPECTED_BRANCH[name] == {"branch-unstable", "branch-stable"}:
        theta_b = float(tj.thresholds(top).theta_b)
        (stable_line,) = [line for line in lines if line.get_gid() == "branch-stable"]
        assert np.asarray(stable_line.get_xdata())[0] == pytest.approx(theta_b, abs=2e-3)
    plt.close(ax.figure)


@pytest.mark.parametrize("name", tj.GROUPS)
def test_vertical_style_matches_potential(name):
    top = tj.TippeTop.from_ratios(*REPRESENTATIVES[name])
    ax = bifurcation_diagram(top, scaled=False)
    lines = _lines(ax, "vertical-")
    assert {line.get_gid().split("-")[1] for line in lines} == {"0", "pi"}
    for line in lines:
        x = np.asarray(line.get_xdata())
        y0, y1 = np.asarray(line.get_ydata())
        stable = line.get_gid().endswith("-stable")
        assert line.get_linestyle() == ("-" if stable else "--")
        assert x[0] == x[1] == (0.0 if "-0-" in line.get_gid() else math.pi)
        # Stability of the vertical state (W'' > 0 at the pole) inside the segment.
        jellet = np.sqrt(np.linspace(y0, y1, 7)[1:-1])
        d2w = np.asarray(_d2w_at_pole(top, x[0], jellet))
        assert np.all((d2w > 0) == stable)
    plt.close(ax.figure)


def test_bifurcation_diagrams_six_panels():
    fig = bifurcation_diagrams(_tops())
    axes = fig.get_axes()
    assert len(axes) == 6
    for name, ax in zip(tj.GROUPS, axes):
        assert ax.get_title().startswith(f"Group {name} ")
    plt.close(fig)
    wrong = dict(_tops(), Ia=_tops()["IIb"])
    with pytest.raises(ValueError, match="Group Ia"):
        bifurcation_diagrams(wrong)


def test_group_map_colours_match_group_index():
    ax = group_map(n=60, inset=False)
    index = np.asarray(ax.images[0].get_array())
    assert index.shape == (60, 60)
    a = np.linspace(0.5, 2.0, 60)
    e = np.linspace(0.0, 1.0, 62)[1:-1]
    for i, j in [(5, 5), (30, 10), (50, 55), (10, 40)]:
        top = tj.TippeTop.from_ratios(a[j], e[i])
        assert index[i, j] == int(ti.group_index(top))
    assert len(set(index.ravel().tolist())) >= 5  # IIc may be too thin for a 60-point grid
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert [f"Group {g}" for g in tj.GROUPS] == labels[:6]
    plt.close(ax.figure)
