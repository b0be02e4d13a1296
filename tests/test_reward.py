"""The reward: its formula, its shape, and that solving pays far more than doing nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ee_formation_env import baselines
from ee_formation_env.baselines.metrics import formation_tolerance, run_episode
from ee_formation_env.reward import RewardConfig, agent_error_ratios, edge_tolerances, rewards_from_ratios


def test_edge_tolerances_are_the_first_order_edge_length_accuracy():
    lengths = np.array([3.0, 3.0 * math.sqrt(2.0)])
    tolerances = edge_tolerances("distance", lengths, 0.01)
    # |z|^2 - d^2 for an edge 1 cm too long, to first order in the 1 cm
    exact = (lengths + 0.01) ** 2 - lengths**2
    np.testing.assert_allclose(tolerances, exact, rtol=0.01)
    np.testing.assert_array_equal(edge_tolerances("displacement", lengths, 0.01), [0.01, 0.01])
    with pytest.raises(ValueError, match="kind"):
        edge_tolerances("bearing", lengths, 0.01)


def test_ratios_and_within_flags_per_agent():
    # 3 agents on a path 0-1-2: edges (0, 1) and (1, 2); agent 1 has both.
    slot_edges = np.array([0, 0, 1, 1])
    slot_starts = np.array([0, 1, 3])
    degrees = np.array([1.0, 2.0, 1.0])
    ratios, within = agent_error_ratios(np.array([0.5, 3.0]), np.array([1.0, 2.0]), slot_edges, slot_starts, degrees)
    np.testing.assert_allclose(ratios, [0.5, (0.5 + 1.5) / 2, 1.5])
    np.testing.assert_array_equal(within, [True, False, False])


def test_reward_rises_over_the_whole_error_range_and_is_steepest_near_the_goal():
    config = RewardConfig()
    ratios = np.array([0.0, 0.5, 1.0, 10.0, 40.0, 99.0, 1e4])
    rewards = rewards_from_ratios(ratios, np.zeros(len(ratios), dtype=bool), config)
    assert rewards[0] == pytest.approx(1.0)
    assert rewards[-1] == 0.0 and np.all(rewards >= 0)
    assert np.all(np.diff(rewards[:-1]) < 0)  # strictly better all the way to 100 tolerances
    slopes = -np.diff(rewards[:-1]) / np.diff(ratios[:-1])
    assert np.all(np.diff(slopes) < 0)  # steepest near the goal
    bonus = rewards_from_ratios(np.array([0.5]), np.array([True]), config)
    assert bonus[0] == pytest.approx(rewards[1] + config.in_tolerance)
    team = rewards_from_ratios(ratios, np.zeros(len(ratios), dtype=bool), RewardConfig(team=True))
    np.testing.assert_allclose(team, np.full(len(ratios), rewards.mean()))
    with pytest.raises(ValueError, match="error_floor"):
        RewardConfig(error_floor=100.0, error_ceiling=10.0)


@pytest.mark.parametrize("formation", ["planar_square", "planar_square_displacement"])
def test_env_reward_is_the_reward_module_of_its_edge_errors(make_env, formation):
    env = make_env(formation, episode_seconds=1.0)
    env.reset(seed=2)
    rng = np.random.default_rng(2)
    for _ in range(3):
        _, rewards, *_ = env.step({a: rng.uniform(-1, 1, env.action_space(a).shape) for a in env.agents})
    config = env.scenario.reward
    edges = env.scenario.edges
    lengths = np.linalg.norm(np.asarray(env.formation.desired, dtype=np.float64).reshape(len(edges), -1), axis=1)
    tolerances = edge_tolerances(env.formation.kind, lengths, config.position_tolerance)
    abs_errors = np.linalg.norm(env.edge_errors().reshape(len(edges), -1), axis=1)
    for i, agent in enumerate(env.possible_agents):
        incident = [k for k, (tail, head) in enumerate(edges) if i in (tail, head)]
        ratio = float(np.mean(abs_errors[incident] / tolerances[incident]))
        within = bool(np.all(abs_errors[incident] <= tolerances[incident]))
        expected = rewards_from_ratios(np.array([ratio]), np.array([within]), config)[0]
        assert rewards[agent] == pytest.approx(expected, rel=1e-9)


def test_metrics_tolerance_is_the_rms_of_the_edge_tolerances(make_env):
    env = make_env("planar_square")
    lengths = np.asarray(env.formation.desired, dtype=np.float64)
    rms = math.sqrt(np.mean(edge_tolerances("distance", lengths, 0.01) ** 2))
    assert formation_tolerance(env) == pytest.approx(rms, rel=1e-12)


def test_solving_pays_far_more_than_doing_nothing(make_env):
    """Over 10 s of planar_square: (R_ref - R_zero) / (|R_ref| + |R_zero|) >= 0.5 for adaptive_jacobian."""
    env = make_env("planar_square", episode_seconds=10.0)
    solved = run_episode(env, baselines.make_policies("adaptive_jacobian", env), seed=0)
    idle = run_episode(env, baselines.make_policies("zero", env), seed=0)
    assert solved.success and not idle.success
    gap = (solved.mean_return - idle.mean_return) / (abs(solved.mean_return) + abs(idle.mean_return))
    assert gap >= 0.5, (solved.mean_return, idle.mean_return)
