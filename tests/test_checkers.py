"""The standard checkers of Gymnasium and PettingZoo, each with its default arguments, on a headless machine."""

from __future__ import annotations

import warnings

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import api_test, max_cycles_test, parallel_api_test, seed_test

import ee_formation_env


@pytest.mark.parametrize("gym_id", ["EEFormation/PlanarSquare-v0", "EEFormation/SpatialTetrahedron-v0"])
def test_gymnasium_check_env_with_default_arguments(closer, gym_id, monkeypatch):
    # Headless as on CI: check_env also builds the declared render modes, "human" included.
    monkeypatch.delenv("DISPLAY", raising=False)
    env = closer(gymnasium.make(gym_id))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # "human" without a display simulates headless
        check_env(env.unwrapped)


def test_pettingzoo_parallel_api_test(closer):
    parallel_api_test(closer(ee_formation_env.parallel_env()))


def test_pettingzoo_api_test(closer):
    api_test(closer(ee_formation_env.env()))


def test_pettingzoo_max_cycles_test():
    max_cycles_test(ee_formation_env)


def test_pettingzoo_seed_test():
    seed_test(ee_formation_env.env)


@pytest.mark.parametrize("scenario, max_cycles", [("planar_square", 7), ("spatial_tetrahedron", 3)])
def test_max_cycles_is_the_number_of_env_steps(closer, scenario, max_cycles):
    env = closer(ee_formation_env.parallel_env(scenario, max_cycles=max_cycles))
    assert env.scenario.max_steps == max_cycles
    env.reset(seed=0)
    steps = 0
    while env.agents:
        _, _, terminations, truncations, _ = env.step({a: np.zeros(env.action_space(a).shape) for a in env.agents})
        steps += 1
    assert steps == max_cycles and all(truncations.values()) and not any(terminations.values())


@pytest.mark.parametrize("bad", [0, -1, 2.5, True, "4"])
def test_max_cycles_rejects_non_positive_integers(bad):
    with pytest.raises(ValueError, match="max_cycles"):
        ee_formation_env.parallel_env(max_cycles=bad)


def test_max_cycles_and_episode_seconds_conflict():
    with pytest.raises(ValueError, match="max_cycles"):
        ee_formation_env.parallel_env(max_cycles=4, episode_seconds=1.0)


def test_space_dicts_match_the_space_methods(closer):
    env = closer(ee_formation_env.parallel_env("spatial_tetrahedron"))
    assert list(env.observation_spaces) == env.possible_agents == list(env.action_spaces)
    for agent in env.possible_agents:
        assert env.observation_spaces[agent] is env.observation_space(agent)
        assert env.action_spaces[agent] is env.action_space(agent)
