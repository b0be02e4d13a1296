"""The layout of one agent's observation vector: built by the env, parsed by controllers.

Per neighbour slot: ``[mask, z_ij (dim), desired (w), edge_error (w)]``, ``n_slots`` times, then
``q (n_joints)`` and ``dq (n_joints)``; ``w`` is 1 for distance and ``dim`` for displacement formations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ObservationParts:
    """One observation split into named parts (views into a float64 copy)."""

    mask: np.ndarray  # (n_slots,) 1 for a real neighbour, 0 for padding
    relative_positions: np.ndarray  # (n_slots, dim) z_ij = x_i - x_j, m
    desired: np.ndarray  # (n_slots, w) d*_ij or z*_ij, m
    edge_errors: np.ndarray  # (n_slots, w) |z_ij|^2 - d*_ij^2 (m^2) or z_ij - z*_ij (m)
    q: np.ndarray  # (n_joints,) rad
    dq: np.ndarray  # (n_joints,) rad/s


@dataclass(frozen=True)
class ObservationLayout:
    """Sizes of an agent's observation; :meth:`split` parses one."""

    n_slots: int
    dim: int
    error_width: int
    n_joints: int

    @property
    def slot_size(self) -> int:
        return 1 + self.dim + 2 * self.error_width

    @property
    def size(self) -> int:
        return self.n_slots * self.slot_size + 2 * self.n_joints

    def split(self, observation: np.ndarray) -> ObservationParts:
        observation = np.asarray(observation, dtype=np.float64)
        if observation.shape != (self.size,):
            raise ValueError(f"observation: expected shape ({self.size},), got {observation.shape}")
        m, w, n = self.dim, self.error_width, self.n_joints
        slots = observation[:self.n_slots * self.slot_size].reshape(self.n_slots, self.slot_size)
        return ObservationParts(
            mask=slots[:, 0],
            relative_positions=slots[:, 1:1 + m],
            desired=slots[:, 1 + m:1 + m + w],
            edge_errors=slots[:, 1 + m + w:],
            q=observation[-2 * n:-n],
            dq=observation[-n:],
        )
