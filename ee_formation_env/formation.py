"""Formation graphs, edge errors and rigidity: the formation side of the paper (Sec. II-B, II-C, III-A).

Conventions (the paper's):

- Edge ``k = (tail, head)``; incidence ``b[tail, k] = +1``, ``b[head, k] = -1``.
- Relative position ``z_k = x_tail - x_head`` (m).
- Distance formations: ``e_k = |z_k|^2 - d_k^2`` (m^2), ``d_k = |z*_k|``.
- Displacement formations: ``e_k = z_k - z*_k`` (m, a vector).
- Agent gradient ``e_hat_i = sum_k b_ik R_k(z_k) e_k``; in neighbour terms with ``z_ij = x_i - x_j``:
  distance ``e_hat_i = 2 sum_j e_ij z_ij``, displacement ``e_hat_i = sum_j (z_ij - z*_ij)``.

Everything here is plain numpy; the environment, the controllers and the metrics all use it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, Sequence

import numpy as np

FormationKind = Literal["distance", "displacement"]
FORMATION_KINDS: tuple[str, ...] = ("distance", "displacement")


@dataclass(frozen=True)
class Neighbor:
    """One neighbour slot of an agent: the edge it shares, the neighbour and the agent's incidence sign."""

    edge: int
    agent: int
    sign: int  # b_ik: +1 if the agent is the edge's tail, -1 if its head


class FormationGraph:
    """Undirected formation graph with ordered edges (tail, head) over ``n_agents`` vertices."""

    def __init__(self, n_agents: int, edges: Sequence[Sequence[int]]):
        if not isinstance(n_agents, (int, np.integer)) or n_agents < 2:
            raise ValueError(f"n_agents: expected an integer >= 2, got {n_agents!r}")
        edge_array = np.asarray(edges)
        if edge_array.ndim != 2 or edge_array.shape[1] != 2 or edge_array.shape[0] == 0:
            raise ValueError(f"edges: expected a non-empty list of [tail, head] pairs, got {edges!r}")
        if not np.issubdtype(edge_array.dtype, np.integer):
            raise ValueError(f"edges: expected integer agent indices, got {edges!r}")
        for k, (tail, head) in enumerate(edge_array.tolist()):
            for end in (tail, head):
                if not 0 <= end < n_agents:
                    raise ValueError(
                        f"edges[{k}] = [{tail}, {head}] references agent {end}, but there are only "
                        f"{n_agents} agents (indices 0..{n_agents - 1})"
                    )
            if tail == head:
                raise ValueError(f"edges[{k}] = [{tail}, {head}] is a self-loop")
        pairs = [frozenset(edge) for edge in edge_array.tolist()]
        if len(set(pairs)) != len(pairs):
            raise ValueError(f"edges: duplicate edge (in either direction) in {edge_array.tolist()}")
        self.n_agents = int(n_agents)
        self.edges = edge_array.astype(np.int64)
        self._tails, self._heads = self.edges[:, 0].copy(), self.edges[:, 1].copy()  # contiguous, for indexing
        self.n_edges = len(self.edges)
        self.incidence = np.zeros((self.n_agents, self.n_edges))
        self.incidence[self.edges[:, 0], np.arange(self.n_edges)] = 1.0
        self.incidence[self.edges[:, 1], np.arange(self.n_edges)] = -1.0
        self.neighbors: tuple[tuple[Neighbor, ...], ...] = tuple(
            tuple(
                Neighbor(edge=k, agent=int(self.edges[k, 1] if self.edges[k, 0] == i else self.edges[k, 0]),
                         sign=int(self.incidence[i, k]))
                for k in range(self.n_edges)
                if self.incidence[i, k] != 0
            )
            for i in range(self.n_agents)
        )
        self.max_degree = max(len(slots) for slots in self.neighbors)

    def is_connected(self) -> bool:
        """True if every agent is reachable from agent 0."""
        seen = {0}
        frontier = [0]
        while frontier:
            i = frontier.pop()
            for slot in self.neighbors[i]:
                if slot.agent not in seen:
                    seen.add(slot.agent)
                    frontier.append(slot.agent)
        return len(seen) == self.n_agents

    def edge_vectors(self, positions: np.ndarray) -> np.ndarray:
        """``z_k = x_tail - x_head`` for every edge, shape (n_edges, dim), from (n_agents, dim) positions (with
        leading axes on ``positions``, e.g. K copies (K, n_agents, dim), the result gets them too)."""
        return positions[..., self._tails, :] - positions[..., self._heads, :]


def rigidity_matrix(graph: FormationGraph, positions: np.ndarray) -> np.ndarray:
    """Rigidity matrix ``R(x) = D_z^T B_bar^T`` of shape (n_edges, n_agents * dim)."""
    n_agents, dim = positions.shape
    z = graph.edge_vectors(positions)
    matrix = np.zeros((graph.n_edges, n_agents * dim))
    for k, (tail, head) in enumerate(graph.edges):
        matrix[k, tail * dim:(tail + 1) * dim] = z[k]
        matrix[k, head * dim:(head + 1) * dim] = -z[k]
    return matrix


def required_rigidity_rank(n_agents: int, dim: int) -> int:
    """Rank of the rigidity matrix of an infinitesimally rigid framework in general position."""
    if n_agents <= dim:
        return n_agents * (n_agents - 1) // 2
    return n_agents * dim - dim * (dim + 1) // 2


@dataclass(frozen=True)
class RigidityReport:
    """Outcome of the infinitesimal rigidity test of a framework (graph, shape)."""

    rank: int
    required_rank: int
    n_edges: int

    @property
    def rigid(self) -> bool:
        return self.rank == self.required_rank

    @property
    def minimal(self) -> bool:
        return self.rigid and self.n_edges == self.required_rank


def check_rigidity(graph: FormationGraph, positions: np.ndarray, tolerance: float = 1e-9) -> RigidityReport:
    """Infinitesimal rigidity of the framework by the rank of its rigidity matrix."""
    matrix = rigidity_matrix(graph, positions)
    singular_values = np.linalg.svd(matrix, compute_uv=False)
    scale = max(1.0, float(singular_values.max(initial=0.0)))
    rank = int(np.sum(singular_values > tolerance * scale))
    return RigidityReport(rank, required_rigidity_rank(graph.n_agents, positions.shape[1]), graph.n_edges)


class Formation:
    """A formation task: graph, formation kind and reference shape ``x*`` (n_agents, dim), in m.

    ``desired`` is ``d*_k = |z*_k|`` (n_edges,) for distance formations and ``z*_k`` (n_edges, dim)
    for displacement formations.
    """

    def __init__(self, graph: FormationGraph, kind: str, shape: np.ndarray):
        if kind not in FORMATION_KINDS:
            raise ValueError(f"formation: expected one of {FORMATION_KINDS}, got {kind!r}")
        self.graph = graph
        self.kind: FormationKind = kind  # type: ignore[assignment]
        self.shape = np.asarray(shape, dtype=np.float64)
        self.dim = self.shape.shape[1]
        self.desired_vectors = graph.edge_vectors(self.shape)
        self.desired = (
            np.linalg.norm(self.desired_vectors, axis=1) if kind == "distance" else self.desired_vectors
        )
        # Width of one edge error: 1 (m^2) for distance, dim (m) for displacement.
        self.error_width = 1 if kind == "distance" else self.dim
        # Size of each edge's error relative to which it is judged: d*_k^2 (m^2) or |z*_k| (m).
        lengths = np.linalg.norm(self.desired_vectors, axis=1)
        self.error_scales = np.maximum(lengths**2 if kind == "distance" else lengths, 1e-6)
        self._desired_squared = self.desired**2 if kind == "distance" else None

    def edge_errors(self, z: np.ndarray) -> np.ndarray:
        """Edge errors e_k from edge vectors z (n_edges, dim): (n_edges,) m^2 or (n_edges, dim) m (leading axes
        of ``z`` carry over)."""
        if self.kind == "distance":
            return np.einsum("...kd,...kd->...k", z, z) - self._desired_squared
        return z - self.desired_vectors

    def formation_error(self, z: np.ndarray) -> float:
        """RMS over all edges of |e_k| (m^2 for distance formations, m for displacement formations)."""
        errors = self.edge_errors(z).reshape(self.graph.n_edges, -1)
        return formation_error_from_squares(np.add.reduce(errors * errors, axis=1))


def formation_error_from_squares(edge_squares: np.ndarray) -> float:
    """The formation error: RMS over all edges of |e_k|, from the squares |e_k|^2 (E,); m^2 for distance
    formations, m for displacement ones. The one definition, used by the env's infos and the metrics."""
    return math.sqrt(float(edge_squares.sum()) / len(edge_squares))


def formation_errors_from_squares(edge_squares: np.ndarray) -> np.ndarray:
    """:func:`formation_error_from_squares` of every row of a stack (..., E): an array (...,), each entry bit
    for bit the scalar function's value on its row (the batched env's infos)."""
    return np.sqrt(np.add.reduce(edge_squares, axis=-1) / edge_squares.shape[-1])


def agent_gradient(kind: str, relative_positions: np.ndarray, edge_errors: np.ndarray) -> np.ndarray:
    """Agent-wise gradient ``e_hat_i`` from its neighbour slots, in any one frame.

    ``relative_positions``: (slots, dim) ``z_ij = x_i - x_j``; ``edge_errors``: (slots,) for distance
    formations (``|z_ij|^2 - d_ij^2``) or (slots, dim) for displacement ones (``z_ij - z*_ij``).
    Padding slots must carry zeros. Returns (dim,). With a leading axis of k agents on both arguments
    ((k, slots, dim) and (k, slots) or (k, slots, dim)), returns the k gradients (k, dim).
    """
    if kind == "distance":
        return 2.0 * (edge_errors[..., None, :] @ relative_positions)[..., 0, :]
    return edge_errors.sum(axis=-2)
