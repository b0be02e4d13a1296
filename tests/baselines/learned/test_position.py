"""Position mode: an action holds its target posture against gravity (a constant action, a constant posture),
the target is the initial configuration plus joint_reach per unit, the torque is the PD rule on the agent's own
observation, a target stays inside the joint limits and the gain is checked against the control period (the
evaluated policy applying the training env's rule: test_modes.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ee_formation_env.baselines.learned.action_scale import initial_mass_matrices
from ee_formation_env.baselines.learned.config import TrainConfig
from ee_formation_env.baselines.learned.options import TrainingOptions
from ee_formation_env.baselines.learned.policy import composed_policy_factory
from ee_formation_env.baselines.learned.position import PositionRows
from ee_formation_env.baselines.learned.training_env import BatchedTrainingEnv


def _position_env(closer, scenario, copies=2, **options):
    options = TrainingOptions(mode="position", obs_features="none", hold_penalty=0.0, **options)
    return closer(BatchedTrainingEnv(scenario, {"episode_seconds": 5.0}, options, num_envs=copies))


def test_the_mode_always_runs_with_gravity_compensation_in_training_and_evaluation(closer):
    assert TrainingOptions(mode="position").env_overrides() == {"gravity_compensation": True}
    env = _position_env(closer, "spatial_tetrahedron", copies=1)
    assert env.scenario.gravity_compensation


@pytest.mark.parametrize("scenario", ["planar_square", "spatial_tetrahedron"])
def test_a_constant_action_reaches_its_target_posture_and_holds_it_at_rest(closer, scenario):
    """Target q_0 + joint_reach * a (inside the joint limits) from a noisy start: reached within a few time
    constants (0.1 s at 10 1/s), then held at rest, no sag under gravity, no drift."""
    env = _position_env(closer, scenario, joint_reach=0.5)
    env.reset_arrays(seed=[0, 1])
    rows, joints = 2 * len(env.possible_agents), env.env.uniform_joints
    homes = np.concatenate([np.concatenate(env.task.initial_q)] * 2).reshape(rows, joints)
    lower = np.concatenate([model.lower for model in env.task.models] * 2).reshape(rows, joints)
    upper = np.concatenate([model.upper for model in env.task.models] * 2).reshape(rows, joints)
    target = np.clip(homes + 0.5 * np.random.default_rng(0).uniform(-0.6, 0.6, (rows, joints)), lower + 0.05,
                     upper - 0.05)
    action = (target - homes) / 0.5
    steps_per_second = round(1.0 / env.scenario.control_dt)
    for _ in range(steps_per_second):  # 1 s: ten time constants
        env.step_arrays(action)
    reached = env.env.joint_positions().reshape(rows, joints)
    np.testing.assert_allclose(reached, target, atol=2e-3)
    assert np.abs(env.env.joint_velocities()).max() < 1e-2
    for _ in range(2 * steps_per_second):  # 2 s more of the same action: the posture stays
        env.step_arrays(action)
    np.testing.assert_allclose(env.env.joint_positions().reshape(rows, joints), reached, atol=1e-3)


def test_the_torque_is_the_pd_rule_on_the_agents_own_observation(closer):
    env = _position_env(closer, "spatial_tetrahedron", copies=1, joint_reach=0.8, position_gain=12.0)
    result = env.reset_arrays(seed=5)
    agents = env.possible_agents
    learned = np.random.default_rng(0).uniform(-1.5, 1.5, (len(agents), env.env.uniform_joints))
    observations = result.observations.reshape(len(agents), -1)
    applied, factors = env.action_rows(observations, learned)
    masses, limits = initial_mass_matrices(env.task), env.task.torque_limits
    for i, agent in enumerate(agents):
        parts = env.observation_layout(agent).split(observations[i])
        model = env.task.models[i]
        error = np.clip(env.task.initial_q[i] + 0.8 * np.clip(learned[i], -1, 1), model.lower, model.upper) - parts.q
        expected = masses[agent] @ (144.0 * error - 24.0 * parts.dq) / limits[i]
        np.testing.assert_allclose(applied[i], expected, rtol=1e-12)
    assert factors is None  # rewards are the env's


def test_a_continuous_joints_angle_error_is_wrapped_the_short_way():
    """The rule's arithmetic on a stand-in layout: q then dq."""
    class Layout:
        def split(self, observations):
            class Parts:
                q = observations[..., :2]
                dq = observations[..., 2:]
            return Parts

    layout = Layout()
    limits = np.array([[-math.inf, -7.0], [math.inf, 7.0]])  # joint 0 continuous, joint 1 within +/- 7 rad
    rows = PositionRows([layout], [np.eye(2)], [np.zeros(2)], [limits], 1.0, 1.0)
    observation = np.array([[2 * math.pi - 0.1, 2 * math.pi - 0.1, 0.0, 0.0]])
    applied, _ = rows(observation, np.zeros((1, 2)))
    np.testing.assert_allclose(applied[0], [0.1, -(2 * math.pi - 0.1)])  # joint 0 wraps, joint 1 does not


def test_a_target_past_a_joint_limit_is_held_at_the_limit():
    class Layout:
        def split(self, observations):
            class Parts:
                q = observations[..., :1]
                dq = observations[..., 1:]
            return Parts

    rows = PositionRows([Layout()], [np.eye(1)], [np.array([0.2])], [np.array([[0.0], [0.3]])], 1.0, 1.0)
    applied, _ = rows(np.array([[0.1, 0.0], [0.1, 0.0]]), np.array([[-1.0], [1.0]]))
    np.testing.assert_allclose(applied[:, 0], [-0.1, 0.2])  # targets 0.0 and 0.3, the limits


def test_rows_of_one_setting_stack_and_others_are_refused():
    layout = object()
    limits = np.array([[-1.0, -1.0], [1.0, 1.0]])
    parts = [PositionRows([layout], [np.eye(2)], [np.zeros(2)], [limits], 1.0, 10.0) for _ in range(2)]
    assert len(PositionRows.concatenate(parts).layouts) == 2
    other = PositionRows([layout], [np.eye(2)], [np.zeros(2)], [limits], 0.5, 10.0)
    with pytest.raises(ValueError, match="joint_reach"):
        PositionRows.concatenate([parts[0], other])


def test_a_gain_the_sampled_loop_cannot_hold_is_refused_naming_position_gain_before_any_step():
    with pytest.raises(ValueError, match=r"position_gain: expected at most 0.5 / control period = 50 1/s on "
                                         r"scenario 'planar_square'"):
        BatchedTrainingEnv("planar_square", None, TrainingOptions(mode="position", position_gain=60.0))


@pytest.mark.parametrize("field, value, error", [
    ("joint_reach", 0.0, ValueError), ("joint_reach", 4.0, ValueError), ("joint_reach", "1", TypeError),
    ("position_gain", -1.0, ValueError), ("position_gain", float("inf"), ValueError),
    ("position_gain", True, TypeError), ("target_smoothing", -0.1, ValueError), ("target_smoothing", None, TypeError)])
def test_bad_position_options_name_the_field(field, value, error):
    with pytest.raises(error, match=field):
        TrainingOptions(mode="position", **{field: value})


def test_train_py_flags_carry_the_position_options():
    config = TrainConfig.from_args(["--mode", "position", "--joint-reach", "0.5", "--position-gain", "8",
                                    "--target-smoothing", "0.05", "--no-progress"])
    options = config.options
    assert (options.mode, options.joint_reach, options.position_gain, options.target_smoothing) == (
        "position", 0.5, 8.0, 0.05)
    assert config.training_overrides()["gravity_compensation"] is True


def test_target_smoothing_low_passes_the_targets_and_restarts_at_a_reset(closer):
    """Each row's target is the first one after a reset, then moves toward each new one by 1 - exp(-dt / tau) a
    step; the PD rule acts on it; a reset row starts again from its next target."""
    tau = 0.05
    env = _position_env(closer, "spatial_tetrahedron", copies=1, target_smoothing=tau)
    result = env.reset_arrays(seed=5)
    agents, n = env.possible_agents, env.env.uniform_joints
    observations = result.observations.reshape(len(agents), -1)
    rng = np.random.default_rng(3)
    first, second, third = (rng.uniform(-1, 1, (len(agents), n)) for _ in range(3))
    unfiltered = closer(BatchedTrainingEnv("spatial_tetrahedron", {"episode_seconds": 5.0}, TrainingOptions(
        mode="position", obs_features="none", hold_penalty=0.0), num_envs=1))
    unfiltered.reset_arrays(seed=5)

    def pd(learned_targets):  # the unfiltered rule acting on the targets the filter should give
        return unfiltered.action_rows(observations, (learned_targets - homes) / 1.0)[0]

    homes = np.concatenate(env.task.initial_q).reshape(len(agents), n)
    targets = [homes + np.clip(a, -1, 1) for a in (first, second, third)]
    lower = np.concatenate([m.lower for m in env.task.models]).reshape(len(agents), n)
    upper = np.concatenate([m.upper for m in env.task.models]).reshape(len(agents), n)
    targets = [np.clip(t, lower, upper) for t in targets]
    decay = math.exp(-env.scenario.control_dt / tau)
    np.testing.assert_allclose(env.action_rows(observations, first)[0], pd(targets[0]), rtol=1e-12)
    filtered = decay * targets[0] + (1 - decay) * targets[1]
    np.testing.assert_allclose(env.action_rows(observations, second)[0], pd(filtered), rtol=1e-12)
    env.action_rows.reset([1])  # agent 1 restarts: its next target is taken as it is
    expected = pd(decay * filtered + (1 - decay) * targets[2])
    expected[1] = pd(targets[2])[1]
    np.testing.assert_allclose(env.action_rows(observations, third)[0], expected, rtol=1e-12)


def test_a_smoothed_policy_acts_as_the_training_env_over_an_episode_alone_and_stacked(closer):
    """The evaluated policy keeps each agent's filter: per agent and as a stack, step after step and across a
    reset, it applies what the training env applies."""
    env = _position_env(closer, "planar_square", copies=1, target_smoothing=0.1)
    agents = env.possible_agents

    class Learned:  # stateless, as a learned part is: an action from the observation alone
        def reset(self):
            pass

        def __call__(self, observation):
            return np.sin(7.0 * np.asarray(observation)[:2])

    build = composed_policy_factory({a: Learned() for a in agents}, env.env, env.options)
    alone, stacked_policies = build(env.env.copy_view(0)), build(env.env.copy_view(0))
    from ee_formation_env.baselines.learned.policy import ComposedPolicy

    stacked = ComposedPolicy.stacked([stacked_policies[a] for a in agents])
    observations = env.reset_arrays(seed=2).observations.reshape(len(agents), -1)
    for episode in range(2):
        env.action_rows.reset()
        for policy in (*alone.values(), *stacked_policies.values()):
            policy.reset()
        for _ in range(4):
            learned = np.sin(7.0 * observations[:, :2])
            expected, _ = env.action_rows(observations, learned)
            per_agent = np.array([alone[a](observations[i]) for i, a in enumerate(agents)])
            np.testing.assert_array_equal(per_agent, expected)
            np.testing.assert_array_equal(stacked(observations), expected)
            observations = observations + 0.01  # the observations move on; the filters keep their state
