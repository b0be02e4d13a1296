"""studies.learning_curves: held-out success and settling against agent steps, from a board's checkpoints."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("stable_baselines3")

from ee_formation_env.baselines.cli import train_command  # noqa: E402
from studies import learning_curves  # noqa: E402

FAST = ["--n-envs", "1", "--n-workers", "0", "--train-episode-seconds", "0.3", "--eval-episodes", "1",
        "--eval-seconds", "0.3", "--no-progress", "--eval-workers", "0", "--total-timesteps", "256",
        "--n-steps", "16"]


def test_every_checkpoint_of_every_seed_becomes_a_point_with_an_interval(tmp_path, capsys):
    board = tmp_path / "board"
    for seed in (0, 1):
        run_dir = board / "runs" / "planar_square" / "residual-ppo" / f"seed-{seed}"
        assert train_command(["--seed", str(seed), "--out", str(run_dir), *FAST]) == 0
    figure, data = tmp_path / "curves.png", tmp_path / "curves.json"
    assert learning_curves.main(["--board", str(board), "--scenario", "planar_square", "--methods", "residual-ppo",
                                 "--episodes", "2", "--figure", str(figure), "--json", str(data)]) == 0
    assert figure.is_file()
    record = json.loads(data.read_text())
    points = record["curves"]["residual-ppo"]
    assert len(points) >= 2 and [p["agent_steps"] for p in points] == sorted(p["agent_steps"] for p in points)
    for point in points:
        assert len(point["agent_steps_per_seed"]) == 2
        for key, _, _ in learning_curves.METRICS:
            assert point[key]["ci_low"] <= point[key]["mean"] <= point[key]["ci_high"]
            assert len(point[key]["per_seed"]) == 2
    assert set(record["references"]) == {"gradient", "approx_jacobian", "adaptive_jacobian"}
    assert "residual-ppo at" in capsys.readouterr().out


def test_a_method_without_finished_runs_is_refused_before_any_episode(tmp_path, capsys):
    with pytest.raises(SystemExit):
        learning_curves.main(["--board", str(tmp_path), "--scenario", "planar_square", "--methods", "torque-ppo",
                              "--figure", str(tmp_path / "f.png")])
    assert "no finished run of ['torque-ppo']" in capsys.readouterr().err
