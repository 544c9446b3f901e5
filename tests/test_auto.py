"""model="auto": the level chooser and its table, checked against benchmarks/LEVELS.md."""

import pathlib

import jax.numpy as jnp
import numpy as np
import pytest

import tippejax as tj
from tippejax._auto import COST_MARGIN, MEASURED, choose_model

LEVELS_MD = pathlib.Path(__file__).parents[1] / "benchmarks" / "LEVELS.md"


def _table_rows():
    rows = {}
    for line in LEVELS_MD.read_text().splitlines():
        if line.startswith("| ") and not line.startswith("| scene") and "---" not in line:
            cells = [c.strip() for c in line.strip("|").split("|")]
            rows[cells[0]] = dict(
                so3=(float(cells[2]), float(cells[4])), routhian=(float(cells[5]), float(cells[7]))
            )
    return rows


def test_table_matches_levels_md():
    rows = _table_rows()
    assert len(rows) == 6
    stiff = [r for name, r in rows.items() if name.startswith("stiff")]
    moving = [r for name, r in rows.items() if "CM velocity" in name]
    plain = [r for name, r in rows.items() if not name.startswith("stiff") and "CM velocity" not in name]
    for level in ("so3", "routhian"):
        err, cost = MEASURED["stiff"][level]
        assert err == pytest.approx(stiff[0][level][0], rel=1e-2)
        assert cost == pytest.approx(stiff[0][level][1], abs=0.01)
        err, cost = MEASURED["non-stiff"][level]
        assert err == pytest.approx(max(r[level][0] for r in plain), rel=1e-2)
        assert cost == pytest.approx(np.median([r[level][1] for r in plain]), abs=0.01)
        err, cost = MEASURED["moving"][level]
        assert err == pytest.approx(max(r[level][0] for r in plain + moving), rel=1e-2)
        assert cost == pytest.approx(np.median([r[level][1] for r in plain + moving]), abs=0.01)


def test_choose_model():
    top = tj.default_top()
    y0 = tj.initial_state(top, 0.1, 100.0)
    assert choose_model(top, y0, tolerance=None) == "full"
    assert choose_model(top, y0, tolerance=1e-3) == "full"
    stiff = tj.TippeTop.from_ratios(0.9, 0.3, mu=300.0)
    # Only a tolerance above the measured error of the cheaper level lets it be used.
    err, cost = MEASURED["stiff"]["routhian"]
    assert cost < 1.0
    assert choose_model(stiff, y0, tolerance=0.5 * err) == "full"
    assert choose_model(stiff, y0, tolerance=2 * err) == "routhian"
    # A level whose measured cost is within the timing noise of the full model is not "cheaper".
    for level, (err, cost) in MEASURED["non-stiff"].items():
        if cost >= COST_MARGIN:
            assert choose_model(top, y0, tolerance=10 * err) != level
    with pytest.raises(ValueError, match="tolerance"):
        choose_model(top, y0, tolerance=-1.0)


def test_auto_reports_level_used():
    top = tj.default_top()
    y0 = tj.initial_state(top, 0.1, 100.0)
    sol = tj.simulate(top, y0, 0.2, model="auto", tolerance=1e-3, saveat=jnp.linspace(0, 0.2, 11))
    assert sol.model == "full"


def test_auto_with_loose_tolerance_uses_cheaper_level_and_says_so():
    top = tj.TippeTop.from_ratios(0.9, 0.3, mu=300.0)  # stiff: the Routhian level is cheaper
    y0 = tj.initial_state(top, 0.8, 60.0)
    expected = choose_model(top, y0, tolerance=1.0)
    assert expected == "routhian"
    sol = tj.simulate(top, y0, 0.2, model="auto", tolerance=1.0, saveat=jnp.linspace(0, 0.2, 11))
    assert sol.model.startswith(expected)
