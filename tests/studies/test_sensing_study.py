"""studies.sensing (the study; the env's sensing is tests/test_sensing.py): the knobs it sets, the rotation it measures, and a quick run's outputs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from studies import sensing


def test_each_knob_sets_only_its_own_field():
    assert sensing.sensing_of("none", 0.0, 4) == {}
    assert sensing.sensing_of("noise", 0.01, 4) == {"noise": 0.01}
    assert sensing.sensing_of("delay", 5, 4) == {"delay": 5}
    assert sensing.sensing_of("yaw", 0.1, 4) == {"yaw": [0.1, -0.1, 0.1, -0.1]}  # alternating: not a common turn


@pytest.mark.parametrize("dim", [2, 3])
def test_rotation_angle_recovers_a_rigid_turn(dim):
    rng = np.random.default_rng(0)
    points = rng.normal(size=(5, dim))
    angle = 0.3
    c, s = np.cos(angle), np.sin(angle)
    turn = np.array([[c, -s], [s, c]]) if dim == 2 else np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    moved = points @ turn.T + 2.0  # turned about the centroid and translated
    assert sensing.rotation_angle(points, moved) == pytest.approx(angle)
    if dim == 2:
        assert sensing.rotation_angle(moved, points, signed=True) == pytest.approx(-angle)


def test_a_quick_run_writes_its_table_and_figure(tmp_path, capsys):
    results = sensing.main(["--quick", "--scenarios", "planar_square", "--out", str(tmp_path)])
    assert {(row["law"], row["knob"]) for row in results["rows"]} == {
        (law, knob) for law in sensing.LAWS for knob in ("none", *sensing.LEVELS)}
    assert json.loads((tmp_path / "sensing.json").read_text())["episode_seconds"] == sensing.QUICK_EPISODE_SECONDS
    assert (tmp_path / "sensing_effects.png").stat().st_size > 10_000
    exact = [r for r in results["runs"] if r["knob"] == "none"]
    assert all(r["final_edge_error"] < 0.01 and not r["physics_fault"] for r in exact)
    assert "| knob | level | law |" in capsys.readouterr().out


def test_an_unknown_scenario_is_refused_before_any_run(tmp_path, capsys):
    with pytest.raises(SystemExit):
        sensing.main(["--scenarios", "nowhere", "--out", str(tmp_path / "x")])
    assert "--scenarios: unknown" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_the_study_resets_with_the_first_held_out_seeds():
    from ee_formation_env.scenario_sets import HELD_OUT_SEED_OFFSET

    assert sensing.SEEDS == tuple(HELD_OUT_SEED_OFFSET + k for k in range(3)) == (10_000, 10_001, 10_002)
