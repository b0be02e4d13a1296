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


@pytest.mark.parametrize("team", ["planar_square", "mixed"])
def test_benchmarl_mappo_trains_two_iterations(tmp_path, team):
    """A homogeneous team (one group) and a mixed one (one group, so one shared policy, per robot kind)."""
    from benchmarl.algorithms import MappoConfig
    from benchmarl.experiment import Experiment
    from benchmarl.models.mlp import MlpConfig

    from conftest import tiny_benchmarl_config
    from ee_formation_env.integrations.benchmarl import EEFormationTask

    config = tiny_benchmarl_config(tmp_path)
    task = EEFormationTask.PLANAR_SQUARE.get_task(
        {"episode_seconds": 0.1, **({"scenario": MIXED, "torque_limits": 5.0} if team == "mixed" else {})})
    experiment = Experiment(task=task, algorithm_config=MappoConfig.get_from_yaml(),
                            model_config=MlpConfig.get_from_yaml(), critic_model_config=MlpConfig.get_from_yaml(),
                            seed=0, config=config)
    experiment.run()
    assert experiment.n_iters_performed == 2
    assert experiment.total_frames == 80
    groups = {"planar_square": ["planar_2link"], "mixed": ["lbr_iiwa", "panda"]}[team]
    assert sorted(experiment.group_map) == groups and sorted(experiment.losses) == groups  # a policy per group


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


# ---------------------------------------------------------------------------------------------- batched (num_envs)
MIXED_SPATIAL = {  # two KUKA iiwa (pybullet_data) and the built-in pera_arm: two groups of one 3D team
    "arms": [dict(KUKA, base_position=[0.0, 0.0, 0.0]), {"robot": "pera_arm", "base_position": [1.0, 0.0, 1.0]},
             dict(KUKA, base_position=[0.5, 0.9, 0.0])],
    "edges": [[0, 1], [1, 2], [0, 2]], "shape": [[0.4, 0.2, 0.6], [0.9, 0.2, 0.6], [0.65, 0.6, 0.6]],
    "formation": "displacement", "dim": 3, "episode_seconds": 0.1, "arm_collisions": False,
}


def _action_steps(env, steps, seed):
    """Fixed random actions per step: group -> (steps, K, n, n_joints) in [-1, 1] (a bit beyond, to clip)."""
    import torch

    generator = torch.Generator().manual_seed(seed)
    return {group: 1.2 * (2 * torch.rand((steps, *env.full_action_spec[group, "action"].shape),
                                          generator=generator) - 1) for group in env.group_map}


@pytest.mark.parametrize("scenario", ["planar_square", "spatial_tetrahedron"])
def test_batched_env_passes_check_env_specs(scenario):
    env = make_torchrl_env(scenario, num_envs=3, seed=0, episode_seconds=0.05)
    try:
        assert env.batch_size == (3,)
        group = next(iter(env.group_map))
        check_env_specs(env)
        m = env.vector_env.scenario.max_steps
        rollout = env.rollout(m + 3, break_when_any_done=False)  # through an episode end
        assert rollout[group, "observation"].shape[:3] == (3, m + 3, 4)
        assert rollout["next", group, "reward"].shape == (3, m + 3, 4, 1)
        assert rollout["next", group, "done"].shape == (3, m + 3, 4, 1)
        assert rollout["next", "done"].shape == (3, m + 3, 1)
        assert rollout["next", "truncated"][:, m - 1].all() and not rollout["next", "done"][:, :m - 1].any()
    finally:
        env.close()


@pytest.mark.parametrize("scenario", [{}, MIXED_SPATIAL])
def test_batched_copy_k_is_the_single_env_seeded_s_plus_k_through_resets(scenario):
    """Copy k under TorchRL's step_and_maybe_reset (resets through the _reset mask) replays parallel_env
    reset with seed s + k, then reset() without a seed at each episode end: observations and rewards."""
    import numpy as np

    import ee_formation_env

    spec = scenario or "planar_square"
    overrides = {} if scenario else {"episode_seconds": 0.05}
    K, steps, seed = 3, 13, 7  # episodes of 5 steps: two resets inside
    env = make_torchrl_env(spec, num_envs=K, seed=seed, **overrides)
    try:
        actions = _action_steps(env, steps, 1)
        td = env.reset()
        first = {group: td[group, "observation"].clone() for group in env.group_map}
        records = []
        for t in range(steps):
            for group in env.group_map:
                td[group, "action"] = actions[group][t]
            out, td = env.step_and_maybe_reset(td)
            records.append((out["next"].clone(), td.clone()))
        for k in range(K):
            with ee_formation_env.parallel_env(spec, **overrides) as single:
                observations, _ = single.reset(seed=seed + k)
                for group, members in env.group_map.items():
                    for j, agent in enumerate(members):
                        np.testing.assert_array_equal(first[group][k, j].numpy(), observations[agent])
                for t, (after, following) in enumerate(records):
                    step_actions = {agent: actions[group][t, k, j].numpy() for group, members in env.group_map.items()
                                    for j, agent in enumerate(members)}
                    observations, rewards, terminations, truncations, _ = single.step(step_actions)
                    ended = any(terminations.values()) or any(truncations.values())
                    assert bool(after["done"][k]) == ended
                    for group, members in env.group_map.items():
                        for j, agent in enumerate(members):
                            np.testing.assert_array_equal(after[group, "observation"][k, j].numpy(),
                                                          observations[agent])
                            assert float(after[group, "reward"][k, j]) == np.float32(rewards[agent])
                    if ended:
                        observations, _ = single.reset()
                        for group, members in env.group_map.items():
                            for j, agent in enumerate(members):
                                np.testing.assert_array_equal(following[group, "observation"][k, j].numpy(),
                                                              observations[agent])
                assert t == steps - 1
    finally:
        env.close()


def test_batched_partial_reset_resets_only_the_masked_copies():
    """env.reset(td) with td["_reset"] (K, 1) or (group, "_reset") (K, n, 1): the masked copies start their
    next episode (the single env's reset() after reset(seed)), the others step on undisturbed."""
    import numpy as np
    import torch

    import ee_formation_env

    K, seed, group = 4, 3, "planar_2link"
    env = make_torchrl_env("planar_square", num_envs=K, seed=seed)
    singles = [ee_formation_env.parallel_env("planar_square") for _ in range(K)]
    try:
        for k, single in enumerate(singles):
            single.reset(seed=seed + k)
        actions = _action_steps(env, 5, 2)

        def step(td, t):
            td[group, "action"] = actions[group][t]
            td = env.step(td)["next"]
            for k, single in enumerate(singles):
                observations, *_ = single.step({a: actions[group][t, k, j].numpy()
                                                for j, a in enumerate(env.group_map[group])})
                for j, agent in enumerate(env.group_map[group]):
                    np.testing.assert_array_equal(td[group, "observation"][k, j].numpy(), observations[agent])
            return td

        td = env.reset()
        for t in range(3):
            td = step(td, t)
        for t, reset_key, mask in ((3, "_reset", [True, False, True, False]),
                                   (4, (group, "_reset"), [False, True, False, False])):
            mask = torch.tensor(mask)
            td.set(reset_key, mask.view(K, 1, 1).expand(K, 4, 1) if isinstance(reset_key, tuple) else mask.view(K, 1))
            td = env.reset(td)
            assert not td["done"].any()
            for k, single in enumerate(singles):
                if mask[k]:
                    observations, _ = single.reset()
                    for j, agent in enumerate(env.group_map[group]):
                        np.testing.assert_array_equal(td[group, "observation"][k, j].numpy(), observations[agent])
            td = step(td, t)  # every copy, reset or not, steps on as its single env
    finally:
        env.close()
        for single in singles:
            single.close()


def test_batched_mixed_robots_one_group_per_robot_kind():
    env = make_torchrl_env(MIXED_SPATIAL, num_envs=2, seed=0)
    try:
        assert env.group_map == {"lbr_iiwa": ["arm_0", "arm_2"], "pera_arm": ["arm_1"]}
        assert env.full_action_spec["lbr_iiwa", "action"].shape == (2, 2, 7)
        assert env.full_action_spec["pera_arm", "action"].shape == (2, 1, 7)
        check_env_specs(env)
    finally:
        env.close()


def test_without_num_envs_it_is_the_pettingzoo_wrapper():
    from torchrl.envs.libs.pettingzoo import PettingZooWrapper

    env = make_torchrl_env("planar_square", seed=0)
    try:
        assert isinstance(env, PettingZooWrapper) and env.batch_size == ()
    finally:
        env.close()


def test_the_docs_benchmarl_snippet_runs_as_written(tmp_path, monkeypatch):
    """docs/training.md's MAPPO snippet, exactly as on the page, with its documented budget knob
    MAX_N_FRAMES at one batch (8,000 frames; csv logs into a temporary folder)."""
    import re
    from pathlib import Path

    page = (Path(__file__).resolve().parents[2] / "docs" / "training.md").read_text(encoding="utf-8")
    blocks = [b for b in re.findall(r"```python\n(.*?)```", page, flags=re.S) if "MAX_N_FRAMES" in b]
    assert len(blocks) == 1, "docs/training.md: expected one BenchMARL snippet using MAX_N_FRAMES"
    monkeypatch.setenv("MAX_N_FRAMES", "8000")
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "__main__"}  # as a script run as written: its main guard lets it train
    exec(compile(blocks[0], "docs/training.md (BenchMARL snippet)", "exec"), namespace)
    assert namespace["config"].loggers == ["csv"]
    assert list(tmp_path.rglob("*.csv")) or list(tmp_path.iterdir())


def test_from_batched_wraps_a_built_batched_env_as_a_scenario_name_does():
    """BatchedTorchRLEnv.from_batched(vector_env(S, K)) and make_torchrl_env(batched_env=...) step exactly as
    make_torchrl_env(S, num_envs=K), through an episode end; overrides beside a built env, a wrong num_envs and
    an env without the array API are refused, naming what is wrong."""
    import ee_formation_env
    from ee_formation_env.integrations.torchrl import BatchedTorchRLEnv

    K, seed, steps = 2, 4, 7
    named = make_torchrl_env("planar_square", num_envs=K, seed=seed, episode_seconds=0.05)
    wrapped = [BatchedTorchRLEnv.from_batched(ee_formation_env.vector_env("planar_square", num_envs=K,
                                                                          episode_seconds=0.05), seed=seed),
               make_torchrl_env(batched_env=ee_formation_env.vector_env("planar_square", num_envs=K,
                                                                        episode_seconds=0.05), seed=seed)]
    try:
        actions = _action_steps(named, steps, 3)
        tds = [env.reset() for env in (named, *wrapped)]
        for t in range(steps):
            outs = []
            for i, env in enumerate((named, *wrapped)):
                tds[i]["planar_2link", "action"] = actions["planar_2link"][t]
                out, tds[i] = env.step_and_maybe_reset(tds[i])
                outs.append(out)
            for out in outs[1:]:
                assert (out == outs[0]).all()
        with pytest.raises(ValueError, match="overrides"):
            make_torchrl_env(batched_env=wrapped[0].vector_env, episode_seconds=1.0)
        with pytest.raises(ValueError, match="num_envs"):
            make_torchrl_env(batched_env=wrapped[0].vector_env, num_envs=K + 1)
        with pytest.raises(TypeError, match="step_arrays"):
            BatchedTorchRLEnv.from_batched(ee_formation_env.parallel_env("planar_square"))
    finally:
        for env in (named, *wrapped):
            env.close()


def test_the_team_env_carries_a_mask_of_each_copys_team():
    import warnings

    import numpy as np

    import ee_formation_env

    with warnings.catch_warnings():  # the ring-and-chords graphs are rigid but not minimally so
        warnings.simplefilter("ignore", UserWarning)
        team = ee_formation_env.team_vector_env("planar_team", num_envs=3, max_cycles=4)
        env = make_torchrl_env(batched_env=team, seed=0)
        try:
            assert env.group_map == {"planar_2link": [f"arm_{i}" for i in range(8)]}
            check_env_specs(env)
            rollout = env.rollout(10, break_when_any_done=False)  # through two autoresets per copy
            mask = rollout["next", "planar_2link", "mask"].numpy()  # (3, 10, 8)
            sizes = mask.sum(-1)
            assert set(np.unique(sizes)) <= set(range(3, 9)) and len(np.unique(sizes)) > 1
            assert (mask == (np.arange(8) < sizes[..., None])).all()  # the first N agents of each episode
            rewards = rollout["next", "planar_2link", "reward"].numpy()[..., 0]
            observations = rollout["next", "planar_2link", "observation"].numpy()
            assert not rewards[~mask].any() and not observations[~mask].any()  # absent agents: zeros
            done = rollout["next", "done"].numpy()[..., 0]
            carried = rollout["planar_2link", "mask"].numpy()[:, 1:] == mask[:, :-1]  # to the next step's input
            assert carried[~done[:, :-1]].all() and not carried[done[:, :-1]].all()  # a new team after an end
        finally:
            env.close()
