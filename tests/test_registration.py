"""Registration of the built-in scenarios with PettingZoo and Gymnasium, and the package entry points."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings

import gymnasium
import numpy as np
import pettingzoo
import pytest
from pettingzoo.utils.env import AECEnv

import ee_formation_env
from ee_formation_env import BUILTIN_SCENARIOS, FormationEnv
from ee_formation_env.integrations.centralized import CentralizedFormationEnv
from ee_formation_env.registration import gymnasium_id, pettingzoo_id, register_all


def test_id_spelling():
    assert gymnasium_id("planar_square") == "EEFormation/PlanarSquare-v0"
    assert gymnasium_id("spatial_tetrahedron_displacement") == "EEFormation/SpatialTetrahedronDisplacement-v0"
    assert pettingzoo_id("planar_square") == "ee_formation/planar_square-v0"


@pytest.mark.parametrize("name", sorted(BUILTIN_SCENARIOS))
def test_every_builtin_is_registered(name):
    assert pettingzoo_id(name) in pettingzoo.parallel_registry
    spec = gymnasium.spec(gymnasium_id(name))
    assert spec.kwargs == {"scenario": name}
    assert spec.entry_point == "ee_formation_env.integrations.centralized:CentralizedFormationEnv"


def test_register_all_is_idempotent():
    before = (len(pettingzoo.parallel_registry), len(gymnasium.registry))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # gymnasium warns when an id is overridden
        register_all()
        register_all()
    assert (len(pettingzoo.parallel_registry), len(gymnasium.registry)) == before


@pytest.mark.parametrize("name", ["planar_square", "spatial_tetrahedron_displacement"])
def test_pettingzoo_make_parallel(closer, name):
    env = closer(pettingzoo.make("parallel", pettingzoo_id(name), episode_seconds=0.3))
    assert isinstance(env, FormationEnv)
    assert env.scenario.name == name and env.scenario.episode_seconds == 0.3
    reference = closer(ee_formation_env.parallel_env(name, episode_seconds=0.3))
    obs, _ = env.reset(seed=1)
    ref, _ = reference.reset(seed=1)
    for agent in ref:
        assert np.array_equal(obs[agent], ref[agent])


@pytest.mark.parametrize("gym_id, dim, n_actions", [("EEFormation/PlanarSquare-v0", 2, 8),
                                                    ("EEFormation/SpatialTetrahedron-v0", 3, 28)])
def test_gymnasium_make(closer, gym_id, dim, n_actions):
    env = closer(gymnasium.make(gym_id, episode_seconds=0.2))
    assert isinstance(env.unwrapped, CentralizedFormationEnv)
    assert env.unwrapped.parallel_env.scenario.episode_seconds == 0.2
    assert env.unwrapped.parallel_env.dim == dim
    assert env.action_space.shape == (n_actions,)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    assert "formation_error" in info


def test_aec_entry_points(closer):
    raw = closer(ee_formation_env.raw_env("planar_square", episode_seconds=0.1))
    assert isinstance(raw, AECEnv)
    wrapped = closer(ee_formation_env.env("planar_square", episode_seconds=0.1))
    wrapped.reset(seed=0)
    assert wrapped.agent_selection == "arm_0"
    steps = 0
    for agent in wrapped.agent_iter(max_iter=1000):
        observation, reward, termination, truncation, info = wrapped.last()
        assert wrapped.observation_space(agent).contains(observation)
        wrapped.step(None if termination or truncation else np.zeros(2, np.float32))
        steps += 1
    assert steps == 4 * 10 + 4  # 10 cycles of 4 agents, then each agent's final None step


@pytest.mark.parametrize("name", sorted(BUILTIN_SCENARIOS))
def test_gymnasium_max_episode_steps_is_the_episode_length(name):
    assert gymnasium.spec(gymnasium_id(name)).max_episode_steps == ee_formation_env.load_scenario(name).max_steps


def test_time_limit_and_env_truncate_on_the_same_step(closer):
    env = closer(gymnasium.make("EEFormation/PlanarSquare-v0", max_episode_steps=5, episode_seconds=0.05))
    env.reset(seed=0)
    for step in range(1, 6):
        _, _, terminated, truncated, _ = env.step(np.zeros(env.action_space.shape, np.float32))
        assert truncated == (step == 5) and not terminated


def test_gymnasium_make_with_module_prefix_needs_no_import():
    code = ("import gymnasium\n"
            "env = gymnasium.make('ee_formation_env:EEFormation/PlanarSquare-v0')\n"
            "print(env.spec.id, env.spec.max_episode_steps)\n"
            "env.close()\n")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                            env={**os.environ, "PYTHONPATH": root})
    assert result.returncode == 0, result.stderr
    assert result.stdout.split()[-2:] == ["EEFormation/PlanarSquare-v0", "3000"]
