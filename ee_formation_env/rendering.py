"""Rendering of the formation env: a camera that frames the arms, the target formation as a ghost, drawing.

Both render modes share one framing (:func:`frame_points`): ``rgb_array`` frames come from PyBullet's
TinyRenderer with the formation drawn into the image; ``human`` points PyBullet's GUI camera the same way
and draws the same lines as debug items. The camera is fixed for an episode: it is framed at the first
render after a reset, on the bases, every link frame and the ghost, so that a video does not shake.

Colours: the current formation's edges are red; the ghost, the desired shape placed where it best fits the
current end-effectors (:func:`ghost_positions`), is light blue, so that the gap between the two is the
remaining formation error.

The pixel helpers (:func:`project_points`, :func:`draw_segment`) live here too: everything drawn into a frame
is this module's; :mod:`ee_formation_env.world` only wraps the PyBullet client.

Options and framing for users: see docs/spaces.md ("Rendering").
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from ee_formation_env.formation import Formation
from ee_formation_env.world import PhysicsWorld

EDGE_COLOR = (220, 30, 30)  # RGB 0-255: the current formation's edges
GHOST_COLOR = (110, 150, 230)  # RGB 0-255: the target formation placed at the best fit
FIELD_OF_VIEW_DEG = 50.0  # vertical field of view of the camera
FRAME_MARGIN = 0.04  # fraction of the frame left free around the framed points, on each side
LINK_PADDING = 0.12  # the framed points' half-extent across the view is widened by this fraction (link bodies)
MIN_RESOLUTION, MAX_RESOLUTION = 16, 4096  # pixels, for render_width and render_height
REAL_TIME_SLACK = 0.25  # s: lagging more than this behind real time restarts the real-time clock

# Viewing directions (PyBullet yaw, pitch in degrees): straight down on a planar formation's plane, and
# from above at an angle for a spatial one.
PLANAR_VIEW = (0.0, -89.9)
SPATIAL_VIEW = (45.0, -30.0)


def validate_render_options(width: object, height: object, real_time: object) -> tuple[int, int, bool]:
    """``(width, height, real_time)``, width and height in pixels, or a ValueError/TypeError naming the bad one."""
    values = []
    for name, value in (("render_width", width), ("render_height", height)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise TypeError(f"{name}: expected an integer number of pixels, got {value!r}")
        if not MIN_RESOLUTION <= value <= MAX_RESOLUTION:
            raise ValueError(f"{name}: expected {MIN_RESOLUTION} to {MAX_RESOLUTION} pixels, got {value}")
        values.append(int(value))
    if not isinstance(real_time, bool):
        raise TypeError(f"real_time: expected True or False, got {real_time!r}")
    return values[0], values[1], real_time


@dataclass(frozen=True)
class Camera:
    """A PyBullet yaw/pitch camera: looks at ``target`` (m, world) from ``distance`` (m)."""

    target: np.ndarray
    distance: float
    yaw: float  # deg
    pitch: float  # deg
    fov_deg: float = FIELD_OF_VIEW_DEG  # vertical


def _view_axes(yaw_deg: float, pitch_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit vectors (forward, right, up) of PyBullet's yaw/pitch camera (z up)."""
    yaw, pitch = math.radians(yaw_deg), math.radians(pitch_deg)
    # PyBullet's computeViewMatrixFromYawPitchRoll (up axis z) puts the eye at target + distance * this vector.
    eye_direction = np.array([math.sin(yaw) * math.cos(pitch), -math.cos(yaw) * math.cos(pitch), -math.sin(pitch)])
    forward = -eye_direction
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return forward, right, up


def frame_points(points: np.ndarray, yaw: float, pitch: float, aspect: float,
                 fov_deg: float = FIELD_OF_VIEW_DEG, margin: float = FRAME_MARGIN) -> Camera:
    """The closest camera looking along (yaw, pitch) that shows every point (k, 3), m, with a margin.

    The target is the centre of the points' extent across the view, and the distance the smallest at which
    every point lies inside the field of view shrunk by ``margin`` on each side (``aspect`` = width / height).
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    forward, right, up = _view_axes(yaw, pitch)
    across, vertical = points @ right, points @ up
    center = points.mean(axis=0)  # moved across the view onto the middle of the points' extent
    target = (center + right * (0.5 * (across.min() + across.max()) - center @ right)
              + up * (0.5 * (vertical.min() + vertical.max()) - center @ up))
    # Links and bases are bodies around their frames: widen every point's footprint across the view.
    padding = LINK_PADDING * 0.5 * max(np.ptp(across), np.ptp(vertical))
    relative = points - target
    tan_vertical = math.tan(math.radians(fov_deg) / 2) * (1.0 - 2.0 * margin)
    tan_horizontal = math.tan(math.radians(fov_deg) / 2) * aspect * (1.0 - 2.0 * margin)
    # A point at depth z = distance + r.forward is inside the view when |r.right| <= z tan_h and |r.up| <= z tan_v.
    needed = np.maximum((np.abs(relative @ right) + padding) / tan_horizontal,
                        (np.abs(relative @ up) + padding) / tan_vertical)
    distance = float(np.max(needed - relative @ forward))
    return Camera(target, max(distance, 0.1), yaw, pitch, fov_deg)


def ghost_positions(formation: Formation, end_effectors: np.ndarray, dim: int) -> np.ndarray:
    """The desired shape (N, 3), m, placed where it best fits ``end_effectors`` (N, 3) in the least-squares sense.

    Displacement formations are goals up to a translation: the shape is moved onto the end-effectors'
    centroid. Distance formations are goals up to a rigid motion (reflections included): the shape is also
    rotated by the orthogonal Procrustes solution. In 2D the ghost lies in the end-effectors' mean plane.
    """
    current = np.asarray(end_effectors, dtype=np.float64)[:, :dim]
    shape = np.asarray(formation.shape, dtype=np.float64)[:, :dim]
    shape_centered = shape - shape.mean(axis=0)
    centroid = current.mean(axis=0)
    if formation.kind == "distance":
        u, _, vt = np.linalg.svd(shape_centered.T @ (current - centroid))
        shape_centered = shape_centered @ (u @ vt)  # rotation or reflection: both keep every distance
    placed = np.zeros((len(shape), 3))
    placed[:, :dim] = shape_centered + centroid
    if dim == 2:
        placed[:, 2] = float(np.mean(end_effectors[:, 2]))
    return placed


def draw_formation(image: np.ndarray, world_to_clip: np.ndarray, edges: Sequence[tuple[int, int]],
                   end_effectors: np.ndarray, ghost: np.ndarray) -> None:
    """Draw the ghost's edges (thin) and then the current edges (thick, on top) into an RGB image, in place."""
    height, width = image.shape[:2]
    thickness = max(2, round(min(width, height) / 180))  # lines stay visible at higher resolutions
    ghost_pixels = project_points(world_to_clip, ghost, width, height)
    current_pixels = project_points(world_to_clip, end_effectors, width, height)
    for tail, head in edges:
        draw_segment(image, ghost_pixels[tail], ghost_pixels[head], GHOST_COLOR, max(1, thickness - 1))
    for tail, head in edges:
        draw_segment(image, current_pixels[tail], current_pixels[head], EDGE_COLOR, thickness)


class SceneRenderer:
    """The env's rendering state: the episode's camera, the GUI's debug items and the real-time pacing.

    ``real_time`` (``human`` mode): each :meth:`render_human` waits until as much wall-clock time has passed
    since the episode's first render as simulated time has, so the GUI plays at the speed of the simulation
    (where the simulation and drawing are slower than that, it plays as fast as they go).
    """

    def __init__(self, world: PhysicsWorld, formation: Formation, dim: int, width: int, height: int,
                 real_time: bool = False):
        self.world, self.formation, self.dim = world, formation, dim
        self.width, self.height, self.real_time = validate_render_options(width, height, real_time)
        self.camera: Camera | None = None
        self._edge_lines = [-1] * formation.graph.n_edges
        self._ghost_lines = [-1] * formation.graph.n_edges
        self._anchor: tuple[float, float] | None = None  # (wall clock s, simulated s) that real time counts from
        self._last_sim_time = 0.0  # s, at the previous human render

    def frame(self, bodies: Sequence[int], end_effectors: np.ndarray) -> Camera:
        """Frame the bases, every link frame and the ghost; the camera then stays until the next call."""
        points = [end_effectors, ghost_positions(self.formation, end_effectors, self.dim)]
        points += [self.world.link_positions(body) for body in bodies]
        points = np.concatenate(points)
        yaw, pitch = PLANAR_VIEW if self.dim == 2 else SPATIAL_VIEW
        self.camera = frame_points(points, yaw, pitch, self.width / self.height)
        if self.world.gui:  # the same framing through the window's own field of view and aspect ratio
            fov_deg, aspect = self.world.gui_field_of_view()
            window = frame_points(points, yaw, pitch, aspect, fov_deg)
            self.world.point_gui_camera(window.target, window.distance, window.yaw, window.pitch)
        return self.camera

    def render_copy(self, mode: str, arms: Sequence[Any], end_effectors: np.ndarray, formation: Formation,
                    step_count: int, control_dt: float) -> np.ndarray | None:
        """Render one env copy at its last reset/step: ``rgb_array``, an RGB frame (height, width, 3) uint8 of
        every arm, the current formation's edges in red and the target ``formation`` (placed at the best fit)
        as a light blue ghost; ``human``, the PyBullet GUI with the same camera and lines (None). Without a
        display, a ``human`` env simulates headless (warning once) and this does nothing. One camera per
        episode (framed at its first step): no shaking."""
        self.formation = formation
        if self.camera is None or step_count == 0:
            self.frame([arm.body for arm in arms], end_effectors)
        if mode == "human":
            self.render_human(end_effectors, step_count * control_dt)
            return None
        return self.render_rgb(end_effectors)

    def render_rgb(self, end_effectors: np.ndarray) -> np.ndarray:
        """An RGB frame (height, width, 3) uint8 with the ghost and the current formation drawn."""
        camera = self.camera
        image, world_to_clip = self.world.render(camera.target, camera.distance, camera.yaw, camera.pitch,
                                                 self.width, self.height, camera.fov_deg)
        ghost = ghost_positions(self.formation, end_effectors, self.dim)
        draw_formation(image, world_to_clip, self.formation.graph.edges, end_effectors, ghost)
        return image

    def render_human(self, end_effectors: np.ndarray, sim_time: float) -> None:
        """Update the GUI's debug lines (no-op without a window) and pace to real time if asked."""
        if not self.world.gui:
            return
        ghost = ghost_positions(self.formation, end_effectors, self.dim)
        edge_color = tuple(c / 255 for c in EDGE_COLOR)
        ghost_color = tuple(c / 255 for c in GHOST_COLOR)
        for k, (tail, head) in enumerate(self.formation.graph.edges):
            self._ghost_lines[k] = self.world.draw_line(ghost[tail], ghost[head], ghost_color, self._ghost_lines[k],
                                                        width=1.5)
            self._edge_lines[k] = self.world.draw_line(end_effectors[tail], end_effectors[head], edge_color,
                                                       self._edge_lines[k], width=3.0)
        if self.real_time:
            self._pace(sim_time)

    def _pace(self, sim_time: float) -> None:
        """Sleep until the wall clock, since the episode's anchor, has caught up with simulated time."""
        now = time.perf_counter()
        previous, self._last_sim_time = self._last_sim_time, sim_time
        if self._anchor is None or sim_time < previous:  # first render, or a new episode
            self._anchor = (now, sim_time)
            return
        delay = self._anchor[0] + (sim_time - self._anchor[1]) - now
        if delay > 0:
            time.sleep(delay)
        elif delay < -REAL_TIME_SLACK:  # the simulation runs slower than real time: do not rush to catch up
            self._anchor = (now, sim_time)


# Drawing into rgb_array frames (pixels), used by the renderer above.
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
