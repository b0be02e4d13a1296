"""Scenario generators: shapes, rigid graphs and ring layouts with any number of arms (scaling benchmarks).

Both families put the arm bases on a circle, each base facing the circle's centre, and use a
trilateration graph (Henneberg type-I extensions): the first ``dim + 1`` vertices are fully connected and
every later vertex is joined to the ``dim`` vertices before it. That gives ``dim N - dim (dim + 1) / 2``
edges, a minimally rigid graph in general position. The shape is the arms' initial end-effector
positions moved by a few centimetres (seeded), which keeps it reachable and generic; the env's own
validation (rigidity, reach, singularities) accepts every scenario built here.

- :func:`planar_ring`: ``planar_2link`` arms (2 DOF), ``dim = 2``;
- :func:`spatial_ring`: ``pera_arm`` arms (7 DOF), ``dim = 3``, with gravity.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ee_formation_env.robots import SPATIAL_INITIAL_Q, ROBOTS
from ee_formation_env.kinematics import chain_model, rpy_to_matrix

_PLANAR_REACH_USED = 2.0  # m, initial base-to-end-effector distance of a planar arm
_PLANAR_BASE_SPACING = 3.5  # m between neighbouring bases on the circle (keeps the arms apart)
_SPATIAL_BASE_SPACING = 0.6  # m


def planar_link_lengths() -> tuple[float, float]:
    """The two link lengths (m) of ``planar_2link``, read from its kinematic model (the x offsets of its
    ``joint_2`` and ``ee_joint`` origins, the chain's nominal parameters): the one source of these numbers."""
    robot = ROBOTS["planar_2link"]
    chain = chain_model(str(robot.urdf), robot.ee_link)
    params = dict(zip(chain.param_names, chain.nominal_params))
    return float(params["joint_2.x"]), float(params["ee_joint.x"])


def square_vertices(side: float, centre: tuple[float, float] = (3.0, 3.0)) -> list[list[float]]:
    """The corners of a square of ``side`` m about ``centre`` (x, y) m, counter-clockwise from the lower left:
    the shape of the built-in planar squares (3.0 m about (3, 3))."""
    half = side / 2
    cx, cy = centre
    return [[cx - half, cy - half], [cx + half, cy - half], [cx + half, cy + half], [cx - half, cy + half]]


def trilateration_edges(n_agents: int, dim: int) -> list[list[int]]:
    """Edges of a minimally rigid trilateration graph on ``n_agents`` vertices in ``dim`` dimensions."""
    edges = []
    for i in range(1, n_agents):
        for j in range(max(0, i - dim), i):
            edges.append([j, i])
    return edges


def _ring(n_agents: int, spacing: float, minimum_radius: float) -> tuple[float, list[float]]:
    radius = max(minimum_radius, spacing * n_agents / (2 * math.pi))
    angles = [2 * math.pi * i / n_agents for i in range(n_agents)]
    return radius, angles


def _perturbed(points: np.ndarray, scale: float, seed: int) -> list[list[float]]:
    rng = np.random.default_rng(seed)
    return (points + rng.uniform(-scale, scale, points.shape)).tolist()


def planar_ring(n_agents: int, **overrides: Any) -> dict[str, Any]:
    """``n_agents`` planar two-link arms (2 DOF) on a circle, distance formation, ``dim = 2``."""
    radius, angles = _ring(n_agents, _PLANAR_BASE_SPACING, minimum_radius=3.0)
    # Elbow-up inverse kinematics for an end-effector _PLANAR_REACH_USED ahead of the base (base x axis).
    d = _PLANAR_REACH_USED
    upper, lower = planar_link_lengths()
    elbow = math.acos((d * d - upper * upper - lower * lower) / (2 * upper * lower))
    shoulder = -math.atan2(lower * math.sin(elbow), upper + lower * math.cos(elbow))
    arms, ee = [], []
    for angle in angles:
        base = [radius * math.cos(angle), radius * math.sin(angle), 0.0]
        yaw = angle + math.pi  # face the centre
        arms.append({"robot": "planar_2link", "base_position": base, "base_rpy": [0.0, 0.0, yaw],
                     "initial_q": [shoulder, elbow]})
        ee.append([base[0] + d * math.cos(yaw), base[1] + d * math.sin(yaw)])
    scenario = {"arms": arms, "edges": trilateration_edges(n_agents, 2), "shape": _perturbed(np.array(ee), 0.05, 0),
                "formation": "distance", "dim": 2, "physics_hz": 1000.0, "frame_skip": 10, "episode_seconds": 30.0}
    scenario.update(overrides)
    return scenario


def spatial_ring(n_agents: int, **overrides: Any) -> dict[str, Any]:
    """``n_agents`` PERA-like arms (7 DOF) on a circle, distance formation, ``dim = 3``, gravity on."""
    radius, angles = _ring(n_agents, _SPATIAL_BASE_SPACING, minimum_radius=0.35)
    robot = ROBOTS["pera_arm"]
    chain = chain_model(str(robot.urdf), robot.ee_link)
    arms, ee = [], []
    for i, angle in enumerate(angles):
        base = np.array([radius * math.cos(angle), radius * math.sin(angle), 0.0])
        rpy = [0.0, 0.0, angle + math.pi]
        q0 = list(SPATIAL_INITIAL_Q[i % 2])
        arms.append({"robot": "pera_arm", "base_position": base.tolist(), "base_rpy": rpy, "initial_q": q0})
        ee.append(rpy_to_matrix(rpy) @ chain.forward(np.array(q0)) + base)
    scenario = {"arms": arms, "edges": trilateration_edges(n_agents, 3), "shape": _perturbed(np.array(ee), 0.02, 0),
                "formation": "distance", "dim": 3, "physics_hz": 1000.0, "frame_skip": 5, "episode_seconds": 50.0}
    scenario.update(overrides)
    return scenario
