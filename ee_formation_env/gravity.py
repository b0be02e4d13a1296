"""Each arm's own gravity torque g(q): what the env adds to an action's torque under ``gravity_compensation``.

Rule: with ``gravity_compensation: true`` the torque sent to arm i for one control step is
``clip(a_i * tau_max_i + g_i(q_i), -tau_max_i, tau_max_i)``, with ``a_i`` the normalized action and ``g_i(q_i)``
the torque that holds the arm at rest at the joint positions the step starts from (robosuite's joint-torque
controller does the same). It is local: arm i's own joints and mounting only. ``g`` is the *simulated*
robot's (its URDF as loaded, the perturbed one under ``model_mismatch``), so it holds the arm exactly still
at rest. The action space, the observations and the rewards are unchanged; ``info["applied_torque"]`` is
the torque sent. docs/spaces.md ("Action conventions") gives the convention's figures.

PyBullet's ``calculateInverseDynamics`` ignores a fixed base's orientation, so g is evaluated in a private
DIRECT client holding each URDF once at the origin, with gravity turned into the arm's base frame; joints
off the chain (e.g. a gripper's fingers) sit at the positions they are held at.
"""

from __future__ import annotations

import functools
from typing import Sequence

import numpy as np
import pybullet


@functools.lru_cache(maxsize=1)
def _dynamics_client() -> int:
    return pybullet.connect(pybullet.DIRECT)


@functools.lru_cache(maxsize=64)
def _loaded(urdf: str) -> tuple[int, tuple[str, ...]]:
    """The body of ``urdf`` in the private client (loaded once per process) and its movable joints' names,
    in PyBullet's degree-of-freedom order."""
    client = _dynamics_client()
    body = pybullet.loadURDF(urdf, useFixedBase=True, flags=pybullet.URDF_USE_INERTIA_FROM_FILE,
                             physicsClientId=client)
    names = []
    for j in range(pybullet.getNumJoints(body, physicsClientId=client)):
        info = pybullet.getJointInfo(body, j, physicsClientId=client)
        if info[2] != pybullet.JOINT_FIXED:
            names.append(info[1].decode())
    return body, tuple(names)


class GravityTorque:
    """g(q) (N m) of one arm's chain joints: ``urdf`` the simulated robot, ``chain_joints`` the chain's joint
    names in order, ``held`` the positions (rad or m) of the other movable joints, by name."""

    def __init__(self, urdf: str, chain_joints: Sequence[str], held: dict[str, float]):
        self._client = _dynamics_client()
        self._body, names = _loaded(urdf)
        self._chain = np.array([names.index(name) for name in chain_joints], dtype=np.intp)
        self._full = np.array([held.get(name, 0.0) for name in names], dtype=np.float64)
        self._zeros = [0.0] * len(names)

    def __call__(self, q: np.ndarray, gravity_in_base: np.ndarray) -> np.ndarray:
        """g at chain joint positions ``q`` (n,), rad, under ``gravity_in_base`` (3,), m/s^2, base frame."""
        full = self._full.copy()
        full[self._chain] = q
        pybullet.setGravity(*gravity_in_base.tolist(), physicsClientId=self._client)
        torques = pybullet.calculateInverseDynamics(self._body, full.tolist(), self._zeros, self._zeros,
                                                    physicsClientId=self._client)
        return np.asarray(torques)[self._chain]


def gravity_torques(models: Sequence[GravityTorque], q: np.ndarray, joint_slices: Sequence[slice],
                    gravity_in_bases: np.ndarray) -> np.ndarray:
    """Every arm's g (T,), N m, flat in agent order, at flat joint positions ``q`` (T,); ``gravity_in_bases``
    (N, 3): each arm's gravity in its base frame."""
    return np.concatenate([model(q[joints], gravity) for model, joints, gravity
                           in zip(models, joint_slices, gravity_in_bases)])
