"""The centralized single-agent Gymnasium view: check_env, joint observation/action and episode ends."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import ee_formation_env
from ee_formation_env.integrations.centralized import CentralizedFormationEnv

IDS = ["EEFormation/PlanarSquare-v0", "EEFormation/SpatialTetrahedron-v0"]


@pytest.mark.parametrize("gym_id", IDS)
def test_check_env(closer, gym_id):
    # Short episodes; the render check with default arguments is in test_checkers.py, rgb_array below.
    env = closer(gymnasium.make(gym_id, episode_seconds=0.2))
    check_env(env.unwrapped, skip_render_check=True)


@pytest.mark.parametrize("gym_id", IDS)
def test_rgb_array_render(closer, gym_id):
    env = closer(gymnasium.make(gym_id, episode_seconds=0.2, render_mode="rgb_array"))
    assert env.unwrapped.render_mode == "rgb_array"
    env.reset(seed=0)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) >= 10
    red = (frame[..., 0] >= 200) & (frame[..., 1] <= 60) & (frame[..., 2] <= 60)
    assert red.sum() >= 50


@pytest.mark.parametrize("scenario", ["planar_square", "spatial_tetrahedron_displacement"])
def test_joint_view_matches_parallel_env(closer, scenario):
    central = closer(CentralizedFormationEnv(scenario, episode_seconds=0.1))
    parallel = closer(ee_formation_env.parallel_env(scenario, episode_seconds=0.1))
    agents = parallel.possible_agents
    obs, info = central.reset(seed=3)
    observations, infos = parallel.reset(seed=3)
    assert obs.dtype == np.float32
    assert np.array_equal(obs, np.concatenate([observations[a] for a in agents]))
    assert info["formation_error"] == infos["arm_0"]["formation_error"]
    assert info["agents"].keys() == infos.keys()
    sizes = [parallel.action_space(a).shape[0] for a in agents]
    assert central.action_space.shape == (sum(sizes),)
    rng = np.random.default_rng(0)
    steps = 0
    while True:
        action = central.action_space.sample() if steps else rng.uniform(-2, 2, central.action_space.shape)
        obs, reward, terminated, truncated, info = central.step(action)
        pieces = np.split(np.asarray(action, np.float64), np.cumsum(sizes)[:-1])
        observations, rewards, terminations, truncations, infos = parallel.step(dict(zip(agents, pieces)))
        steps += 1
        assert np.array_equal(obs, np.concatenate([observations[a] for a in agents]))
        assert reward == pytest.approx(np.mean([rewards[a] for a in agents]), rel=1e-12)
        assert terminated == any(terminations.values()) and truncated == any(truncations.values())
        assert [info["agents"][a]["clipped_actions"] for a in agents] == [infos[a]["clipped_actions"] for a in agents]
        if terminated or truncated:
            break
    assert truncated and not terminated
    assert steps == parallel.scenario.max_steps


def test_a_joint_action_of_the_wrong_shape_names_the_full_joint_shape_and_a_bad_value_its_agent(closer):
    central = closer(CentralizedFormationEnv("planar_square", episode_seconds=0.1))
    central.reset(seed=0)
    with pytest.raises(ValueError, match=r"^action: expected the joint action of shape \(8,\) \(every agent's "
                                         r"joints in agent order\), got shape \(7,\)"):
        central.step(np.zeros(7))
    with pytest.raises(ValueError, match=r"got shape \(2, 4\)"):
        central.step(np.zeros((2, 4)))
    with pytest.raises(ValueError, match="arm_1"):
        central.step(np.array([0, 0, np.nan, 0, 0, 0, 0, 0]))
    obs, *_ = central.step(np.zeros(8))
    assert central.observation_space.contains(obs)


def test_close_disconnects(closer):
    central = CentralizedFormationEnv("planar_square", episode_seconds=0.1)
    central.close()
    assert not central.parallel_env.world.connected
    central.close()

