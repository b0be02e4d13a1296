"""Nominal rigid-body dynamics of an arm (gravity torque, mass matrix) for the reference controllers.

The controllers know only the nominal URDF, never the simulated robot. Its dynamics are PyBullet's rigid-body
model of it (:func:`ee_formation_env.engines.rigid_body_model`: recursive Newton-Euler, the robot at the
origin in a private client shared by every arm model), separate from any environment's world, whichever
engine simulates the arms (MuJoCo's model agrees to 1e-6, ``tests/engines/test_mujoco_engine.py``).
"""

from __future__ import annotations

import functools

import numpy as np

from ee_formation_env.engines import rigid_body_model

#: The engine whose model the laws use.
NOMINAL_ENGINE = "pybullet"


class NominalDynamics:
    """Gravity torques and mass matrix of the chain joints of a nominal URDF (fixed base)."""

    def __init__(self, urdf: str, joint_names: tuple[str, ...]):
        self._model = rigid_body_model(NOMINAL_ENGINE, urdf, joint_names)

    def gravity_torque(self, q: np.ndarray, gravity_in_base: np.ndarray) -> np.ndarray:
        """G(q) (N m): the torques that hold the arm still against ``gravity_in_base`` (m/s^2, base frame)."""
        return self._model.gravity_torque(q, gravity_in_base)

    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        """H(q) (kg m^2) of the chain joints."""
        return self._model.mass_matrix(q)


@functools.lru_cache(maxsize=32)
def nominal_dynamics(urdf: str, joint_names: tuple[str, ...]) -> NominalDynamics:
    """The (cached) nominal dynamics of a URDF's chain joints."""
    return NominalDynamics(urdf, joint_names)
