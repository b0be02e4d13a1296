"""Position mode: the learned action is each joint's target angle about the arm's initial configuration, held by
a critically damped PD loop on the agent's own joints, with the env's gravity compensation.

For each agent row, with ``r = clip(learned, -1, 1)`` and ``q``, ``dq`` the joint positions and velocities of
the agent's own observation:

``target = clip(q_0 + joint_reach * r, lower, upper)``
``torque = H(q_0) * (position_gain^2 * wrap(target - q) - 2 * position_gain * dq)``, plus the env's ``g(q)``

``q_0`` the arm's initial configuration of the scenario (rad; the same in every episode, whatever the start
noise), ``H(q_0)`` its nominal mass matrix there (kg m^2,
:func:`~ee_formation_env.baselines.learned.action_scale.initial_mass_matrices`), ``joint_reach`` (rad per unit
of action) and ``position_gain`` (1/s: the loop's natural frequency) the training options, ``lower`` and
``upper`` the joint's limits (rad: a target past a limit would only push the joint into its stop); ``wrap``
takes a continuous joint's angle error to [-pi, pi). With ``target_smoothing`` (s) above 0 the PD loop tracks
the targets through a first-order low-pass filter of that time constant, restarted at each episode's first
target (each row keeps its filtered target: state, like the residual mode's reference controllers); without
it, a policy that switches its targets from step to step chatters. The env clips the torque to each joint's
limit. A constant action holds a constant posture, so a policy that reaches the formation holds it without integrating its own small
errors (the velocity mode's joint speeds do). This is the joint-position controller of robot-learning
practice (a torque relative to a PD hold), built from local information only. The mode always runs with
``gravity_compensation`` on (:attr:`PositionMode.env_settings`), in training and evaluation. Rewards are the
env's. Why this convention, with its figures: docs/training.md ("Modes").
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np

from ee_formation_env.baselines.learned.action_scale import initial_mass_matrices
from ee_formation_env.baselines.learned.modes import ActionRows, RowJointStates, TrainingMode, register_mode
from ee_formation_env.baselines.learned.velocity import VelocityMode
from ee_formation_env.observation import ObservationLayout

#: The largest ``position_gain * control period`` accepted: the sampled loop's damping term stays well inside
#: its stable range (it diverges where ``2 * position_gain * period`` passes 2).
MAX_GAIN_PERIOD = 0.5


class TargetFilter:
    """One row's filtered joint target (n,), rad; None until the first step after a reset."""

    __slots__ = ("value",)

    def __init__(self) -> None:
        self.value: np.ndarray | None = None


class PositionRows(ActionRows):
    """The position rule (module docstring) over R rows.

    ``layouts`` (R,): each row's observation layout (where its ``q`` and ``dq`` are). ``masses`` (R,): each row's
    ``H(q_0)`` over its joints' torque limits (n, n), normalized torque per rad/s² of acceleration. ``homes``
    (R,): each row's ``q_0`` (n,), rad. ``limits`` (R,): each row's joint limits (2, n), rad (lower, upper; infinite
    for a continuous joint, whose angle error is wrapped). ``decays`` (R,): each row's filter factor per control
    step, ``exp(-control period / target_smoothing)`` (0: no filter; default). ``filters`` (R,): each row's
    :class:`TargetFilter` (default: new ones); a rule of one row and a stack of such rules share them.
    """

    def __init__(self, layouts: Sequence[ObservationLayout], masses: Sequence[np.ndarray], homes: Sequence[np.ndarray],
                 limits: Sequence[np.ndarray], joint_reach: float, position_gain: float,
                 decays: Sequence[float] | None = None, filters: Sequence["TargetFilter"] | None = None):
        self.layouts, self.masses, self.homes = list(layouts), list(masses), list(homes)
        self.limits = list(limits)
        self.joint_reach, self.position_gain = float(joint_reach), float(position_gain)
        self.decays = [0.0] * len(self.layouts) if decays is None else [float(d) for d in decays]
        self.filters = [TargetFilter() for _ in self.layouts] if filters is None else list(filters)
        self._decays = np.array(self.decays)[:, None]  # (R, 1)
        self._filtered = bool(np.any(self._decays > 0))
        self._masses, self._homes = np.stack(self.masses), np.stack(self.homes)  # (R, n, n), (R, n)
        stacked = np.stack(self.limits)  # (R, 2, n)
        self._lower, self._upper = stacked[:, 0], stacked[:, 1]
        self._continuous = ~np.isfinite(self._lower) & ~np.isfinite(self._upper)
        self._any_continuous = bool(self._continuous.any())
        self._joint_states = RowJointStates(self.layouts)

    def __call__(self, observations: np.ndarray, learned: np.ndarray) -> tuple[np.ndarray, None]:
        targets = self._homes + self.joint_reach * np.clip(np.asarray(learned, dtype=np.float64), -1.0, 1.0)
        targets = np.minimum(np.maximum(targets, self._lower), self._upper)
        if self._filtered:
            targets = self._filter(targets)
        q, dq = self._joint_states(observations, targets.shape[1])
        error = targets - q
        if self._any_continuous:
            error = np.where(self._continuous, (error + math.pi) % (2 * math.pi) - math.pi, error)
        gain = self.position_gain
        accelerations = gain * gain * error - 2.0 * gain * dq  # rad/s², critically damped
        return np.einsum("rjk,rk->rj", self._masses, accelerations), None

    def _filter(self, targets: np.ndarray) -> np.ndarray:
        """The filtered targets (R, n): each row's previous filtered target moved toward ``targets`` by
        ``1 - decay``, or ``targets`` itself on a row's first step since its reset."""
        previous = np.array([targets[r] if f.value is None else f.value for r, f in enumerate(self.filters)])
        filtered = self._decays * previous + (1.0 - self._decays) * targets
        for row, target_filter in enumerate(self.filters):
            target_filter.value = filtered[row]
        return filtered

    def reset(self, rows: Sequence[int] | np.ndarray | None = None) -> None:
        for row in range(len(self.filters)) if rows is None else rows:
            self.filters[int(row)].value = None

    def split(self) -> list["PositionRows"]:
        return [PositionRows([layout], [mass], [home], [limits], self.joint_reach, self.position_gain, [decay],
                             [target_filter])
                for layout, mass, home, limits, decay, target_filter in zip(
                    self.layouts, self.masses, self.homes, self.limits, self.decays, self.filters)]

    @property
    def stack_key(self) -> Any:
        return type(self), self.joint_reach, self.position_gain

    @classmethod
    def concatenate(cls, parts: Sequence["PositionRows"]) -> "PositionRows":
        if any(part.stack_key != parts[0].stack_key for part in parts):
            raise ValueError("joint_reach, position_gain: rows of different settings cannot be stacked into one rule")
        return cls([layout for part in parts for layout in part.layouts],
                   [mass for part in parts for mass in part.masses], [home for part in parts for home in part.homes],
                   [limits for part in parts for limits in part.limits], parts[0].joint_reach,
                   parts[0].position_gain, [decay for part in parts for decay in part.decays],
                   [target_filter for part in parts for target_filter in part.filters])


@register_mode
class PositionMode(TrainingMode):
    """``mode="position"`` (module docstring)."""

    name = "position"
    help = ("learn the joint target angles about the initial configuration (a damped PD loop with gravity "
            "compensation holds them)")
    env_settings = {"gravity_compensation": True}
    #: The velocity preset (10 s episodes, start noise, log-scaled error features, the hold penalty, 128 x 128,
    #: an initial spread of e^-1 of a unit of action). docs/training.md gives the evidence.
    preset = VelocityMode.preset

    def action_rows(self, options: Any, copies: Sequence[Any], agents: Sequence[str],
                    joint_scales: Mapping[str, np.ndarray] | None) -> PositionRows:
        layouts, masses, homes, limits, decays = [], [], [], [], []
        for copy_env in copies:
            task, period = copy_env.task, copy_env.scenario.control_dt
            if options.position_gain * period > MAX_GAIN_PERIOD:
                raise ValueError(f"position_gain: expected at most {MAX_GAIN_PERIOD:g} / control period = "
                                 f"{MAX_GAIN_PERIOD / period:.4g} 1/s on scenario {copy_env.scenario.name!r} (control "
                                 f"period {period:.4g} s), got {options.position_gain:g}")
            mass_matrices, torque_limits = initial_mass_matrices(task), dict(zip(task.agents, task.torque_limits))
            index = {agent: i for i, agent in enumerate(task.agents)}
            for agent in agents:
                i = index[agent]
                layouts.append(copy_env.observation_layout(agent))
                masses.append(mass_matrices[agent] / torque_limits[agent][:, None])
                homes.append(np.asarray(task.initial_q[i], dtype=np.float64))
                limits.append(np.array([task.models[i].lower, task.models[i].upper], dtype=np.float64))
                decays.append(math.exp(-period / options.target_smoothing) if options.target_smoothing > 0 else 0.0)
        return PositionRows(layouts, masses, homes, limits, options.joint_reach, options.position_gain, decays)

