"""Geometric validation of a scenario with the arms' kinematic models, before any physics starts.

Checks, each failure a ``ValueError`` naming the problem:

- every arm's URDF parses, its end-effector link exists and the chain is serial and revolute;
- ``initial_q`` has one entry per joint and lies within the joint limits;
- planar (``dim = 2``) scenarios use arms that move in their base x-y plane, with yaw-only bases;
- the graph is connected; for distance formations it is infinitesimally rigid at the shape (a
  ``UserWarning`` says when it is rigid but not minimally rigid, the paper's assumption);
- the shape is reachable: some placement of it (translations, and for distance formations rotations and
  reflections) puts every vertex inside its arm's sampled workspace;
- no initial configuration is at a kinematic singularity.
"""

from __future__ import annotations

import functools
import math
import warnings
from dataclasses import dataclass

import numpy as np

from ee_formation_env.formation import FormationGraph, check_rigidity
from ee_formation_env.kinematics import SerialChain
from ee_formation_env.scenario import ArmConfig, Scenario


@functools.lru_cache(maxsize=32)
def chain_model(urdf: str, ee_link: str) -> SerialChain:
    """The (cached) kinematic model of a URDF up to ``ee_link``."""
    return SerialChain.from_urdf(urdf, ee_link)


def rpy_matrix(rpy: tuple[float, float, float] | np.ndarray) -> np.ndarray:
    """Rotation matrix of URDF/PyBullet roll-pitch-yaw angles: ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    roll, pitch, yaw = rpy
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def initial_configuration(arm: ArmConfig, model: SerialChain) -> np.ndarray:
    """The arm's nominal initial joint positions (rad); zeros when the scenario gives none."""
    if arm.initial_q is None:
        return np.zeros(model.n_joints)
    return np.asarray(arm.initial_q, dtype=np.float64)


@dataclass(frozen=True)
class Workspace:
    """Occupancy grid of an arm's reachable end-effector positions in its base frame (first ``dim`` axes)."""

    origin: np.ndarray  # (dim,) m, lower corner of cell 0
    cell: float  # m
    occupied: np.ndarray  # bool grid, dim axes
    reach: float  # m, largest distance of a sampled position from the base origin

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Which of the (k, dim) base-frame points fall in an occupied cell."""
        index = np.floor((points - self.origin) / self.cell).astype(np.int64)
        inside = np.all((index >= 0) & (index < np.array(self.occupied.shape)), axis=1)
        result = np.zeros(len(points), dtype=bool)
        result[inside] = self.occupied[tuple(index[inside].T)]
        return result

    def cell_centres(self) -> np.ndarray:
        """(k, dim) base-frame centres of the occupied cells."""
        return (np.argwhere(self.occupied) + 0.5) * self.cell + self.origin


@functools.lru_cache(maxsize=32)
def workspace(urdf: str, ee_link: str, dim: int) -> Workspace:
    """Sampled workspace of an arm (seeded, so validation is deterministic), dilated by one cell.

    The dilation makes the test generous: a shape is reported out of reach only when it is clearly so.
    """
    model = chain_model(urdf, ee_link)
    rng = np.random.default_rng(0)
    count, cells_across_reach = (20_000, 40) if dim == 2 else (60_000, 14)
    points = model.forward_batch(model.sample_configurations(count, rng))[:, :dim]
    reach = float(np.max(np.linalg.norm(points, axis=1)))
    cell = max(reach, 1e-3) / cells_across_reach
    origin = points.min(axis=0) - 2 * cell
    index = np.floor((points - origin) / cell).astype(np.int64)
    grid = np.zeros(tuple(index.max(axis=0) + 3), dtype=bool)
    grid[tuple(index.T)] = True
    dilated = grid.copy()
    for axis in range(dim):
        dilated |= np.roll(grid, 1, axis=axis) | np.roll(grid, -1, axis=axis)
    return Workspace(origin=origin, cell=cell, occupied=dilated, reach=reach)


def _candidate_rotations(dim: int, allow_rotation: bool) -> list[np.ndarray]:
    if not allow_rotation:
        return [np.eye(dim)]
    if dim == 2:
        rotations = [np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
                     for a in np.linspace(0.0, 2 * math.pi, 360, endpoint=False)]
        mirror = np.diag([1.0, -1.0])
    else:
        rng = np.random.default_rng(0)
        quaternions = rng.normal(size=(400, 4))
        quaternions /= np.linalg.norm(quaternions, axis=1, keepdims=True)
        rotations = [np.eye(3)] + [_quaternion_matrix(q) for q in quaternions]
        mirror = np.diag([1.0, 1.0, -1.0])
    # Distances are preserved by reflections too, so mirrored placements are goals as well.
    return rotations + [rotation @ mirror for rotation in rotations]


def _quaternion_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def find_reachable_placement(scenario: Scenario) -> np.ndarray | None:
    """A placement (N, dim) of the scenario's shape inside every arm's workspace, or None if none is found."""
    dim = scenario.dim
    shape = np.asarray(scenario.shape)
    spaces = [workspace(arm.urdf, arm.ee_link, dim) for arm in scenario.arms]
    rotations_to_base = [rpy_matrix(arm.base_rpy)[:dim, :dim] for arm in scenario.arms]
    bases = [np.asarray(arm.base_position)[:dim] for arm in scenario.arms]
    # Candidate positions of vertex 0: the centres of arm 0's workspace cells, in the world frame.
    anchors = spaces[0].cell_centres() @ rotations_to_base[0].T + bases[0]
    for rotation in _candidate_rotations(dim, scenario.formation == "distance"):
        placed_shape = shape @ rotation.T
        translations = anchors - placed_shape[0]
        feasible = np.ones(len(translations), dtype=bool)
        for i in range(1, scenario.n_agents):
            vertex = translations[feasible] + placed_shape[i]
            local = (vertex - bases[i]) @ rotations_to_base[i]
            feasible[np.flatnonzero(feasible)[~spaces[i].contains(local)]] = False
            if not feasible.any():
                break
        if feasible.any():
            return placed_shape + translations[np.flatnonzero(feasible)[0]]
    return None


def validate_scenario(scenario: Scenario) -> list[SerialChain]:
    """Run every geometric check; return the arms' kinematic models (one per arm)."""
    models = []
    for i, arm in enumerate(scenario.arms):
        try:
            model = chain_model(arm.urdf, arm.ee_link)
        except ValueError as error:
            raise ValueError(f"arms[{i}]: {error}") from None
        models.append(model)
        _check_arm(i, arm, model, scenario)

    graph = FormationGraph(scenario.n_agents, scenario.edges)
    if not graph.is_connected():
        raise ValueError(f"edges: the formation graph is not connected: {list(scenario.edges)}")
    if scenario.formation == "distance":
        report = check_rigidity(graph, np.asarray(scenario.shape))
        if not report.rigid:
            raise ValueError(
                f"edges: the graph is not infinitesimally rigid at the shape (rigidity matrix rank "
                f"{report.rank} < {report.required_rank} needed in {scenario.dim}D with {scenario.n_agents} "
                "agents); a distance formation needs more edges, or a shape in general position"
            )
        if not report.minimal:
            warnings.warn(
                f"edges: the graph is infinitesimally rigid but not minimally rigid ({report.n_edges} edges, "
                f"{report.required_rank} suffice); the paper's convergence proof assumes minimal rigidity",
                UserWarning, stacklevel=3,
            )

    if find_reachable_placement(scenario) is None:
        spaces = [workspace(arm.urdf, arm.ee_link, scenario.dim) for arm in scenario.arms]
        raise ValueError(
            "shape: the formation is out of reach: no placement of the shape "
            f"({'translations, rotations and reflections' if scenario.formation == 'distance' else 'translations'}) "
            "puts every vertex inside its arm's workspace (arm reaches "
            f"{[round(space.reach, 3) for space in spaces]} m from their bases)"
        )
    return models


def singularity_margin(model: SerialChain, q: np.ndarray, dim: int) -> float:
    """Smallest singular value (m) of the arm's translational Jacobian restricted to the formation's axes."""
    return float(np.linalg.svd(model.jacobian(q)[:dim], compute_uv=False).min())


def _check_arm(index: int, arm: ArmConfig, model: SerialChain, scenario: Scenario) -> None:
    where = f"arms[{index}]"
    q0 = initial_configuration(arm, model)
    if q0.shape != (model.n_joints,):
        raise ValueError(
            f"{where}.initial_q: expected {model.n_joints} values (joints {list(model.joint_names)}), "
            f"got {len(q0)}"
        )
    outside = (q0 < model.lower - 1e-9) | (q0 > model.upper + 1e-9)
    if outside.any():
        j = int(np.flatnonzero(outside)[0])
        raise ValueError(
            f"{where}.initial_q: joint {model.joint_names[j]} = {q0[j]:.4f} rad is outside its limits "
            f"[{model.lower[j]:.4f}, {model.upper[j]:.4f}]"
        )
    limits = scenario.torque_limits
    if isinstance(limits, tuple):
        row = limits[index] if isinstance(limits[0], tuple) else limits
        if len(row) != model.n_joints:
            raise ValueError(f"torque_limits: {where} has {model.n_joints} joints, got {len(row)} limits")
    if scenario.dim == 2:
        if abs(arm.base_rpy[0]) > 1e-9 or abs(arm.base_rpy[1]) > 1e-9:
            raise ValueError(f"{where}.base_rpy: a planar (dim = 2) scenario needs yaw-only bases, got {arm.base_rpy}")
        samples = model.forward_batch(model.sample_configurations(64, np.random.default_rng(0)))
        if np.ptp(samples[:, 2]) > 1e-9:
            raise ValueError(
                f"{where}: robot {model.robot_name!r} does not move in its base x-y plane; use dim = 3"
            )
    margin = singularity_margin(model, q0, scenario.dim)
    if margin < scenario.singularity_threshold:
        raise ValueError(
            f"{where}.initial_q: {q0.tolist()} is at a kinematic singularity (smallest Jacobian singular "
            f"value {margin:.2e} m < singularity_threshold {scenario.singularity_threshold:.1e} m)"
        )
