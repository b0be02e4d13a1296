"""The comparison of a run (baselines/learned/compare.py): the learned policy in its own action convention, the
reference laws in theirs, on the same scenario and seeds."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from ee_formation_env import baselines  # noqa: E402
from ee_formation_env.baselines.cli import train_command  # noqa: E402
from ee_formation_env.baselines.learned.compare import learned_shortfall, reference_returns  # noqa: E402
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


def _summary(success_rate, settling_time):
    return {"success_rate": success_rate, "settling_time": settling_time}


def test_a_learned_policy_below_the_best_references_success_is_named_worse():
    results = {"learned": _summary(0.5, 1.0), "gradient": _summary(1.0, 2.0), "adaptive_jacobian": _summary(0.9, 0.5)}
    line = learned_shortfall(results)
    assert "50%" in line and "'gradient'" in line and "100%" in line


def test_a_learned_policy_as_successful_but_slower_than_the_best_reference_is_named_worse():
    results = {"learned": _summary(1.0, 1.5), "gradient": _summary(1.0, 0.9), "approx_jacobian": _summary(1.0, 1.2)}
    line = learned_shortfall(results)
    assert "1.50 s" in line and "'gradient'" in line and "0.90 s" in line


def test_a_learned_policy_that_never_settles_is_worse_than_a_reference_that_does():
    results = {"learned": _summary(0.0, float("nan")), "gradient": _summary(0.0, float("nan")),
               "adaptive_jacobian": _summary(0.2, 3.0)}
    assert "'adaptive_jacobian'" in learned_shortfall(results)


def test_a_learned_policy_at_least_as_good_as_every_reference_has_no_shortfall():
    results = {"learned": _summary(1.0, 0.7), "gradient": _summary(1.0, 0.9), "adaptive_jacobian": _summary(0.9, 0.5)}
    assert learned_shortfall(results) is None
    assert learned_shortfall({"learned": _summary(0.0, float("nan")), "gradient": _summary(0.0, float("nan"))}) is None


def test_a_run_worse_than_its_references_warns_at_its_end(tmp_path, capsys):
    run_dir = tmp_path / "run"
    assert train_command(["--total-timesteps", "200", "--mode", "torque", "--out", str(run_dir), *FAST]) == 0
    comparison = json.loads((run_dir / "comparison.json").read_text())
    assert comparison["shortfall"] == learned_shortfall(comparison["results"])
    assert ("warning: the learned policy" in capsys.readouterr().out) == bool(comparison["shortfall"])
