"""The mode registry: a mode is one class registered once, and a toy mode registered here trains and evaluates
through the same path as the built-in ones (the training env, ``train.py``, the saved run's policies)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

import ee_formation_env
from ee_formation_env.baselines.learned.modes import (PLUGIN_GROUP, ActionRows, TrainingMode, mode_names,
                                                      register_mode, training_mode, unregister_mode)
from ee_formation_env.baselines.learned.options import TrainingOptions
from ee_formation_env.baselines.learned.policy import composed_policy_factory
from ee_formation_env.baselines.learned.torque import TorqueMode
from ee_formation_env.baselines.learned.training_env import BatchedTrainingEnv


class HalfTorqueRows(ActionRows):
    """Half of the clipped learned action as the normalized torque; rewards unchanged."""

    def __init__(self, count: int):
        self.count = count

    def __call__(self, observations, learned):
        return 0.5 * np.clip(np.asarray(learned, dtype=np.float64), -1.0, 1.0), None

    def split(self):
        return [HalfTorqueRows(1) for _ in range(self.count)]

    @classmethod
    def concatenate(cls, parts):
        return cls(sum(part.count for part in parts))


class HalfTorqueMode(TrainingMode):
    name = "half_torque"
    help = "learn half of the joint torques"
    preset = dataclasses.replace(TorqueMode.preset, n_envs=1, n_workers=0, train_episode_seconds=0.5)

    def action_rows(self, options, copies, agents, joint_scales):
        return HalfTorqueRows(len(copies) * len(agents))


@pytest.fixture
def half_torque():
    register_mode(HalfTorqueMode)
    try:
        yield HalfTorqueMode
    finally:
        unregister_mode(HalfTorqueMode.name)


def test_the_builtin_modes_come_first_and_unknown_ones_name_the_field():
    assert mode_names()[:2] == ("residual", "torque")
    assert training_mode("residual").name == "residual"
    with pytest.raises(ValueError, match=r"mode: expected one of \['residual', 'torque', 'velocity', 'position'\], got 'torques'"):
        training_mode("torques")
    with pytest.raises(ValueError, match="mode: expected one of"):
        TrainingOptions(mode="torques")


def test_a_name_is_registered_once(half_torque):
    assert "half_torque" in mode_names()
    with pytest.raises(ValueError, match="mode: 'half_torque' is already registered"):
        register_mode(HalfTorqueMode)


def test_a_registered_mode_acts_in_the_training_env(half_torque, closer):
    options = TrainingOptions(mode="half_torque", obs_features="none", hold_penalty=0.0)
    env = closer(BatchedTrainingEnv("planar_square", {"episode_seconds": 0.1}, options, num_envs=2))
    env.reset_arrays(seed=[0, 1])
    actions = np.random.default_rng(0).uniform(-1.5, 1.5, (8, 2))
    result = env.step_arrays(actions)
    limits = np.concatenate(env.task.torque_limits)
    expected = 0.5 * np.clip(actions, -1.0, 1.0).reshape(2, -1) * limits
    np.testing.assert_allclose(result.infos["applied_torque"], expected, rtol=1e-12)


def test_a_registered_mode_trains_and_evaluates_through_train_py(half_torque, tmp_path, closer):
    pytest.importorskip("stable_baselines3")
    from ee_formation_env.baselines.cli import train_command
    from ee_formation_env.baselines.learned.policy import learned_policies

    run_dir = tmp_path / "run"
    assert train_command(["--mode", "half_torque", "--total-timesteps", "200", "--out", str(run_dir),
                          "--eval-episodes", "1", "--eval-seconds", "0.1", "--eval-workers", "0",
                          "--no-progress"]) == 0
    config = json.loads((run_dir / "config.json").read_text())
    assert config["mode"] == "half_torque" and config["n_envs"] == 1  # the mode's preset
    assert json.loads((run_dir / "comparison.json").read_text())["results"]["learned"]["episodes"] == 1
    env = closer(ee_formation_env.parallel_env("planar_square"))
    policies = learned_policies(run_dir, env, config)
    observations, _ = env.reset(seed=0)
    for agent, policy in policies.items():
        assert isinstance(policy.rows, HalfTorqueRows)
        featured = policy.features(observations[agent][None])[0]  # the preset's features, as in training
        raw = policy.learned(featured)  # the actor's own action, in [-1, 1]
        np.testing.assert_array_equal(policy(observations[agent]), 0.5 * np.asarray(raw, dtype=np.float64))


PLUGIN_MODULE = """
import dataclasses

import numpy as np

from ee_formation_env.baselines.learned.modes import ActionRows, TrainingMode, register_mode
from ee_formation_env.baselines.learned.torque import TorqueMode


class ThirdTorqueRows(ActionRows):
    def __init__(self, count):
        self.count = count

    def __call__(self, observations, learned):
        return np.clip(np.asarray(learned, dtype=np.float64), -1.0, 1.0) / 3.0, None

    def split(self):
        return [ThirdTorqueRows(1) for _ in range(self.count)]

    @classmethod
    def concatenate(cls, parts):
        return cls(sum(part.count for part in parts))


@register_mode
class ThirdTorqueMode(TrainingMode):
    name = "third_torque"
    help = "learn a third of the joint torques"
    preset = dataclasses.replace(TorqueMode.preset, n_envs=1, n_workers=0, train_episode_seconds=0.5)

    def action_rows(self, options, copies, agents, joint_scales):
        return ThirdTorqueRows(len(copies) * len(agents))
"""


def installed_plugin(folder, monkeypatch, module, text, entry_name):
    """A package installed in ``folder`` (on ``sys.path``): the module ``module`` of ``text``, named in its
    entry points under the mode plugins' group, as ``pip install`` of a package declaring it would leave it."""
    (folder / f"{module}.py").write_text(text)
    info = folder / f"{module}-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {module}\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(f"[{PLUGIN_GROUP}]\n{entry_name} = {module}\n")
    monkeypatch.syspath_prepend(str(folder))


def test_a_mode_of_another_package_is_one_file_and_trains_through_train_py(tmp_path, monkeypatch):
    """A plugin's mode is seen by the CLI without any import of the caller's: its entry point is enough."""
    pytest.importorskip("stable_baselines3")
    from ee_formation_env.baselines.cli import train_command

    installed_plugin(tmp_path, monkeypatch, "third_torque_plugin", PLUGIN_MODULE, "third_torque")
    run_dir = tmp_path / "run"
    try:
        assert train_command(["--mode", "third_torque", "--total-timesteps", "200", "--out", str(run_dir),
                              "--eval-episodes", "1", "--eval-seconds", "0.1", "--eval-workers", "0",
                              "--no-progress"]) == 0
        assert "third_torque" in mode_names()
    finally:
        unregister_mode("third_torque")
    config = json.loads((run_dir / "config.json").read_text())
    assert config["mode"] == "third_torque" and config["n_envs"] == 1  # the plugin mode's preset


def test_a_plugin_that_fails_to_load_is_named(tmp_path, monkeypatch):
    installed_plugin(tmp_path, monkeypatch, "broken_mode_plugin", "raise RuntimeError('no torque here')\n",
                     "broken")
    with pytest.raises(ValueError, match=r"^mode: the plugin 'broken' \(ee_formation.training_modes: "
                                         r"broken_mode_plugin\) failed to load: RuntimeError: no torque here$"):
        training_mode("broken_mode")
    with pytest.raises(ValueError, match=r"^mode: expected one of \['residual', "):  # tried once, then unknown
        training_mode("broken_mode")


def test_the_fault_guard_is_the_modes_own_and_the_flag_wins():
    """A mode learning from scratch tolerates its exploration faults (0.9, judged from a quarter of the budget
    on); a residual on a law does not (0.5, from the start)."""
    from ee_formation_env.baselines.learned.config import TrainConfig

    def guard(*argv):
        config = TrainConfig.from_args([*argv, "--recipe", "none", "--no-progress"])
        return config.max_fault_fraction, config.fault_guard_start

    assert guard("--mode", "residual") == (0.5, 0.0)
    assert guard("--mode", "torque") == guard("--mode", "velocity") == guard("--mode", "position") == (0.9, 0.25)
    assert guard("--mode", "torque", "--max-fault-fraction", "0.3", "--fault-guard-start", "0") == (0.3, 0.0)


@pytest.mark.parametrize("mode", ["torque", "velocity", "position"])
def test_the_evaluated_policy_applies_the_training_envs_rule_row_for_row(mode, closer):
    """A saved policy composes its learned actions with the mode's rule as the training env does (the stateless
    built-in modes; the residual rule's reference controllers: test_residual.py)."""
    options = TrainingOptions(mode=mode, obs_features="none", hold_penalty=0.0)
    env = closer(BatchedTrainingEnv("planar_square", {"episode_seconds": 5.0}, options, num_envs=1))
    result = env.reset_arrays(seed=2)
    agents = env.possible_agents
    observations = result.observations.reshape(len(agents), -1)
    learned = np.random.default_rng(1).uniform(-1, 1, (len(agents), 2))

    class Fixed:
        def __init__(self, action):
            self.action = action

        def reset(self):
            pass

        def __call__(self, observation):
            return self.action

    policies = composed_policy_factory({a: Fixed(learned[i]) for i, a in enumerate(agents)}, env.env,
                                       env.options)(env.env.copy_view(0))
    expected, _ = env.action_rows(observations, learned)
    for i, agent in enumerate(agents):
        np.testing.assert_array_equal(policies[agent](observations[i]), expected[i])
