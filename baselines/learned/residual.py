"""Residual mode: the learned action is a correction added to a reference controller's normalized torque.

For each agent row, with ``r = clip(learned, -1, 1)``:

``action = reference(observation) + residual_scale * g * joint_scale * r``

``g = min(1, x) ** p`` with ``residual_gate`` (:func:`error_gates`: ``x`` the agent's mean edge error in success
tolerances, read from its own observation; ``p`` the ``residual_gate_power``, 1 by default), else 1;
``joint_scale`` the per-joint physical scale of a learned action
(:mod:`~ee_formation_env.baselines.learned.action_scale`; 1 on the built-in robots). Each agent's reward is
multiplied by ``1 - correction_penalty * mean(r^2)``, in [0, 1]. A zero correction applies the reference's
action bit for bit and receives the env's reward exactly.

:class:`ResidualRows` is the rule over a stack of rows; the training env applies it to its K x N agents and
an evaluated per-agent policy is its one-row case. Why the gate and the penalty, with the figures: the
training docs (docs/training.md, "Modes").
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from ee_formation_env import baselines
from ee_formation_env.baselines.learned.modes import ActionRows, ModePreset, PPOSettings, TrainingMode, register_mode
from ee_formation_env.baselines.reference.team import PolicyTeam
from ee_formation_env.observation import ObservationLayout
from ee_formation_env.reward import DEFAULT_POSITION_TOLERANCE


def error_gates(layout: ObservationLayout, observations: np.ndarray,
                position_tolerance: float = DEFAULT_POSITION_TOLERANCE) -> np.ndarray:
    """``min(1, x)`` per row of a stack (k, size) of observations of one layout: (k,). ``x`` is the mean over
    the agent's neighbour slots of ``|e_ij| / tol_ij``, ``tol_ij = 2 d*_ij delta`` (distance, one error entry
    per slot) or ``delta`` (displacement), ``delta = position_tolerance`` (m): the reward's error ratio, seen
    by the agent."""
    parts = layout.split(observations)
    real = parts.mask > 0.5  # (k, slots)
    errors = np.linalg.norm(parts.edge_errors, axis=2)  # |e_ij| per slot
    ratios = np.where(real, errors / layout.slot_tolerances(parts, position_tolerance), 0.0)
    return np.minimum(1.0, ratios.sum(axis=1) / real.sum(axis=1))


def error_gate(layout: ObservationLayout, observation: np.ndarray,
               position_tolerance: float = DEFAULT_POSITION_TOLERANCE) -> float:
    """:func:`error_gates` of one observation."""
    return float(error_gates(layout, np.asarray(observation)[None], position_tolerance)[0])


class ResidualRows(ActionRows):
    """The residual rule (module docstring) over R rows, in one set of batched calls: the rows' reference
    controllers as one :class:`~ee_formation_env.baselines.reference.team.PolicyTeam`, the gates of the
    rows of one observation layout in one call.

    ``references`` (R,): each row's reference controller (stateful: :meth:`reset` restarts it).
    ``gate_layouts`` (R,): each row's observation layout where its correction is gated, else None.
    ``joint_scales`` (R,): each row's per-joint scale (n,), or None for 1 on every joint.
    """

    def __init__(self, references: Sequence[Any], scale: float, correction_penalty: float,
                 gate_layouts: Sequence[ObservationLayout | None], joint_scales: Sequence[np.ndarray | None],
                 gate_power: float = 1.0):
        self.references, self.scale, self.gate_power = list(references), float(scale), float(gate_power)
        self.correction_penalty = float(correction_penalty)
        self.gate_layouts, self.joint_scales = list(gate_layouts), list(joint_scales)
        self.team = PolicyTeam(dict(enumerate(self.references)))
        self._scales = np.full(len(self.references), self.scale)
        given = [scale for scale in self.joint_scales if scale is not None]
        self._joint_scales = None if not given else np.stack(
            [np.ones_like(given[0]) if scale is None else scale for scale in self.joint_scales])  # (R, n)
        groups: dict[ObservationLayout, list[int]] = {}
        for row, layout in enumerate(self.gate_layouts):
            if layout is not None:
                groups.setdefault(layout, []).append(row)
        self._gate_groups = [(layout, np.array(rows)) for layout, rows in groups.items()]

    def reset(self, rows: Sequence[int] | np.ndarray | None = None) -> None:
        """Restart the reference controllers of ``rows`` (default: all), at the start of their episodes."""
        for row in range(len(self.references)) if rows is None else rows:
            self.references[int(row)].reset()

    def __call__(self, observations: np.ndarray, learned: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The applied actions (R, n), float64, and the reward factors ``1 - correction_penalty * mean(r^2)``
        (R,), or None without a penalty."""
        residuals = np.clip(np.asarray(learned, dtype=np.float64), -1.0, 1.0)
        references = self.team.act_on_stack(observations)
        scales = self._scales.copy()
        for layout, rows in self._gate_groups:
            gates = error_gates(layout, observations[rows])
            scales[rows] *= gates if self.gate_power == 1.0 else gates ** self.gate_power
        scales = scales[:, None] if self._joint_scales is None else scales[:, None] * self._joint_scales
        factors = None
        if self.correction_penalty > 0:
            factors = 1.0 - self.correction_penalty * np.mean(residuals * residuals, axis=1)
        return references + scales * residuals, factors

    def split(self) -> list["ResidualRows"]:
        return [ResidualRows([reference], self.scale, self.correction_penalty, [layout], [scale], self.gate_power)
                for reference, layout, scale in zip(self.references, self.gate_layouts, self.joint_scales)]

    @property
    def stack_key(self) -> Any:
        return type(self), self.scale, self.correction_penalty, self.gate_power

    @classmethod
    def concatenate(cls, parts: Sequence["ResidualRows"]) -> "ResidualRows":
        """One rule over the rows of ``parts`` in order (the same controller objects); they must share the
        scale, the penalty and the gate's power."""
        first = parts[0]
        if any((part.scale, part.correction_penalty, part.gate_power) !=
               (first.scale, first.correction_penalty, first.gate_power) for part in parts):
            raise ValueError("residual_scale: rows of different residual scales, correction penalties or gate "
                             "powers cannot be stacked into one rule")
        return cls([r for part in parts for r in part.references], first.scale, first.correction_penalty,
                   [layout for part in parts for layout in part.gate_layouts],
                   [scale for part in parts for scale in part.joint_scales], first.gate_power)


@register_mode
class ResidualMode(TrainingMode):
    """``mode="residual"`` (module docstring)."""

    name = "residual"
    help = "learn a correction on top of the reference controller"
    #: Short episodes, the raw observation, 32 envs of which 18 in the learner's process beside one worker
    #: (throughput); docs/training.md gives the evidence.
    preset = ModePreset(
        total_timesteps=600_000, train_episode_seconds=3.0, train_initial_q_noise=None, obs_features="none",
        gamma=0.99, hold_penalty=0.0, log_std_init=-1.0,
        ppo=PPOSettings(net_arch=(64, 64), n_epochs=5, learning_rate=3e-4, learning_rate_decay=False),
        n_envs=32, n_steps=32, n_workers=1, in_process_envs=18)

    def check(self, options: Any) -> None:
        if options.gravity_compensation:
            raise ValueError("gravity_compensation: residual mode corrects a reference law's raw torques; use it "
                             "with mode torque")

    def action_rows(self, options: Any, copies: Sequence[Any], agents: Sequence[str],
                    joint_scales: Mapping[str, np.ndarray] | None) -> ResidualRows:
        references, layouts = [], []
        for copy_env in copies:
            team = baselines.make_policies(options.reference, copy_env)
            references += [team[agent] for agent in agents]
            layouts += [copy_env.observation_layout(agent) if options.residual_gate else None for agent in agents]
        scales = [None if joint_scales is None else joint_scales[agent] for _ in copies for agent in agents]
        return ResidualRows(references, options.residual_scale, options.correction_penalty, layouts, scales,
                            options.residual_gate_power)
