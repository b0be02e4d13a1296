"""What the batched env (:mod:`ee_formation_env.vector`) hands out besides arrays: its step record
(:class:`BatchedStep`) and its view of one copy (:class:`CopyView`)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

if TYPE_CHECKING:
    from ee_formation_env.vector import VectorFormationEnv

__all__ = ["BatchedStep", "CopyView"]


class BatchedStep(NamedTuple):
    """One batched step (or reset) as stacked arrays: what
    :meth:`~ee_formation_env.vector.VectorFormationEnv.step_arrays` returns.

    ``observations`` (K, O) float32, agents concatenated (agent i's: ``env.observation_slices[i]``);
    ``rewards`` (K, N) float64; ``terminations``, ``truncations`` (K,) bool; ``infos``: per-agent keys
    (:data:`~ee_formation_env.infos.PER_AGENT_INFO`) (K, N, ...), per-copy keys
    (:data:`~ee_formation_env.infos.PER_COPY_INFO`) (K,), ``applied_torque`` (K, T) N m and, with autoreset,
    ``final_observation`` (K, O) (the observation each copy ended in).
    """

    observations: np.ndarray
    rewards: np.ndarray
    terminations: np.ndarray
    truncations: np.ndarray
    infos: dict[str, np.ndarray]


class CopyView:
    """One copy of a batched env (:meth:`~ee_formation_env.vector.VectorFormationEnv.copy_view`): the env's
    attributes, with ``task`` the copy's current one, read when asked (so a controller built on it follows the
    copy's draws)."""

    def __init__(self, env: "VectorFormationEnv", k: int):
        self._env, self._k = env, k

    @property
    def task(self) -> Any:
        return self._env.tasks[self._k]

    def __getattr__(self, name: str) -> Any:
        return getattr(self._env, name)

