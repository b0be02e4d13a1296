"""Tests of ee_formation_env.formation: graphs, edge vectors, rigidity, edge errors and agent gradients.

Reference values are computed independently of the module (the paper's printed incidence matrix, hand
counts of rigidity ranks, a finite-difference gradient of the formation potential), so a wrong sign, a
transposed incidence or a missing factor fails here.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from ee_formation_env.formation import (
    Formation,
    FormationGraph,
    Neighbor,
    agent_gradient,
    check_rigidity,
    required_rigidity_rank,
    rigidity_matrix,
)

# The paper's 2D graph (Sec. VI-A), 0-based (tail, head): 1-2, 2-3, 3-4, 4-1, 1-3.
PAPER_2D_EDGES = [[0, 1], [1, 2], [2, 3], [3, 0], [0, 2]]
# The paper's printed 2D incidence matrix (agents as rows, edges as columns, +1 tail, -1 head).
PAPER_2D_INCIDENCE = np.array([[1, 0, 0, -1, 1], [-1, 1, 0, 0, 0], [0, -1, 1, 0, -1], [0, 0, -1, 1, 0]])
SQUARE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
TETRAHEDRON = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, np.sqrt(3) / 2, 0.0],
                        [0.5, np.sqrt(3) / 6, np.sqrt(2.0 / 3.0)]])
K4_EDGES = [list(pair) for pair in itertools.combinations(range(4), 2)]


# ------------------------------------------------------------------------------------------------ graph
def test_incidence_matches_the_papers_printed_2d_matrix() -> None:
    graph = FormationGraph(4, PAPER_2D_EDGES)
    np.testing.assert_array_equal(graph.incidence, PAPER_2D_INCIDENCE)
    assert graph.n_agents == 4 and graph.n_edges == 5
    np.testing.assert_array_equal(graph.incidence.sum(axis=0), np.zeros(5))  # one tail and one head per edge


def test_neighbours_carry_the_shared_edge_the_other_agent_and_the_incidence_sign() -> None:
    graph = FormationGraph(4, PAPER_2D_EDGES)
    assert graph.neighbors[0] == (Neighbor(edge=0, agent=1, sign=1), Neighbor(edge=3, agent=3, sign=-1),
                                  Neighbor(edge=4, agent=2, sign=1))
    assert graph.neighbors[1] == (Neighbor(edge=0, agent=0, sign=-1), Neighbor(edge=1, agent=2, sign=1))
    assert graph.neighbors[2] == (Neighbor(edge=1, agent=1, sign=-1), Neighbor(edge=2, agent=3, sign=1),
                                  Neighbor(edge=4, agent=0, sign=-1))
    assert graph.neighbors[3] == (Neighbor(edge=2, agent=2, sign=-1), Neighbor(edge=3, agent=0, sign=1))
    assert [len(slots) for slots in graph.neighbors] == [3, 2, 3, 2]
    assert graph.max_degree == 3
    # Every edge appears exactly twice, once from each end, with opposite signs.
    for k, (tail, head) in enumerate(PAPER_2D_EDGES):
        ends = {(i, slot.sign) for i, slots in enumerate(graph.neighbors) for slot in slots if slot.edge == k}
        assert ends == {(tail, 1), (head, -1)}


def test_degree_of_a_star_graph() -> None:
    graph = FormationGraph(5, [[0, 1], [0, 2], [3, 0], [0, 4]])
    assert graph.max_degree == 4
    assert [len(slots) for slots in graph.neighbors] == [4, 1, 1, 1, 1]


@pytest.mark.parametrize("n_agents, edges, connected", [
    (4, PAPER_2D_EDGES, True),
    (4, [[0, 1], [1, 2], [2, 3]], True),          # a path
    (4, [[0, 1], [2, 3]], False),                 # two components
    (4, [[1, 2], [2, 3], [3, 1]], False),         # agent 0 isolated
    (3, [[2, 0], [1, 2]], True),                  # reachable only through heads
])
def test_connectivity(n_agents: int, edges: list[list[int]], connected: bool) -> None:
    assert FormationGraph(n_agents, edges).is_connected() is connected


@pytest.mark.parametrize("n_agents, edges, message", [
    (1, [[0, 0]], "n_agents"),
    (3, [[0, 3]], "references agent 3"),
    (3, [[1, 1]], "self-loop"),
    (3, [[0, 1], [1, 0]], "duplicate edge"),
    (3, [], "non-empty"),
    (3, [[0.0, 1.0]], "integer"),
])
def test_bad_graphs_are_rejected_with_the_field_named(n_agents: int, edges: list, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        FormationGraph(n_agents, edges)


def test_edge_vectors_are_tail_minus_head() -> None:
    graph = FormationGraph(4, PAPER_2D_EDGES)
    positions = np.array([[0.3, -1.0], [2.0, 0.5], [1.5, 4.0], [-2.0, 1.0]])
    z = graph.edge_vectors(positions)
    assert z.shape == (5, 2)
    np.testing.assert_allclose(z[3], positions[3] - positions[0])
    np.testing.assert_allclose(z, PAPER_2D_INCIDENCE.T @ positions)  # z = (B^T (x) I) x


# ---------------------------------------------------------------------------------------------- rigidity
def test_rigidity_matrix_rows_are_kron_of_incidence_column_and_edge_vector() -> None:
    rng = np.random.default_rng(0)
    graph = FormationGraph(4, K4_EDGES)
    positions = rng.normal(size=(4, 3))
    matrix = rigidity_matrix(graph, positions)
    assert matrix.shape == (6, 12)
    z = graph.edge_vectors(positions)
    expected = np.stack([np.kron(graph.incidence[:, k], z[k]) for k in range(graph.n_edges)])
    np.testing.assert_allclose(matrix, expected)
    # R(x) x = |z_k|^2, and rigid translations and rotations are infinitesimal motions (R v = 0).
    np.testing.assert_allclose(matrix @ positions.ravel(), np.sum(z**2, axis=1))
    np.testing.assert_allclose(matrix @ np.tile([0.3, -1.0, 2.0], 4), np.zeros(6), atol=1e-12)
    omega = np.array([0.2, -0.5, 1.0])
    rotation_velocity = np.cross(omega, positions).ravel()
    np.testing.assert_allclose(matrix @ rotation_velocity, np.zeros(6), atol=1e-12)


@pytest.mark.parametrize("n_agents, dim, rank", [(2, 2, 1), (3, 2, 3), (4, 2, 5), (2, 3, 1), (3, 3, 3),
                                                 (4, 3, 6), (5, 3, 9), (16, 3, 42)])
def test_required_rigidity_rank(n_agents: int, dim: int, rank: int) -> None:
    assert required_rigidity_rank(n_agents, dim) == rank


@pytest.mark.parametrize("positions, edges, rank, rigid, minimal", [
    (SQUARE, PAPER_2D_EDGES, 5, True, True),                       # the paper's square: 2N - 3 = 5 edges
    (SQUARE, PAPER_2D_EDGES[:4], 4, False, False),                 # the 4-cycle flexes
    (SQUARE, K4_EDGES, 5, True, False),                            # both diagonals: one edge redundant
    (SQUARE[:3], [[0, 1], [1, 2], [2, 0]], 3, True, True),         # a triangle
    (np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]), [[0, 1], [1, 2], [2, 0]], 2, False, False),  # collinear
    (TETRAHEDRON, K4_EDGES, 6, True, True),                        # the tetrahedron: 3N - 6 = 6 edges
    (TETRAHEDRON, K4_EDGES[:5], 5, False, False),                  # one edge short
    (np.c_[SQUARE, np.zeros(4)], K4_EDGES, 5, False, False),       # coplanar in 3D: flexes out of the plane
    (np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), [[0, 1], [1, 2], [2, 0]], 3, True, True),
], ids=["square-5", "square-cycle", "square-K4", "triangle", "collinear", "tetrahedron", "tetra-5",
        "coplanar-K4", "triangle-3d"])
def test_check_rigidity(positions: np.ndarray, edges: list[list[int]], rank: int, rigid: bool,
                        minimal: bool) -> None:
    report = check_rigidity(FormationGraph(len(positions), edges), positions)
    assert report.rank == rank
    assert report.n_edges == len(edges)
    assert report.rigid is rigid
    assert report.minimal is minimal


def test_rigidity_does_not_depend_on_scale_or_edge_direction() -> None:
    flipped = [[head, tail] for tail, head in PAPER_2D_EDGES]
    for positions in (1e-3 * SQUARE, 1e3 * SQUARE):
        assert check_rigidity(FormationGraph(4, flipped), positions).minimal


# ----------------------------------------------------------------------------------------------- errors
def test_distance_edge_errors_are_squared_length_differences() -> None:
    graph = FormationGraph(4, PAPER_2D_EDGES)
    formation = Formation(graph, "distance", 3.0 * SQUARE)
    np.testing.assert_allclose(formation.desired, [3.0, 3.0, 3.0, 3.0, 3.0 * np.sqrt(2)])
    assert formation.error_width == 1
    np.testing.assert_allclose(formation.error_scales, [9.0, 9.0, 9.0, 9.0, 18.0])
    # Rotated and translated: still the shape.
    angle = 0.7
    rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    moved = 3.0 * SQUARE @ rotation.T + [5.0, -2.0]
    np.testing.assert_allclose(formation.edge_errors(graph.edge_vectors(moved)), np.zeros(5), atol=1e-12)
    # Twice the size: e_k = (2 d)^2 - d^2 = 3 d^2.
    errors = formation.edge_errors(graph.edge_vectors(6.0 * SQUARE))
    np.testing.assert_allclose(errors, [27.0, 27.0, 27.0, 27.0, 54.0])
    assert formation.formation_error(graph.edge_vectors(6.0 * SQUARE)) == pytest.approx(
        np.sqrt((4 * 27.0**2 + 54.0**2) / 5))


def test_displacement_edge_errors_are_vector_differences() -> None:
    graph = FormationGraph(4, PAPER_2D_EDGES)
    formation = Formation(graph, "displacement", 3.0 * SQUARE)
    np.testing.assert_allclose(formation.desired, graph.edge_vectors(3.0 * SQUARE))
    assert formation.error_width == 2
    np.testing.assert_allclose(formation.error_scales, [3.0, 3.0, 3.0, 3.0, 3.0 * np.sqrt(2)])
    translated = 3.0 * SQUARE + [5.0, -2.0]
    np.testing.assert_allclose(formation.edge_errors(graph.edge_vectors(translated)), np.zeros((5, 2)))
    # A rotation keeps distances but not displacements.
    rotated = 3.0 * SQUARE @ np.array([[0.0, -1.0], [1.0, 0.0]]).T
    errors = formation.edge_errors(graph.edge_vectors(rotated))
    np.testing.assert_allclose(errors, graph.edge_vectors(rotated) - graph.edge_vectors(3.0 * SQUARE))
    assert np.abs(errors).max() > 1.0
    z = graph.edge_vectors(rotated)
    assert formation.formation_error(z) == pytest.approx(np.sqrt(np.mean(np.sum(errors**2, axis=1))))


def test_error_scales_have_a_floor_for_coincident_agents() -> None:
    shape = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    graph = FormationGraph(3, [[0, 1], [1, 2], [2, 0]])
    for kind in ("distance", "displacement"):
        scales = Formation(graph, kind, shape).error_scales
        np.testing.assert_allclose(scales, [1e-6, 1.0, 1.0])


def test_unknown_formation_kind_is_rejected() -> None:
    with pytest.raises(ValueError, match="formation"):
        Formation(FormationGraph(4, PAPER_2D_EDGES), "bearing", SQUARE)


# -------------------------------------------------------------------------------------------- gradients
def _potential(formation: Formation, positions: np.ndarray) -> float:
    """V(x) = 1/2 sum_k |e_k|^2, the potential whose gradient the agents descend."""
    errors = formation.edge_errors(formation.graph.edge_vectors(positions))
    return 0.5 * float(np.sum(errors**2))


def _slots(formation: Formation, positions: np.ndarray, agent: int, padding: int) -> tuple[np.ndarray, np.ndarray]:
    """The agent's neighbour slots (z_ij = x_i - x_j and its edge errors), plus ``padding`` zero slots."""
    graph = formation.graph
    errors = formation.edge_errors(graph.edge_vectors(positions))
    relative, slot_errors = [], []
    for slot in graph.neighbors[agent]:
        relative.append(positions[agent] - positions[slot.agent])
        # Distance errors are symmetric in the edge direction; displacement errors flip with it.
        slot_errors.append(errors[slot.edge] if formation.kind == "distance" else slot.sign * errors[slot.edge])
    dim = positions.shape[1]
    relative += [np.zeros(dim)] * padding
    slot_errors += [0.0 if formation.kind == "distance" else np.zeros(dim)] * padding
    return np.array(relative), np.array(slot_errors)


@pytest.mark.parametrize("kind", ["distance", "displacement"])
@pytest.mark.parametrize("shape, edges", [(3.0 * SQUARE, PAPER_2D_EDGES), (0.4 * TETRAHEDRON, K4_EDGES)],
                         ids=["square", "tetrahedron"])
def test_agent_gradient_is_the_gradient_of_the_potential(kind: str, shape: np.ndarray, edges: list) -> None:
    formation = Formation(FormationGraph(len(shape), edges), kind, shape)
    rng = np.random.default_rng(1)
    positions = shape + rng.normal(scale=0.5, size=shape.shape)
    step = 1e-6
    for agent in range(len(shape)):
        relative, errors = _slots(formation, positions, agent, padding=2)
        gradient = agent_gradient(kind, relative, errors)
        assert gradient.shape == (shape.shape[1],)
        numeric = np.zeros(shape.shape[1])
        for c in range(shape.shape[1]):
            plus, minus = positions.copy(), positions.copy()
            plus[agent, c] += step
            minus[agent, c] -= step
            numeric[c] = (_potential(formation, plus) - _potential(formation, minus)) / (2 * step)
        np.testing.assert_allclose(gradient, numeric, rtol=1e-6, atol=1e-6)
        assert np.linalg.norm(gradient) > 1e-3  # off the shape, every agent is pushed


@pytest.mark.parametrize("kind", ["distance", "displacement"])
def test_agent_gradient_vanishes_on_the_shape(kind: str) -> None:
    formation = Formation(FormationGraph(4, K4_EDGES), kind, TETRAHEDRON)
    for agent in range(4):
        gradient = agent_gradient(kind, *_slots(formation, TETRAHEDRON + 1.0, agent, padding=0))
        np.testing.assert_allclose(gradient, np.zeros(3), atol=1e-12)
