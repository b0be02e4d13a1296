"""A thin wrapper over one PyBullet physics client: connection, stepping, state snapshots, camera."""

from __future__ import annotations

import math
import os
import sys
from typing import Sequence

import numpy as np
import pybullet

RenderMode = str  # "human" | "rgb_array" | None


class PhysicsWorld:
    """One PyBullet client (DIRECT, or GUI for ``render_mode="human"``) with a fixed time step.

    Each instance owns its client, so several worlds can live in one process. ``close()`` is idempotent.
    """

    def __init__(self, physics_hz: float, gravity: tuple[float, float, float], render_mode: str | None = None):
        mode = pybullet.GUI if render_mode == "human" else pybullet.DIRECT
        if mode == pybullet.GUI and sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
            # PyBullet's GUI calls exit() when it finds no X server: fail here with an exception instead.
            raise RuntimeError('render_mode="human" needs a display (DISPLAY is not set); use "rgb_array" headless')
        self.client = pybullet.connect(mode)
        if self.client < 0:
            raise RuntimeError("PyBullet could not connect (is another GUI client already open?)")
        self.time_step = 1.0 / physics_hz
        pybullet.setTimeStep(self.time_step, physicsClientId=self.client)
        pybullet.setGravity(*gravity, physicsClientId=self.client)
        # One solver pass per step and a fixed pair order: bit-identical trajectories from one state.
        pybullet.setPhysicsEngineParameter(numSubSteps=0, deterministicOverlappingPairs=1,
                                           physicsClientId=self.client)
        if mode == pybullet.GUI:
            pybullet.configureDebugVisualizer(pybullet.COV_ENABLE_GUI, 0, physicsClientId=self.client)
        self._snapshot: int | None = None

    @property
    def connected(self) -> bool:
        return self.client >= 0

    def load_urdf(self, urdf: str, position: tuple[float, ...], rpy: tuple[float, ...]) -> int:
        """Load a fixed-base body; inertias are taken from the URDF, not recomputed from collision shapes."""
        orientation = pybullet.getQuaternionFromEuler(rpy)
        return pybullet.loadURDF(urdf, basePosition=position, baseOrientation=orientation, useFixedBase=True,
                                 flags=pybullet.URDF_USE_INERTIA_FROM_FILE, physicsClientId=self.client)

    def step(self) -> None:
        pybullet.stepSimulation(physicsClientId=self.client)

    def step_with_torques(self, commands: Sequence[tuple[int, Sequence[int], Sequence[float]]], steps: int) -> None:
        """``steps`` physics steps, each preceded by every ``(body, joint indices, torques N m)`` command.

        PyBullet's TORQUE_CONTROL lasts one step, so the torques are re-sent before every step; this is the
        env's inner loop, kept free of per-call Python overhead.
        """
        client, set_motors, step = self.client, pybullet.setJointMotorControlArray, pybullet.stepSimulation
        torque_control = pybullet.TORQUE_CONTROL
        for _ in range(steps):
            for body, joints, torques in commands:
                set_motors(body, joints, torque_control, forces=torques, physicsClientId=client)
            step(physicsClientId=client)

    def send_torques(self, commands: Sequence[tuple[int, Sequence[int], Sequence[float]]]) -> None:
        """Send every ``(body, joint indices, torques N m)`` command for the next physics step only."""
        for body, joints, torques in commands:
            pybullet.setJointMotorControlArray(body, joints, pybullet.TORQUE_CONTROL, forces=torques,
                                               physicsClientId=self.client)

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
        renderer = pybullet.ER_BULLET_HARDWARE_OPENGL if self._is_gui() else pybullet.ER_TINY_RENDERER
        _, _, rgba, _, _ = pybullet.getCameraImage(width, height, view, projection, renderer=renderer,
                                                   physicsClientId=self.client)
        image = np.reshape(np.asarray(rgba, dtype=np.uint8), (height, width, 4))[:, :, :3].copy()
        world_to_clip = np.asarray(projection).reshape(4, 4).T @ np.asarray(view).reshape(4, 4).T
        return image, world_to_clip

    def draw_line(self, start: np.ndarray, end: np.ndarray, color: tuple[float, float, float],
                  replace_id: int = -1) -> int:
        """A debug line in the GUI (ignored by the headless renderer); returns its id for replacement."""
        return pybullet.addUserDebugLine(start.tolist(), end.tolist(), color, lineWidth=2.0,
                                         replaceItemUniqueId=replace_id, physicsClientId=self.client)

    def _is_gui(self) -> bool:
        return pybullet.getConnectionInfo(self.client)["connectionMethod"] == pybullet.GUI

    def close(self) -> None:
        if self.client >= 0:
            try:
                pybullet.disconnect(physicsClientId=self.client)
            except pybullet.error:
                pass  # already gone (e.g. the GUI window was closed)
            self.client = -1


def project_points(world_to_clip: np.ndarray, points: np.ndarray, width: int, height: int) -> np.ndarray:
    """Pixel coordinates (k, 2) as (column, row) of world points (k, 3)."""
    homogeneous = np.hstack([points, np.ones((len(points), 1))]) @ world_to_clip.T
    ndc = homogeneous[:, :2] / homogeneous[:, 3:4]
    return np.stack([(ndc[:, 0] + 1) * 0.5 * width, (1 - ndc[:, 1]) * 0.5 * height], axis=1)


def draw_segment(image: np.ndarray, start: np.ndarray, end: np.ndarray, color: tuple[int, int, int],
                 thickness: int = 2) -> None:
    """Draw a line segment between two pixel positions into an RGB image, in place."""
    length = int(math.ceil(np.linalg.norm(end - start))) + 1
    samples = np.linspace(0.0, 1.0, max(length, 2))[:, None]
    points = np.round(start + samples * (end - start)).astype(np.int64)
    height, width = image.shape[:2]
    for dx in range(-(thickness // 2), thickness - thickness // 2):
        for dy in range(-(thickness // 2), thickness - thickness // 2):
            cols, rows = points[:, 0] + dx, points[:, 1] + dy
            keep = (cols >= 0) & (cols < width) & (rows >= 0) & (rows < height)
            image[rows[keep], cols[keep]] = color
