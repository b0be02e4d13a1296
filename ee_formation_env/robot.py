"""One torque-controlled arm in a :class:`~ee_formation_env.world.PhysicsWorld`."""

from __future__ import annotations

import numpy as np
import pybullet

from ee_formation_env.kinematics import SerialChain
from ee_formation_env.scenario import ArmConfig
from ee_formation_env.validation import rpy_matrix
from ee_formation_env.world import PhysicsWorld

# PyBullet clamps joint speeds at 100 rad/s by default, which would hide a blow-up; lift it far above
# the env's own runaway threshold (Scenario.max_joint_velocity) so that the env detects it instead.
PYBULLET_MAX_JOINT_VELOCITY = 1.0e4


class Arm:
    """A fixed-base serial arm whose chain joints are driven by torques.

    Physics set-up (FACTS.md, "PyBullet torque control"): the default velocity motors are disabled,
    link linear/angular damping is zeroed, URDF joint damping is replaced by ``joint_damping``, and the
    velocity clamp is lifted. Torques last one physics step, so :meth:`apply_torques` is called before
    every ``stepSimulation``. Movable joints that are not on the chain (e.g. a gripper's fingers) are
    held where they are by position motors.
    """

    def __init__(self, world: PhysicsWorld, config: ArmConfig, model: SerialChain,
                 joint_damping: float | str, collide_with_other_arms: bool, urdf: str | None = None):
        """``model`` is the kinematic model of the simulated robot, loaded from ``urdf`` (default: the
        scenario's URDF; a perturbed copy under model mismatch)."""
        self.world = world
        self.config = config
        self.model = model
        self.body = world.load_urdf(urdf or config.urdf, config.base_position, config.base_rpy)
        self.base_position = np.asarray(config.base_position, dtype=np.float64)
        self.base_rotation = rpy_matrix(config.base_rpy)  # base frame -> world frame
        client = world.client

        index_by_name: dict[str, int] = {}
        movable: list[int] = []
        for j in range(pybullet.getNumJoints(self.body, physicsClientId=client)):
            info = pybullet.getJointInfo(self.body, j, physicsClientId=client)
            index_by_name[info[1].decode()] = j
            if info[2] != pybullet.JOINT_FIXED:
                movable.append(j)
        self.joint_indices = [index_by_name[name] for name in model.joint_names]
        self.extra_joint_indices = [j for j in movable if j not in self.joint_indices]

        for link in [-1, *range(pybullet.getNumJoints(self.body, physicsClientId=client))]:
            pybullet.changeDynamics(self.body, link, linearDamping=0.0, angularDamping=0.0,
                                    maxJointVelocity=PYBULLET_MAX_JOINT_VELOCITY, physicsClientId=client)
            if not collide_with_other_arms:
                pybullet.setCollisionFilterGroupMask(self.body, link, 0, 0, physicsClientId=client)
        damping = model.joint_damping if joint_damping == "urdf" else np.full(model.n_joints, float(joint_damping))
        for j, value in zip(self.joint_indices, damping):
            pybullet.changeDynamics(self.body, j, jointDamping=float(value), physicsClientId=client)
        for j in self.extra_joint_indices:
            pybullet.changeDynamics(self.body, j, jointDamping=0.0, physicsClientId=client)

        # Switch off the default velocity motors, which would otherwise fight the applied torques.
        pybullet.setJointMotorControlArray(self.body, self.joint_indices, pybullet.VELOCITY_CONTROL,
                                           forces=[0.0] * model.n_joints, physicsClientId=client)
        if self.extra_joint_indices:
            held = [pybullet.getJointState(self.body, j, physicsClientId=client)[0] for j in self.extra_joint_indices]
            pybullet.setJointMotorControlArray(self.body, self.extra_joint_indices, pybullet.POSITION_CONTROL,
                                               targetPositions=held, physicsClientId=client)

    @property
    def n_joints(self) -> int:
        return self.model.n_joints

    def reset_state(self, q: np.ndarray) -> None:
        """Place the chain joints at ``q`` (rad) with zero velocity."""
        for j, value in zip(self.joint_indices, q):
            pybullet.resetJointState(self.body, j, float(value), 0.0, physicsClientId=self.world.client)

    def read_state(self) -> tuple[np.ndarray, np.ndarray]:
        """Joint positions (rad) and velocities (rad/s) of the chain joints."""
        states = pybullet.getJointStates(self.body, self.joint_indices, physicsClientId=self.world.client)
        positions, velocities, _, _ = zip(*states)
        return np.array(positions), np.array(velocities)

    def apply_torques(self, torques: list[float]) -> None:
        """Joint torques (N m) for the next physics step only."""
        pybullet.setJointMotorControlArray(self.body, self.joint_indices, pybullet.TORQUE_CONTROL,
                                           forces=torques, physicsClientId=self.world.client)
