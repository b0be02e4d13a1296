"""The observation layout: one definition of the slots, sizes, bounds and the documentation table."""

from __future__ import annotations

import numpy as np
import pytest

import ee_formation_env
from ee_formation_env.observation import (JOINT_ENTRIES, SLOT_ENTRIES, ObservationBuilder, ObservationLayout,
                                          observation_table)
from ee_formation_env.scenario import load_scenario
from ee_formation_env.task import build_task


def test_split_names_every_entry_in_the_documented_order():
    layout = ObservationLayout(n_slots=2, dim=3, error_width=3, n_joints=4)
    assert layout.slot_size == 1 + 3 + 3 + 3 and layout.size == 2 * 10 + 2 * 4
    observation = np.arange(layout.size, dtype=np.float64)
    parts = layout.split(observation)
    np.testing.assert_array_equal(parts.mask, [0, 10])
    np.testing.assert_array_equal(parts.relative_positions, [[1, 2, 3], [11, 12, 13]])
    np.testing.assert_array_equal(parts.desired, [[4, 5, 6], [14, 15, 16]])
    np.testing.assert_array_equal(parts.edge_errors, [[7, 8, 9], [17, 18, 19]])
    np.testing.assert_array_equal(parts.q, [20, 21, 22, 23])
    np.testing.assert_array_equal(parts.dq, [24, 25, 26, 27])


def test_split_of_a_stack_is_the_split_of_each_observation():
    layout = ObservationLayout(n_slots=3, dim=2, error_width=1, n_joints=2)
    stack = np.random.default_rng(0).normal(size=(5, layout.size))
    parts = layout.split(stack)
    assert parts.relative_positions.shape == (5, 3, 2) and parts.q.shape == (5, 2)
    for k in range(5):
        single = layout.split(stack[k])
        for name in ("mask", "relative_positions", "desired", "edge_errors", "q", "dq"):
            np.testing.assert_array_equal(getattr(parts, name)[k], getattr(single, name))
    with pytest.raises(ValueError, match="observation: expected shape"):
        layout.split(np.zeros((2, 2, layout.size)))


def test_split_rejects_a_wrong_size():
    with pytest.raises(ValueError, match=r"observation: expected shape \(9,\)"):
        ObservationLayout(n_slots=1, dim=2, error_width=1, n_joints=2).split(np.zeros(10))


def test_the_table_lists_every_entry_and_is_in_the_env_docstring():
    table = observation_table()
    for name, _, meaning in SLOT_ENTRIES + JOINT_ENTRIES:
        assert f"``{name}``" in table and meaning in table
    assert "x_i - x_j, end-effector displacement (m)" in ee_formation_env.FormationEnv.__doc__
    assert "{observation_table}" not in ee_formation_env.FormationEnv.__doc__


@pytest.mark.parametrize("name", ["planar_square", "planar_square_displacement", "spatial_tetrahedron"])
def test_spaces_match_the_layouts_and_share_bounds_between_identical_arms(name):
    task = build_task(load_scenario(name))
    builder = ObservationBuilder(task, max_joint_velocity=50.0)
    for layout, space in zip(builder.layouts, builder.spaces):
        assert space.shape == (layout.size,) and space.dtype == np.float32
        assert np.all(np.isfinite(space.low)) and np.all(np.isfinite(space.high))
        parts = layout.split(space.high)
        np.testing.assert_array_equal(parts.mask, 1.0)
        np.testing.assert_array_equal(parts.dq, np.float32(50.0))
    # Identical arms get identical spaces (one policy can be shared).
    assert all(np.array_equal(builder.spaces[0].low, space.low) for space in builder.spaces)
    n_joints = sum(model.n_joints for model in task.models)
    assert builder.state_space.shape == (task.n_agents * task.dim + 2 * n_joints,)


def test_observations_gather_each_agents_slots_and_pad_the_rest():
    task = build_task(load_scenario("planar_square"))  # degrees 3, 2, 3, 2: arms 1 and 3 have one padding slot
    builder = ObservationBuilder(task, max_joint_velocity=50.0)
    positions = np.asarray(task.scenario.shape) + 0.01
    z = task.graph.edge_vectors(positions)
    slot_z, slot_errors = builder.slots_in_own_frames(z, task.formation.edge_errors(z))
    q = np.linspace(-1, 1, 8)
    matrix = builder.observation_matrix(slot_z, slot_errors, q, -q)
    for i, agent in enumerate(task.agents):
        parts = builder.layouts[i].split(matrix[builder.observation_slices[i]])
        degree = len(task.graph.neighbors[i])
        np.testing.assert_array_equal(parts.mask, [1.0] * degree + [0.0] * (3 - degree))
        for s, neighbor in enumerate(task.graph.neighbors[i]):
            np.testing.assert_allclose(parts.relative_positions[s], positions[i] - positions[neighbor.agent], atol=1e-6)
            np.testing.assert_allclose(parts.desired[s, 0], task.formation.desired[neighbor.edge], atol=1e-6)
        np.testing.assert_allclose(parts.q, q[2 * i:2 * i + 2], atol=1e-7)
        np.testing.assert_allclose(parts.dq, -q[2 * i:2 * i + 2], atol=1e-7)


@pytest.mark.parametrize("name", ["planar_square", "planar_square_displacement", "spatial_tetrahedron"])
def test_length_errors_are_each_neighbour_edges_error_in_metres(name):
    """| |p_j - p_i| - d_ij | (distance) or |(p_j - p_i) - z*_ij| (displacement), from the end-effector positions,
    is what an agent's slots give in metres (the precision bonus and metrics read the same length)."""
    import ee_formation_env

    env = ee_formation_env.parallel_env(name)
    observations, _ = env.reset(seed=3)
    positions = np.asarray(env.end_effector_positions())[:, :env.dim]
    shape = np.asarray(env.scenario.shape, dtype=np.float64)
    for i, agent in enumerate(env.possible_agents):
        errors, real = env.observation_layout(agent).length_errors(observations[agent])
        expected = []
        for a, b in np.asarray(env.graph.edges):
            if i in (a, b):
                j = b if a == i else a
                actual, desired = positions[j] - positions[i], shape[j] - shape[i]
                expected.append(abs(np.linalg.norm(actual) - np.linalg.norm(desired))
                                if env.observation_layout(agent).formation_kind == "distance"
                                else np.linalg.norm(actual - desired))
        assert sorted(errors[real]) == pytest.approx(sorted(expected), abs=1e-6)  # float32 observations
        assert np.all(errors[~real] == 0.0)
    env.close()
