"""Torque-controlled arms in a :class:`~ee_formation_env.world.PhysicsWorld`: one :class:`Arm`, and the
:class:`ArmSet` of every arm of a task, which owns the flat joint vectors the env steps with."""

from __future__ import annotations

import tempfile
from typing import Callable

import numpy as np
import pybullet

from ee_formation_env.kinematics import ChainBatch, SerialChain, rpy_to_matrix
from ee_formation_env.gravity import GravityTorque, gravity_torques
from ee_formation_env.mismatch import write_perturbed_urdf
from ee_formation_env.scenario import ArmConfig
from ee_formation_env.task import FormationTask
from ee_formation_env.validation import missing_meshes
from ee_formation_env.world import PhysicsWorld

# PyBullet clamps joint speeds at 100 rad/s by default, which would hide a blow-up; lift it far above
# the env's own runaway threshold (Scenario.max_joint_velocity) so that the env detects it instead.
PYBULLET_MAX_JOINT_VELOCITY = 1.0e4


class Arm:
    """A fixed-base serial arm whose chain joints are driven by torques.

    Physics set-up (``docs/physics.md``, "PyBullet torque control"): the default velocity motors are disabled,
    link linear/angular damping is zeroed, URDF joint damping is replaced by ``joint_damping``, and the
    velocity clamp is lifted. A torque lasts one ``stepSimulation`` call, so it is sent before every call, which
    makes the env step's ``frame_skip`` physics steps as substeps (:meth:`torque_command` is the one definition
    of that command; :meth:`~ee_formation_env.world.PhysicsWorld.step_with_torques`). Movable joints that are not on the chain (e.g. a gripper's fingers) are
    held where they are by position motors.
    """

    def __init__(self, world: PhysicsWorld, config: ArmConfig, model: SerialChain,
                 joint_damping: float | str, collide_with_other_arms: bool, urdf: str | None = None):
        """``model`` is the kinematic model of the simulated robot, loaded from ``urdf`` (default: the
        scenario's URDF; a perturbed copy under model mismatch)."""
        self.world = world
        self.config = config
        self.model = model
        self.urdf = urdf or config.urdf  # the simulated robot
        self.body = world.load_urdf(self.urdf, config.base_position, config.base_rpy)
        self.base_position = np.asarray(config.base_position, dtype=np.float64)
        self.base_rotation = rpy_to_matrix(config.base_rpy)  # base frame -> world frame
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
        self._held_positions: dict[str, float] = {}  # the joints off the chain, by name: where they are held
        self._gravity: GravityTorque | None = None

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
            names = {j: name for name, j in index_by_name.items()}
            self._held_positions = {names[j]: position for j, position in zip(self.extra_joint_indices, held)}
            pybullet.setJointMotorControlArray(self.body, self.extra_joint_indices, pybullet.POSITION_CONTROL,
                                               targetPositions=held, physicsClientId=client)

    @property
    def n_joints(self) -> int:
        return self.model.n_joints

    @property
    def gravity(self) -> GravityTorque:
        """This robot's own g(q) (:mod:`ee_formation_env.gravity`), built on first use."""
        if self._gravity is None:
            self._gravity = GravityTorque(self.urdf, self.model.joint_names, self._held_positions)
        return self._gravity

    def place_base(self, position: tuple[float, ...], rpy: tuple[float, ...]) -> None:
        """Move the fixed base to ``position`` (m) and ``rpy`` (rad), as if loaded there (a sampled
        scenario's layout). PyBullet places a body by its base link's inertial frame, so the link frame's
        pose is composed with that frame's offset."""
        client = self.world.client
        info = pybullet.getDynamicsInfo(self.body, -1, physicsClientId=client)
        com_position, com_orientation = pybullet.multiplyTransforms(
            list(position), pybullet.getQuaternionFromEuler(rpy), info[3], info[4])
        pybullet.resetBasePositionAndOrientation(self.body, com_position, com_orientation, physicsClientId=client)
        self.base_position = np.asarray(position, dtype=np.float64)
        self.base_rotation = rpy_to_matrix(rpy)

    def reset_state(self, q: np.ndarray) -> None:
        """Place the chain joints at ``q`` (rad) with zero velocity."""
        for j, value in zip(self.joint_indices, q):
            pybullet.resetJointState(self.body, j, float(value), 0.0, physicsClientId=self.world.client)

    def read_state_lists(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """Joint positions (rad) and velocities (rad/s) of the chain joints, as Python tuples (the env joins
        every arm's into one array)."""
        states = pybullet.getJointStates(self.body, self.joint_indices, physicsClientId=self.world.client)
        positions, velocities, _, _ = zip(*states)  # (q, dq, reaction wrench, applied torque) per joint
        return positions, velocities

    def torque_command(self, torques: list[float]) -> tuple[int, list[int], list[float]]:
        """``(body, joint indices, torques N m)``: what :meth:`PhysicsWorld.step_with_torques` sends before
        each physics step for this arm."""
        return self.body, self.joint_indices, torques


class ArmSet:
    """Every arm of a task in one world, with flat joint vectors (q, dq, torques): arm i's joints are
    ``joint_slices[i]``. Loaded once; resets only set joint states.

    Under ``model_mismatch`` each arm is a perturbed copy of its URDF (the "true" robot) and ``arm.model``
    is that robot's kinematic model; the controllers keep the task's nominal models.
    """

    def __init__(self, world: PhysicsWorld, task: FormationTask):
        self.world = world
        self.arms = _load_arms(world, task)
        sizes = [arm.n_joints for arm in self.arms]
        bounds = np.concatenate([[0], np.cumsum(sizes)]).astype(np.intp)
        self.n_joints = int(bounds[-1])
        self.joint_slices = [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]
        self.joint_starts = bounds[:-1]  # for np.add.reduceat over flat joint vectors
        self.joint_counts = np.asarray(sizes, dtype=np.float64)
        self.continuous = np.concatenate([arm.model.continuous for arm in self.arms])
        self.kinematics = ChainBatch([arm.model for arm in self.arms])  # the true (simulated) robots
        self._body_to_agent = {arm.body: i for i, arm in enumerate(self.arms)}

    def __len__(self) -> int:
        return len(self.arms)

    def place_bases(self, task: FormationTask) -> None:
        """Move every arm's base to the pose ``task`` gives it (a sampled scenario's layout; the robots are
        the same, so nothing is reloaded)."""
        for arm, config in zip(self.arms, task.scenario.arms):
            arm.place_base(config.base_position, config.base_rpy)

    def reset(self, q: list[np.ndarray]) -> None:
        """Place every arm at its joint positions (rad), at rest."""
        for arm, q_arm in zip(self.arms, q):
            arm.reset_state(q_arm)

    def step(self, torques: np.ndarray, physics_steps: int) -> None:
        """Hold every arm's torques (flat, N m) for ``physics_steps`` physics steps (one call, as substeps)."""
        values = torques.tolist()
        commands = [arm.torque_command(values[joints]) for arm, joints in zip(self.arms, self.joint_slices)]
        self.world.step_with_torques(commands, physics_steps)

    def gravity_torques(self, q: np.ndarray, gravity_in_bases: np.ndarray) -> np.ndarray:
        """Every arm's own gravity torque (T,), N m, at flat joint positions ``q`` (T,), rad;
        ``gravity_in_bases`` (N, 3): each arm's gravity in its base frame, m/s^2."""
        return gravity_torques([arm.gravity for arm in self.arms], q, self.joint_slices, gravity_in_bases)

    def contacts_per_arm(self) -> list[int]:
        """Contact points of each arm with other arms (contacts with itself do not count)."""
        counts = [0] * len(self.arms)
        pairs = self.world.contact_pairs()
        if not pairs:  # the common case
            return counts
        for body_a, body_b in pairs:
            a, b = self._body_to_agent.get(body_a), self._body_to_agent.get(body_b)
            if a is not None and b is not None and a != b:
                counts[a] += 1
                counts[b] += 1
        return counts


def _load_arms(world: PhysicsWorld, task: FormationTask) -> list[Arm]:
    """Load every arm once: the nominal URDF, or a perturbed copy under ``model_mismatch``."""
    scenario = task.scenario
    mismatch = scenario.model_mismatch
    if not mismatch.active:
        return [_loaded(i, arm, lambda arm=arm, model=model: Arm(world, arm, model, scenario.joint_damping,
                                                                   scenario.arm_collisions))
                for i, (arm, model) in enumerate(zip(scenario.arms, task.models))]
    rng = np.random.default_rng(mismatch.seed)
    arms = []
    with tempfile.TemporaryDirectory(prefix="ee_formation_") as directory:
        for arm, model in zip(scenario.arms, task.models):
            joints = [joint.name for joint in model.joints]
            links = [joint.child for joint in model.joints]
            length_scales = 1.0 + rng.uniform(-mismatch.length, mismatch.length, len(joints))
            mass_scales = 1.0 + rng.uniform(-mismatch.mass, mismatch.mass, len(links))
            urdf = write_perturbed_urdf(arm.urdf, joints, links, length_scales, mass_scales, directory)
            true_model = SerialChain.from_urdf(urdf, arm.ee_link)
            arms.append(_loaded(len(arms), arm, lambda: Arm(world, arm, true_model, scenario.joint_damping,
                                                             scenario.arm_collisions, urdf=urdf)))
    return arms


def _loaded(index: int, config: ArmConfig, load: Callable[[], Arm]) -> Arm:
    """``load()``, with PyBullet's refusal of a URDF (``pybullet.error``, e.g. a mesh it cannot find or
    parse) turned into a ``ValueError`` naming the arm and its URDF (the caller closes the world)."""
    try:
        return load()
    except pybullet.error as error:
        missing = missing_meshes(config.urdf)
        hint = f"; mesh files not found next to it: {missing[:5]}" if missing else ""
        raise ValueError(f"arms[{index}].urdf: PyBullet could not load {config.urdf} ({error}){hint}") from None


def check_start_contacts(arm_set: ArmSet) -> None:
    """Refuse arms that touch or overlap at their initial configurations (checked after loading, before the
    first physics step; only while ``arm_collisions`` is on: the contact forces would throw them apart).
    ``ValueError`` starting with ``arms:``, naming the first pair."""
    client = arm_set.world.client
    arms = arm_set.arms
    for a in range(len(arms)):
        for b in range(a + 1, len(arms)):
            points = pybullet.getClosestPoints(arms[a].body, arms[b].body, 0.0, physicsClientId=client)
            if points:
                depth = -min(point[8] for point in points)
                raise ValueError(
                    f"arms: arm_{a} and arm_{b} are in contact at their initial configurations (initial_q, "
                    f"penetration {max(depth, 0.0):.3f} m); move their bases apart, bend them away from each other, "
                    "or set arm_collisions: false")


def build_world(task: FormationTask, render_mode: str | None = None) -> tuple[PhysicsWorld, ArmSet]:
    """One PyBullet client holding the task's arms at their initial configurations (start contacts refused
    while ``arm_collisions`` is on), its state saved for :func:`reset_world`: one copy of the env."""
    scenario = task.scenario
    world = PhysicsWorld(scenario.physics_hz, scenario.gravity, render_mode)
    try:  # a refusal after connecting (a URDF PyBullet rejects, arms in contact) leaves no client behind
        arm_set = ArmSet(world, task)
        arm_set.reset(list(task.initial_q))
        if scenario.arm_collisions:
            check_start_contacts(arm_set)
    except BaseException:
        world.close()
        raise
    world.save_snapshot()
    return world, arm_set


def start_problem(arm_set: ArmSet, task: FormationTask) -> str | None:
    """Place ``arm_set``'s arms as ``task`` (a scenario distribution's draw) has them, at its initial
    configurations; why they cannot start there (arms in contact, while ``arm_collisions`` is on), or None."""
    arm_set.place_bases(task)
    arm_set.reset(list(task.initial_q))
    if task.scenario.arm_collisions:
        try:
            check_start_contacts(arm_set)
        except ValueError as error:
            return str(error)
    return None


def reset_world(world: PhysicsWorld, arm_set: ArmSet, task: FormationTask, rng: np.random.Generator) -> None:
    """Restore the saved world, then place the arms at the scenario's initial joint positions plus uniform
    noise of half-width ``initial_q_noise`` drawn from ``rng`` (clipped to the joint limits), at rest. A task
    whose bases are not the saved ones (a scenario distribution's draw) has its bases moved there first."""
    world.restore_snapshot()
    if any(arm.config is not config for arm, config in zip(arm_set.arms, task.scenario.arms)):
        arm_set.place_bases(task)
    noise = task.scenario.initial_q_noise
    starts = []
    for arm, q0 in zip(arm_set.arms, task.initial_q):
        q = q0 + rng.uniform(-noise, noise, size=q0.shape) if noise > 0 else q0.copy()
        starts.append(np.clip(q, arm.model.lower, arm.model.upper))
    arm_set.reset(starts)
