"""The formation task: everything derived from a parsed scenario, built once.

:func:`build_task` turns a :class:`~ee_formation_env.scenario.Scenario` into a :class:`FormationTask`, the
one place where the scenario's derived objects are made: the arms' nominal kinematic models, the formation
(graph, desired relations), per-joint torque limits, nominal initial configurations, reaches and base
poses. It then runs the geometric checks of :mod:`ee_formation_env.validation` on what it derived (passed
as arguments: validation does not import this module, so there is no import circle), so a task that exists
is a valid one, and no physics has started. The env, the reference controllers and their gain rule only read
it. The scenario format is documented in ``docs/scenarios.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ee_formation_env.formation import Formation, FormationGraph
from ee_formation_env.kinematics import SerialChain, chain_model, rpy_to_matrix
from ee_formation_env.robots import ROBOTS
from ee_formation_env.scenario import ArmConfig, Scenario
from ee_formation_env.validation import check_task
from ee_formation_env.workspace import workspace


@dataclass(frozen=True, eq=False)
class FormationTask:
    """A validated scenario and everything derived from it. Build with :func:`build_task`.

    Per-arm sequences are in agent order (``arm_0 .. arm_{N-1}``).
    """

    scenario: Scenario
    models: tuple[SerialChain, ...]  # nominal kinematic models (what a controller may know)
    formation: Formation
    torque_limits: tuple[np.ndarray, ...]  # N m, one entry per chain joint
    initial_q: tuple[np.ndarray, ...]  # rad, the scenario's initial joint positions (before reset noise)
    reaches: tuple[float, ...]  # m, farthest end-effector position from the base, in the formation's axes
    base_positions: np.ndarray  # (N, 3) m, world frame
    base_rotations: np.ndarray  # (N, 3, 3) base frame -> world frame

    @property
    def n_agents(self) -> int:
        return len(self.models)

    @property
    def agents(self) -> list[str]:
        """Agent names, ``arm_0 .. arm_{N-1}``."""
        return [f"arm_{i}" for i in range(self.n_agents)]

    @property
    def graph(self) -> FormationGraph:
        return self.formation.graph

    @property
    def dim(self) -> int:
        return self.scenario.dim

    def agent_index(self, agent: str) -> int:
        """Index of ``agent`` (``arm_i``); ValueError for an unknown name."""
        agents = self.agents
        if agent not in agents:
            raise ValueError(f"agent: expected one of {agents}, got {agent!r}")
        return agents.index(agent)

    def gravity_in_base_frame(self, index: int) -> np.ndarray:
        """World gravity (m/s^2) in arm ``index``'s base frame: what its own mounting tells it."""
        return self.base_rotations[index].T @ np.asarray(self.scenario.gravity)

    def gravity_in_base_frames(self) -> np.ndarray:
        """Every arm's :meth:`gravity_in_base_frame` (N, 3), m/s^2."""
        return np.stack([self.gravity_in_base_frame(i) for i in range(self.n_agents)])


def build_task(scenario: Scenario) -> FormationTask:
    """Derive everything from ``scenario`` and validate it; ``ValueError`` naming the field otherwise."""
    models = []
    for i, arm in enumerate(scenario.arms):
        try:
            models.append(chain_model(arm.urdf, arm.ee_link))
        except ValueError as error:
            raise ValueError(f"arms[{i}]: {error}") from None
    task = FormationTask(
        scenario=scenario,
        models=tuple(models),
        formation=Formation(FormationGraph(scenario.n_agents, scenario.edges), scenario.formation,
                            np.asarray(scenario.shape)),
        torque_limits=tuple(_torque_limits(scenario, i, model) for i, model in enumerate(models)),
        initial_q=tuple(_initial_q(arm, model) for arm, model in zip(scenario.arms, models)),
        reaches=tuple(workspace(arm.urdf, arm.ee_link, scenario.dim).reach for arm in scenario.arms),
        base_positions=np.array([arm.base_position for arm in scenario.arms], dtype=np.float64),
        base_rotations=np.stack([rpy_to_matrix(arm.base_rpy) for arm in scenario.arms]),
    )
    check_task(scenario, task.models, task.initial_q, task.graph, task.reaches)
    return task


def _initial_q(arm: ArmConfig, model: SerialChain) -> np.ndarray:
    """The arm's ``initial_q`` (rad); if it gives none, its robot's default start pose (``ROBOTS[...].start_q``),
    or all zeros for an arm given by its URDF."""
    if arm.initial_q is not None:
        return np.asarray(arm.initial_q, dtype=np.float64)
    if arm.robot is not None and len(ROBOTS[arm.robot].start_q) == model.n_joints:
        return np.asarray(ROBOTS[arm.robot].start_q, dtype=np.float64)
    return np.zeros(model.n_joints)


def _torque_limits(scenario: Scenario, index: int, model: SerialChain) -> np.ndarray:
    """Arm ``index``'s per-joint torque limits (N m) from the scenario's ``torque_limits`` (see its docs)."""
    limits = scenario.torque_limits
    if limits is None:
        values = model.effort_limits
        if not np.all(np.isfinite(values) & (values > 0)):
            raise ValueError(
                f"torque_limits: arms[{index}] URDF has joints without a positive effort limit; set torque_limits"
            )
        return values.astype(np.float64)
    if isinstance(limits, float):
        return np.full(model.n_joints, limits)
    row = limits[index] if isinstance(limits[0], tuple) else limits
    if len(row) != model.n_joints:
        raise ValueError(f"torque_limits: arms[{index}] has {model.n_joints} joints, got {len(row)} limits")
    return np.asarray(row, dtype=np.float64)
