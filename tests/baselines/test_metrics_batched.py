"""``run_episodes``: K seeded episodes at once on the batched env give, field for field, the metrics of the
one-episode loop ``run_episode`` (reference controllers batched across copies as one team; learned policies
in ``tests/baselines/learned/test_run.py``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

import ee_formation_env
from ee_formation_env import baselines
from ee_formation_env.baselines.metrics import (EpisodeMetrics, evaluation_env, run_episode, run_episodes,
                                                stack_policies)


def one_by_one(scenario, name, seeds, **overrides) -> list[EpisodeMetrics]:
    with ee_formation_env.parallel_env(scenario, **overrides) as env:
        policies = baselines.make_policies(name, env)
        return [run_episode(env, policies, seed=seed) for seed in seeds]


def assert_same(expected: list[EpisodeMetrics], got: list[EpisodeMetrics]) -> None:
    assert len(expected) == len(got)
    for one, batched in zip(expected, got):
        a, b = one.as_dict(), batched.as_dict()
        assert a.keys() == b.keys()
        for key in a:
            same = a[key] == b[key] or (isinstance(a[key], float) and math.isnan(a[key]) and math.isnan(b[key]))
            assert same and type(a[key]) is type(b[key]), (key, a[key], b[key])


@pytest.mark.parametrize("scenario, seconds", [("planar_square", 1.5), ("spatial_tetrahedron", 0.6)])
@pytest.mark.parametrize("name", ["adaptive_jacobian", "gradient", "random"])
def test_batched_episodes_equal_the_one_episode_loop(scenario, seconds, name):
    seeds = [4, 0, 7, 1]  # out of order and not consecutive
    assert_same(one_by_one(scenario, name, seeds, episode_seconds=seconds),
                run_episodes(scenario, name, seeds, overrides={"episode_seconds": seconds}))


def test_faulting_episodes_of_different_lengths_end_on_their_own():
    """Random torques at 170 N m: every episode faults, at different steps; a copy that ended stops counting
    while the others run on (its autoreset episode is ignored)."""
    overrides = {"episode_seconds": 2.0, "torque_limits": 170}
    seeds = list(range(6))
    expected = one_by_one("planar_square", "random", seeds, **overrides)
    assert all(e.physics_fault for e in expected) and len({e.sim_time for e in expected}) > 1
    assert_same(expected, run_episodes("planar_square", "random", seeds, overrides=overrides))


def test_a_fault_in_one_copy_while_the_others_run_to_the_end():
    """A policy that kicks one arm at full torque when its first joint starts above zero: some episodes
    fault, the others are truncated."""

    class Kick:
        def __init__(self, n):
            self.n, self.kick = n, None

        def reset(self):
            self.kick = None

        def __call__(self, observation):
            if self.kick is None:
                self.kick = bool(observation[-2 * self.n] > 0)
            return np.full(self.n, 1.0 if self.kick else 0.0, dtype=np.float32)

    def kicks(env):
        return {agent: Kick(env.action_space(agent).shape[0]) if agent == env.possible_agents[0] else
                baselines.make_policy("zero", env, agent) for agent in env.possible_agents}

    overrides = {"episode_seconds": 1.0, "torque_limits": 1e4}
    seeds = list(range(8))
    with ee_formation_env.parallel_env("planar_square", **overrides) as env:
        expected = [run_episode(env, kicks(env), seed=seed) for seed in seeds]
    faults = {bool(e.physics_fault) for e in expected}
    assert faults == {True, False}
    assert_same(expected, run_episodes("planar_square", kicks, seeds, overrides=overrides))


def test_more_seeds_than_copies_run_in_rounds_and_duplicates_are_answered():
    seeds = [3, 2, 3, 5, 6]
    expected = one_by_one("planar_square", "approx_jacobian", seeds, episode_seconds=0.5)
    with evaluation_env("planar_square", 2, episode_seconds=0.5) as env:
        got = run_episodes(None, "approx_jacobian", seeds, env=env)
    assert_same(expected, got)
    assert run_episodes("planar_square", "zero", []) == []


def test_stacked_controllers_give_each_row_its_own_action():
    with ee_formation_env.parallel_env("spatial_tetrahedron") as env:
        observations, _ = env.reset(seed=2)
        policies = baselines.make_policies("adaptive_jacobian", env)
        stack = np.stack([observations[agent] for agent in env.possible_agents])
        alone = np.stack([policies[agent](observations[agent]) for agent in env.possible_agents])
        for policy in policies.values():
            policy.reset()
        assert np.array_equal(stack_policies(list(policies.values()))(stack), alone)


def test_several_policies_share_one_batched_env_each_episode_from_a_fresh_world():
    """run_policies: every (policy, seed) episode a copy of one env, the same metrics as each policy's
    episodes run one by one, each in a fresh env (a PyBullet world that ran another episode before can
    differ once arms touch: restoreState does not clear every contact cache)."""
    from ee_formation_env.baselines.metrics import run_policies

    seeds = [2, 5]
    names = ["gradient", "zero", "random"]
    got = run_policies("spatial_tetrahedron", dict(zip(names, names)), seeds, overrides={"episode_seconds": 0.4},
                       max_copies=4)
    for name in names:
        expected = [one_by_one("spatial_tetrahedron", name, [seed], episode_seconds=0.4)[0] for seed in seeds]
        assert_same(expected, got[name])
