"""The project's BenchMARL configurations (their YAML files, advantage normalization) and the task's TorchRL
transforms (observation normalization, reward scale), their export and evaluation (the ``torchrl`` extra)."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("torchrl")
pytest.importorskip("benchmarl")

import torch  # noqa: E402
import yaml  # noqa: E402
from torchrl.envs import Compose, TransformedEnv  # noqa: E402
from torchrl.envs.utils import check_env_specs  # noqa: E402

from ee_formation_env.baselines.learned import benchmarl_configs, benchmarl_task  # noqa: E402
from ee_formation_env.baselines.learned.benchmarl_configs import (CONFIG_DIR, algorithm_config,  # noqa: E402
                                                                  experiment_config, model_config, task_config)
from ee_formation_env.baselines.learned.benchmarl_task import (EEFormationTrainingTask, TaskTransforms,  # noqa: E402
                                                               actors_from_experiment, evaluate_benchmarl_policy,
                                                               export_benchmarl_policy, load_benchmarl_policy)
from ee_formation_env.baselines.learned.algorithms import algorithm_names  # noqa: E402
from ee_formation_env.baselines.learned.modes import mode_names  # noqa: E402

FAST = {"train_episode_seconds": 0.05, "episode_seconds": 0.3}


def test_every_shipped_yaml_loads_with_benchmarls_own_loaders():
    from benchmarl.experiment import ExperimentConfig

    base = set(ExperimentConfig.get_from_yaml().__dict__)
    for algorithm in algorithm_names("benchmarl"):
        config = algorithm_config(algorithm)
        assert type(config) is benchmarl_configs.algorithm_config_class(algorithm)
        experiment = experiment_config(algorithm)
        assert set(experiment.__dict__) == base  # every field of BenchMARL's base experiment, none unknown
        assert experiment.lr == 3e-4 and experiment.evaluation is False
    assert algorithm_config("mappo").normalize_advantage is True and algorithm_config("ippo").lmbda == 0.95
    assert model_config().num_cells == [128, 128]
    deepsets = model_config("deepsets")  # the set actor: the project's masked slot aggregation
    assert type(deepsets) is benchmarl_configs.SlotDeepsetsConfig and deepsets.aggr == "mean"
    assert deepsets.associated_class() is benchmarl_configs.SlotDeepsets
    with pytest.raises(ValueError, match="model"):
        model_config("gnn")
    for mode in mode_names():
        config = task_config(mode)
        assert config["mode"] == mode
        task = EEFormationTrainingTask.PLANAR_SQUARE.get_from_yaml(str(CONFIG_DIR / "task" / "ee_formation_training"
                                                                       / f"{mode}.yaml"))
        assert task.transforms() == TaskTransforms(observation_normalization=True, global_state=False,
                                                   reward_normalization=True)
    files = sorted(path.relative_to(CONFIG_DIR).as_posix() for path in CONFIG_DIR.rglob("*.yaml"))
    assert files == ["algorithm/ippo.yaml", "algorithm/mappo.yaml", "algorithm/masac.yaml",
                     "experiment/off_policy.yaml", "experiment/on_policy.yaml", "model/layers/deepsets.yaml",
                     "model/layers/mlp.yaml",
                     "task/ee_formation_training/position.yaml", "task/ee_formation_training/residual.yaml",
                     "task/ee_formation_training/torque.yaml", "task/ee_formation_training/velocity.yaml"]
    for path in CONFIG_DIR.rglob("*.yaml"):
        assert isinstance(yaml.safe_load(path.read_text()), dict), path


@pytest.mark.parametrize("name, error", [("mapo", ValueError), (None, ValueError)])
def test_an_unknown_algorithm_is_refused_naming_the_field(name, error):
    with pytest.raises(error, match="algorithm"):
        algorithm_config(name)
    with pytest.raises(error, match="algorithm"):
        experiment_config(name)


def test_a_non_boolean_advantage_normalization_is_refused():
    with pytest.raises(TypeError, match="normalize_advantage"):
        benchmarl_configs.FormationMappoConfig(**{**algorithm_config("mappo").__dict__,
                                                            "normalize_advantage": "yes"})


@pytest.mark.parametrize("config, field, error", [
    ({"observation_normalization": 1}, "observation_normalization", TypeError),
    ({"state_normalization": 1}, "state_normalization", TypeError),
    ({"state_normalization": True}, "state_normalization: needs observation_normalization", ValueError),
    ({"global_state": "no"}, "global_state", TypeError),
    ({"observation_normalization": True, "state_normalization": True, "global_state": False},
     "state_normalization: the task has no state without global_state", ValueError),
    ({"reward_scale": 0.0}, "reward_scale", ValueError),
    ({"reward_scale": float("inf")}, "reward_scale", ValueError),
    ({"reward_scale": "0.1"}, "reward_scale", TypeError),
    ({"reward_normalization": "yes"}, "reward_normalization", TypeError),
    ({"reward_normalization": True, "reward_scale": 0.005}, "reward_normalization: not with reward_scale", ValueError),
    ({"reward_normalization_gamma": 0.0}, "reward_normalization_gamma", ValueError),
    ({"reward_normalization_gamma": 1.5}, "reward_normalization_gamma", ValueError),
    ({"reward_normalization_gamma": True}, "reward_normalization_gamma", TypeError),
])
def test_bad_transform_values_raise_naming_the_field_before_any_env_is_built(config, field, error, monkeypatch):
    monkeypatch.setattr(benchmarl_task, "BatchedTrainingEnv", lambda *args, **kwargs: pytest.fail("an env was built"))
    with pytest.raises(error, match=field):
        EEFormationTrainingTask.PLANAR_SQUARE.get_task(config)


def test_the_transform_keys_are_not_scenario_overrides():
    task = EEFormationTrainingTask.PLANAR_SQUARE.get_task({"observation_normalization": True, "reward_scale": 0.5,
                                                           "episode_seconds": 2.0})
    assert task.parts()[2] == {"episode_seconds": 2.0}


def _transformed_env(config, num_envs=2, seed=0):
    task = EEFormationTrainingTask.PLANAR_SQUARE.get_task({"mode": "torque", **FAST, **config})
    env = task.get_env_fun(num_envs=num_envs, continuous_actions=True, seed=seed, device="cpu")()
    transforms = task.get_env_transforms(env)
    return TransformedEnv(env, Compose(*transforms)) if transforms else env  # as BenchMARL composes them


def test_without_transforms_the_task_adds_none():
    task = EEFormationTrainingTask.PLANAR_SQUARE.get_task({"mode": "torque", **FAST})
    env = task.get_env_fun(num_envs=2, continuous_actions=True, seed=0, device="cpu")()
    try:
        assert task.get_env_transforms(env) == []
    finally:
        env.close()


def test_state_normalization_normalizes_the_critics_state_too():
    plain, normalized = _transformed_env({"observation_normalization": True}), _transformed_env(
        {"observation_normalization": True, "state_normalization": True})
    try:
        assert "state" not in plain.transform[0].in_keys and "state" in normalized.transform[0].in_keys
        check_env_specs(normalized)
        raw = _transformed_env({})
        states = {}
        for name, env in (("raw", raw), ("normalized", normalized)):
            td = env.rollout(20, break_when_any_done=False)
            states[name] = td["next", "state"]
        raw.close()
        # raw states hold joint speeds and positions of several units; normalized ones are about centred
        assert states["normalized"].mean(dim=(0, 1)).abs().max() < 3.0 < states["raw"].abs().max()
    finally:
        plain.close()
        normalized.close()


def test_the_reward_scale_multiplies_every_reward_and_the_observations_normalize():
    torch.manual_seed(0)
    transforms = {"reward_scale": 0.25, "observation_normalization": True}
    checked = _transformed_env(transforms)
    try:
        check_env_specs(checked)
    finally:
        checked.close()
    plain, scaled = _transformed_env({}), _transformed_env(transforms)
    try:
        group = next(iter(plain.group_map))
        actions = torch.rand(6, 2, 4, 2) * 2 - 1  # the same actions in both (steps, copies, agents, joints)
        plain_rewards, scaled_rewards, observations = [], [], []
        for env, rewards in ((plain, plain_rewards), (scaled, scaled_rewards)):
            td = env.reset()
            for action in actions:
                td[group, "action"] = action
                td = env.step(td)
                rewards.append(td["next", group, "reward"].clone())
                if env is scaled:
                    observations.append(td["next", group, "observation"].clone())
                td = td["next"]
        torch.testing.assert_close(torch.stack(scaled_rewards), 0.25 * torch.stack(plain_rewards))
        # The running statistics are the observations' own: over what it saw, each feature is about centred.
        assert torch.stack(observations).mean(dim=(0, 1)).abs().max() < 3.0
    finally:
        plain.close()
        scaled.close()


def test_reward_normalization_divides_by_the_running_std_of_the_discounted_return_as_sb3():
    """The transform against SB3's own ``VecNormalize`` fed the same rewards and dones (agents as SB3's envs)."""
    import gymnasium
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    gamma = 0.9
    transforms = {"reward_normalization": True, "reward_normalization_gamma": gamma}
    checked = _transformed_env(transforms)
    try:
        check_env_specs(checked)
    finally:
        checked.close()
    # 0.05 s training episodes of a few steps: the returns restart within the rollout
    plain, normalized = _transformed_env({}), _transformed_env(transforms)
    try:
        group = next(iter(plain.group_map))
        actions = torch.rand(30, 2, 4, 2) * 2 - 1  # (steps, copies, agents, joints)
        rewards, dones, normalized_rewards = [], [], []
        for env in (plain, normalized):
            td = env.reset()
            for action in actions:
                td[group, "action"] = action
                td = env.step(td)
                if env is plain:
                    rewards.append(td["next", group, "reward"].reshape(-1).double().numpy())
                    dones.append(td["next", group, "done"].reshape(-1).numpy())
                else:
                    normalized_rewards.append(td["next", group, "reward"].reshape(-1).double().numpy())
                td = td["next"]
        assert np.concatenate(dones).any()  # episodes ended inside the rollout
        # only its reward statistics are used; its envs are stand-ins (8 = copies x agents)
        reference = VecNormalize(DummyVecEnv([lambda: gymnasium.make("Pendulum-v1")] * 8), norm_obs=False, norm_reward=True, gamma=gamma)
        expected = []
        for reward, done in zip(rewards, dones):
            reference.returns = reference.returns * gamma + reward  # VecNormalize.step_wait, in its order
            reference.ret_rms.update(reference.returns)
            expected.append(reference.normalize_reward(reward))
            reference.returns[done] = 0.0
        np.testing.assert_allclose(np.stack(normalized_rewards), np.stack(expected), rtol=1e-5, atol=1e-7)
        assert normalized.transform[0].return_std(group) != 1.0
        tally = normalized.transform[0].take_env_reward()  # the env's rewards, not the normalized ones
        assert tally == pytest.approx(np.mean(rewards), rel=1e-5) and np.isnan(normalized.transform[0].take_env_reward())
        twin = normalized.transform[0].clone()  # BenchMARL's clones share the statistics
        assert twin.return_std(group) == normalized.transform[0].return_std(group)
    finally:
        plain.close()
        normalized.close()


@pytest.fixture(scope="module")
def normalized_experiment(tmp_path_factory):
    """MAPPO with the shipped configs (sizes cut to a smoke test) on the torque task with its transforms, trained
    2 iterations."""
    from benchmarl.experiment import Experiment

    from conftest import tiny_benchmarl_config

    config = tiny_benchmarl_config(tmp_path_factory.mktemp("benchmarl-normalized"))
    model = model_config()
    model.num_cells = [16, 16]
    task = EEFormationTrainingTask.PLANAR_SQUARE.get_task({**task_config("torque"), **FAST})
    experiment = Experiment(task=task, algorithm_config=algorithm_config("mappo"), model_config=model,
                            critic_model_config=model, seed=0, config=config)
    experiment.run()
    return experiment


def test_the_shipped_mappo_normalizes_advantages(normalized_experiment):
    losses = normalized_experiment.losses
    assert losses and all(loss.normalize_advantage for loss in losses.values())


@pytest.mark.parametrize("algorithm", ["mappo", "ippo"])
def test_the_shipped_ppo_configs_start_from_orthogonal_layers(algorithm):
    """From scratch in torque mode the first batch must start near zero torque (docs/results.md)."""
    assert algorithm_config(algorithm).orthogonal_init is True


def test_the_shipped_mappo_gives_each_agent_its_own_value_of_every_agents_observation(normalized_experiment):
    """One critic per agent (share_param_critic False) on every agent's observation (the task's global_state off):
    two agents get two values of one joint observation."""
    from tensordict import TensorDict

    experiment = normalized_experiment
    (group, agents), = experiment.group_map.items()
    assert experiment.algorithm_config.share_param_critic is False and experiment.state_spec is None
    observation = experiment.observation_spec[group, "observation"]
    batch = TensorDict({group: TensorDict({"observation": torch.randn(3, *observation.shape)}, [3, len(agents)])}, [3])
    values = experiment.algorithm.get_critic(group)(batch)[group, "state_value"]
    assert values.shape == (3, len(agents), 1)
    assert not torch.allclose(values[:, 0], values[:, 1])  # not one value expanded over the agents


def test_without_the_global_state_mappo_s_critics_read_every_agents_observation(tmp_path):
    from benchmarl.experiment import Experiment
    from tensordict import TensorDict

    from conftest import tiny_benchmarl_config

    model = model_config()
    model.num_cells = [16, 16]
    config = {**task_config("torque"), **FAST, "global_state": False, "state_normalization": False}
    experiment = Experiment(task=EEFormationTrainingTask.PLANAR_SQUARE.get_task(config),
                            algorithm_config=algorithm_config("mappo"), model_config=model, critic_model_config=model,
                            seed=0, config=tiny_benchmarl_config(tmp_path))
    assert experiment.state_spec is None and "state" not in experiment.test_env.observation_spec.keys()
    (group, agents), = experiment.group_map.items()
    observation = experiment.observation_spec[group, "observation"]
    batch = TensorDict({group: TensorDict({"observation": torch.randn(3, *observation.shape)}, [3, len(agents)])}, [3])
    values = experiment.algorithm.get_critic(group)(batch)[group, "state_value"]
    assert values.shape == (3, len(agents), 1)
    first = next(p for name, p in experiment.algorithm.get_critic(group).named_parameters() if name.endswith("weight"))
    assert first.shape[-1] == len(agents) * observation.shape[-1]  # every agent's observation, concatenated


def test_the_shipped_mappo_has_one_learned_scale_per_joint_in_every_state(normalized_experiment):
    """The Gaussian's scale is a parameter (trained: it moved from its initial value), not an actor output: two
    different observations get the same scale, their means differ."""
    from tensordict import TensorDict

    experiment = normalized_experiment
    (group, agents), = experiment.group_map.items()
    policy = experiment.algorithm.get_policy_for_loss(group)
    scales = [module for module in policy.modules() if isinstance(module, benchmarl_configs.StateIndependentScale)]
    assert len(scales) == 1 and scales[0].scale_parameter.shape == (experiment.action_spec[group, "action"].shape[-1],)
    assert scales[0].scale_parameter.abs().max() > 0  # the optimizer updated it
    observation = experiment.observation_spec[group, "observation"]
    batch = TensorDict({group: TensorDict({"observation": torch.randn(2, *observation.shape)}, [2, len(agents)])}, [2])
    out = policy.module[0](batch)
    assert not torch.allclose(out[group, "loc"][0], out[group, "loc"][1])
    torch.testing.assert_close(out[group, "scale"][0], out[group, "scale"][1])


@pytest.mark.parametrize("algorithm, global_state", [("mappo", False), ("mappo", True), ("ippo", False)])
def test_orthogonal_init_starts_the_ppo_from_sb3_s_initialization(algorithm, global_state, tmp_path):
    """``orthogonal_init: True`` (on in the shipped PPO YAMLs), before any update: every weight matrix of actor and critic is orthogonal at its gain (sqrt 2 hidden, 0.01
    the actor's output, 1 the critic's), biases 0, so the initial mean action is ~0 for any observation; with
    the option off, BenchMARL's default initialization (a mean action of the size of the observation's)."""
    from benchmarl.experiment import Experiment
    from tensordict import TensorDict

    from conftest import tiny_benchmarl_config

    def experiment(orthogonal: bool) -> Experiment:
        model = model_config()
        model.num_cells = [16, 16]
        chosen = algorithm_config(algorithm)
        chosen.orthogonal_init = orthogonal
        task = EEFormationTrainingTask.PLANAR_SQUARE.get_task({**task_config("torque"), **FAST,
                                                               "global_state": global_state})
        folder = tmp_path / f"orthogonal-{orthogonal}"
        folder.mkdir()
        return Experiment(task=task, algorithm_config=chosen, model_config=model, critic_model_config=model, seed=0,
                          config=tiny_benchmarl_config(folder))

    def mean_actions(made: Experiment) -> torch.Tensor:
        (group, agents), = made.group_map.items()
        observation = made.observation_spec[group, "observation"]
        batch = TensorDict({group: TensorDict({"observation": 3 * torch.randn(64, *observation.shape)},
                                              [64, len(agents)])}, [64])
        return made.algorithm.get_policy_for_loss(group).module[0](batch)[group, "loc"]

    made = experiment(True)
    (group, agents), = made.group_map.items()
    actor = made.algorithm.get_policy_for_loss(group).module[0].module[0]
    for module, output_gain in ((actor, 0.01), (made.algorithm.get_critic(group), 1.0)):
        weights = [p for name, p in module.named_parameters() if name.endswith("weight") and p.dim() >= 2]
        # MAPPO's critic on the global state: one 3-layer network per agent (share_param_critic False, a
        # ModuleList), each with its output layer; on the observations: one stacked over the agents
        assert len(weights) == (3 * len(agents) if global_state and module is not actor else 3)
        for index, weight in enumerate(weights):
            gain = output_gain if index % 3 == 2 else 2 ** 0.5
            matrix = weight.detach().reshape(-1, *weight.shape[-2:])[0]
            gram = matrix @ matrix.T if matrix.shape[0] <= matrix.shape[1] else matrix.T @ matrix
            torch.testing.assert_close(gram, gain ** 2 * torch.eye(gram.shape[0]), atol=1e-5, rtol=1e-5)
        assert all(not p.any() for name, p in module.named_parameters() if name.endswith("bias"))
    assert mean_actions(made).abs().max() < 0.1
    assert mean_actions(experiment(False)).abs().max() > 0.3


def test_the_orthogonal_init_option_is_refused_when_not_a_bool():
    with pytest.raises(TypeError, match="orthogonal_init"):
        benchmarl_configs.FormationMappoConfig(**{**algorithm_config("mappo").__dict__, "orthogonal_init": "yes"})


def test_the_scale_option_is_refused_when_not_a_bool():
    with pytest.raises(TypeError, match="state_independent_scale"):
        benchmarl_configs.FormationIppoConfig(**{**algorithm_config("ippo").__dict__, "state_independent_scale": 1})


def test_the_export_carries_the_observation_statistics_and_acts_as_the_experiment(normalized_experiment, tmp_path):
    from tensordict import TensorDict
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    experiment = normalized_experiment
    group = next(iter(experiment.group_map))
    actors = actors_from_experiment(experiment)
    actor = actors.groups[group]
    assert actor.observation_loc.shape == actor.observation_scale.shape == (4, actor.layer_sizes[0])
    assert np.all(actor.observation_scale > 0) and np.any(actor.observation_loc != 0)
    folder = export_benchmarl_policy(experiment, tmp_path / "actor")
    description = json.loads((folder / "actor.json").read_text())
    assert description["transforms"] == {"observation_normalization": True, "state_normalization": False,
                                         "global_state": False,
                                         "reward_scale": 1.0, "reward_normalization": True,
                                         "reward_normalization_gamma": 0.99, "observation_sets": False}
    loaded = load_benchmarl_policy(folder)
    np.testing.assert_array_equal(loaded.groups[group].observation_loc, actor.observation_loc.astype(np.float32))
    # The experiment's policy on the normalized observations = the numpy actor on the raw ones.
    raw = torch.randn(5, 4, actor.layer_sizes[0], generator=torch.Generator().manual_seed(1))
    normalized = (raw - torch.from_numpy(actor.observation_loc).float()) / torch.from_numpy(
        actor.observation_scale).float()
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        out = experiment.group_policies[group](TensorDict(
            {group: TensorDict({"observation": normalized}, batch_size=(5, 4))}, batch_size=(5,)))
    expected = out[group, "action"].numpy()
    np.testing.assert_allclose(loaded.groups[group].act(raw.numpy()), expected, atol=1e-5, rtol=0)
    policies = loaded.learned_policies()
    np.testing.assert_allclose(policies["arm_1"](raw[:, 1].numpy()[0]), np.clip(expected[0, 1], -1, 1), atol=1e-5)
    # and evaluates like the experiment itself
    assert evaluate_benchmarl_policy(folder, episodes=1) == evaluate_benchmarl_policy(experiment, episodes=1)


def test_a_malformed_exported_normalization_is_refused(normalized_experiment, tmp_path):
    folder = export_benchmarl_policy(normalized_experiment, tmp_path / "actor")
    description = json.loads((folder / "actor.json").read_text())
    group = next(iter(description["groups"]))
    description["groups"][group]["observation_normalization"]["scale"] = [[1.0]]
    (folder / "actor.json").write_text(json.dumps(description))
    with pytest.raises(ValueError, match="observation_normalization"):
        load_benchmarl_policy(folder)
