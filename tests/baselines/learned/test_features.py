"""Observation features: computed from the agent's own observation, the same in training and evaluation."""

from __future__ import annotations

import numpy as np
import pytest

import ee_formation_env

from ee_formation_env.baselines.learned.features import (FEATURE_SETS, FeatureRows, feature_size, log_error_features,
                                                         transform_stack)
from ee_formation_env.baselines.learned.options import TrainingOptions
from ee_formation_env.baselines.learned.policy import ComposedPolicy
from ee_formation_env.baselines.learned.torque import TorqueRows
from ee_formation_env.baselines.learned.training_env import BatchedTrainingEnv, ParallelTrainingEnv

# Torque mode with features and nothing else: the env's actions and rewards.
FEATURED = TrainingOptions(mode="torque", obs_features="log-error", hold_penalty=0.0)


def transform(layout, features):
    """One observation's transform: the one-row case of the stack's."""
    return lambda observation: transform_stack(layout, features)(np.asarray(observation)[None])[0]


def test_feature_env_appends_the_transform_of_each_agents_own_observation(make_env, closer):
    plain, wrapped = make_env("planar_square"), closer(ParallelTrainingEnv("planar_square", None, FEATURED))
    observations, _ = plain.reset(seed=3)
    featured, _ = wrapped.reset(seed=3)
    for _ in range(3):
        for agent in plain.possible_agents:
            layout = plain.observation_layout(agent)
            raw = observations[agent]
            assert featured[agent].shape == wrapped.observation_space(agent).shape
            assert featured[agent].shape == (layout.size + feature_size(layout, "log-error"),)
            np.testing.assert_array_equal(featured[agent][:layout.size], raw)
            np.testing.assert_array_equal(featured[agent], transform(layout, "log-error")(raw))
            assert wrapped.observation_space(agent).contains(featured[agent])
        actions = {agent: np.full(2, 0.1, dtype=np.float32) for agent in plain.possible_agents}
        observations, rewards, *_ = plain.step(actions)
        featured, featured_rewards, *_ = wrapped.step(actions)
        assert rewards == featured_rewards  # the env's reward, unchanged


def test_features_resolve_the_error_in_tolerances_and_point_downhill(make_env):
    env = make_env("planar_square")
    layout = env.observation_layout(env.possible_agents[0])
    observation, _ = env.reset(seed=0)
    raw = observation[env.possible_agents[0]].astype(np.float64)
    parts = layout.split(raw)
    n_errors = layout.n_slots * layout.error_width
    # At the goal (every edge error zero): error and direction features vanish.
    at_goal = raw.copy()
    at_goal[[k * layout.slot_size + layout.slot_size - 1 for k in range(layout.n_slots)]] = 0.0
    features = log_error_features(layout, at_goal)
    assert np.all(features[:n_errors + layout.dim] == 0.0)
    # One edge 1 cm too long (one tolerance): log1p(1); the direction pulls the end-effector toward that neighbour.
    one_long = at_goal.copy()
    d = parts.desired[0, 0]
    one_long[layout.slot_size - 1] = 2 * d * 0.01
    features = log_error_features(layout, one_long)
    assert features[0] == pytest.approx(np.log1p(1.0))
    direction = features[n_errors:n_errors + layout.dim]
    toward = -parts.relative_positions[0] / np.linalg.norm(parts.relative_positions[0])
    np.testing.assert_allclose(direction, toward * np.log1p(1.0), atol=1e-12)
    # "none" appends nothing.
    stack = raw[None]
    assert feature_size(layout, "none") == 0 and transform_stack(layout, "none")(stack) is stack
    assert FeatureRows([layout], ["none"])(stack) is stack


def test_feature_policy_sees_what_training_saw(make_env):
    env = make_env("planar_square")
    agent = env.possible_agents[0]
    layout = env.observation_layout(agent)
    seen = []

    class Recorder:
        def reset(self) -> None:
            pass

        def __call__(self, observation):
            seen.append(observation)
            return np.zeros(2)

    policy = ComposedPolicy(Recorder(), layout, "log-error", TorqueRows([None]))
    observations, _ = env.reset(seed=1)
    policy(observations[agent])
    training_env = ParallelTrainingEnv("planar_square", {"episode_seconds": 0.3}, FEATURED)
    try:
        featured, _ = training_env.reset(seed=1)
        np.testing.assert_array_equal(seen[0], featured[agent])
    finally:
        training_env.close()


def test_unknown_feature_set_is_rejected(make_env):
    assert FEATURE_SETS == ("none", "log-error", "invariant")
    with pytest.raises(ValueError, match="obs_features"):
        TrainingOptions(obs_features="squared")
    with pytest.raises(ValueError, match="obs_features"):
        FeatureRows([make_env("planar_square").observation_layout("arm_0")], ["squared"])


@pytest.mark.parametrize("scenario, rotated", [
    ("planar_square", "planar_square_rotated"),
    ("planar_square_displacement", "planar_square_displacement_rotated"),
])
def test_invariant_features_do_not_see_the_base_yaw(closer, scenario, rotated):
    """The same physical start on yawed bases: raw observations differ, invariant ones agree (float32 rounding)."""
    from ee_formation_env.scenario_sets import held_out_scenarios

    plain = closer(ee_formation_env.parallel_env(scenario, initial_q_noise=0.0))
    turned = closer(ee_formation_env.parallel_env(held_out_scenarios(scenario)[rotated], initial_q_noise=0.0))
    first, _ = plain.reset(seed=0)
    second, _ = turned.reset(seed=0)
    for agent in plain.possible_agents:
        layout = plain.observation_layout(agent)
        assert np.abs(first[agent] - second[agent]).max() > 0.5  # the raw inputs do see it
        a, b = (transform(layout, "invariant")(obs[agent]) for obs in (first, second))
        assert a.shape == (layout.size + feature_size(layout, "invariant"),)
        assert np.allclose(a, b, atol=1e-5), agent
        assert a[layout.size - 2 * layout.n_joints] == 0.0  # q_1 is not an input


def test_invariant_features_need_a_first_joint_about_the_base_z_axis(closer):
    from ee_formation_env.baselines.learned.features import check_invariant_arms

    check_invariant_arms(closer(ee_formation_env.parallel_env("planar_square")).task)
    with pytest.raises(ValueError, match="obs_features: 'invariant' needs arms whose first joint turns about their "
                                         "base z axis; arms\\[0\\] joint 'joint_1'"):
        check_invariant_arms(closer(ee_formation_env.parallel_env("spatial_tetrahedron")).task)
    with pytest.raises(ValueError, match="obs_features: 'invariant'"):
        BatchedTrainingEnv("spatial_tetrahedron", options=TrainingOptions(obs_features="invariant"))
