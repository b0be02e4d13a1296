"""TorchRL and BenchMARL load the env: specs check out, rollouts run, MAPPO trains (the ``torchrl`` extra)."""

from __future__ import annotations

import pytest

torchrl = pytest.importorskip("torchrl")
pytest.importorskip("benchmarl")

from torchrl.envs.utils import MarlGroupMapType, check_env_specs  # noqa: E402

from ee_formation_env.builtin import BUILTIN_SCENARIOS  # noqa: E402
from ee_formation_env.integrations.torchrl import group_map, make_torchrl_env  # noqa: E402

KUKA = {"urdf": "kuka_iiwa/model.urdf", "ee_link": "lbr_iiwa_link_7", "initial_q": [0.0, 0.5, 0.0, -1.2, 0.0, 0.8, 0.0]}
PANDA = {"urdf": "franka_panda/panda.urdf", "ee_link": "panda_hand", "initial_q": [0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.8]}
MIXED = {  # two KUKA iiwa and one Franka Panda (both 7 joints, different limits): two groups
    "arms": [dict(KUKA, base_position=[0.0, 0.0, 0.0]), dict(PANDA, base_position=[1.0, 0.0, 0.0]),
             dict(KUKA, base_position=[0.5, 0.9, 0.0])],
    "edges": [[0, 1], [1, 2], [0, 2]], "shape": [[0.4, 0.2, 0.6], [0.9, 0.2, 0.6], [0.65, 0.6, 0.6]],
    "formation": "displacement", "dim": 3, "episode_seconds": 0.1, "arm_collisions": False,
}


@pytest.mark.parametrize("scenario", sorted(BUILTIN_SCENARIOS))
def test_every_builtin_scenario_passes_check_env_specs_and_rolls_out(scenario):
    env = make_torchrl_env(scenario, episode_seconds=0.1, seed=0)
    try:
        assert list(env.group_map) == [next(iter(env.group_map))] and len(env.group_map[next(iter(env.group_map))]) == 4
        check_env_specs(env)
        rollout = env.rollout(20, break_when_any_done=False)  # through an episode end (10 steps at 100 Hz)
        group = next(iter(env.group_map))
        assert rollout[group, "observation"].shape[:2] == (20, 4)
        assert rollout["next", group, "info", "physics_fault"].shape == (20, 4)
        assert rollout["next", group, "info", "edge_mask"].shape[:2] == (20, 4)
    finally:
        env.close()


@pytest.mark.parametrize("grouping", [None, MarlGroupMapType.ONE_GROUP_PER_AGENT])
def test_mixed_robots_need_one_group_per_robot_kind_or_per_agent(grouping):
    env = make_torchrl_env(MIXED, group_map_type=grouping, seed=0)
    try:
        if grouping is None:
            assert env.group_map == {"lbr_iiwa": ["arm_0", "arm_2"], "panda": ["arm_1"]}
        else:
            assert env.group_map == {agent: [agent] for agent in ("arm_0", "arm_1", "arm_2")}
        check_env_specs(env)
        env.rollout(12, break_when_any_done=False)
    finally:
        env.close()


def test_group_map_of_a_homogeneous_team_is_one_group():
    import ee_formation_env

    with ee_formation_env.parallel_env("planar_square") as env:
        assert group_map(env) == {"planar_2link": ["arm_0", "arm_1", "arm_2", "arm_3"]}


def test_benchmarl_mappo_trains_two_iterations(tmp_path):
    from benchmarl.algorithms import MappoConfig
    from benchmarl.experiment import Experiment, ExperimentConfig
    from benchmarl.models.mlp import MlpConfig

    from ee_formation_env.integrations.benchmarl import EEFormationTask

    config = ExperimentConfig.get_from_yaml()
    config.max_n_iters = 2
    config.max_n_frames = None
    config.on_policy_collected_frames_per_batch = 40
    config.on_policy_n_envs_per_worker = 2
    config.on_policy_n_minibatch_iters = 1
    config.on_policy_minibatch_size = 20
    config.evaluation = False
    config.render = False
    config.loggers = []
    config.create_json = False
    config.save_folder = str(tmp_path)
    config.checkpoint_at_end = False
    task = EEFormationTask.PLANAR_SQUARE.get_task({"episode_seconds": 0.1})
    experiment = Experiment(task=task, algorithm_config=MappoConfig.get_from_yaml(),
                            model_config=MlpConfig.get_from_yaml(), critic_model_config=MlpConfig.get_from_yaml(),
                            seed=0, config=config)
    experiment.run()
    assert experiment.n_iters_performed == 2
    assert experiment.total_frames == 80


def test_benchmarl_tasks_are_the_builtin_registry():
    from benchmarl.environments.common import Task

    from ee_formation_env.integrations.benchmarl import EEFormationTask, EEFormationTaskClass

    assert [member.name for member in EEFormationTask] == [name.upper() for name in BUILTIN_SCENARIOS]
    assert [member.value for member in EEFormationTask] == list(range(1, len(BUILTIN_SCENARIOS) + 1))
    assert issubclass(EEFormationTask, Task) and EEFormationTask.env_name() == "ee_formation"
    for name in BUILTIN_SCENARIOS:
        task = EEFormationTask[name.upper()].get_task()
        assert isinstance(task, EEFormationTaskClass) and task.config == {}
        assert task._scenario_and_overrides() == (name, {})
    assert EEFormationTask.PLANAR_SQUARE.get_task({"episode_seconds": 5.0}).config == {"episode_seconds": 5.0}
