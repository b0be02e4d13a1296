"""Torque mode: the learned action is the normalized joint torque, in physical units.

For each agent row: ``action = clip(learned, -1, 1) * joint_scale``, ``joint_scale`` the per-joint physical
scale of one unit of learned action (:mod:`~ee_formation_env.baselines.learned.action_scale`). Where every
joint keeps its torque limit (every built-in robot) the learned action is the env's action, passed on as it
is (the env clips it). Rewards are the env's. The mode's design and its figures: docs/training.md ("Modes").
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from ee_formation_env.baselines.learned.modes import ActionRows, ModePreset, PPOSettings, TrainingMode, register_mode


class TorqueRows(ActionRows):
    """The torque rule (module docstring) over R rows; ``joint_scales`` (R,): each row's per-joint scale (n,),
    or None where the learned action is the env's."""

    def __init__(self, joint_scales: Sequence[np.ndarray | None]):
        self.joint_scales = list(joint_scales)
        given = [scale for scale in self.joint_scales if scale is not None]
        self._scales = None if not given else np.stack(
            [np.ones_like(given[0]) if scale is None else scale for scale in self.joint_scales])  # (R, n)

    def __call__(self, observations: np.ndarray, learned: np.ndarray) -> tuple[np.ndarray, None]:
        if self._scales is None:
            return learned, None
        return np.clip(np.asarray(learned, dtype=np.float64), -1.0, 1.0) * self._scales, None

    def split(self) -> list["TorqueRows"]:
        return [TorqueRows([scale]) for scale in self.joint_scales]

    @classmethod
    def concatenate(cls, parts: Sequence["TorqueRows"]) -> "TorqueRows":
        return cls([scale for part in parts for scale in part.joint_scales])


@register_mode
class TorqueMode(TrainingMode):
    """``mode="torque"`` (module docstring)."""

    name = "torque"
    help = "learn the joint torques"
    imitation = True
    #: Longer episodes, wider start noise, log-scaled error features, the hold penalty and a larger network; the
    #: layout of its documented 30-minute run (8 envs in-process, 128 steps). docs/training.md gives the evidence.
    preset = ModePreset(
        total_timesteps=5_000_000, train_episode_seconds=10.0, train_initial_q_noise=0.1, obs_features="log-error",
        gamma=0.99, hold_penalty=0.5, log_std_init=-2.0,
        ppo=PPOSettings(net_arch=(128, 128), n_epochs=10, learning_rate=3e-4, learning_rate_decay=True),
        n_envs=8, n_steps=128, n_workers=0, in_process_envs=0, max_fault_fraction=0.9,
        fault_guard_start=0.25)

    def action_rows(self, options: Any, copies: Sequence[Any], agents: Sequence[str],
                    joint_scales: Mapping[str, np.ndarray] | None) -> TorqueRows:
        return TorqueRows([None if joint_scales is None else joint_scales[agent] for _ in copies for agent in agents])
