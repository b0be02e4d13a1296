"""studies.manoeuvres (the study; the env's manoeuvres are tests/test_manoeuvre.py): a quick run's table,
records and figure, and the worst-case summary."""

from __future__ import annotations

import json

import pytest

from studies import manoeuvres

pytest.importorskip("matplotlib")


def test_a_quick_run_writes_its_table_and_figure(tmp_path, capsys):
    """With a scoreboard's trained run (a tiny one) the learned method gets its row beside the laws'."""
    from studies import scoreboard

    board = tmp_path / "board"
    assert scoreboard.main(["--quick", "--out", str(board), "--scenarios", "planar_square_transport", "--methods",
                            "residual-ppo", "--seeds", "0", "--episodes", "1", "--no-test-sets"]) == 0
    assert [(task, method, seed) for task, method, seed, _ in manoeuvres.learned_runs(board)] == [
        ("planar_square_transport", "residual-ppo", 0)]
    results = manoeuvres.main(["--quick", "--out", str(tmp_path), "--learned", str(board)])
    assert {(row["task"], row["law"], row["feedforward"]) for row in results["rows"]} == {
        (task, law, feedforward) for task in manoeuvres.TASKS for law in manoeuvres.LAWS
        for feedforward in manoeuvres.FEEDFORWARDS} | {("planar_square_transport", "residual-ppo", "hold")}
    (learned,) = [run for run in results["runs"] if run["law"] == "residual-ppo"]
    assert learned["training_seed"] == 0 and learned["max_centroid_error"] >= 0
    saved = json.loads((tmp_path / "manoeuvres.json").read_text())
    assert saved["quick"] and saved["seeds"] == list(manoeuvres.SEEDS[:1])
    assert (tmp_path / "manoeuvre_tracking.png").stat().st_size > 10_000
    for run in results["runs"]:
        assert not run["physics_fault"] and run["max_reach_fraction"] < 1.0
        assert run["max_motion_error"] >= 0 and run["max_centroid_error"] >= run["rms_centroid_error"]
        if run["task"] == "planar_square_transport":
            assert run["max_orientation_error"] >= 0 and run["peak_speed"] > 0
        else:
            assert run["peak_angular_speed"] > 0
    assert "| task | law | feedforward | success |" in capsys.readouterr().out


def test_the_summary_keeps_the_worst_seed():
    base = {"task": "t", "law": "law-I", "feedforward": "hold", "success": True, "physics_fault": "", "contact_steps": 0}
    records = [{**base, **{name: 0.001 for name in manoeuvres.SUMMED}, "seed": 0},
               {**base, **{name: 0.03 for name in manoeuvres.SUMMED}, "seed": 1, "contact_steps": 2}]
    (row,) = manoeuvres.summarize(records)
    assert row["max_centroid_error"] == 0.03 and row["contact_steps"] == 2 and row["runs"] == 2
    assert not row["centroid_target_met"] and not row["edge_target_met"]


def test_learned_needs_a_scoreboard_folder(tmp_path, capsys):
    with pytest.raises(SystemExit):
        manoeuvres.main(["--quick", "--out", str(tmp_path), "--learned", str(tmp_path / "nothing")])
    assert "--learned:" in capsys.readouterr().err


def test_the_study_resets_with_the_first_held_out_seeds():
    from ee_formation_env.scenario_sets import HELD_OUT_SEED_OFFSET

    assert manoeuvres.SEEDS == tuple(HELD_OUT_SEED_OFFSET + k for k in range(3)) == (10_000, 10_001, 10_002)
