"""Hold shaping: only joint speed inside the formation is charged; leaving the formation never pays. Contact
shaping: every step an arm touches another arm is charged, to both arms. The training reward's error ceiling:
starts beyond the scenario's 100 tolerances earn a reward again, and only in training."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import CLOSING, two_planar_arms
from ee_formation_env.baselines.learned.options import TrainingOptions
from ee_formation_env.baselines.learned.shaping import SPEED_SCALE, hold_penalty_factors, precision_factors, shaped_rewards
from ee_formation_env.baselines.learned.training_env import BatchedTrainingEnv, ParallelTrainingEnv


def hold_penalty_factor(layout, observation):
    """One observation's factor: the one-row case of the stack's."""
    return float(hold_penalty_factors(layout, np.asarray(observation)[None])[0])


def _torque(hold_penalty=0.0, contact_penalty=0.0):
    """Torque mode with only the given shaping."""
    return TrainingOptions(mode="torque", obs_features="none", hold_penalty=hold_penalty,
                           contact_penalty=contact_penalty)


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


def test_shaped_rewards_are_the_envs_outside_the_formation(make_env, closer):
    plain, shaped = make_env("planar_square"), closer(ParallelTrainingEnv("planar_square", None, _torque(0.5)))
    plain.reset(seed=2)
    shaped.reset(seed=2)
    for _ in range(5):  # the start is ~40 tolerances away: nothing is charged
        actions = {agent: np.full(2, 0.2, dtype=np.float32) for agent in plain.possible_agents}
        _, rewards, *_ = plain.step(actions)
        _, shaped_rewards, *_ = shaped.step(actions)
        assert shaped_rewards == rewards
    with pytest.raises(ValueError, match="hold_penalty"):
        TrainingOptions(hold_penalty=1.5)


def test_contact_steps_are_charged_to_both_arms_and_only_those(make_env, closer):
    scenario = two_planar_arms()
    plain = make_env(scenario, episode_seconds=2.0)
    shaped = closer(ParallelTrainingEnv(scenario, {"episode_seconds": 2.0}, _torque(contact_penalty=2.5)))
    batched = closer(BatchedTrainingEnv(scenario, {"episode_seconds": 2.0}, _torque(contact_penalty=2.5), num_envs=1))
    plain.reset(seed=0)
    shaped.reset(seed=0)
    batched.reset_arrays(seed=[0])
    touching = 0
    for _ in range(150):  # the closing torques bring the forearms into contact and hold them there
        _, rewards, _, _, infos = plain.step(CLOSING)
        _, shaped_rewards, *_ = shaped.step(CLOSING)
        result = batched.step_arrays(np.stack([CLOSING["arm_0"], CLOSING["arm_1"]]))
        for i, agent in enumerate(plain.possible_agents):
            expected = rewards[agent] - 2.5 * (infos[agent]["contacts"] > 0)
            assert shaped_rewards[agent] == pytest.approx(expected) and result.rewards[0, i] == pytest.approx(expected)
        touching += infos["arm_0"]["contacts"] > 0 and infos["arm_1"]["contacts"] > 0
        if not plain.agents:
            break
    assert touching >= 10


@pytest.mark.parametrize("penalty", [-0.1, float("inf"), float("nan")])
def test_a_bad_contact_penalty_names_the_field(penalty):
    with pytest.raises(ValueError, match="contact_penalty: expected a finite value >= 0"):
        TrainingOptions(contact_penalty=penalty)


def test_a_wider_error_ceiling_rewards_far_starts_in_training_only():
    """planar_random's draws start beyond 100 tolerances: the scenario's reward is 0 for almost every agent, the
    widened training reward for none; the scenario the policy is evaluated on keeps its own ceiling."""
    from ee_formation_env.scenario import load_scenario

    rewards = {}
    for ceiling in (None, 1e4):
        options = TrainingOptions(mode="position", reward_error_ceiling=ceiling)
        env = BatchedTrainingEnv("planar_random", options.training_overrides(), options, num_envs=4)
        try:
            env.reset_arrays(seed=0)
            rewards[ceiling] = env.step_arrays(np.zeros((4, env.task.n_agents, 2))).rewards
            assert env.scenario.reward.error_ceiling == (100.0 if ceiling is None else ceiling)
        finally:
            env.env.close()
    assert (rewards[None] == 0).mean() > 0.75 and (rewards[1e4] > 0).all()
    assert load_scenario("planar_random").reward.error_ceiling == 100.0  # what evaluation runs on


@pytest.mark.parametrize("ceiling, error", [(1.0, ValueError), (float("nan"), ValueError), ("100", TypeError)])
def test_a_bad_reward_error_ceiling_names_the_field(ceiling, error):
    with pytest.raises(error, match="reward_error_ceiling"):
        TrainingOptions(reward_error_ceiling=ceiling)


def test_the_tracking_weight_reaches_the_training_reward_only_and_merges_with_the_ceiling():
    from ee_formation_env.scenario import load_scenario

    options = TrainingOptions(mode="position", reward_tracking=0.5, reward_error_ceiling=1e3)
    assert options.episode_overrides()["reward"] == {"error_ceiling": 1e3, "tracking": 0.5}
    env = BatchedTrainingEnv("planar_square_transport", options.training_overrides(), options, num_envs=2)
    try:
        assert (env.scenario.reward.tracking, env.scenario.reward.error_ceiling) == (0.5, 1e3)
        env.reset_arrays(seed=0)
        # before the motion starts the term is its full weight: every agent gets at least 0.5
        assert (env.step_arrays(np.zeros((2, env.task.n_agents, 2))).rewards >= 0.5).all()
    finally:
        env.env.close()
    assert load_scenario("planar_square_transport").reward.tracking == 0.0  # what evaluation runs on
    with pytest.raises(ValueError, match="reward.tracking: the tracking term needs a manoeuvre"):
        BatchedTrainingEnv("planar_square", options.training_overrides(), options, num_envs=1)


@pytest.mark.parametrize("weight, error", [(-0.1, ValueError), (float("nan"), ValueError), ("1", TypeError)])
def test_a_bad_reward_tracking_names_the_field(weight, error):
    with pytest.raises(error, match="reward_tracking"):
        TrainingOptions(reward_tracking=weight)


def test_the_precision_bonus_is_paid_only_while_every_edge_of_the_agent_is_within_its_band(make_env):
    env = make_env("planar_square")  # distance formation: a slot's error is |z|^2 - d^2 (m^2)
    agent = env.possible_agents[0]
    layout, at_goal = _observation_at_goal(env, agent, [0.0, 0.0])
    desired = layout.split(at_goal).desired[0, 0]  # m: the first slot's edge length

    def off_by(metres):  # the first edge `metres` longer than its length, the others exact
        observation = at_goal.copy()
        observation[layout.slot_size - 1] = (desired + metres) ** 2 - desired**2
        return observation

    stack = np.stack([at_goal, off_by(0.5e-3), off_by(2e-3), off_by(-2e-3)])
    assert list(precision_factors(layout, stack, 1e-3)) == [1.0, 1.0, 0.0, 0.0]
    assert list(precision_factors(layout, stack, 3e-3)) == [1.0, 1.0, 1.0, 1.0]
    rewards = np.array([[0.25, 0.5], [0.75, 1.0]])  # K = 2 copies of 2 agents: the four rows above
    rows = [(layout, np.arange(4))]
    contacts = np.zeros((2, 2))
    bonus = shaped_rewards(rewards, stack, contacts, rows, 0.0, 0.0, precision_bonus=2.0, precision_band=1e-3)
    assert bonus.tolist() == [[2.25, 2.5], [0.75, 1.0]]
    assert shaped_rewards(rewards, stack, contacts, rows, 0.0, 0.0).tolist() == rewards.tolist()  # off by default


def test_the_precision_bonus_pays_nothing_far_from_the_formation(make_env, closer):
    plain = make_env("planar_square")
    shaped = closer(ParallelTrainingEnv("planar_square", None, TrainingOptions(
        mode="torque", obs_features="none", hold_penalty=0.0, precision_bonus=5.0)))
    plain.reset(seed=2)
    shaped.reset(seed=2)
    for _ in range(3):
        actions = {agent: np.full(2, 0.2, dtype=np.float32) for agent in plain.possible_agents}
        assert shaped.step(actions)[1] == plain.step(actions)[1]


@pytest.mark.parametrize("field, value, error", [("precision_bonus", -1.0, "precision_bonus: expected a finite value >= 0"),
                                                 ("precision_band", 0.0, "precision_band: expected a length > 0 m")])
def test_a_bad_precision_setting_names_the_field(field, value, error):
    with pytest.raises(ValueError, match=error):
        TrainingOptions(**{field: value})


def test_the_precision_settings_are_set_by_name_and_have_no_flag(capsys):
    from ee_formation_env.baselines.learned.config import TrainConfig

    config = TrainConfig.from_args(["--set", "precision_bonus=0.5", "--set", "precision_band=0.002", "--no-progress"])
    assert (config.options.precision_bonus, config.options.precision_band) == (0.5, 0.002)
    assert TrainConfig().options.precision_bonus == 0.0  # off by default
    with pytest.raises(SystemExit):
        TrainConfig.from_args(["--set", "precision_bonus=-1", "--no-progress"])
    assert "precision_bonus: expected a finite value >= 0" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        TrainConfig.from_args(["--precision-bonus", "0.5"])
    assert "unrecognized arguments: --precision-bonus" in capsys.readouterr().err
