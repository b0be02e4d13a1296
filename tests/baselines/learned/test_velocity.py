"""Velocity mode: a zero action holds every joint at rest against gravity, a command drives the joint's speed
toward it and the loop's gain is checked against the control period (the evaluated policy applying the
training env's rule: test_modes.py)."""

from __future__ import annotations

import numpy as np
import pytest

from ee_formation_env.baselines.learned.action_scale import initial_mass_matrices
from ee_formation_env.baselines.learned.config import TrainConfig
from ee_formation_env.baselines.learned.options import TrainingOptions
from ee_formation_env.baselines.learned.training_env import BatchedTrainingEnv
from ee_formation_env.baselines.learned.velocity import VelocityRows


def _velocity_env(closer, scenario, copies=2, **options):
    options = TrainingOptions(mode="velocity", obs_features="none", hold_penalty=0.0, **options)
    return closer(BatchedTrainingEnv(scenario, {"episode_seconds": 5.0}, options, num_envs=copies))


def test_the_mode_always_runs_with_gravity_compensation_in_training_and_evaluation(closer):
    options = TrainingOptions(mode="velocity")
    assert options.env_overrides() == {"gravity_compensation": True}
    assert TrainingOptions(mode="torque").env_overrides() == {}
    env = _velocity_env(closer, "spatial_tetrahedron", copies=1)  # built without the overrides: added anyway
    assert env.scenario.gravity_compensation


def test_a_zero_action_brakes_and_holds_every_joint_of_a_spatial_arm_against_gravity(closer):
    env = _velocity_env(closer, "spatial_tetrahedron")
    env.reset_arrays(seed=[0, 1])
    rows, joints = 2 * len(env.possible_agents), env.env.uniform_joints
    steps_per_second = round(1.0 / env.scenario.control_dt)
    for _ in range(steps_per_second // 5):  # 0.2 s: set the arms moving
        env.step_arrays(np.full((rows, joints), 0.8))
    assert np.abs(env.env.joint_velocities()).max() > 0.3
    for _ in range(steps_per_second):  # 1 s of zero action: the loop brakes them (time constant 0.1 s)
        env.step_arrays(np.zeros((rows, joints)))
    held = env.env.joint_positions()
    assert np.abs(env.env.joint_velocities()).max() < 1e-3
    for _ in range(2 * steps_per_second):  # 2 s more: no sag under gravity
        env.step_arrays(np.zeros((rows, joints)))
    assert np.abs(env.env.joint_positions() - held).max() < 1e-3


@pytest.mark.parametrize("scenario", ["planar_square", "spatial_tetrahedron"])
def test_a_command_drives_each_joint_toward_its_speed_in_the_commanded_sense(closer, scenario):
    env = _velocity_env(closer, scenario, joint_speed=0.5)
    env.reset_arrays(seed=[3, 4])
    rows, joints = 2 * len(env.possible_agents), env.env.uniform_joints
    command = np.where(np.arange(rows)[:, None] % 2 == 0, 1.0, -1.0) * np.eye(joints)[0]  # joint 0, +/- in turn
    for _ in range(int(0.5 / env.scenario.control_dt)):  # 5 time constants
        env.step_arrays(command)
    speeds = env.env.joint_velocities().reshape(rows, joints)
    assert np.all(np.sign(speeds[:, 0]) == np.sign(command[:, 0]))
    assert np.all((np.abs(speeds[:, 0]) > 0.25) & (np.abs(speeds[:, 0]) < 0.55))  # toward 0.5 rad/s, not past it
    assert np.abs(speeds[:, 1:]).max() < 0.5 * np.abs(speeds[:, 0]).min()  # the other joints held near rest


def test_the_torque_is_the_velocity_loop_on_the_agents_own_observation(closer):
    env = _velocity_env(closer, "spatial_tetrahedron", copies=1, joint_speed=2.0, velocity_gain=8.0)
    result = env.reset_arrays(seed=5)
    learned = np.random.default_rng(0).uniform(-1.5, 1.5, (len(env.possible_agents), env.env.uniform_joints))
    observations = result.observations.reshape(len(env.possible_agents), -1)
    applied, factors = env.action_rows(observations, learned)
    masses, limits = initial_mass_matrices(env.task), env.task.torque_limits
    for i, agent in enumerate(env.possible_agents):
        dq = env.observation_layout(agent).split(observations[i]).dq
        expected = masses[agent] @ (8.0 * (2.0 * np.clip(learned[i], -1, 1) - dq)) / limits[i]
        np.testing.assert_allclose(applied[i], expected, rtol=1e-12)
    assert factors is None  # rewards are the env's


def test_rows_of_one_joint_speed_stack_and_others_are_refused():
    layout = object()
    rows = [VelocityRows([layout], [np.eye(2)], 1.0), VelocityRows([layout], [np.eye(2)], 1.0)]
    assert len(VelocityRows.concatenate(rows).layouts) == 2
    with pytest.raises(ValueError, match="joint_speed"):
        VelocityRows.concatenate([rows[0], VelocityRows([layout], [np.eye(2)], 2.0)])


def test_a_gain_the_sampled_loop_cannot_hold_is_refused_naming_velocity_gain_before_any_step():
    with pytest.raises(ValueError, match=r"velocity_gain: expected at most 1 / control period = 100 1/s on "
                                         r"scenario 'planar_square'"):
        BatchedTrainingEnv("planar_square", None, TrainingOptions(mode="velocity", velocity_gain=150.0))


@pytest.mark.parametrize("field, value, error", [
    ("joint_speed", 0.0, ValueError), ("joint_speed", float("nan"), ValueError), ("joint_speed", "1", TypeError),
    ("velocity_gain", -1.0, ValueError), ("velocity_gain", True, TypeError)])
def test_bad_velocity_options_name_the_field(field, value, error):
    with pytest.raises(error, match=field):
        TrainingOptions(mode="velocity", **{field: value})


def test_train_py_flags_carry_the_velocity_options():
    config = TrainConfig.from_args(["--mode", "velocity", "--joint-speed", "2", "--velocity-gain", "5",
                                    "--no-progress"])
    options = config.options
    assert (options.mode, options.joint_speed, options.velocity_gain) == ("velocity", 2.0, 5.0)
    assert config.training_overrides()["gravity_compensation"] is True
