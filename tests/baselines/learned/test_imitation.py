"""Demonstrations of a reference controller (DAgger's data)."""

from __future__ import annotations

import numpy as np
import pytest

from ee_formation_env import baselines
from ee_formation_env.baselines.reference.team import PolicyTeam
from ee_formation_env.baselines.learned.imitation import demonstrations


def test_labels_are_the_references_clipped_actions_where_the_reference_drives(make_env):
    env = make_env("planar_square", episode_seconds=0.2)
    observations, labels = demonstrations(env, "adaptive_jacobian", 2, np.array([3, 4]))
    assert observations.shape == (2 * 20 * 4, env.observation_space("arm_0").shape[0])
    assert labels.shape == (2 * 20 * 4, 2) and np.all(np.abs(labels) <= 1.0)
    team = PolicyTeam(baselines.make_policies("adaptive_jacobian", env))  # replay the first episode
    replayed, _ = env.reset(seed=3)
    team.reset()
    for step in range(20):
        actions = team(replayed)
        rows = slice(4 * step, 4 * step + 4)
        np.testing.assert_array_equal(observations[rows], np.stack([replayed[a] for a in env.possible_agents]))
        np.testing.assert_array_equal(labels[rows], np.clip(np.stack([actions[a] for a in env.possible_agents]), -1, 1))
        replayed, *_ = env.step(actions)


def test_a_learner_share_of_one_lets_the_learner_drive(make_env):
    env = make_env("planar_square", episode_seconds=0.1)
    still = lambda stacked: np.zeros((len(stacked), 2))  # noqa: E731
    driven, _ = demonstrations(env, "gradient", 1, np.array([0]), learner=still, learner_share=1.0)
    zero = baselines.make_policies("zero", env)
    observations, _ = env.reset(seed=0)
    for step in range(10):
        np.testing.assert_array_equal(driven[4 * step:4 * step + 4],
                                      np.stack([observations[a] for a in env.possible_agents]))
        observations, *_ = env.step({a: zero[a](observations[a]) for a in env.possible_agents})


@pytest.mark.parametrize("kwargs, match", [
    (dict(reference="zero"), "reference"),
    (dict(episodes=0), "episodes"),
    (dict(episodes=3), "episodes"),  # more episodes than seeds
    (dict(learner_share=1.5), "learner_share"),
    (dict(learner_share=0.5), "learner"),
])
def test_bad_arguments_are_refused(make_env, kwargs, match):
    env = make_env("planar_square", episode_seconds=0.1)
    arguments = dict(env=env, reference="gradient", episodes=2, seeds=np.array([0, 1]))
    arguments.update(kwargs)
    with pytest.raises(ValueError, match=match):
        demonstrations(**arguments)
