"""The learned policy of a run evaluated on the batched env (``run_episodes``, what the comparison uses):
each episode's metrics equal the one-episode loop's, in torque mode with observation features and in
residual mode with the error gate, planar and spatial, and on a KUKA team (physically scaled actions)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

pytest.importorskip("stable_baselines3")

import ee_formation_env  # noqa: E402
from ee_formation_env.baselines.cli import train_command  # noqa: E402
from ee_formation_env.baselines.learned.policy import learned_policies, learned_policy_factory  # noqa: E402
from ee_formation_env.baselines.metrics import evaluation_env, run_episode, run_episodes  # noqa: E402

FAST = ["--n-envs", "1", "--n-workers", "0", "--train-episode-seconds", "0.5", "--eval-episodes", "1",
        "--eval-seconds", "0.1", "--no-progress", "--eval-workers", "0", "--total-timesteps", "200"]


KUKA_TEAM = str(Path(__file__).parents[3] / "studies" / "scenarios" / "kuka_team.yaml")  # physical action scales


@pytest.mark.parametrize("scenario, mode", [("planar_square", ["--mode", "torque", "--obs-features", "log-error"]),
                                            ("spatial_tetrahedron", ["--mode", "residual", "--residual-gate"]),
                                            (KUKA_TEAM, ["--mode", "torque"]),
                                            (KUKA_TEAM, ["--mode", "residual", "--residual-gate"])])
def test_learned_policy_batched_equals_one_episode_at_a_time(tmp_path, scenario, mode):
    run_dir = tmp_path / "run"
    assert train_command(["--scenario", scenario, *mode, "--out", str(run_dir), *FAST]) == 0
    config = json.loads((run_dir / "config.json").read_text())
    seeds, seconds = [10003, 10000, 10001], 0.4
    with ee_formation_env.parallel_env(scenario, episode_seconds=seconds) as env:
        policies = learned_policies(run_dir, env, config)
        expected = [run_episode(env, policies, seed=seed) for seed in seeds]
    with evaluation_env(scenario, len(seeds), episode_seconds=seconds) as env:
        got = run_episodes(None, learned_policy_factory(run_dir, env, config), seeds, env=env)
    assert [repr(e) for e in expected] == [repr(g) for g in got]
