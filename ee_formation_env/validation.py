"""Geometric checks of a formation task (a scenario with its derived models), before any physics starts.

They only check: :func:`ee_formation_env.task.build_task` derives, then calls :func:`check_task` with what
it derived (the models, initial configurations, graph, reaches). This module takes those as arguments and
imports nothing from :mod:`ee_formation_env.task`, so the two modules form no import circle. The checks are
described with the scenario format in ``docs/scenarios.md``.

Checks, each failure a ``ValueError`` naming the problem:

- every arm's URDF parses and the mesh files it names exist (PyBullet ends the whole process on a missing
  visual mesh, so this is checked before any client connects); its end-effector link exists and the chain
  is serial and revolute; no link has a negative mass or an inertia tensor that is not positive
  semi-definite;
- ``initial_q`` has one entry per joint and lies within the joint limits;
- planar (``dim = 2``) scenarios use arms that move in their base x-y plane, with yaw-only bases;
- the graph is connected; for distance formations it is infinitesimally rigid at the shape (a
  :class:`RigidityWarning`, a ``UserWarning``, says when it is rigid but not minimally rigid, the paper's
  assumption);
- the shape is reachable: some placement of it (translations, and for distance formations rotations and
  reflections) puts every vertex inside its arm's sampled workspace;
- no initial configuration is at a kinematic singularity;
- a manoeuvre's translation is at most twice the shortest arm's reach (no end-effector follows farther).
"""

from __future__ import annotations

import math
import os
import warnings
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import numpy as np

from typing import Any, Sequence

from ee_formation_env.formation import FormationGraph, check_rigidity
from ee_formation_env.inputs import excerpt, user_stacklevel
from ee_formation_env.kinematics import SerialChain, rpy_to_matrix, singularity_margins
from ee_formation_env.robots import PYBULLET_DATA_ROBOTS, ROBOTS
from ee_formation_env.scenario import ArmConfig, Scenario
from ee_formation_env.workspace import workspace


class RigidityWarning(UserWarning):
    """A distance formation's graph is rigid but not minimally rigid (the paper's assumption); warned once per
    build, attributed to the user's line that built the env or scenario."""


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
    rotations_to_base = [rpy_to_matrix(arm.base_rpy)[:dim, :dim] for arm in scenario.arms]
    bases = [np.asarray(arm.base_position)[:dim] for arm in scenario.arms]
    if not _pairs_can_reach(shape, np.asarray(bases), spaces):
        return None
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


def _pairs_can_reach(shape: np.ndarray, bases: np.ndarray, spaces: Sequence[Any]) -> bool:
    """A necessary condition of a placement, checked in microseconds before the search: every point of arm i's
    (dilated) workspace lies within ``reach_i + 3 cells`` of its base, and placements preserve the shape's
    distances, so each pair's target distance d_ij must be within the bases' distance plus or minus the two
    bounds. False means no placement exists."""
    bounds = np.array([space.reach + 3.0 * space.cell for space in spaces])
    targets = np.linalg.norm(shape[:, None, :] - shape[None, :, :], axis=-1)
    apart = np.linalg.norm(bases[:, None, :] - bases[None, :, :], axis=-1)
    slack = bounds[:, None] + bounds[None, :]
    return bool(np.all(np.abs(targets - apart) <= slack))


def check_task(scenario: Scenario, models: Sequence[SerialChain], initial_q: Sequence[np.ndarray],
               graph: FormationGraph, reaches: Sequence[float]) -> None:
    """Run every geometric check (module docstring) on a scenario and what the task derived from it.

    ``models``, ``initial_q`` (rad) and ``reaches`` (m) are per arm in agent order, ``graph`` the formation
    graph (:class:`ee_formation_env.task.FormationTask`'s fields). ``ValueError`` naming the problem on the
    first failure.
    """
    for i, (arm, model) in enumerate(zip(scenario.arms, models)):
        _check_arm(i, initial_q[i], model, scenario)

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
                RigidityWarning, stacklevel=user_stacklevel(),
            )

    translation = float(np.linalg.norm(scenario.manoeuvre.translation)) if scenario.manoeuvre.active else 0.0
    if translation > 2.0 * min(reaches):
        raise ValueError(
            f"manoeuvre.translation: |A| = {translation:g} m is beyond what the arms can follow: an end-effector "
            f"moves at most across its workspace, twice its reach (shortest reach {min(reaches):.3f} m)")

    if find_reachable_placement(scenario) is None:
        raise ValueError(
            "shape: the formation is out of reach: no placement of the shape "
            f"({'translations, rotations and reflections' if scenario.formation == 'distance' else 'translations'}) "
            "puts every vertex inside its arm's workspace (arm reaches "
            f"{[round(reach, 3) for reach in reaches]} m from their bases)"
        )


def check_inertials(urdf: str | os.PathLike, where: str = "urdf") -> None:
    """Refuse a URDF link whose mass is negative or non-finite, or whose inertia tensor is non-finite or not
    positive semi-definite (PyBullet accepts them and the dynamics then break mid-episode). Massless links
    (mass 0, inertia 0, e.g. an end-effector frame) are fine. ``ValueError`` starting with ``where``."""
    try:
        root = ElementTree.parse(urdf).getroot()
    except (ElementTree.ParseError, OSError):
        return  # the kinematic model's parser reports unreadable files
    for link in root.iter("link"):
        name = link.get("name", "?")
        inertial = link.find("inertial")
        if inertial is None:
            continue
        mass_el, inertia_el = inertial.find("mass"), inertial.find("inertia")
        if mass_el is not None:
            mass = _urdf_number(mass_el.get("value", "0"))
            if not (math.isfinite(mass) and mass >= 0):
                raise ValueError(f"{where}: link {name} has mass {excerpt(mass_el.get('value'))} kg; a link's mass "
                                 "must be a finite number >= 0")
        if inertia_el is not None:
            values = {key: _urdf_number(inertia_el.get(key, "0"))
                      for key in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")}
            tensor = np.array([[values["ixx"], values["ixy"], values["ixz"]],
                               [values["ixy"], values["iyy"], values["iyz"]],
                               [values["ixz"], values["iyz"], values["izz"]]])
            if not np.all(np.isfinite(tensor)):
                raise ValueError(f"{where}: link {name} has a non-finite inertia {values}")
            eigenvalues = np.linalg.eigvalsh(tensor)
            if eigenvalues[0] < -1e-9 * max(1.0, float(np.abs(eigenvalues).max())):
                raise ValueError(f"{where}: link {name} has an inertia tensor that is not positive semi-definite "
                                 f"(principal moments {np.round(eigenvalues, 6).tolist()} kg m^2; {values})")


def _urdf_number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        return math.nan


def missing_meshes(urdf: str) -> list[str]:
    """The ``<mesh filename>`` entries of ``urdf`` (not ``package://``) that name no file next to it."""
    try:
        root = ElementTree.parse(urdf).getroot()
    except (ElementTree.ParseError, OSError):
        return []
    folder = Path(urdf).parent
    names = [mesh.get("filename", "") for mesh in root.iter("mesh")]
    return sorted({name for name in names
                   if name and "://" not in name and not (folder / name).is_file()})


def _check_arm(index: int, q0: np.ndarray, model: SerialChain, scenario: Scenario) -> None:
    where = f"arms[{index}]"
    arm = scenario.arms[index]
    check_inertials(arm.urdf, f"{where}.urdf")
    missing = missing_meshes(arm.urdf)
    if missing:
        raise ValueError(f"{where}.urdf: {arm.urdf} names mesh files that do not exist next to it: "
                         f"{excerpt(missing)}")
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
    if scenario.dim == 2:
        if abs(arm.base_rpy[0]) > 1e-9 or abs(arm.base_rpy[1]) > 1e-9:
            raise ValueError(f"{where}.base_rpy: a planar (dim = 2) scenario needs yaw-only bases, got {arm.base_rpy}")
        samples = model.forward_batch(model.sample_configurations(64, np.random.default_rng(0)))
        if np.ptp(samples[:, 2]) > 1e-9:
            raise ValueError(
                f"{where}: robot {model.robot_name!r} does not move in its base x-y plane; use dim = 3"
            )
    margin = float(singularity_margins(model.jacobian(q0)[None], scenario.dim)[0])
    if margin < scenario.singularity_threshold:
        raise ValueError(
            f"{where}.initial_q: {q0.tolist()} is at a kinematic singularity (smallest Jacobian singular "
            f"value {margin:.2e} m < singularity_threshold {scenario.singularity_threshold:.1e} m); "
            + _bent_pose_hint(arm, model, q0, scenario.dim, scenario.singularity_threshold)
        )


#: The bends (rad) tried, one joint or two at a time, from a singular start to find a suggestion.
_HINT_BENDS = (1.0, -1.0, 0.5, -0.5)


def nonsingular_pose(model: SerialChain, q0: np.ndarray, dim: int, threshold: float,
                     preferred: Sequence[Sequence[float]] = ()) -> tuple[float, ...] | None:
    """A configuration (rad) near ``q0`` within the joint limits whose singularity margin (the smallest Jacobian
    singular value in ``dim`` dimensions, m) is at least ``threshold``, as :func:`check_task` tests a start:
    the first of ``preferred`` (e.g. the robot's start pose) that passes, else ``q0`` with one joint bent by
    one of :data:`_HINT_BENDS`, else with two joints bent; None if none passes."""
    start = np.clip(np.asarray(q0, dtype=np.float64), model.lower, model.upper)
    candidates = [np.asarray(q, dtype=np.float64) for q in preferred if len(q) == model.n_joints]
    joints = range(model.n_joints)
    for first_bend in _HINT_BENDS:
        candidates += [start + first_bend * np.eye(model.n_joints)[j] for j in joints]
    for first_bend in _HINT_BENDS:
        for second_bend in _HINT_BENDS:
            for j in joints:
                candidates += [start + first_bend * np.eye(model.n_joints)[j] + second_bend * np.eye(model.n_joints)[k]
                               for k in joints if k > j]
    for candidate in candidates:
        q = np.round(np.clip(candidate, model.lower, model.upper), 4)  # a suggestion as written, then tested
        if float(singularity_margins(model.jacobian(q)[None], dim)[0]) >= threshold:
            return tuple(q.tolist())
    return None


def _bent_pose_hint(arm: ArmConfig, model: SerialChain, q0: np.ndarray, dim: int, threshold: float) -> str:
    """A concrete suggestion of an initial_q away from singularities, itself checked as the start is."""
    defaults = {spec.urdf.resolve(): spec.start_q for spec in (*ROBOTS.values(), *PYBULLET_DATA_ROBOTS.values())}
    default = ROBOTS[arm.robot].start_q if arm.robot is not None else defaults.get(Path(arm.urdf).resolve())
    pose = nonsingular_pose(model, q0, dim, threshold, preferred=[default] if default is not None else [])
    if pose is None:
        return "bend a joint away from the stretched pose"
    source = " (the robot's default start)" if default is not None and np.allclose(pose, default) else ""
    return f"bend a joint away from the stretched pose, e.g. initial_q: {list(pose)}{source}"
