"""The PyBullet engine (:mod:`ee_formation_env.engines.base`): one physics client per world, torque-controlled
arms loaded from URDFs, and a private client for the rigid-body dynamics of single URDFs.

Rule: this module (with :mod:`ee_formation_env.generators`' clearance checks, which draw the random spatial
family in a client of their own) is where the env talks to PyBullet; what is drawn into frames (pixel
projection, line drawing) lives in :mod:`ee_formation_env.rendering`.

Arm set-up (``docs/physics.md``, "PyBullet torque control"): the default velocity motors are disabled, link
linear/angular damping is zeroed, URDF joint damping is replaced by the scenario's, and the velocity clamp is
lifted. A torque lasts one ``stepSimulation`` call, so it is sent before every call, which makes the env
step's ``frame_skip`` physics steps as substeps (:meth:`PyBulletEngine.step_with_torques`). Movable joints
that are not on the chain (e.g. a gripper's fingers) are held where they are by position motors.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import math
import os
import sys
import warnings
from typing import Iterator, Sequence

import numpy as np
import pybullet

from ee_formation_env.engines.base import LoadedArm, URDFLoadError

# PyBullet clamps joint speeds at 100 rad/s by default, which would hide a blow-up; lift it far above
# the env's own runaway threshold (Scenario.max_joint_velocity) so that the env detects it instead.
PYBULLET_MAX_JOINT_VELOCITY = 1.0e4


class PyBulletEngine:
    """One PyBullet client (DIRECT, or GUI for ``render_mode="human"``) with a fixed time step: the
    :class:`~ee_formation_env.engines.base.Engine` on PyBullet.

    Each instance owns its client, so several worlds can live in one process. ``close()`` is idempotent.
    An arm's ``body`` is its PyBullet body id; its joint indices are PyBullet's.
    """

    name = "pybullet"
    label = "PyBullet"

    def __init__(self, physics_hz: float, gravity: tuple[float, float, float], render_mode: str | None = None):
        self.gui = render_mode == "human"
        if self.gui and not display_available():
            # PyBullet's GUI calls exit() when it finds no X server. Headless checkers (gymnasium's check_env
            # builds every declared render mode) must still get a working env: simulate without a window.
            _warn_no_display_once()
            self.gui = False
        if self.gui:
            # The GUI prints ~45 lines of OpenGL and driver details on connect. Its window thread may still
            # print one line ("ven = ...") after connect returns: there is no call to wait for it.
            with c_stdout_silenced():
                self.client = pybullet.connect(pybullet.GUI)
                if self.client >= 0:
                    pybullet.configureDebugVisualizer(pybullet.COV_ENABLE_GUI, 0, physicsClientId=self.client)
        else:
            self.client = pybullet.connect(pybullet.DIRECT)
        if self.client < 0:
            raise RuntimeError("PyBullet could not connect (is another GUI client already open?)")
        self.time_step = 1.0 / physics_hz
        pybullet.setTimeStep(self.time_step, physicsClientId=self.client)
        pybullet.setGravity(*gravity, physicsClientId=self.client)
        # One solver pass per step and a fixed pair order: bit-identical trajectories from one state.
        pybullet.setPhysicsEngineParameter(numSubSteps=0, deterministicOverlappingPairs=1,
                                           physicsClientId=self.client)
        self._steps_per_call = 1  # physics steps one stepSimulation call makes now (step_with_torques)
        self._arms: list[tuple[int, list[int], slice]] = []  # per loaded arm: body, chain joints, torque slice
        self._snapshot: int | None = None
        # Kept on the instance for close(): at interpreter exit the module's globals (pybullet itself,
        # pybullet.error) may already be None when a forgotten env is finally collected.
        self._disconnect = pybullet.disconnect
        self._client_error = pybullet.error

    @property
    def connected(self) -> bool:
        return self.client >= 0

    def load_urdf(self, urdf: str, position: tuple[float, ...], rpy: tuple[float, ...]) -> int:
        """Load a fixed-base body; inertias are taken from the URDF, not recomputed from collision shapes."""
        orientation = pybullet.getQuaternionFromEuler(rpy)
        return pybullet.loadURDF(urdf, basePosition=position, baseOrientation=orientation, useFixedBase=True,
                                 flags=pybullet.URDF_USE_INERTIA_FROM_FILE, physicsClientId=self.client)

    def load_arm(self, urdf: str, position: Sequence[float], rpy: Sequence[float], chain_joints: Sequence[str],
                 joint_damping: np.ndarray, collide_with_other_arms: bool) -> LoadedArm:
        """Load a torque-controlled arm (the module docstring's set-up); PyBullet's refusal of the URDF is a
        :class:`~ee_formation_env.engines.base.URDFLoadError`."""
        try:
            body = self.load_urdf(urdf, position, rpy)
        except pybullet.error as error:
            raise URDFLoadError(str(error)) from None
        client = self.client
        index_by_name: dict[str, int] = {}
        movable: list[int] = []
        for j in range(pybullet.getNumJoints(body, physicsClientId=client)):
            info = pybullet.getJointInfo(body, j, physicsClientId=client)
            index_by_name[info[1].decode()] = j
            if info[2] != pybullet.JOINT_FIXED:
                movable.append(j)
        joint_indices = [index_by_name[name] for name in chain_joints]
        extra_joint_indices = [j for j in movable if j not in joint_indices]

        for link in [-1, *range(pybullet.getNumJoints(body, physicsClientId=client))]:
            pybullet.changeDynamics(body, link, linearDamping=0.0, angularDamping=0.0,
                                    maxJointVelocity=PYBULLET_MAX_JOINT_VELOCITY, physicsClientId=client)
            if not collide_with_other_arms:
                pybullet.setCollisionFilterGroupMask(body, link, 0, 0, physicsClientId=client)
        for j, value in zip(joint_indices, joint_damping):
            pybullet.changeDynamics(body, j, jointDamping=float(value), physicsClientId=client)
        for j in extra_joint_indices:
            pybullet.changeDynamics(body, j, jointDamping=0.0, physicsClientId=client)

        # Switch off the default velocity motors, which would otherwise fight the applied torques.
        pybullet.setJointMotorControlArray(body, joint_indices, pybullet.VELOCITY_CONTROL,
                                           forces=[0.0] * len(joint_indices), physicsClientId=client)
        held_positions: dict[str, float] = {}
        if extra_joint_indices:
            held = [pybullet.getJointState(body, j, physicsClientId=client)[0] for j in extra_joint_indices]
            names = {j: name for name, j in index_by_name.items()}
            held_positions = {names[j]: position for j, position in zip(extra_joint_indices, held)}
            pybullet.setJointMotorControlArray(body, extra_joint_indices, pybullet.POSITION_CONTROL,
                                               targetPositions=held, physicsClientId=client)
        start = self._arms[-1][2].stop if self._arms else 0
        self._arms.append((body, joint_indices, slice(start, start + len(joint_indices))))
        return LoadedArm(body, tuple(joint_indices), tuple(extra_joint_indices), held_positions)

    def place_base(self, arm: LoadedArm, position: Sequence[float], rpy: Sequence[float]) -> None:
        """Move the fixed base to ``position`` (m) and ``rpy`` (rad). PyBullet places a body by its base link's
        inertial frame, so the link frame's pose is composed with that frame's offset."""
        client = self.client
        info = pybullet.getDynamicsInfo(arm.body, -1, physicsClientId=client)
        com_position, com_orientation = pybullet.multiplyTransforms(
            list(position), pybullet.getQuaternionFromEuler(rpy), info[3], info[4])
        pybullet.resetBasePositionAndOrientation(arm.body, com_position, com_orientation, physicsClientId=client)

    def reset_joints(self, arm: LoadedArm, q: np.ndarray) -> None:
        for j, value in zip(arm.joint_indices, q):
            pybullet.resetJointState(arm.body, j, float(value), 0.0, physicsClientId=self.client)

    def joint_state(self, arm: LoadedArm) -> tuple[tuple[float, ...], tuple[float, ...]]:
        states = pybullet.getJointStates(arm.body, arm.joint_indices, physicsClientId=self.client)
        positions, velocities, _, _ = zip(*states)  # (q, dq, reaction wrench, applied torque) per joint
        return positions, velocities

    def step_torques(self, torques: np.ndarray, steps: int) -> None:
        """Every loaded arm's slice of the flat ``torques`` (N m) held for ``steps`` physics steps: one
        :meth:`step_with_torques` call."""
        values = torques.tolist()
        self.step_with_torques([(body, joints, values[part]) for body, joints, part in self._arms], steps)

    def _make_steps_per_call(self, steps: int) -> None:
        """Have one ``stepSimulation`` call make ``steps`` physics steps of :attr:`time_step` each (PyBullet's
        ``numSubSteps``; 1: its plain single step)."""
        if steps != self._steps_per_call:
            if steps == 1:
                pybullet.setPhysicsEngineParameter(fixedTimeStep=self.time_step, numSubSteps=0,
                                                   physicsClientId=self.client)
            else:
                pybullet.setPhysicsEngineParameter(fixedTimeStep=self.time_step * steps, numSubSteps=steps,
                                                   physicsClientId=self.client)
            self._steps_per_call = steps

    def step(self) -> None:
        """One physics step of :attr:`time_step`."""
        self._make_steps_per_call(1)
        pybullet.stepSimulation(physicsClientId=self.client)

    def step_with_torques(self, commands: Sequence[tuple[int, Sequence[int], Sequence[float]]], steps: int) -> None:
        """``steps`` physics steps under every ``(body, joint indices, torques N m)`` command, held constant.

        PyBullet's TORQUE_CONTROL torque lasts one ``stepSimulation`` call and acts in each of that call's
        substeps, so one command and one call with ``numSubSteps = steps`` make the same ``steps`` physics steps
        as re-sending the torques before each of ``steps`` single steps, bit for bit (``tests/test_world.py``),
        with ``steps`` times fewer calls: the env's inner loop.
        """
        self._make_steps_per_call(steps)
        client, set_motors = self.client, pybullet.setJointMotorControlArray
        torque_control = pybullet.TORQUE_CONTROL
        for body, joints, torques in commands:
            set_motors(body, joints, torque_control, forces=torques, physicsClientId=client)
        pybullet.stepSimulation(physicsClientId=client)

    def save_snapshot(self) -> None:
        """Remember the current world (including contact caches) for :meth:`restore_snapshot`."""
        self._snapshot = pybullet.saveState(physicsClientId=self.client)

    def restore_snapshot(self) -> None:
        """Return to the saved world, so that a reset does not depend on what ran before."""
        if self._snapshot is not None:
            pybullet.restoreState(stateId=self._snapshot, physicsClientId=self.client)

    def contact_pairs(self) -> list[tuple[int, int]]:
        """(bodyA, bodyB) of every current contact point."""
        return [(c[1], c[2]) for c in pybullet.getContactPoints(physicsClientId=self.client)]

    contact_bodies = contact_pairs  # the seam's name; PyBullet has no contacts within an arm

    def closest_distance(self, a: LoadedArm, b: LoadedArm, max_distance: float) -> float | None:
        points = pybullet.getClosestPoints(a.body, b.body, max_distance, physicsClientId=self.client)
        return min(point[8] for point in points) if points else None

    def render(self, target: np.ndarray, distance: float, yaw: float, pitch: float,
               width: int, height: int, fov_deg: float = 50.0) -> tuple[np.ndarray, np.ndarray]:
        """RGB image (height, width, 3) uint8 and the 4x4 world-to-clip matrix used for it."""
        view = pybullet.computeViewMatrixFromYawPitchRoll(target.tolist(), distance, yaw, pitch, 0.0, 2,
                                                          physicsClientId=self.client)
        projection = pybullet.computeProjectionMatrixFOV(fov_deg, width / height, 0.05, 10.0 * distance + 10.0,
                                                         physicsClientId=self.client)
        renderer = pybullet.ER_BULLET_HARDWARE_OPENGL if self.gui else pybullet.ER_TINY_RENDERER
        _, _, rgba, _, _ = pybullet.getCameraImage(width, height, view, projection, renderer=renderer,
                                                   physicsClientId=self.client)
        image = np.reshape(np.asarray(rgba, dtype=np.uint8), (height, width, 4))[:, :, :3].copy()
        world_to_clip = np.asarray(projection).reshape(4, 4).T @ np.asarray(view).reshape(4, 4).T
        return image, world_to_clip

    def draw_line(self, start: np.ndarray, end: np.ndarray, color: tuple[float, float, float],
                  replace_id: int = -1, width: float = 2.0) -> int:
        """A debug line in the GUI (ignored by the headless renderer); returns its id for replacement."""
        return pybullet.addUserDebugLine(start.tolist(), end.tolist(), color, lineWidth=width,
                                         replaceItemUniqueId=replace_id, physicsClientId=self.client)

    def point_gui_camera(self, target: np.ndarray, distance: float, yaw: float, pitch: float) -> None:
        """Point the GUI's camera (``human`` mode) at ``target`` (m) from ``distance`` (m), yaw/pitch in deg."""
        pybullet.resetDebugVisualizerCamera(distance, yaw, pitch, target.tolist(), physicsClientId=self.client)

    def gui_field_of_view(self) -> tuple[float, float]:
        """The GUI camera's vertical field of view (deg) and aspect ratio (width / height)."""
        projection = pybullet.getDebugVisualizerCamera(physicsClientId=self.client)[3]  # column-major 4x4
        focal = projection[5]  # 1 / tan(fov_vertical / 2)
        return math.degrees(2.0 * math.atan(1.0 / focal)), focal / projection[0]

    def link_positions(self, body: int) -> np.ndarray:
        """World positions (k + 1, 3), m, of a body's base and of every link frame."""
        client = self.client
        base, _ = pybullet.getBasePositionAndOrientation(body, physicsClientId=client)
        links = range(pybullet.getNumJoints(body, physicsClientId=client))
        states = pybullet.getLinkStates(body, list(links), physicsClientId=client) if links else []
        return np.array([base, *(state[4] for state in states)], dtype=np.float64)

    def close(self) -> None:
        """Disconnect the client; idempotent, and safe from ``__del__`` at interpreter exit."""
        if self.client >= 0:
            try:
                if self.gui:
                    with c_stdout_silenced():  # the GUI prints ~17 lines about its threads on disconnect
                        self._disconnect(physicsClientId=self.client)
                else:
                    self._disconnect(physicsClientId=self.client)
            except self._client_error:
                pass  # already gone (e.g. the GUI window was closed)
            self.client = -1


_warned_no_display = False


def display_available() -> bool:
    """Whether a GUI window can open: on Linux an X display must be named by ``DISPLAY``."""
    return not sys.platform.startswith("linux") or bool(os.environ.get("DISPLAY"))


def _warn_no_display_once() -> None:
    global _warned_no_display
    if not _warned_no_display:
        _warned_no_display = True
        warnings.warn('render_mode="human" without a display (DISPLAY is not set): simulating headless, '
                      'render() returns None; use render_mode="rgb_array" for frames', RuntimeWarning, stacklevel=4)


@contextlib.contextmanager
def c_stdout_silenced() -> Iterator[None]:
    """Redirect the process's C-level stdout (file descriptor 1) to /dev/null for the duration.

    PyBullet's C++ code writes straight to fd 1, so ``contextlib.redirect_stdout`` cannot silence it; C's
    stdio buffer is flushed before fd 1 is restored, or buffered chatter would still come out later.
    """
    sys.stdout.flush()
    try:
        saved = os.dup(1)
    except OSError:  # no usable fd 1 (e.g. a closed stdout): nothing to silence
        yield
        return
    try:
        with open(os.devnull, "wb") as devnull:
            os.dup2(devnull.fileno(), 1)
        yield
    finally:
        _flush_c_stdio()
        os.dup2(saved, 1)
        os.close(saved)


def _flush_c_stdio() -> None:
    """``fflush(NULL)``: write out C stdio buffers (where the C library can be found)."""
    try:
        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError):
        pass



@functools.lru_cache(maxsize=1)
def _dynamics_client() -> int:
    """The private DIRECT client of every :class:`PyBulletModel` (one per process), apart from any world."""
    return pybullet.connect(pybullet.DIRECT)


@functools.lru_cache(maxsize=64)
def _dynamics_body(urdf: str) -> tuple[int, tuple[str, ...]]:
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


class PyBulletModel:
    """The :class:`~ee_formation_env.engines.base.RigidBodyModel` on PyBullet's recursive Newton-Euler.

    PyBullet's ``calculateInverseDynamics`` ignores a fixed base's orientation, so the URDF sits at the origin
    of a private client and gravity is given in the arm's base frame. Its dynamics calls take every movable
    DOF (e.g. gripper fingers too); the chain's are a subset, the others at ``held`` (by name; default 0).
    """

    def __init__(self, urdf: str, chain_joints: Sequence[str], held: dict[str, float] | None = None):
        self._client = _dynamics_client()
        self._body, names = _dynamics_body(urdf)
        self._chain = np.array([names.index(name) for name in chain_joints], dtype=np.intp)
        held = held or {}
        self._full = np.array([held.get(name, 0.0) for name in names], dtype=np.float64)
        self._zeros = [0.0] * len(names)

    def _with_chain(self, q: np.ndarray) -> list[float]:
        full = self._full.copy()
        full[self._chain] = q
        return full.tolist()

    def gravity_torque(self, q: np.ndarray, gravity_in_base: np.ndarray) -> np.ndarray:
        pybullet.setGravity(*gravity_in_base.tolist(), physicsClientId=self._client)
        torques = pybullet.calculateInverseDynamics(self._body, self._with_chain(q), self._zeros, self._zeros,
                                                    physicsClientId=self._client)
        return np.asarray(torques)[self._chain]

    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        matrix = np.asarray(pybullet.calculateMassMatrix(self._body, self._with_chain(q), physicsClientId=self._client))
        return matrix[np.ix_(self._chain, self._chain)]
