"""Hold shaping: only joint speed inside the formation is charged; leaving the formation never pays."""

from __future__ import annotations

import numpy as np
import pytest

from ee_formation_env.baselines.learned.shaping import SPEED_SCALE, HoldShapingEnv, hold_penalty_factor


def _observation_at_goal(env, agent, dq):
    layout = env.observation_layout(agent)
    observations, _ = env.reset(seed=0)
    observation = observations[agent].astype(np.float64).copy()
    for k in range(layout.n_slots):
        observation[(k + 1) * layout.slot_size - 1] = 0.0  # every edge error zero
    observation[-layout.n_joints:] = dq
    return layout, observation


def test_penalty_factor_charges_speed_only_in_formation(make_env):
    env = make_env("planar_square")
    agent = env.possible_agents[0]
    layout, still = _observation_at_goal(env, agent, [0.0, 0.0])
    assert hold_penalty_factor(layout, still) == 0.0
    _, slow = _observation_at_goal(env, agent, [0.6 * SPEED_SCALE, 0.8 * SPEED_SCALE * 0.5])
    assert hold_penalty_factor(layout, slow) == pytest.approx(np.hypot(0.6, 0.4))
    _, fast = _observation_at_goal(env, agent, [5.0, 0.0])
    assert hold_penalty_factor(layout, fast) == 1.0
    out_of_formation = fast.copy()
    out_of_formation[layout.slot_size - 1] = 1.0  # m^2: far beyond one tolerance (0.06 m^2 on a 3 m edge)
    assert hold_penalty_factor(layout, out_of_formation) == 0.0


def test_shaped_rewards_are_the_envs_outside_the_formation(make_env):
    plain, shaped = make_env("planar_square"), HoldShapingEnv(make_env("planar_square"), 0.5)
    plain.reset(seed=2)
    shaped.reset(seed=2)
    for _ in range(5):  # the start is ~40 tolerances away: nothing is charged
        actions = {agent: np.full(2, 0.2, dtype=np.float32) for agent in plain.possible_agents}
        _, rewards, *_ = plain.step(actions)
        _, shaped_rewards, *_ = shaped.step(actions)
        assert shaped_rewards == rewards
    with pytest.raises(ValueError, match="hold_penalty"):
        HoldShapingEnv(make_env("planar_square"), 1.5)
