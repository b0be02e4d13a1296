"""Learned actions in physical units: built-in robots keep their torque limits, a KUKA team is drivable."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ee_formation_env import parallel_env
from ee_formation_env.env import PHYSICS_FAULTS
from ee_formation_env.baselines.learned.action_scale import (DEFAULT_ACTION_ACCELERATION, action_scales, all_ones,
                                                             check_action_acceleration, unit_torques)
from ee_formation_env.baselines.learned.options import TrainingOptions
from ee_formation_env.baselines.learned.policy import ComposedPolicy
from ee_formation_env.baselines.learned.torque import TorqueRows
from ee_formation_env.baselines.learned.training_env import ParallelTrainingEnv
from ee_formation_env.baselines.metrics import stack_policies
from ee_formation_env.baselines.reference.dynamics import nominal_dynamics
from ee_formation_env.scenario import BUILTIN_SCENARIOS, load_scenario
from ee_formation_env.task import build_task

KUKA_TEAM = str(Path(__file__).parents[3] / "studies" / "scenarios" / "kuka_team.yaml")
# Torque mode, physically scaled actions and nothing else.
TORQUE = TrainingOptions(mode="torque", obs_features="none", hold_penalty=0.0)


@pytest.mark.parametrize("name", BUILTIN_SCENARIOS)
def test_builtin_robots_keep_their_torque_limits_exactly(name):
    task = build_task(load_scenario(name))
    scales = action_scales(task)
    assert all_ones(scales)
    for agent, limits in zip(task.agents, task.torque_limits):
        assert np.array_equal(unit_torques(task)[agent], limits)


def test_kuka_units_are_joint_inertia_times_the_acceleration():
    task = build_task(load_scenario(KUKA_TEAM))
    torques, scales = unit_torques(task), action_scales(task)
    model = task.models[0]
    mass_matrix = nominal_dynamics(task.scenario.arms[0].urdf, model.joint_names).mass_matrix(task.initial_q[0])
    # A unit torque on joint j alone accelerates it by the acceleration: H^-1 tau_j e_j has j-th entry a.
    accelerations = [np.linalg.solve(mass_matrix, torque * np.eye(7)[j])[j] for j, torque in enumerate(torques["arm_0"])]
    assert np.allclose(accelerations, DEFAULT_ACTION_ACCELERATION)
    assert np.allclose(scales["arm_0"] * 300.0, torques["arm_0"])
    # The 300 N m URDF efforts are far above what the links need: the wrist's unit is well under 1 N m.
    assert torques["arm_0"][-1] < 1.0 and torques["arm_0"][1] > 36.0  # joint 2 still holds gravity (36 N m)
    assert not all_ones(scales)


@pytest.mark.parametrize("value, error, message", [
    (0.0, ValueError, "action_acceleration: expected a finite value > 0"),
    (-5.0, ValueError, "action_acceleration: expected a finite value > 0"),
    (float("nan"), ValueError, "action_acceleration"),
    (True, TypeError, "action_acceleration: expected a number"),
    ("100", TypeError, "action_acceleration: expected a number"),
])
def test_bad_accelerations_are_refused_naming_the_field(value, error, message):
    with pytest.raises(error, match=message):
        check_action_acceleration(value)


def _random_episode_steps(env, rng, steps=100):
    env.reset(seed=3)
    for step in range(steps):
        actions = {agent: rng.uniform(-1, 1, env.action_space(agent).shape) for agent in env.agents}
        _, _, terminations, truncations, infos = env.step(actions)
        if any(terminations.values()) or any(truncations.values()):
            return step + 1, max(info["physics_fault"] for info in infos.values())
    return steps, 0  # no fault, no end


def test_random_learned_actions_drive_a_kuka_team_without_faults(closer):
    """In the env's own units random actions fault in one step; in physical units they run 1 s without."""
    rng = np.random.default_rng(0)
    raw = closer(parallel_env(KUKA_TEAM))
    steps, fault = _random_episode_steps(raw, rng)
    assert steps == 1 and PHYSICS_FAULTS[fault].startswith("joint speed")
    scaled = closer(ParallelTrainingEnv(KUKA_TEAM, None, TORQUE))
    steps, fault = _random_episode_steps(scaled, rng)
    assert (steps, fault) == (100, 0)


def test_scaled_env_applies_clipped_actions_times_the_scales(closer):
    env = closer(parallel_env(KUKA_TEAM))
    scales = action_scales(env.task)
    wrapped = closer(ParallelTrainingEnv(KUKA_TEAM, None, TORQUE))
    env.reset(seed=1)
    wrapped.reset(seed=1)
    actions = {agent: np.linspace(-1.5, 1.5, 7) for agent in env.possible_agents}
    expected = env.step({agent: np.clip(a, -1, 1) * scales[agent] for agent, a in actions.items()})[0]
    observed = wrapped.step(actions)[0]
    for agent in env.possible_agents:
        assert observed[agent].tobytes() == expected[agent].tobytes()
    with pytest.raises(ValueError, match="arm_0"):  # malformed actions get the env's own error
        wrapped.step({**actions, "arm_0": np.zeros(3)})


def test_scaled_policies_stack_row_by_row_exactly():
    rng = np.random.default_rng(2)

    class Linear:
        def __init__(self, weights):
            self.weights = weights

        def reset(self):
            pass

        def __call__(self, observation):
            return observation @ self.weights

    policies = [ComposedPolicy(Linear(rng.normal(size=(5, 3))), None, "none", TorqueRows([rng.uniform(0.01, 1, 3)]))
                for _ in range(4)]
    observations = rng.normal(size=(4, 5))
    stacked = stack_policies(policies)(observations)
    for row, policy in enumerate(policies):
        assert stacked[row].tobytes() == policy(observations[row]).tobytes()
        assert np.all(np.abs(stacked[row]) <= policy.rows.joint_scales[0])


@pytest.mark.parametrize("mode", ["torque", "residual"])
def test_a_saved_run_acts_with_the_scales_it_trained_with(tmp_path, closer, mode):
    pytest.importorskip("stable_baselines3")
    import json

    from ee_formation_env.baselines.cli import train_command
    from ee_formation_env.baselines.learned.policy import learned_policies

    run_dir = tmp_path / "run"
    assert train_command(["--scenario", KUKA_TEAM, "--mode", mode, "--action-acceleration", "40",
                          "--out", str(run_dir), "--n-envs", "1", "--n-workers", "0", "--total-timesteps", "100",
                          "--train-episode-seconds", "0.2", "--eval-episodes", "1", "--eval-seconds", "0.05",
                          "--eval-workers", "0", "--no-progress"]) == 0
    config = json.loads((run_dir / "config.json").read_text())
    assert config["action_acceleration"] == 40.0
    env = closer(parallel_env(KUKA_TEAM))
    expected = action_scales(env.task, 40.0)
    policies = learned_policies(run_dir, env, config)
    for agent, policy in policies.items():
        assert np.array_equal(policy.rows.joint_scales[0], expected[agent]), agent
