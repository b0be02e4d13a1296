"""Velocity mode: the learned action is each joint's commanded speed, turned into a torque by a damped velocity
loop on the agent's own joints, with the env's gravity compensation.

For each agent row, with ``r = clip(learned, -1, 1)`` and ``dq`` the joint velocities of the agent's own
observation:

``torque = H(q_0) * velocity_gain * (joint_speed * r - dq)``, plus the env's ``g(q)``

``H(q_0)`` the arm's nominal mass matrix at its initial configuration (kg m^2,
:func:`~ee_formation_env.baselines.learned.action_scale.initial_mass_matrices`), ``joint_speed`` (rad/s) and
``velocity_gain`` (1/s: the inverse time constant of reaching the commanded speed) the training options. The
full matrix, not its diagonal, makes every joint reach its speed at the one rate near ``q_0`` (a diagonal loop
leaves coupled modes three times slower on the built-in arms). The env clips the torque to each joint's limit. A zero action brakes every joint to rest and holds it there against
gravity: the torque relative to a PD hold of robot-learning practice (a joint velocity controller), built from
local information only. The mode always runs with ``gravity_compensation`` on (:attr:`VelocityMode.env_settings`),
in training and evaluation. Rewards are the env's. Why this convention, with its figures: docs/training.md
("Modes").
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping, Sequence

import numpy as np

from ee_formation_env.baselines.learned.action_scale import initial_mass_matrices
from ee_formation_env.baselines.learned.modes import ActionRows, RowJointStates, TrainingMode, register_mode
from ee_formation_env.baselines.learned.torque import TorqueMode
from ee_formation_env.observation import ObservationLayout


class VelocityRows(ActionRows):
    """The velocity rule (module docstring) over R rows.

    ``layouts`` (R,): each row's observation layout (where its ``dq`` is). ``gains`` (R,): each row's
    normalized torques per rad/s of speed error (n, n): ``H(q_0) * velocity_gain``, row j over joint j's torque
    limit.
    ``joint_speed``: rad/s of one unit of learned action.
    """

    def __init__(self, layouts: Sequence[ObservationLayout], gains: Sequence[np.ndarray], joint_speed: float):
        self.layouts, self.gains, self.joint_speed = list(layouts), list(gains), float(joint_speed)
        self._gains = np.stack(self.gains)  # (R, n, n)
        self._joint_states = RowJointStates(self.layouts)

    def __call__(self, observations: np.ndarray, learned: np.ndarray) -> tuple[np.ndarray, None]:
        commanded = self.joint_speed * np.clip(np.asarray(learned, dtype=np.float64), -1.0, 1.0)  # (R, n), rad/s
        speeds = self._joint_states(observations, commanded.shape[1])[1]
        return np.einsum("rjk,rk->rj", self._gains, commanded - speeds), None

    def split(self) -> list["VelocityRows"]:
        return [VelocityRows([layout], [gain], self.joint_speed) for layout, gain in zip(self.layouts, self.gains)]

    @property
    def stack_key(self) -> Any:
        return type(self), self.joint_speed

    @classmethod
    def concatenate(cls, parts: Sequence["VelocityRows"]) -> "VelocityRows":
        if any(part.joint_speed != parts[0].joint_speed for part in parts):
            raise ValueError("joint_speed: rows of different joint speeds cannot be stacked into one rule")
        return cls([layout for part in parts for layout in part.layouts],
                   [gain for part in parts for gain in part.gains], parts[0].joint_speed)


@register_mode
class VelocityMode(TrainingMode):
    """``mode="velocity"`` (module docstring)."""

    name = "velocity"
    help = "learn the joint speeds (a damped velocity loop with gravity compensation turns them into torques)"
    env_settings = {"gravity_compensation": True}
    #: The torque preset (10 s episodes, start noise, log-scaled error features, the hold penalty, 128 x 128),
    #: with a wider initial spread: a unit of action is a speed, not a torque, so exploring at a third of it is
    #: safe. docs/training.md gives the evidence.
    preset = dataclasses.replace(TorqueMode.preset, log_std_init=-1.0)

    def action_rows(self, options: Any, copies: Sequence[Any], agents: Sequence[str],
                    joint_scales: Mapping[str, np.ndarray] | None) -> VelocityRows:
        layouts, gains = [], []
        for copy_env in copies:
            task, period = copy_env.task, copy_env.scenario.control_dt
            if options.velocity_gain * period > 1.0:  # the sampled loop overshoots, then diverges past 2
                raise ValueError(f"velocity_gain: expected at most 1 / control period = {1.0 / period:.4g} 1/s on "
                                 f"scenario {copy_env.scenario.name!r} (control period {period:.4g} s), got "
                                 f"{options.velocity_gain:g}")
            masses, limits = initial_mass_matrices(task), dict(zip(task.agents, task.torque_limits))
            for agent in agents:
                layouts.append(copy_env.observation_layout(agent))
                gains.append(masses[agent] * options.velocity_gain / limits[agent][:, None])
        return VelocityRows(layouts, gains, options.joint_speed)
