"""A thin wrapper over one PyBullet physics client: connection, stepping, state snapshots, camera.

Rule: this module talks to PyBullet and nothing else; what is drawn into frames (pixel projection, line
drawing) lives in :mod:`ee_formation_env.rendering`, its only user.
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import os
import sys
import warnings
from typing import Iterator, Sequence

import numpy as np
import pybullet

class PhysicsWorld:
    """One PyBullet client (DIRECT, or GUI for ``render_mode="human"``) with a fixed time step.

    Each instance owns its client, so several worlds can live in one process. ``close()`` is idempotent.
    """

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

