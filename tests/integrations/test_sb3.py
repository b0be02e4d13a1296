"""The SB3 adapter: truncation bootstrapping, seeding, one physics client per copy, worker processes."""

from __future__ import annotations

import functools
import os

import numpy as np
import pytest

import ee_formation_env
from conftest import mixed_team

pytest.importorskip("stable_baselines3")

from stable_baselines3 import PPO  # noqa: E402

from ee_formation_env.baselines.learned.options import TrainingOptions  # noqa: E402
from ee_formation_env.baselines.learned.training_env import BatchedTrainingEnv  # noqa: E402

# The plain torque-mode training env: no features, no shaping.
TORQUE = TrainingOptions(mode="torque", obs_features="none", hold_penalty=0.0)
from ee_formation_env.integrations.sb3 import SharedPolicyVecEnv  # noqa: E402


def _factory(**overrides):
    overrides.setdefault("episode_seconds", 0.05)  # 5 env steps at 100 Hz
    return functools.partial(BatchedTrainingEnv, "planar_square", overrides, TORQUE)


def test_a_plain_batched_env_works_as_well():
    """Any batched env factory: here the env itself, without the training modes."""
    venv = SharedPolicyVecEnv(functools.partial(ee_formation_env.vector_env, "planar_square", episode_seconds=0.05),
                              2, info_keys=("formation_error", "applied_torque", "edge_errors"))
    try:
        venv.seed(0)
        observations = venv.reset()
        single = ee_formation_env.parallel_env("planar_square", episode_seconds=0.05)
        single_observations, _ = single.reset(seed=4)  # copy 1's seed: that of slot 4
        np.testing.assert_array_equal(observations[4:], np.stack([single_observations[a] for a in single.agents]))
        actions = np.random.default_rng(1).uniform(-1, 1, (8, 2)).astype(np.float32)
        _, rewards, _, infos = venv.step(actions)
        _, single_rewards, _, _, single_infos = single.step({a: actions[4 + i] for i, a in enumerate(single.agents)})
        for i, agent in enumerate(single.agents):
            assert rewards[4 + i] == np.float32(single_rewards[agent])
            for key in ("formation_error", "applied_torque", "edge_errors"):
                np.testing.assert_array_equal(infos[4 + i][key], single_infos[agent][key])
        single.close()
    finally:
        venv.close()


def test_bad_arguments_are_refused_before_any_env_is_built():
    with pytest.raises(TypeError, match="factory: expected a callable"):
        SharedPolicyVecEnv("planar_square", 2)
    with pytest.raises(ValueError, match="n_envs: expected an integer >= 1"):
        SharedPolicyVecEnv(_factory(), 0)


def test_slots_flatten_agents_of_every_env():
    venv = SharedPolicyVecEnv(_factory(), 2, n_workers=0)
    try:
        assert venv.num_envs == 8
        observations = venv.reset()
        assert observations.shape == (8,) + venv.observation_space.shape
        assert observations.dtype == np.float32
    finally:
        venv.close()


def test_truncation_is_reported_for_bootstrapping():
    venv = SharedPolicyVecEnv(_factory(), 1, n_workers=0)
    try:
        venv.reset()
        zeros = np.zeros((venv.num_envs, 2), dtype=np.float32)
        for _ in range(4):
            _, _, dones, infos = venv.step(zeros)
            assert not dones.any()
            assert not any("TimeLimit.truncated" in info for info in infos)
        observations, _, dones, infos = venv.step(zeros)
        assert dones.all()
        for slot, info in enumerate(infos):
            assert info["TimeLimit.truncated"] is True  # SB3 bootstraps from the value of terminal_observation
            assert info["terminal_observation"].shape == venv.observation_space.shape
            # the returned observation is the first of the next episode, not the terminal one
            assert not np.array_equal(info["terminal_observation"], observations[slot])
    finally:
        venv.close()


def test_physics_fault_is_termination_not_truncation():
    venv = SharedPolicyVecEnv(_factory(torque_limits=1e5, episode_seconds=5.0), 1, n_workers=0)
    try:
        venv.reset()
        for _ in range(100):
            _, _, dones, infos = venv.step(np.ones((venv.num_envs, 2), dtype=np.float32))
            if dones.any():
                break
        assert dones.all()
        assert all(info["physics_fault"] for info in infos)
        assert all(info["TimeLimit.truncated"] is False for info in infos)
    finally:
        venv.close()


def test_seed_gives_reproducible_and_distinct_env_resets():
    def first_observations(seed):
        venv = SharedPolicyVecEnv(_factory(), 2, n_workers=0)
        try:
            venv.seed(seed)
            return venv.reset()
        finally:
            venv.close()

    a, b, c = first_observations(3), first_observations(3), first_observations(4)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert not np.array_equal(a[:4], a[4:])  # the two envs got different seeds


def test_ppo_accepts_a_seed_and_reproduces_its_first_rollout():
    """SuperSuit's ConcatVecEnv crashes on PPO(seed=...); ours seeds every env."""

    def first_rollout(seed):
        venv = SharedPolicyVecEnv(_factory(episode_seconds=0.2), 1, n_workers=0)
        model = PPO("MlpPolicy", venv, n_steps=16, batch_size=32, n_epochs=1, seed=seed, device="cpu")
        model.learn(total_timesteps=64)
        buffer = model.rollout_buffer
        result = (buffer.observations.copy(), buffer.actions.copy(), buffer.rewards.copy())
        venv.close()
        return result

    for left, right in zip(first_rollout(1), first_rollout(1)):
        np.testing.assert_array_equal(left, right)


def test_each_copy_has_its_own_physics_client_in_process():
    venv = SharedPolicyVecEnv(_factory(), 3, n_workers=0)
    try:
        batched = venv._local.env.env
        clients = [batched.world(k).client for k in range(batched.num_envs)]
        assert len(set(clients)) == 3
    finally:
        venv.close()


def test_worker_processes_build_their_own_worlds():
    venv = SharedPolicyVecEnv(_factory(), 2, n_workers=2)
    try:
        pids = venv.worker_pids()
        assert len(set(pids)) == 2 and os.getpid() not in pids
        observations = venv.reset()
        in_process = SharedPolicyVecEnv(_factory(), 2, n_workers=0)
        try:
            in_process.seed(0)
            venv.seed(0)
            np.testing.assert_array_equal(venv.reset(), in_process.reset())
            actions = np.random.default_rng(0).uniform(-1, 1, (venv.num_envs, 2)).astype(np.float32)
            for _ in range(6):  # across an auto-reset
                left, right = venv.step(actions), in_process.step(actions)
                np.testing.assert_array_equal(left[0], right[0])
                np.testing.assert_array_equal(left[1], right[1])
                np.testing.assert_array_equal(left[2], right[2])
        finally:
            in_process.close()
        assert observations.shape[0] == 8
    finally:
        venv.close()


def test_envs_in_process_beside_workers_step_as_all_in_process():
    """One copy stepped by this process while a worker steps two: the same rollout as all three in-process."""
    factory = _factory(episode_seconds=0.05)
    residual = functools.partial(BatchedTrainingEnv, "planar_square", {"episode_seconds": 0.05},
                                 TrainingOptions(mode="residual"))
    for chosen in (factory, residual):
        split = SharedPolicyVecEnv(chosen, 3, n_workers=1, in_process_envs=1)
        in_process = SharedPolicyVecEnv(chosen, 3, n_workers=0)
        try:
            assert split.n_local == 1 and split._local.count == 1 and len(split.worker_pids()) == 1
            split.seed(0)
            in_process.seed(0)
            np.testing.assert_array_equal(split.reset(), in_process.reset())
            assert split.get_attr("scenario") == in_process.get_attr("scenario")
            actions = np.random.default_rng(0).uniform(-1, 1, (split.num_envs, 2)).astype(np.float32)
            for _ in range(6):  # across an auto-reset
                left, right = split.step(actions), in_process.step(actions)
                for part in range(3):
                    np.testing.assert_array_equal(left[part], right[part])
        finally:
            split.close()
            in_process.close()


@pytest.mark.parametrize("n_workers,in_process_envs", [(1, -1), (1, 2), (1, 1.5), (0, 1)])
def test_bad_in_process_envs_are_rejected_before_any_worker_starts(n_workers, in_process_envs):
    with pytest.raises(ValueError, match=r"in_process_envs: expected an integer in \[0, 1\], and 0 without worker"):
        SharedPolicyVecEnv(_factory(), 2, n_workers=n_workers, in_process_envs=in_process_envs)


def test_worker_errors_surface_in_the_parent():
    bad = functools.partial(BatchedTrainingEnv, "planar_square", {"episode_seconds": 0.05}, TORQUE)
    venv = SharedPolicyVecEnv(bad, 1, n_workers=1)
    try:
        venv.reset()
        with pytest.raises(RuntimeError, match="worker failed"):
            venv.step(np.zeros((venv.num_envs, 3), dtype=np.float32))  # wrong action shape
    finally:
        venv.close()


def test_heterogeneous_agents_are_rejected():
    scenario = mixed_team()
    with pytest.raises(ValueError, match="parameter sharing"):
        SharedPolicyVecEnv(functools.partial(ee_formation_env.vector_env, scenario), 1, n_workers=0)


@pytest.mark.parametrize("n_workers", [0, 1])
def test_info_keys_choose_what_each_slot_info_keeps(n_workers):
    venv = SharedPolicyVecEnv(_factory(), 1, n_workers=n_workers, info_keys=("formation_error",))
    lean = SharedPolicyVecEnv(_factory(), 1, n_workers=n_workers, info_keys=())
    try:
        venv.reset()
        lean.reset()
        actions = np.zeros((venv.num_envs, 2), dtype=np.float32)
        for step in range(5):  # the fifth step ends the 5-step episode
            infos, lean_infos = venv.step(actions)[3], lean.step(actions)[3]
            ending = {"terminal_observation", "TimeLimit.truncated", "physics_fault_reason"} if step == 4 else set()
            assert all(set(info) == {"formation_error"} | ending for info in infos)
            assert all(set(info) == ending for info in lean_infos)
    finally:
        venv.close()
        lean.close()


def test_bad_info_keys_are_rejected_before_any_worker_starts():
    with pytest.raises(ValueError, match=r"info_keys: unknown info key\(s\) \['formation_eror'\]"):
        SharedPolicyVecEnv(_factory(), 1, n_workers=1, info_keys=("formation_eror",))
    with pytest.raises(TypeError, match="info_keys"):
        SharedPolicyVecEnv(_factory(), 1, n_workers=0, info_keys="formation_error")


def test_the_docs_sb3_snippet_runs_as_written():
    """docs/training.md's SharedPolicyVecEnv snippet, exactly as on the page, then one short learn."""
    import re
    from pathlib import Path

    page = (Path(__file__).resolve().parents[2] / "docs" / "training.md").read_text(encoding="utf-8")
    blocks = [b for b in re.findall(r"```python\n(.*?)```", page, flags=re.S) if "SharedPolicyVecEnv(" in b]
    assert len(blocks) == 1, "docs/training.md: expected one SharedPolicyVecEnv snippet"
    namespace: dict = {}
    exec(compile(blocks[0], "docs/training.md (SB3 snippet)", "exec"), namespace)
    venv, model = namespace["venv"], namespace["model"]
    try:
        assert venv.num_envs == 64
        model.learn(total_timesteps=64 * 64)
        assert model.num_timesteps == 64 * 64
    finally:
        venv.close()
