"""Torque-controlled arms in a physics world (an :class:`~ee_formation_env.engines.base.Engine`): one
:class:`Arm`, and the :class:`ArmSet` of every arm of a task, which owns the flat joint vectors the env steps
with."""

from __future__ import annotations

import tempfile
from typing import Callable

import numpy as np

from ee_formation_env.engines import Engine, URDFLoadError
from ee_formation_env.kinematics import ChainBatch, SerialChain, rpy_to_matrix
from ee_formation_env.gravity import GravityTorque, gravity_torques
from ee_formation_env.mismatch import write_perturbed_urdf
from ee_formation_env.scenario import ArmConfig
from ee_formation_env.task import FormationTask
from ee_formation_env.validation import missing_meshes
from ee_formation_env.world import make_world


class Arm:
    """A fixed-base serial arm whose chain joints are driven by torques, loaded into ``world``.

    The engine sets it up (``docs/physics.md``, "PyBullet torque control"; :mod:`ee_formation_env.engines`):
    no motors, no link damping, joint damping ``joint_damping`` in place of the URDF's (``"urdf"`` keeps it),
    no velocity clamp; movable joints that are not on the chain (e.g. a gripper's fingers) are held where
    they are.
    """

    def __init__(self, world: Engine, config: ArmConfig, model: SerialChain,
                 joint_damping: float | str, collide_with_other_arms: bool, urdf: str | None = None):
        """``model`` is the kinematic model of the simulated robot, loaded from ``urdf`` (default: the
        scenario's URDF; a perturbed copy under model mismatch)."""
        self.world = world
        self.config = config
        self.model = model
        self.urdf = urdf or config.urdf  # the simulated robot
        damping = model.joint_damping if joint_damping == "urdf" else np.full(model.n_joints, float(joint_damping))
        self.loaded = world.load_arm(self.urdf, config.base_position, config.base_rpy, model.joint_names, damping,
                                     collide_with_other_arms)
        self.body = self.loaded.body
        self.joint_indices = list(self.loaded.joint_indices)
        self.extra_joint_indices = list(self.loaded.extra_joint_indices)
        self.base_position = np.asarray(config.base_position, dtype=np.float64)
        self.base_rotation = rpy_to_matrix(config.base_rpy)  # base frame -> world frame
        self._gravity: GravityTorque | None = None

    @property
    def n_joints(self) -> int:
        return self.model.n_joints

    @property
    def gravity(self) -> GravityTorque:
        """This robot's own g(q) (:mod:`ee_formation_env.gravity`), built on first use."""
        if self._gravity is None:
            self._gravity = GravityTorque(self.world.name, self.urdf, self.model.joint_names,
                                          self.loaded.held_positions)
        return self._gravity

    def place_base(self, position: tuple[float, ...], rpy: tuple[float, ...]) -> None:
        """Move the fixed base to ``position`` (m) and ``rpy`` (rad), as if loaded there (a sampled
        scenario's layout)."""
        self.world.place_base(self.loaded, position, rpy)
        self.base_position = np.asarray(position, dtype=np.float64)
        self.base_rotation = rpy_to_matrix(rpy)

    def reset_state(self, q: np.ndarray) -> None:
        """Place the chain joints at ``q`` (rad) with zero velocity."""
        self.world.reset_joints(self.loaded, q)

    def read_state_lists(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """Joint positions (rad) and velocities (rad/s) of the chain joints, as Python tuples (the env joins
        every arm's into one array)."""
        return self.world.joint_state(self.loaded)

    def torque_command(self, torques: list[float]) -> tuple[int, list[int], list[float]]:
        """``(body, joint indices, torques N m)``: what PyBullet's
        :meth:`~ee_formation_env.engines.pybullet_engine.PyBulletEngine.step_with_torques` sends before each
        physics step for this arm."""
        return self.body, self.joint_indices, torques


class ArmSet:
    """Every arm of a task in one world, with flat joint vectors (q, dq, torques): arm i's joints are
    ``joint_slices[i]``. Loaded once; resets only set joint states.

    Under ``model_mismatch`` each arm is a perturbed copy of its URDF (the "true" robot) and ``arm.model``
    is that robot's kinematic model; the controllers keep the task's nominal models.
    """

    def __init__(self, world: Engine, task: FormationTask):
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
        self.world.step_torques(torques, physics_steps)

    def gravity_torques(self, q: np.ndarray, gravity_in_bases: np.ndarray) -> np.ndarray:
        """Every arm's own gravity torque (T,), N m, at flat joint positions ``q`` (T,), rad;
        ``gravity_in_bases`` (N, 3): each arm's gravity in its base frame, m/s^2."""
        return gravity_torques([arm.gravity for arm in self.arms], q, self.joint_slices, gravity_in_bases)

    def contacts_per_arm(self) -> list[int]:
        """Contact points of each arm with other arms (contacts with itself do not count)."""
        counts = [0] * len(self.arms)
        pairs = self.world.contact_bodies()
        if not pairs:  # the common case
            return counts
        for body_a, body_b in pairs:
            a, b = self._body_to_agent.get(body_a), self._body_to_agent.get(body_b)
            if a is not None and b is not None and a != b:
                counts[a] += 1
                counts[b] += 1
        return counts


def _load_arms(world: Engine, task: FormationTask) -> list[Arm]:
    """Load every arm once: the nominal URDF, or a perturbed copy under ``model_mismatch``."""
    scenario = task.scenario
    mismatch = scenario.model_mismatch
    if not mismatch.active:
        return [_loaded(i, arm, lambda arm=arm, model=model: Arm(world, arm, model, scenario.joint_damping,
                                                                   scenario.arm_collisions), world.label)
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
                                                             scenario.arm_collisions, urdf=urdf), world.label))
    return arms


def _loaded(index: int, config: ArmConfig, load: Callable[[], Arm], label: str) -> Arm:
    """``load()``, with the engine's refusal of a URDF (:class:`~ee_formation_env.engines.base.URDFLoadError`,
    e.g. a mesh it cannot find or parse) turned into a ``ValueError`` naming the arm and its URDF (the caller
    closes the world)."""
    try:
        return load()
    except URDFLoadError as error:
        missing = missing_meshes(config.urdf)
        hint = f"; mesh files not found next to it: {missing[:5]}" if missing else ""
        raise ValueError(f"arms[{index}].urdf: {label} could not load {config.urdf} ({error}){hint}") from None


def check_start_contacts(arm_set: ArmSet) -> None:
    """Refuse arms that touch or overlap at their initial configurations (checked after loading, before the
    first physics step; only while ``arm_collisions`` is on: the contact forces would throw them apart).
    ``ValueError`` starting with ``arms:``, naming the first pair."""
    world, arms = arm_set.world, arm_set.arms
    for a in range(len(arms)):
        for b in range(a + 1, len(arms)):
            distance = world.closest_distance(arms[a].loaded, arms[b].loaded, 0.0)
            if distance is not None:
                depth = -distance
                raise ValueError(
                    f"arms: arm_{a} and arm_{b} are in contact at their initial configurations (initial_q, "
                    f"penetration {max(depth, 0.0):.3f} m); move their bases apart, bend them away from each other, "
                    "or set arm_collisions: false")


def build_world(task: FormationTask, render_mode: str | None = None) -> tuple[Engine, ArmSet]:
    """One world of the scenario's ``engine`` holding the task's arms at their initial configurations (start contacts refused
    while ``arm_collisions`` is on), its state saved for :func:`reset_world`: one copy of the env."""
    scenario = task.scenario
    world = make_world(scenario.engine, scenario.physics_hz, scenario.gravity, render_mode)
    try:  # a refusal after connecting (a URDF the engine rejects, arms in contact) leaves no client behind
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


def reset_world(world: Engine, arm_set: ArmSet, task: FormationTask, rng: np.random.Generator) -> None:
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
