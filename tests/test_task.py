"""The task: everything derived from a scenario, built once, validated, and consumed without an env."""

from __future__ import annotations

import numpy as np
import pytest

import ee_formation_env
from ee_formation_env.kinematics import rpy_to_matrix
from ee_formation_env.scenario import load_scenario
from ee_formation_env.task import build_task

from conftest import nominal_initial_q


def test_builtin_task_derives_models_limits_and_poses():
    task = build_task(load_scenario("planar_square_rotated"))
    assert task.n_agents == 4 and task.agents == ["arm_0", "arm_1", "arm_2", "arm_3"]
    assert all(model is task.models[0] for model in task.models)  # one shared (cached) model per URDF
    np.testing.assert_array_equal(task.torque_limits[0], [50.0, 50.0])  # the URDF efforts
    assert task.reaches[0] == pytest.approx(3.0, abs=1e-3)  # l1 + l2
    for arm, rotation in zip(task.scenario.arms, task.base_rotations):
        np.testing.assert_array_equal(rotation, rpy_to_matrix(arm.base_rpy))
    np.testing.assert_allclose(task.gravity_in_base_frame(1), [0.0, 0.0, -9.81])
    assert task.graph.n_edges == 5 and task.formation.kind == "distance"


def test_torque_limit_forms_are_expanded_per_joint():
    assert build_task(load_scenario("planar_square", torque_limits=7.0)).torque_limits[2].tolist() == [7.0, 7.0]
    task = build_task(load_scenario("planar_square", torque_limits=[[1, 2], [3, 4], [5, 6], [7, 8]]))
    assert task.torque_limits[3].tolist() == [7.0, 8.0]
    with pytest.raises(ValueError, match=r"torque_limits: arms\[0\] has 2 joints, got 3 limits"):
        build_task(load_scenario("planar_square", torque_limits=[1.0, 2.0, 3.0]))


def test_agent_index_names_the_agents():
    task = build_task(load_scenario("planar_square"))
    assert task.agent_index("arm_2") == 2
    with pytest.raises(ValueError, match="agent: expected one of"):
        task.agent_index("arm_9")


def test_env_consumes_the_task_it_built():
    with ee_formation_env.parallel_env("planar_square") as env:
        assert env.nominal_models is env.task.models
        assert env.torque_limits is env.task.torque_limits
        np.testing.assert_array_equal(nominal_initial_q(env, "arm_1"), env.task.initial_q[1])
