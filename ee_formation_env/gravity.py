"""Each arm's own gravity torque g(q): what the env adds to an action's torque under ``gravity_compensation``.

Rule: with ``gravity_compensation: true`` the torque sent to arm i for one control step is
``clip(a_i * tau_max_i + g_i(q_i), -tau_max_i, tau_max_i)``, with ``a_i`` the normalized action and ``g_i(q_i)``
the torque that holds the arm at rest at the joint positions the step starts from (robosuite's joint-torque
controller does the same). It is local: arm i's own joints and mounting only. ``g`` is the *simulated*
robot's (its URDF as loaded, the perturbed one under ``model_mismatch``, in the world's own engine), so it
holds the arm exactly still at rest. The action space, the observations and the rewards are unchanged;
``info["applied_torque"]`` is the torque sent. docs/spaces.md ("Action conventions") gives the convention's
figures.

g is the engine's rigid-body model (:func:`ee_formation_env.engines.rigid_body_model`): the URDF at the
origin with gravity turned into the arm's base frame; joints off the chain (e.g. a gripper's fingers) sit at
the positions they are held at.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ee_formation_env.engines import rigid_body_model


class GravityTorque:
    """g(q) (N m) of one arm's chain joints in ``engine``: ``urdf`` the simulated robot, ``chain_joints`` the
    chain's joint names in order, ``held`` the positions (rad or m) of the other movable joints, by name."""

    def __init__(self, engine: str, urdf: str, chain_joints: Sequence[str], held: dict[str, float]):
        self._model = rigid_body_model(engine, urdf, chain_joints, held)

    def __call__(self, q: np.ndarray, gravity_in_base: np.ndarray) -> np.ndarray:
        """g at chain joint positions ``q`` (n,), rad, under ``gravity_in_base`` (3,), m/s^2, base frame."""
        return self._model.gravity_torque(q, gravity_in_base)


def gravity_torques(models: Sequence[GravityTorque], q: np.ndarray, joint_slices: Sequence[slice],
                    gravity_in_bases: np.ndarray) -> np.ndarray:
    """Every arm's g (T,), N m, flat in agent order, at flat joint positions ``q`` (T,); ``gravity_in_bases``
    (N, 3): each arm's gravity in its base frame."""
    return np.concatenate([model(q[joints], gravity) for model, joints, gravity
                           in zip(models, joint_slices, gravity_in_bases)])
