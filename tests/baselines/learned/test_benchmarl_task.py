"""The BenchMARL training task: options, specs, the residual rule through TorchRL, MAPPO, evaluation and export
(the ``torchrl`` extra)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

pytest.importorskip("torchrl")
pytest.importorskip("benchmarl")

import torch  # noqa: E402
from torchrl.envs.utils import check_env_specs  # noqa: E402

import ee_formation_env  # noqa: E402
from ee_formation_env.baselines import make_policies  # noqa: E402
from ee_formation_env.baselines.learned import benchmarl_task  # noqa: E402
from ee_formation_env.baselines.learned.benchmarl_task import (EEFormationTrainingTask, TrainingTaskClass,  # noqa: E402
                                                               TrainingTaskOptions, evaluate_benchmarl_policy,
                                                               export_benchmarl_policy, load_benchmarl_policy)
from ee_formation_env.baselines.learned.config import PRESETS, TrainConfig  # noqa: E402
from ee_formation_env.baselines.learned.training_env import BatchedTrainingEnv  # noqa: E402
from ee_formation_env.baselines.metrics import (METRIC_COLUMNS, EpisodeMetrics, format_table,  # noqa: E402
                                               stack_policies)
from ee_formation_env.builtin import BUILTIN_SCENARIOS  # noqa: E402
from ee_formation_env.scenario import load_scenario  # noqa: E402

# 5 training steps per episode (100 Hz control), 30 evaluation steps: a few seconds per test.
FAST = {"train_episode_seconds": 0.05, "episode_seconds": 0.3}


@pytest.mark.parametrize("config, field, error", [
    ({"mode": "residuals"}, "mode", ValueError),
    ({"reference": "zero"}, "reference", ValueError),
    ({"residual_scale": 0.0}, "residual_scale", ValueError),
    ({"residual_scale": "0.3"}, "residual_scale", TypeError),
    ({"residual_gate": 1}, "residual_gate", TypeError),
    ({"correction_penalty": 1.5}, "correction_penalty", ValueError),
    ({"obs_features": "log"}, "obs_features", ValueError),
    ({"hold_penalty": -0.1}, "hold_penalty", ValueError),
    ({"contact_penalty": -1.0}, "contact_penalty", ValueError),
    ({"action_acceleration": 0.0}, "action_acceleration", ValueError),
    ({"action_acceleration": True}, "action_acceleration", TypeError),
    ({"train_episode_seconds": 0}, "train_episode_seconds", ValueError),
    ({"train_initial_q_noise": float("nan")}, "train_initial_q_noise", ValueError),
    ({"episode_secs": 1.0}, "episode_secs", ValueError),  # not an option: a scenario override, the loader's error
])
def test_bad_options_raise_naming_the_field_before_any_env_is_built(config, field, error, monkeypatch):
    monkeypatch.setattr(benchmarl_task, "BatchedTrainingEnv", lambda *args, **kwargs: pytest.fail("an env was built"))
    with pytest.raises(error, match=field):
        EEFormationTrainingTask.PLANAR_SQUARE.get_task(config)


def test_defaults_are_train_configs_and_none_takes_the_mode_preset():
    options = TrainingTaskOptions()
    for name in ("reference", "residual_scale", "residual_gate", "correction_penalty", "action_acceleration"):
        assert getattr(options, name) == getattr(TrainConfig().options, name), name
    for mode in ("torque", "residual"):
        resolved = TrainingTaskOptions(mode=mode).resolved()
        for name in ("obs_features", "hold_penalty", "train_episode_seconds", "train_initial_q_noise"):
            assert getattr(resolved, name) == getattr(PRESETS[mode], name), (mode, name)
    assert TrainingTaskOptions(mode="residual").training_overrides() == {"episode_seconds": 3.0}
    assert TrainingTaskOptions(hold_penalty=0, train_initial_q_noise=0.2).resolved().hold_penalty == 0.0


def test_tasks_are_the_builtin_registry_and_the_config_splits_into_options_and_overrides(tmp_path):
    from benchmarl.environments.common import Task

    assert [member.name for member in EEFormationTrainingTask] == [name.upper() for name in BUILTIN_SCENARIOS]
    assert issubclass(EEFormationTrainingTask, Task) and EEFormationTrainingTask.env_name() == "ee_formation_training"
    task = EEFormationTrainingTask.SPATIAL_TETRAHEDRON.get_task({"mode": "residual", "episode_seconds": 5.0})
    assert isinstance(task, TrainingTaskClass)
    options, scenario, overrides = task.parts()
    assert (options.mode, scenario, overrides) == ("residual", "spatial_tetrahedron", {"episode_seconds": 5.0})
    # BenchMARL's rollouts are training episodes: the residual preset's 3 s
    assert task.max_steps(None) == load_scenario("spatial_tetrahedron", episode_seconds=3.0).max_steps
    path = tmp_path / "task.yaml"
    path.write_text("mode: residual\nresidual_scale: 0.2\nepisode_seconds: 4.0\n")
    assert EEFormationTrainingTask.PLANAR_SQUARE.get_from_yaml(str(path)).config == {
        "mode": "residual", "residual_scale": 0.2, "episode_seconds": 4.0}
    assert EEFormationTrainingTask.PLANAR_SQUARE.get_from_yaml().config == {}


def _env(config, num_envs=2, seed=0):
    task = EEFormationTrainingTask.PLANAR_SQUARE.get_task({**FAST, **config})
    return task.get_env_fun(num_envs=num_envs, continuous_actions=True, seed=seed, device="cpu")()


@pytest.mark.parametrize("config", [{"mode": "torque", "obs_features": "log-error"}, {"mode": "residual"}])
def test_training_task_env_passes_check_env_specs(config):
    env = _env(config)
    try:
        assert isinstance(env.vector_env, BatchedTrainingEnv)
        group = next(iter(env.group_map))
        size = env.vector_env.observation_space("arm_0").shape[0]
        raw = env.vector_env.env.observation_space("arm_0").shape[0]
        assert size > raw if config.get("obs_features") == "log-error" else size == raw
        assert env.full_observation_spec[group, "observation"].shape == (2, 4, size)
        check_env_specs(env)
        rollout = env.rollout(7, break_when_any_done=False)  # through a training episode end (5 steps)
        assert rollout["next", "truncated"][:, 4].all()
    finally:
        env.close()


def test_a_zero_residual_steps_exactly_the_reference_controller():
    """Residual mode through TorchRL with zero corrections: each step's observations, rewards and applied
    torques are those of the raw batched env driven by the reference controller, bit for bit."""
    K, seed, steps = 2, 3, 4
    env = _env({"mode": "residual"}, num_envs=K, seed=seed)
    group = next(iter(env.group_map))
    training_overrides = {"episode_seconds": FAST["episode_seconds"], **TrainingTaskOptions(
        mode="residual", train_episode_seconds=FAST["train_episode_seconds"]).training_overrides()}
    with ee_formation_env.vector_env("planar_square", num_envs=K, **training_overrides) as vec:
        try:
            teams = [make_policies("adaptive_jacobian", vec) for _ in range(K)]
            reference = stack_policies([team[agent] for team in teams for agent in vec.possible_agents])
            td = env.reset()
            result = vec.reset_arrays(seed=seed)
            N, size = len(vec.possible_agents), vec.observation_space("arm_0").shape[0]
            for _ in range(steps):
                np.testing.assert_array_equal(td[group, "observation"].numpy(), result.observations.reshape(K, N, size))
                td[group, "action"] = torch.zeros(env.full_action_spec[group, "action"].shape)
                td = env.step(td)["next"]
                result = vec.step_arrays(np.asarray(reference(result.observations.reshape(K * N, size))))
                np.testing.assert_array_equal(td[group, "reward"][..., 0].numpy(), result.rewards.astype(np.float32))
                np.testing.assert_array_equal(td[group, "info", "applied_torque"].numpy().reshape(K, -1),
                                              result.infos["applied_torque"].astype(np.float32))
            np.testing.assert_array_equal(td[group, "observation"].numpy(), result.observations.reshape(K, N, size))
        finally:
            env.close()


def _experiment(save_folder, share_policy_params=True, use_tanh_normal=True):
    """MAPPO on the residual task with log-error features, tiny batches (BenchMARL's test env of 2 copies)."""
    from benchmarl.algorithms import MappoConfig
    from benchmarl.experiment import Experiment
    from benchmarl.models.mlp import MlpConfig

    from conftest import tiny_benchmarl_config

    config = tiny_benchmarl_config(save_folder)
    config.evaluation_episodes = 2
    config.share_policy_params = share_policy_params
    model = MlpConfig.get_from_yaml()
    model.num_cells = [32, 32]
    algorithm = MappoConfig.get_from_yaml()
    algorithm.use_tanh_normal = use_tanh_normal
    task = EEFormationTrainingTask.PLANAR_SQUARE.get_task({"mode": "residual", "obs_features": "log-error", **FAST})
    return Experiment(task=task, algorithm_config=algorithm, model_config=model,
                      critic_model_config=MlpConfig.get_from_yaml(), seed=0, config=config)


@pytest.fixture(scope="module")
def experiment(tmp_path_factory):
    """:func:`_experiment` trained 2 iterations."""
    experiment = _experiment(tmp_path_factory.mktemp("benchmarl"))
    experiment.run()
    return experiment


def _deterministic_actions(experiment, group, observations):
    from tensordict import TensorDict
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    batch = observations.shape[:-1]
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        out = experiment.group_policies[group](TensorDict(
            {group: TensorDict({"observation": observations}, batch_size=batch)}, batch_size=batch[:-1]))
    return out[group, "action"]


def test_mappo_trains_on_the_residual_task_and_evaluates_with_the_project_metrics(experiment, tmp_path):
    assert experiment.n_iters_performed == 2 and experiment.total_frames == 80
    summary = evaluate_benchmarl_policy(experiment, episodes=2)
    assert summary["episodes"] == 2 and len(summary["per_episode"]) == 2
    fields = {spec.name for spec in dataclasses.fields(EpisodeMetrics)} - {"trajectory"}
    assert all(set(row) == fields for row in summary["per_episode"])
    assert all(row["sim_time"] == pytest.approx(FAST["episode_seconds"]) for row in summary["per_episode"])
    assert {column.key for column in METRIC_COLUMNS} <= set(summary)
    table = format_table({"mappo": summary})
    assert all(column.header in table for column in METRIC_COLUMNS) and "| mappo |" in table
    # The exported actors evaluate the same, episode for episode; seeds below 10,000 are refused.
    assert evaluate_benchmarl_policy(export_benchmarl_policy(experiment, tmp_path / "actor"), episodes=2) == summary
    with pytest.raises(ValueError, match="seed"):
        evaluate_benchmarl_policy(experiment, episodes=1, seed=0)


@pytest.mark.parametrize("options, expected", [
    ({"mode": "residual"}, {}),
    ({"mode": "position"}, {"gravity_compensation": True}),
    ({"mode": "torque", "gravity_compensation": True}, {"gravity_compensation": True}),
])
def test_the_evaluation_runs_the_actors_in_their_action_convention(experiment, monkeypatch, options, expected):
    """A position-mode (or gravity-compensated) policy trained in a gravity-compensated env is evaluated in one,
    as train.py's runs are (their SavedRun.env_overrides)."""
    from ee_formation_env.baselines.learned.benchmarl_task import actors_from_experiment
    from ee_formation_env.baselines.learned.options import TrainingOptions

    seen = {}

    def capture(scenario, policy, seeds, **kwargs):
        seen.update(kwargs["overrides"])
        raise KeyboardInterrupt  # stop before any episode: only the env settings are checked

    actors = dataclasses.replace(actors_from_experiment(experiment), overrides={"episode_seconds": 0.3},
                                 options=TrainingOptions(**options).resolved())
    assert actors.env_overrides() == expected
    monkeypatch.setattr(benchmarl_task, "run_episodes", capture)
    with pytest.raises(KeyboardInterrupt):
        evaluate_benchmarl_policy(actors, episodes=1)
    assert seen == {"episode_seconds": 0.3, **expected}


def test_the_evaluate_command_evaluates_an_export_folder_as_evaluate_benchmarl_policy(experiment, tmp_path, capsys):
    from ee_formation_env.baselines.evaluate import main

    folder = export_benchmarl_policy(experiment, tmp_path / "actor")
    summary = evaluate_benchmarl_policy(folder, episodes=2)
    assert main(["--policy", str(folder), "--episodes", "2", "--seed", "10000", "--quiet",
                 "--json", str(tmp_path / "eval.json")]) == 0
    record = json.loads((tmp_path / "eval.json").read_text())
    assert record["scenario"] == "planar_square" and record["overrides"] == {"episode_seconds": 0.3}
    assert record["learned_label"] == "learned (benchmarl, residual)"
    learned = record["results"]["learned"]
    for key in ("success_rate", "final_formation_error", "mean_return", "settling_time"):
        assert learned[key] == pytest.approx(summary[key], nan_ok=True), key
    assert "learned (benchmarl, residual)" in capsys.readouterr().out
    # the command's overrides come over the task's
    assert main(["--policy", str(folder), "--episodes", "1", "--seed", "10000", "--quiet", "--set",
                 "episode_seconds=0.2", "--json", str(tmp_path / "short.json")]) == 0
    short = json.loads((tmp_path / "short.json").read_text())
    assert short["overrides"] == {"episode_seconds": 0.2}
    assert short["results"]["learned"]["per_episode"][0]["sim_time"] == pytest.approx(0.2)


def test_the_evaluate_command_refuses_a_malformed_export_folder_in_one_line(tmp_path, capsys):
    from ee_formation_env.baselines.evaluate import main

    (tmp_path / "actor.json").write_text("{}")
    with pytest.raises(SystemExit) as exit_info:
        main(["--policy", str(tmp_path), "--episodes", "1"])
    error = capsys.readouterr().err
    assert exit_info.value.code == 2 and "error: actor.pt:" in error  # the missing file, named
    torch.save({}, tmp_path / "actor.pt")
    with pytest.raises(SystemExit):
        main(["--policy", str(tmp_path), "--episodes", "1"])
    assert "error: actor.json: expected format" in capsys.readouterr().err


def test_the_evaluated_policies_act_as_the_training_env_with_the_actor(experiment):
    """The per-agent policies evaluation runs (reference + scaled, gated correction on featured observations)
    apply the torques the TorchRL training env applies when the experiment's actor drives it."""
    from ee_formation_env.baselines.learned.benchmarl_task import actors_from_experiment

    K, seed, steps = 2, 5, 4
    env = _env({"mode": "residual", "obs_features": "log-error"}, num_envs=K, seed=seed)
    group = next(iter(env.group_map))
    factory = actors_from_experiment(experiment).policy_factory()
    with ee_formation_env.vector_env("planar_square", num_envs=K, episode_seconds=FAST["train_episode_seconds"]) as vec:
        try:
            policies = [factory(vec) for _ in range(K)]
            act = stack_policies([team[agent] for team in policies for agent in vec.possible_agents])
            td = env.reset()
            result = vec.reset_arrays(seed=seed)
            N, size = len(vec.possible_agents), vec.observation_space("arm_0").shape[0]
            for _ in range(steps):
                td[group, "action"] = _deterministic_actions(experiment, group, td[group, "observation"])
                td = env.step(td)["next"]
                result = vec.step_arrays(np.asarray(act(result.observations.reshape(K * N, size))))
                # float32 torch actor against the float64 numpy one: equal to rounding
                np.testing.assert_allclose(td[group, "info", "applied_torque"].numpy().reshape(K, -1),
                                           result.infos["applied_torque"], rtol=0, atol=1e-4)
        finally:
            env.close()


def test_export_loads_without_pickle_and_acts_as_the_experiments_policy(experiment, tmp_path):
    folder = export_benchmarl_policy(experiment, tmp_path / "actor")
    description = json.loads((folder / "actor.json").read_text())
    group = next(iter(experiment.group_map))
    entry = description["groups"][group]
    assert entry["activation"] == "Tanh" and entry["distribution"] == "tanh_normal" and entry["shared_parameters"]
    assert entry["layer_sizes"][1:] == [32, 32, 4] and entry["observation_normalization"] is None
    assert description["options"]["mode"] == "residual" and description["options"]["hold_penalty"] == 0.0
    tensors = torch.load(folder / "actor.pt", weights_only=True)
    assert [tuple(w.shape) for w in tensors[group]["weight"]] == [(1, 32, entry["layer_sizes"][0]), (1, 32, 32),
                                                                  (1, 4, 32)]
    actors = load_benchmarl_policy(folder)
    observations = torch.randn(6, 4, entry["layer_sizes"][0], generator=torch.Generator().manual_seed(0))
    expected = _deterministic_actions(experiment, group, observations).numpy()
    np.testing.assert_allclose(actors.groups[group].act(observations.numpy()), expected, atol=1e-6, rtol=0)
    predict = actors.groups[group].predict("arm_2")
    np.testing.assert_allclose(predict(observations[:, 2].numpy()), expected[:, 2], atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="actor.json"):
        load_benchmarl_policy(tmp_path / "missing")


def test_export_of_per_agent_parameters_and_a_plain_normal_actor(tmp_path):
    """share_policy_params=False (one parameter set per agent) and use_tanh_normal=False (the action is the
    Gaussian's mean itself), on an untrained experiment."""
    experiment = _experiment(tmp_path, share_policy_params=False, use_tanh_normal=False)
    group = next(iter(experiment.group_map))
    actors = load_benchmarl_policy(export_benchmarl_policy(experiment, tmp_path / "actor"))
    actor = actors.groups[group]
    assert not actor.shared and actor.distribution == "normal" and len(actor.weights[0]) == 4
    observations = torch.randn(5, 4, actor.layer_sizes[0], generator=torch.Generator().manual_seed(1))
    expected = _deterministic_actions(experiment, group, observations).numpy()
    np.testing.assert_allclose(actor.act(observations.numpy()), expected, atol=1e-6, rtol=0)
    for j, agent in enumerate(actor.agents):
        np.testing.assert_allclose(actor.predict(agent)(observations[:, j].numpy()), expected[:, j], atol=1e-6, rtol=0)
