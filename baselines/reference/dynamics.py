"""Nominal rigid-body dynamics of an arm (gravity torque, mass matrix) for the reference controllers.

The controllers know only the nominal URDF, never the simulated robot. Its dynamics are evaluated by
PyBullet's recursive Newton-Euler in a private DIRECT client holding the nominal robot at the origin
(one client per process, shared by every arm model), separate from any environment's world.
"""

from __future__ import annotations

import functools

import numpy as np
import pybullet


@functools.lru_cache(maxsize=1)
def _model_client() -> int:
    return pybullet.connect(pybullet.DIRECT)


class NominalDynamics:
    """Gravity torques and mass matrix of the chain joints of a nominal URDF (fixed base)."""

    def __init__(self, urdf: str, joint_names: tuple[str, ...]):
        self.client = _model_client()
        self.body = pybullet.loadURDF(urdf, useFixedBase=True, flags=pybullet.URDF_USE_INERTIA_FROM_FILE,
                                      physicsClientId=self.client)
        movable, names = [], []
        for j in range(pybullet.getNumJoints(self.body, physicsClientId=self.client)):
            info = pybullet.getJointInfo(self.body, j, physicsClientId=self.client)
            if info[2] != pybullet.JOINT_FIXED:
                movable.append(j)
                names.append(info[1].decode())
        # PyBullet's dynamics calls take every movable DOF (e.g. gripper fingers too); ours are a subset.
        self._n_dof = len(movable)
        self._chain = np.array([names.index(name) for name in joint_names], dtype=np.int64)

    def _full(self, q: np.ndarray) -> list[float]:
        full = np.zeros(self._n_dof)
        full[self._chain] = q
        return full.tolist()

    def gravity_torque(self, q: np.ndarray, gravity_in_base: np.ndarray) -> np.ndarray:
        """G(q) (N m): the torques that hold the arm still against ``gravity_in_base`` (m/s^2, base frame)."""
        pybullet.setGravity(*gravity_in_base.tolist(), physicsClientId=self.client)
        zeros = [0.0] * self._n_dof
        torque = pybullet.calculateInverseDynamics(self.body, self._full(q), zeros, zeros, physicsClientId=self.client)
        return np.asarray(torque)[self._chain]

    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        """H(q) (kg m^2) of the chain joints."""
        matrix = np.asarray(pybullet.calculateMassMatrix(self.body, self._full(q), physicsClientId=self.client))
        return matrix[np.ix_(self._chain, self._chain)]


@functools.lru_cache(maxsize=32)
def nominal_dynamics(urdf: str, joint_names: tuple[str, ...]) -> NominalDynamics:
    """The (cached) nominal dynamics of a URDF's chain joints."""
    return NominalDynamics(urdf, joint_names)
