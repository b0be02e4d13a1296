"""Rendering: framing, the ghost formation, resolution options, real-time pacing, and the GUI under Xvfb."""

from __future__ import annotations

import os
import pickle
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import ee_formation_env
from ee_formation_env import rendering
from ee_formation_env.engines.pybullet_engine import PyBulletEngine
from ee_formation_env.formation import Formation, FormationGraph
from ee_formation_env.rendering import GHOST_COLOR, frame_points, ghost_positions
from ee_formation_env.rendering import project_points

REPO = Path(__file__).resolve().parents[1]


def content_box_fraction(frame: np.ndarray) -> float:
    """Area of the bounding box of the pixels that differ from the background (the most common colour),
    as a fraction of the frame."""
    colors, counts = np.unique(frame.reshape(-1, 3), axis=0, return_counts=True)
    rows, cols = np.nonzero(np.any(frame != colors[counts.argmax()], axis=2))
    return (rows.max() - rows.min() + 1) * (cols.max() - cols.min() + 1) / (frame.shape[0] * frame.shape[1])


@pytest.mark.parametrize("name", ["planar_square", "spatial_tetrahedron"])
def test_camera_frames_the_arms(make_env, name):
    env = make_env(name, render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert content_box_fraction(frame) >= 0.30  # the default PyBullet framing gave about 0.11 and 0.07
    # Nothing cut off: the frame's border rows and columns are background.
    border = np.concatenate([frame[0], frame[-1], frame[:, 0], frame[:, -1]])
    assert np.all(border == frame[0, 0])


@pytest.mark.parametrize("yaw, pitch", [(0.0, -89.9), (45.0, -30.0), (-120.0, -60.0)])
def test_frame_points_keeps_every_point_in_view(yaw, pitch):
    import pybullet

    points = np.random.default_rng(0).uniform(-2.0, 3.0, (40, 3))
    camera = frame_points(points, yaw, pitch, aspect=4 / 3)
    view = pybullet.computeViewMatrixFromYawPitchRoll(camera.target.tolist(), camera.distance, yaw, pitch, 0.0, 2)
    projection = pybullet.computeProjectionMatrixFOV(camera.fov_deg, 4 / 3, 0.01, 100.0)
    world_to_clip = np.asarray(projection).reshape(4, 4).T @ np.asarray(view).reshape(4, 4).T
    pixels = project_points(world_to_clip, points, 400, 300)
    assert np.all(pixels >= 0) and np.all(pixels[:, 0] <= 400) and np.all(pixels[:, 1] <= 300)
    # ... and tightly: the points span most of the frame in at least one direction.
    span = np.ptp(pixels, axis=0) / [400, 300]
    assert span.max() >= 0.6


def _rotation_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_ghost_of_a_distance_formation_is_the_shape_at_the_best_rigid_fit():
    shape = np.array([[0.0, 0.0, 0.0], [0.4, 0.0, 0.0], [0.2, 0.35, 0.0], [0.2, 0.1, 0.3]])
    formation = Formation(FormationGraph(4, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]), "distance", shape)
    moved = shape @ _rotation_z(0.7).T + [1.0, -2.0, 0.5]
    assert np.allclose(ghost_positions(formation, moved, 3), moved)  # in formation: the ghost coincides
    noisy = moved + np.random.default_rng(1).normal(0, 0.05, moved.shape)
    ghost = ghost_positions(formation, noisy, 3)
    edges = formation.graph.edges
    assert np.allclose([np.linalg.norm(ghost[a] - ghost[b]) for a, b in edges],
                       [np.linalg.norm(shape[a] - shape[b]) for a, b in edges])
    assert np.allclose(ghost.mean(axis=0), noisy.mean(axis=0))


def test_ghost_of_a_displacement_formation_is_only_translated():
    shape = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 3.0], [0.0, 3.0]])
    formation = Formation(FormationGraph(4, [[0, 1], [1, 2], [2, 3], [3, 0]]), "displacement", shape)
    end_effectors = np.array([[1.0, 1.0, 0.2], [2.0, 1.5, 0.2], [2.5, 2.0, 0.2], [0.5, 3.0, 0.2]])
    ghost = ghost_positions(formation, end_effectors, 2)
    assert np.allclose(ghost[:, :2] - ghost[0, :2], shape - shape[0])  # no rotation
    assert np.allclose(ghost[:, :2].mean(axis=0), end_effectors[:, :2].mean(axis=0))
    assert np.allclose(ghost[:, 2], 0.2)  # in the end-effectors' plane


def test_ghost_is_drawn_until_the_formation_is_reached(make_env):
    env = make_env("planar_square", render_mode="rgb_array")
    env.reset(seed=0)
    ghost_pixels = np.all(env.render() == GHOST_COLOR, axis=2).sum()
    assert ghost_pixels >= 50


def test_resolution_is_configurable(make_env):
    env = make_env("spatial_tetrahedron", render_mode="rgb_array", render_width=320, render_height=200)
    env.reset(seed=0)
    assert env.render().shape == (200, 320, 3)
    copy = pickle.loads(pickle.dumps(env))
    try:
        assert (copy.render_width, copy.render_height, copy.render_mode) == (320, 200, "rgb_array")
    finally:
        copy.close()


@pytest.mark.parametrize("options, error, field", [
    ({"render_width": 0}, ValueError, "render_width"),
    ({"render_height": 10_000}, ValueError, "render_height"),
    ({"render_width": 640.0}, TypeError, "render_width"),
    ({"render_height": True}, TypeError, "render_height"),
    ({"real_time": "yes"}, TypeError, "real_time"),
])
def test_bad_render_options_raise_before_any_physics(monkeypatch, options, error, field):
    def no_world(*args, **kwargs):
        raise AssertionError("a physics world was created")

    monkeypatch.setattr(PyBulletEngine, "__init__", no_world)
    with pytest.raises(error, match=field):
        ee_formation_env.parallel_env("planar_square", render_mode="rgb_array", **options)


class _FakeClock:
    def __init__(self) -> None:
        self.now, self.slept = 100.0, []

    def perf_counter(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.slept.append(seconds)
        self.now += seconds


def test_real_time_pacing_follows_simulated_time(monkeypatch):
    clock = _FakeClock()
    monkeypatch.setattr(rendering, "time", clock)
    renderer = rendering.SceneRenderer.__new__(rendering.SceneRenderer)
    renderer._anchor, renderer._last_sim_time = None, 0.0
    renderer._pace(0.0)  # the episode's first render: the anchor
    clock.now += 0.004  # 4 ms of computing, 10 ms simulated: wait 6 ms
    renderer._pace(0.01)
    assert clock.slept == [pytest.approx(0.006)]
    clock.now += 0.015  # 15 ms of computing, 10 ms simulated: 5 ms late, no sleep
    renderer._pace(0.02)
    assert len(clock.slept) == 1
    clock.now += 0.001  # caught up against the anchor: 10 ms simulated, 1 ms spent, 4 ms behind
    renderer._pace(0.03)
    assert clock.slept[-1] == pytest.approx(0.004)
    renderer._pace(0.0)  # a new episode (simulated time went back) re-anchors
    assert renderer._anchor == (clock.now, 0.0)


_GUI_SMOKE = """
import sys
sys.path.insert(0, {repo!r})
import numpy as np
import pybullet
import ee_formation_env
env = ee_formation_env.parallel_env("spatial_tetrahedron", render_mode="human", real_time=True, episode_seconds=0.05)
env.reset(seed=0)
assert env.render() is None
while env.agents:
    env.step({{a: np.zeros(env.action_space(a).shape) for a in env.agents}})
    env.render()
camera = pybullet.getDebugVisualizerCamera(physicsClientId=env.world.client)
print("RESULT", env.world.gui, round(camera[10], 3), flush=True)
env.close()
"""


@pytest.mark.skipif(shutil.which("Xvfb") is None, reason="Xvfb is not installed")
def test_gui_smoke_under_xvfb():
    display = f":{90 + os.getpid() % 500}"
    server = subprocess.Popen(["Xvfb", display, "-screen", "0", "800x600x24", "-nolisten", "tcp"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        # Xvfb accepts clients once its socket exists: wait for it (a fixed sleep lost the race on a loaded machine).
        socket = Path(f"/tmp/.X11-unix/X{display[1:]}")
        deadline = time.monotonic() + 30.0
        while not socket.exists() and server.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert server.poll() is None and socket.exists(), "Xvfb did not start"
        result = subprocess.run([sys.executable, "-c", _GUI_SMOKE.format(repo=str(REPO))], capture_output=True,
                                text=True, timeout=300, env={**os.environ, "DISPLAY": display})
    finally:
        server.terminate()
        server.wait(timeout=30)
    assert result.returncode == 0, result.stdout + result.stderr
    lines = result.stdout.splitlines()
    gui, distance = lines[-1].split()[1:]
    assert gui == "True"
    assert float(distance) < 2.0  # framed on the 0.4 m tetrahedron's arms, not PyBullet's default view
    # PyBullet's GUI prints ~45 lines on connect and ~17 on disconnect; at most its window thread's one remains.
    assert len(lines) <= 3, result.stdout
