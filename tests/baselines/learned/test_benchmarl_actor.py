"""A BenchMARL policy that serves any team size: the task's set observations (``observation_sets``), the
project's masked Deepsets model, its numpy export, and the exported actor acting for teams of other sizes
(the ``torchrl`` extra)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torchrl")
pytest.importorskip("benchmarl")

import torch  # noqa: E402
from torchrl.envs import TransformedEnv  # noqa: E402
from torchrl.envs.utils import check_env_specs  # noqa: E402

from ee_formation_env.baselines.learned import benchmarl_configs  # noqa: E402
from ee_formation_env.baselines.learned.benchmarl_task import (EEFormationTrainingTask, actors_from_experiment,  # noqa: E402
                                                               export_benchmarl_policy, load_benchmarl_policy)
from ee_formation_env.baselines.metrics import run_episodes  # noqa: E402
from ee_formation_env.scenario_sets import TEST_SEEDS  # noqa: E402
from ee_formation_env.team_families import team_scenario  # noqa: E402

# planar_random: 4 arms on a graph of degrees 3 and 2, so two agents have a padding slot; 5 training steps.
SETS = {"mode": "residual", "observation_sets": True, "train_episode_seconds": 0.05, "episode_seconds": 0.3}


def _task(**config):
    return EEFormationTrainingTask.PLANAR_RANDOM.get_task({**SETS, **config})


def _transformed_env(task, num_envs=2):
    base = task.get_env_fun(num_envs=num_envs, continuous_actions=True, seed=0, device="cpu")()
    return TransformedEnv(base, task.get_env_transforms(base)[0])


def test_set_observations_split_each_observation_into_its_slots_and_own_state():
    task = _task()
    layout = task.slot_layout()
    env = _transformed_env(task)
    try:
        group = next(iter(env.group_map))
        spec = env.full_observation_spec[group, "observation"]
        assert spec["neighbour_slots"].shape == (2, 4, layout.n_slots, layout.slot_size)
        assert spec["own_state"].shape == (2, 4, layout.own_size)
        check_env_specs(env)
        raw = env.base_env.reset()
        td = env.transform.forward(raw.clone())
        slots, own = td[group, "observation", "neighbour_slots"], td[group, "observation", "own_state"]
        torch.testing.assert_close(torch.cat([slots.flatten(-2), own], dim=-1), raw[group, "observation"], rtol=0, atol=0)
        assert (slots[..., 0] == 0).any()  # a padding slot: mask 0
    finally:
        env.close()


@pytest.mark.parametrize("config, field", [
    ({"observation_sets": 1}, "observation_sets"),
    ({"observation_normalization": True}, "observation_sets"),  # per-agent statistics: no transfer
])
def test_bad_set_options_are_refused_naming_the_field(config, field):
    with pytest.raises((TypeError, ValueError), match=field):
        _task(**config)


def test_a_set_task_with_features_that_mix_slots_and_own_state_is_refused_naming_the_field():
    with pytest.raises(ValueError, match="obs_features"):
        _task(obs_features="log-error")


def _experiment(save_folder, **config):
    from benchmarl.experiment import Experiment

    from conftest import tiny_benchmarl_config

    return Experiment(task=_task(**config), algorithm_config=benchmarl_configs.algorithm_config("mappo"),
                      model_config=benchmarl_configs.model_config("deepsets"),
                      critic_model_config=benchmarl_configs.model_config("mlp"), seed=0,
                      config=tiny_benchmarl_config(save_folder))


@pytest.fixture(scope="module")
def experiment(tmp_path_factory):
    """MAPPO with the masked Deepsets actor on planar_random's set observations, 2 tiny iterations."""
    experiment = _experiment(tmp_path_factory.mktemp("benchmarl_sets"))
    experiment.run()
    return experiment


def test_a_padding_slot_takes_no_part_in_the_deepsets_actor(experiment):
    group = next(iter(experiment.group_map))
    net = experiment.group_policies[group].module[0].module[0].local_deepsets[0]
    generator = torch.Generator().manual_seed(0)
    slots, own = torch.randn(5, 3, 5, generator=generator), torch.randn(5, 4, generator=generator)
    slots[..., 0] = 1.0
    padded = torch.cat([slots, torch.zeros(5, 2, 5)], dim=1)  # two padding slots (mask 0)
    with torch.no_grad():
        torch.testing.assert_close(net(padded, own), net(slots, own), rtol=0, atol=1e-6)


def test_the_exported_set_actor_acts_as_the_experiments_and_for_teams_of_any_size(experiment, tmp_path):
    group = next(iter(experiment.group_map))
    actors = load_benchmarl_policy(export_benchmarl_policy(experiment, tmp_path / "actor"))
    actor = actors.groups[group]
    assert actor.slots["masked"] and actor.slots["aggregation"] == "mean" and actor.shared
    env = _transformed_env(experiment.task, num_envs=3)
    try:
        td = env.reset()
        with torch.no_grad():
            expected = experiment.group_policies[group](td.clone())[group, "loc"].numpy()
        slots, own = td[group, "observation", "neighbour_slots"], td[group, "observation", "own_state"]
        flat = torch.cat([slots.flatten(-2), own], dim=-1).numpy()
        np.testing.assert_allclose(actor.act(flat), expected, atol=1e-6, rtol=0)  # float32 torch, float64 numpy
        np.testing.assert_allclose(actors_from_experiment(experiment).groups[group].act(flat), expected, atol=1e-6,
                                   rtol=0)
    finally:
        env.close()
    # Zero-shot at other team sizes: 3 arms (2 slots each) and 8 arms (4 slots each), the family's test draws.
    for n in (3, 8):
        (episode,) = run_episodes(team_scenario("planar_team", n), actors.policy_factory(), TEST_SEEDS[:1],
                                  overrides={"episode_seconds": 0.3})
        assert np.isfinite(episode.final_formation_error) and not episode.physics_fault
    with pytest.raises(ValueError, match="policy"):  # 7-DOF arms in 3D: other slot and own sizes
        run_episodes("spatial_tetrahedron", actors.policy_factory(), TEST_SEEDS[:1], overrides={"episode_seconds": 0.1})
