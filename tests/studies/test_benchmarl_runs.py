"""studies.benchmarl_runs: a wall-clock-bounded BenchMARL run, evaluated with the project's metrics, exported."""

from __future__ import annotations

import csv
import json

import pytest

pytest.importorskip("benchmarl")

from studies import benchmarl_runs  # noqa: E402


def test_a_short_run_stops_on_the_clock_and_writes_its_evaluation(tmp_path, capsys):
    out = tmp_path / "run"
    assert benchmarl_runs.main(["--minutes", "0.2", "--episodes", "1", "--mode", "residual", "--out", str(out)]) == 0
    record = json.loads((out / "evaluation.json").read_text())
    assert record["algorithm"] == "mappo" and record["mode"] == "residual" and record["iterations"] >= 1
    assert record["agent_steps"] == record["frames"] * 4 > 0
    assert record["train_seconds"] < 60  # stopped by the clock, not by its 10^10-frame budget
    evaluation = record["evaluation"]
    assert {"success_rate", "physics_faults", "per_episode"} <= set(evaluation)
    assert len(evaluation["per_episode"]) == 1 and "trajectory" not in evaluation["per_episode"][0]
    rows = list(csv.DictReader((out / "curve.csv").open()))
    assert rows and int(rows[0]["agent_steps"]) == 4 * int(rows[0]["frames"])
    assert (out / "policy" / "actor.pt").is_file() and (out / "policy" / "actor.json").is_file()
    printed = capsys.readouterr().out
    assert "| mappo (residual) |" in printed and "training stopped: wall-clock budget of 12 s reached" in printed


@pytest.mark.parametrize("argv, message", [
    (["--scenario", "nowhere"], "--scenario: unknown"),
    (["--minutes", "0"], "--minutes: expected a duration > 0"),
    (["--episodes", "0"], "--episodes: expected an integer >= 1"),
])
def test_bad_arguments_are_refused_before_anything_runs(tmp_path, argv, message, capsys):
    with pytest.raises(SystemExit):
        benchmarl_runs.main([*argv, "--out", str(tmp_path / "run")])
    assert message in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_the_scoreboard_runs_a_benchmarl_method_with_its_test_split(tmp_path, capsys):
    from studies import scoreboard

    argv = ["--quick", "--out", str(tmp_path), "--scenarios", "planar_square", "--methods", "mappo-residual",
            "--seeds", "0", "--episodes", "1"]
    assert scoreboard.main(argv) == 0
    rows = json.loads((tmp_path / "scoreboard.json").read_text())["rows"]
    assert [row["split"] for row in rows] == ["train", "test", "test", "test", "test"]
    assert all(row["method"] == "mappo-residual" and row["seeds"] == [0] and row["metrics"] for row in rows)
    assert (tmp_path / "runs" / "planar_square" / "mappo-residual" / "seed-0" / "policy" / "actor.pt").is_file()
    capsys.readouterr()
    assert scoreboard.main(argv) == 0  # resumed: every cell from its file
    assert "running" not in capsys.readouterr().out
