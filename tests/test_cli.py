"""The command line: every subcommand runs and writes its files."""

import matplotlib

matplotlib.use("Agg")

import pytest  # noqa: E402

import tippejax as tj  # noqa: E402
from tippejax._cli import _demo_simulation, default_spin, main  # noqa: E402


def test_classify_default(tmp_path, capsys):
    assert main(["classify", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "Group IIb" in out
    assert "theta_c" in out and "n1" in out
    assert (tmp_path / "group_map.png").stat().st_size > 10_000


def test_classify_ratios(tmp_path, capsys):
    assert main(["classify", "--A-over-C", "1.6", "--eps-over-R", "0.2", "--out", str(tmp_path)]) == 0
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
    path = _demo_simulation(tj.default_top(), 0.1, 99.0, str(tmp_path))
    assert (tmp_path / "demo.png").is_file() and path.endswith("demo.png")
    out = capsys.readouterr().out
    line = next(s for s in out.splitlines() if "inversion time" in s)
    # ERRATA.md: the standard top launched at theta0 = 0.1 with n0 = 100 inverts at t = 5.70 s.
    assert 5.5 < float(line.split(":")[1].split()[0]) < 5.9
    assert "result:            success" in out
