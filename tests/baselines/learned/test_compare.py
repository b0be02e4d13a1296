"""The comparison of a run (baselines/learned/compare.py): the learned policy in its own action convention, the
reference laws in theirs, on the same scenario and seeds."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from ee_formation_env import baselines  # noqa: E402
from ee_formation_env.baselines.cli import train_command  # noqa: E402
from ee_formation_env.baselines.learned.compare import reference_returns  # noqa: E402
from ee_formation_env.baselines.learned.options import TrainingOptions  # noqa: E402
from ee_formation_env.baselines.metrics import run_policies  # noqa: E402

FAST = ["--n-envs", "1", "--n-workers", "0", "--train-episode-seconds", "0.3", "--eval-episodes", "2",
        "--eval-seconds", "0.3", "--no-progress", "--eval-workers", "0"]


def test_a_gravity_compensated_run_is_compared_with_the_laws_in_their_raw_torques(tmp_path):
    run_dir = tmp_path / "run"
    assert train_command(["--scenario", "spatial_tetrahedron", "--mode", "torque", "--gravity-compensation",
                          "--total-timesteps", "200", "--out", str(run_dir), *FAST]) == 0
    config = json.loads((run_dir / "config.json").read_text())
    assert config["gravity_compensation"] is True
    results = json.loads((run_dir / "comparison.json").read_text())["results"]
    assert set(results) == {"learned", *baselines.POLICIES}
    # The laws ran on the scenario as it is: their episodes are those of a plain evaluation, seed for seed.
    seeds = json.loads((run_dir / "comparison.json").read_text())["seeds"]
    plain = run_policies("spatial_tetrahedron", {"gradient": "gradient"}, seeds,
                         overrides={"episode_seconds": 0.3})["gradient"]
    assert json.dumps([m.as_dict() for m in plain]) == json.dumps(results["gradient"]["per_episode"])  # NaN too
    assert all(np.isfinite(e["final_formation_error"]) for e in results["learned"]["per_episode"])
    # The learning curve's reference lines are the laws' returns in the training episodes, without the convention.
    assert set(reference_returns(config, episodes=1)) == set(baselines.POLICIES)


def test_gravity_compensation_is_refused_in_residual_mode_before_training(tmp_path, capsys):
    with pytest.raises(ValueError, match="gravity_compensation: residual mode"):
        TrainingOptions(mode="residual", gravity_compensation=True)
    with pytest.raises(SystemExit):
        train_command(["--mode", "residual", "--gravity-compensation", "--out", str(tmp_path / "run"), *FAST])
    assert "--gravity-compensation: residual mode" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_only_the_learned_policy_gets_the_action_convention():
    options = TrainingOptions(mode="torque", gravity_compensation=True)
    assert options.env_overrides() == {"gravity_compensation": True}
    assert "gravity_compensation" in options.training_overrides()
    assert "gravity_compensation" not in options.episode_overrides()
    assert TrainingOptions(mode="torque").env_overrides() == {}
