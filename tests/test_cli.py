"""The command line: every subcommand runs and writes its files."""

import matplotlib

matplotlib.use("Agg")

import pytest  # noqa: E402

import tippejax as tj  # noqa: E402
from tippejax._cli import main  # noqa: E402
from tippejax._cli.common import default_spin  # noqa: E402
from tippejax._cli.demo import demo_simulation  # noqa: E402


def test_classify_default(tmp_path, capsys):
    assert main(["classify", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "Group IIb" in out
    assert "theta_c" in out and "n1" in out
    assert (tmp_path / "group_map.png").stat().st_size > 10_000


def test_classify_ratios(tmp_path, capsys):
    assert (
        main(["classify", "--A-over-C", "1.6", "--eps-over-R", "0.2", "--out", str(tmp_path)]) == 0
    )
    out = capsys.readouterr().out
    assert "Group III" in out
    # n2 is undefined in Group III and shown as "-".
    line = next(s for s in out.splitlines() if s.strip().startswith("n2"))
    assert line.split("=")[1].split()[0] == "-"
    assert (tmp_path / "group_map.png").exists()


def test_classify_needs_both_ratios(tmp_path):
    with pytest.raises(SystemExit):
        main(["classify", "--A-over-C", "1.6", "--out", str(tmp_path)])


def test_diagram(tmp_path, capsys):
    assert main(["diagram", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    for name in ("bifurcation_diagrams.png", "group_map.png"):
        assert (tmp_path / name).stat().st_size > 10_000
        assert str(tmp_path / name) in out
    for group in tj.GROUPS:
        assert f"Group {group}" in out


def test_demo(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    top = tj.default_top()
    spin = default_spin(top)
    assert spin == 99.0  # 1.5 x n2 (R+eps)/(R-eps) = 98.2 rounded up
    assert f"spin n0 = {spin:g} rad/s" in out
    assert "Group IIb" in out
    # Above the inversion threshold: theta = 0 unstable, theta = pi stable, no intermediate state.
    assert any("theta = 0" in s and s.rstrip().endswith("unstable") for s in out.splitlines())
    assert any("theta = pi" in s and s.rstrip().endswith(" stable") for s in out.splitlines())
    assert "intermediate none" in out


def test_demo_slow_spin_has_intermediate_state(tmp_path, capsys):
    # J between J1 and J2 (IIb): theta = 0 and pi both unstable, one stable intermediate state.
    assert main(["demo", "--spin", "40", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    intermediate = [s for s in out.splitlines() if "intermediate theta" in s]
    assert len(intermediate) == 1 and intermediate[0].rstrip().endswith(" stable")


def test_demo_simulation_inverts_and_writes_figure(tmp_path, capsys):
    path = demo_simulation(tj.default_top(), 0.1, 99.0, str(tmp_path))
    assert (tmp_path / "demo.png").is_file() and path.endswith("demo.png")
    out = capsys.readouterr().out
    line = next(s for s in out.splitlines() if "inversion time" in s)
    # ERRATA.md: the standard top launched at theta0 = 0.1 with n0 = 100 inverts at t = 5.70 s.
    assert 5.5 < float(line.split(":")[1].split()[0]) < 5.9
    assert "result:            success" in out


# ---------------------------------------------------------------------------------------------
# tippejax fit. Every fit here has the same data shape and free set (one compilation).

FIT_FREE = "mu,eps"


@pytest.fixture(scope="module")
def fit_csv(tmp_path_factory):
    """3 s of the standard top (theta0 0.1, spin 100) at 50 Hz with noise 0.01 rad, and a gap."""
    import numpy as np

    top = tj.default_top()
    ts = np.linspace(0.0, 3.0, 151)
    sol = tj.simulate(top, tj.initial_state(top, 0.1, 100.0), 3.0, saveat=ts)
    theta = np.asarray(sol.theta) + 0.01 * np.random.default_rng(0).standard_normal(ts.shape)
    path = tmp_path_factory.mktemp("fit") / "data.csv"
    lines = ["t,theta"] + [f"{t:.6g},{th:.10g}" for t, th in zip(ts, theta)]
    lines[20] = f"{ts[19]:.6g},"  # a missing sample (empty cell)
    lines[21] = f"{ts[20]:.6g},nan"  # and another
    path.write_text("\n".join(lines) + "\n")
    return path


def test_fit_recovers_mu_and_writes_outputs(fit_csv, tmp_path, capsys):
    import numpy as np

    out = tmp_path / "out"
    # Guesses 10% off: mu 0.33 (true 0.3), eps 0.00675 m (true 0.0075).
    args = [
        "fit",
        str(fit_csv),
        "--free",
        FIT_FREE,
        "--mu",
        "0.33",
        "--eps",
        "0.00675",
        "--out",
        str(out),
    ]
    assert main(args) == 0
    text = capsys.readouterr().out
    rows = {
        s.split()[0]: s.split() for s in text.splitlines() if s.split()[:1] in (["mu"], ["eps"])
    }
    assert set(rows) == {"mu", "eps"}
    mu = float(rows["mu"][1])
    assert abs(mu - 0.3) < 0.02 * 0.3
    assert abs(float(rows["eps"][1]) - 0.0075) < 0.02 * 0.0075
    assert "149 with theta" in text  # two samples missing
    assert "model:           full" in text and "describes until" in text
    assert "converged:       True" in text
    # The launch tilt was not given: it is freed (from the smoothed start of the record).
    assert "theta0" in text.split("fitting ")[1].splitlines()[0]
    assert "over the whole record" in text
    assert (out / "fit.png").stat().st_size > 10_000
    table = np.genfromtxt(out / "fit.csv", delimiter=",", names=True)
    assert table.dtype.names == ("t", "theta_obs", "theta_fit", "residual")
    assert table.shape == (151,)
    assert np.isnan(table["theta_obs"][19]) and np.isnan(table["residual"][20])
    ok = np.isfinite(table["residual"])
    assert ok.sum() == 149
    assert np.allclose(table["residual"][ok], (table["theta_fit"] - table["theta_obs"])[ok])
    assert np.sqrt(np.mean(table["residual"][ok] ** 2)) < 0.012  # the noise is 0.01 rad


def test_fit_unknown_free_name(fit_csv, tmp_path, capsys):
    assert main(["fit", str(fit_csv), "--free", "mu,friction", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "friction" in err
    for name in ("mu", "eps", "theta0", "spin", "phi_dot"):  # the allowed names are listed
        assert f"'{name}'" in err
    assert not (tmp_path / "fit.png").exists()


def test_fit_needs_theta_column(tmp_path, capsys):
    path = tmp_path / "bad.csv"
    path.write_text("t,tilt\n0,0.1\n0.1,0.2\n0.2,0.3\n")
    assert main(["fit", str(path), "--free", FIT_FREE, "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "'theta'" in err


def test_fit_bad_input_messages(tmp_path, capsys):
    assert main(["fit", str(tmp_path / "absent.csv"), "--out", str(tmp_path)]) == 2
    assert "not found" in capsys.readouterr().err
    path = tmp_path / "data.csv"
    path.write_text("t,theta\n0,0.1\n0.1,abc\n0.2,0.3\n")
    assert main(["fit", str(path), "--out", str(tmp_path)]) == 2
    assert "line 3" in capsys.readouterr().err
    path.write_text("t,theta\n0,0.1\n0.1,0.2\n0.2,0.3\n")
    args = ["fit", str(path), "--eps", "0.007", "--eps-over-R", "0.3", "--out", str(tmp_path)]
    assert main(args) == 2
    assert "--eps-over-R" in capsys.readouterr().err


def test_fit_guess_from_options():
    from tippejax._cli.common import top_from_options
    from tippejax._cli.parser import build_parser

    def guess(*options):
        return top_from_options(build_parser().parse_args(["fit", "x.csv", *options]))

    default, top = tj.default_top(), guess("--mu", "2.5", "--eps", "0.005")
    assert float(top.mu) == 2.5 and float(top.eps) == 0.005
    assert float(top.A) == float(default.A) and float(top.m) == float(default.m)
    top = guess("--A-over-C", "0.8", "--m", "0.03", "--mu", "0.4")
    assert abs(float(top.A_over_C) - 0.8) < 1e-12 and abs(float(top.eps_over_R) - 0.3) < 1e-12
    assert float(top.m) == 0.03 and float(top.mu) == 0.4


def test_fit_figure_draws_recording_zero_and_the_describes_line():
    """fit_figure on a stand-in result (no fit needed): two axes, dashed line, rms band."""
    from types import SimpleNamespace

    import matplotlib.pyplot as plt
    import numpy as np

    from tippejax._plot import fit_figure

    ts = np.linspace(0.0, 4.0, 81)
    fitted = np.stack([0.1 + 0.7 * ts, 0.2 + 0.1 * ts])  # two recordings
    obs = fitted + 0.01 * np.cos(7 * ts)
    obs[0, 5] = np.nan
    result = SimpleNamespace(
        ts=ts,
        theta_obs=obs,
        theta_fit=fitted,
        residuals=fitted - obs,
        free=("mu", "eps"),
        values=np.array([[0.3, 0.0075], [0.4, 0.007]]),
        std_errors=np.full((2, 2), 1e-3),
        rms=np.array([0.007, 0.007]),
        describes_until=np.array([2.5, 4.0]),
        model="full",
    )
    fig = fit_figure(result)
    top, bottom = fig.axes
    assert bottom.get_shared_x_axes().joined(top, bottom)
    # Recording 0 only: the dots are its 80 finite samples.
    dots = [line for line in top.lines if line.get_linestyle() == "None"]
    assert len(dots) == 1 and len(dots[0].get_xdata()) == 80
    dashed = [line for line in top.lines if line.get_linestyle() == "--"]
    assert [float(line.get_xdata()[0]) for line in dashed] == [2.5]
    assert "(rad)" in top.get_ylabel() and "(rad)" in bottom.get_ylabel()
    assert "(s)" in bottom.get_xlabel() and "recording 0 of 2" in fig._suptitle.get_text()
    plt.close(fig)
    # The whole record described: no dashed line.
    single = SimpleNamespace(
        **{
            **vars(result),
            "theta_obs": obs[1],
            "theta_fit": fitted[1],
            "residuals": (fitted - obs)[1],
            "values": result.values[1],
            "std_errors": result.std_errors[1],
            "rms": np.float64(0.007),
            "describes_until": np.float64(4.0),
        }
    )
    fig = fit_figure(single, title="one")
    assert not [line for line in fig.axes[0].lines if line.get_linestyle() == "--"]
    assert fig._suptitle.get_text() == "one"
    plt.close(fig)
