"""Learned actions in physical units: one unit of a learned action is a joint acceleration, not an effort limit.

The env's actions are torques normalized by each joint's torque limit, and a URDF's effort limits say little
about its links: ``kuka_iiwa`` gives 300 N m to every joint, its 0.3 kg wrist included, where a learned
action of 0.1 spins the wrist past the env's joint-speed fault in one step. So the learner's actions (torque
mode) and corrections (residual mode) are scaled per joint: one unit is the torque

    tau_unit_j = min(torque_limit_j, action_acceleration / (H(q_0)^-1)_jj)

with ``H`` the arm's nominal mass matrix (kg m^2) at its initial configuration ``q_0`` and
``action_acceleration`` in rad/s^2 (default :data:`DEFAULT_ACTION_ACCELERATION`): a unit torque on joint j
alone (the other joints free) accelerates it by ``action_acceleration`` from rest, gravity aside. The
applied normalized action is the learned one times ``tau_unit / torque_limit`` (a number in (0, 1] per
joint). At the default every joint of the built-in robots keeps its torque limit (the scale is exactly 1,
so their runs are unchanged); the figures are in the training docs ("Action scales").
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ee_formation_env.baselines.reference.dynamics import nominal_dynamics

#: rad/s^2: the joint acceleration one unit of learned action gives at the initial configuration. The built-in
#: arms' torque limits give 17-123 rad/s^2 per joint, so 150 leaves each of them its limit.
DEFAULT_ACTION_ACCELERATION = 150.0


def check_action_acceleration(acceleration: Any) -> float:
    """``acceleration`` as a float; ``ValueError`` naming ``action_acceleration`` unless finite and > 0."""
    if isinstance(acceleration, bool) or not isinstance(acceleration, (int, float)):
        raise TypeError(f"action_acceleration: expected a number (rad/s^2), got {type(acceleration).__name__}")
    if not (math.isfinite(acceleration) and acceleration > 0):
        raise ValueError(f"action_acceleration: expected a finite value > 0 (rad/s^2), got {acceleration!r}")
    return float(acceleration)


def initial_mass_matrices(task: Any) -> dict[str, np.ndarray]:
    """Agent -> its arm's nominal mass matrix ``H(q_0)`` (n, n), kg m^2, at the initial configuration."""
    return {agent: nominal_dynamics(task.scenario.arms[i].urdf, task.models[i].joint_names).mass_matrix(
        task.initial_q[i]) for i, agent in enumerate(task.agents)}


def joint_inertias(task: Any) -> dict[str, np.ndarray]:
    """Agent -> each joint's effective inertia ``1 / (H(q_0)^-1)_jj`` (kg m^2) at the initial configuration:
    what a torque on joint j alone drives, the other joints free (module docstring)."""
    inertias = {}
    for i, (agent, mass_matrix) in enumerate(initial_mass_matrices(task).items()):
        model = task.models[i]
        try:
            inertia = 1.0 / np.diag(np.linalg.inv(mass_matrix))
        except np.linalg.LinAlgError:
            inertia = np.zeros(model.n_joints)
        if not np.all(np.isfinite(inertia) & (inertia > 0)):
            raise ValueError(f"arms[{i}]: the nominal URDF's mass matrix at initial_q is singular (a joint without "
                             "inertia), so a learned action has no physical scale there")
        inertias[agent] = inertia
    return inertias


def unit_torques(task: Any, acceleration: float = DEFAULT_ACTION_ACCELERATION) -> dict[str, np.ndarray]:
    """Agent -> the torque (N m) of one unit of learned action on each of its joints (module docstring)."""
    acceleration = check_action_acceleration(acceleration)
    limits = dict(zip(task.agents, task.torque_limits))
    return {agent: np.minimum(limits[agent], inertia * acceleration) for agent, inertia in joint_inertias(task).items()}


def action_scales(task: Any, acceleration: float = DEFAULT_ACTION_ACCELERATION) -> dict[str, np.ndarray]:
    """Agent -> the normalized env action of one unit of learned action, per joint, in (0, 1]: exactly 1.0
    where the torque limit is the smaller (:func:`unit_torques` / torque limit)."""
    limits = dict(zip(task.agents, task.torque_limits))
    scales = {}
    for agent, torque in unit_torques(task, acceleration).items():
        scale = torque / limits[agent]
        scale[torque == limits[agent]] = 1.0  # exactly: a joint that keeps its limit is not rescaled
        scales[agent] = scale
    return scales


def all_ones(scales: dict[str, np.ndarray]) -> bool:
    """Whether no joint is rescaled (the learned action is the env's action)."""
    return all(bool(np.all(scale == 1.0)) for scale in scales.values())


def rescaling(task: Any, acceleration: float = DEFAULT_ACTION_ACCELERATION) -> dict[str, np.ndarray] | None:
    """:func:`action_scales`, or None where no joint is rescaled (the learned action is the env's action, as
    on every built-in robot): what the training env, the saved policy and the labels apply."""
    scales = action_scales(task, acceleration)
    return None if all_ones(scales) else scales
