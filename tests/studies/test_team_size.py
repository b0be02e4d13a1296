"""studies.team_size: its statistics, its refusals, and a quick run's outputs end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from studies import team_size  # noqa: E402
from studies.bootstrap import wilson_interval  # noqa: E402


def test_wilson_interval_brackets_the_rate():
    assert wilson_interval(20, 20)[1] == 1.0
    low, high = wilson_interval(18, 20)
    assert low == pytest.approx(0.699, abs=1e-3) and high == pytest.approx(0.972, abs=1e-3)
    assert all(np.isnan(wilson_interval(0, 0)))


def test_the_best_law_is_the_most_successful_then_the_fastest():
    rows = {"gradient": {"success": 0.9, "settle": 3.0}, "approx_jacobian": {"success": 0.95, "settle": 5.0},
            "adaptive_jacobian": {"success": 0.95, "settle": 4.0}}
    assert team_size.best_law(rows) == "adaptive_jacobian"


def test_a_team_size_outside_the_family_is_refused_before_training(tmp_path, capsys):
    with pytest.raises(SystemExit):
        team_size.main(["--quick", "--sizes", "9", "--out", str(tmp_path / "out")])
    assert "n_agents: planar_team is defined for 3 to 8 arms" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_the_quick_run_trains_evaluates_and_writes_its_table_and_figure(tmp_path):
    out = tmp_path / "study"
    results = team_size.main(["--quick", "--out", str(out)])
    assert sorted(results["sizes"]) == ["3", "8"]
    for rows in results["sizes"].values():
        assert set(rows) == {"gradient", "approx_jacobian", "adaptive_jacobian", team_size.LEARNED}
        assert rows[team_size.LEARNED]["episodes"] == 1
    assert set(results["planar_square"]) == {"planar_square_rotated", "planar_square_3.5m", "planar_square_4.0m",
                                             "planar_square_rect_2.5x3.5m"}
    assert json.loads((out / "team_size.json").read_text())["runs"] == ["seed_0"]
    text = (out / "team_size.md").read_text()
    assert "| N = 8 |" in text and "planar_random test set" in text and "Targets" in text
    assert (out / "team_size_success.png").stat().st_size > 0
