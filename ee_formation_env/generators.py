"""Scenario generators: shapes, rigid graphs and ring layouts with any number of arms (scaling benchmarks).

Both families put the arm bases on a circle, each base facing the circle's centre, and use a
trilateration graph (Henneberg type-I extensions): the first ``dim + 1`` vertices are fully connected and
every later vertex is joined to the ``dim`` vertices before it. That gives ``dim N - dim (dim + 1) / 2``
edges, a minimally rigid graph in general position. The shape is the arms' initial end-effector
positions moved by a few centimetres (seeded), which keeps it reachable and generic; the env's own
validation (rigidity, reach, singularities) accepts every scenario built here.

- :func:`planar_ring`: ``planar_2link`` arms (2 DOF), ``dim = 2``;
- :func:`spatial_ring`: ``pera_arm`` arms (7 DOF), ``dim = 3``, with gravity.

The random families of the random-scenario study (and of :data:`ee_formation_env.scenario_sets.RANDOM_FAMILIES`)
are here too: :func:`planar_scenario` and :func:`spatial_scenario`, one seeded scenario per seed. So is the
sampling of a scenario distribution (:mod:`ee_formation_env.distribution`): :func:`sample_task` draws and
validates one problem for the scenario's fixed team, :func:`distribution_bounds` bounds the spaces over all
of them.
"""

from __future__ import annotations

import math
import time
import warnings
from typing import Any, Callable

import numpy as np
import pybullet

from ee_formation_env.robots import RANDOM_SPATIAL_ROBOTS, ROBOTS, SPATIAL_INITIAL_Q
from ee_formation_env.kinematics import chain_model, rpy_to_matrix, singularity_margins
from ee_formation_env.distribution import FIRST_DRAW_DEADLINE_SECONDS
from ee_formation_env.robot import start_problem
from ee_formation_env.scenario import load_scenario
from ee_formation_env.task import build_task

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


# -- the random-scenario study's families (seeded generators of plain scenario data) ----------------------
PLANAR_SECONDS = 20.0  # s, episode length of a random planar scenario
SPATIAL_SECONDS = 30.0  # s, of a random spatial scenario

_SPATIAL_REGION_HEIGHT = (0.35, 0.65)  # m, z range of the shared end-effector region
_SPATIAL_REGION_RADIUS = 0.25  # m, horizontal radius of the shared region around the ring's centre
_MIN_VERTEX_SPACING = 0.15  # m between any two end-effectors (initial) or target vertices
_MIN_ARM_CLEARANCE = 0.03  # m between the collision shapes of two arms in their initial poses


def planar_scenario(seed: int) -> dict[str, Any]:
    """One random planar scenario of the random-scenario study (``studies/random_scenarios.py`` describes the
    family); the same ``seed`` gives the same dict."""
    rng = np.random.default_rng([0, seed])
    n_agents = int(rng.integers(3, 7))
    radius = float(rng.uniform(4.0, 6.0))
    offset = float(rng.uniform(-math.pi, math.pi))
    reach = sum(planar_link_lengths())  # m
    arms, targets = [], []
    for i in range(n_agents):
        angle = offset + 2 * math.pi * i / n_agents
        base = np.array([radius * math.cos(angle), radius * math.sin(angle)])
        yaw = float(rng.uniform(-math.pi, math.pi))
        elbow = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.4, math.pi - 0.4))
        arms.append({"robot": "planar_2link", "base_position": [*base.tolist(), 0.0], "base_rpy": [0.0, 0.0, yaw],
                     "initial_q": [float(rng.uniform(-math.pi, math.pi)), elbow]})
        # Target vertex: 0.8-2.6 m from its own base, within +-60 deg of the direction to the ring's centre.
        distance = float(rng.uniform(0.8, reach - 0.4))
        direction = angle + math.pi + float(rng.uniform(-math.pi / 3, math.pi / 3))
        targets.append((base + distance * np.array([math.cos(direction), math.sin(direction)])).tolist())
    return {"name": f"random_planar_{seed}", "arms": arms, "edges": trilateration_edges(n_agents, 2),
            "shape": targets, "formation": "distance", "dim": 2, "initial_q_noise": 0.0,
            "episode_seconds": PLANAR_SECONDS}


def _sample_pose(robot: str, base: np.ndarray, yaw: float, centre: np.ndarray, rng: np.random.Generator,
                 taken: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """A configuration (rad) of ``robot`` putting its end-effector (world, m) in the shared region."""
    spec = RANDOM_SPATIAL_ROBOTS[robot]
    chain = chain_model(str(spec.urdf), spec.ee_link)
    rotation = rpy_to_matrix(np.array([0.0, 0.0, yaw]))
    # Keep away from the joint limits (10 % margin) and from singular configurations.
    span = chain.upper - chain.lower
    for _ in range(50):
        q = rng.uniform(chain.lower + 0.1 * span, chain.upper - 0.1 * span, size=(512, chain.n_joints))
        ee = base + chain.forward_batch(q) @ rotation.T
        inside = ((np.linalg.norm(ee[:, :2] - centre[:2], axis=1) <= _SPATIAL_REGION_RADIUS)
                  & (ee[:, 2] >= _SPATIAL_REGION_HEIGHT[0]) & (ee[:, 2] <= _SPATIAL_REGION_HEIGHT[1]))
        for k in np.flatnonzero(inside):
            if all(np.linalg.norm(ee[k] - other) >= _MIN_VERTEX_SPACING for other in taken):
                if np.linalg.svd(chain.jacobian(q[k]), compute_uv=False).min() >= 0.05:
                    return q[k], ee[k]
    raise LookupError(f"no configuration of {robot} reaches the shared region")


class _ClearanceChecker:
    """Loads arms into a private DIRECT PyBullet client to reject initial poses that touch another arm."""

    def __init__(self) -> None:
        self.client = pybullet.connect(pybullet.DIRECT)
        self.bodies: list[int] = []

    def place(self, robot: str, base: np.ndarray, yaw: float, q: np.ndarray) -> int:
        spec = RANDOM_SPATIAL_ROBOTS[robot]
        body = pybullet.loadURDF(str(spec.urdf), base.tolist(), pybullet.getQuaternionFromEuler([0.0, 0.0, yaw]),
                                 useFixedBase=True, physicsClientId=self.client)
        names = chain_model(str(spec.urdf), spec.ee_link).joint_names
        for j in range(pybullet.getNumJoints(body, physicsClientId=self.client)):
            name = pybullet.getJointInfo(body, j, physicsClientId=self.client)[1].decode()
            if name in names:
                pybullet.resetJointState(body, j, float(q[names.index(name)]), physicsClientId=self.client)
        return body

    def clear(self, body: int) -> bool:
        """True if ``body`` is at least :data:`_MIN_ARM_CLEARANCE` from every arm placed before it."""
        return all(not pybullet.getClosestPoints(body, other, _MIN_ARM_CLEARANCE, physicsClientId=self.client)
                   for other in self.bodies)

    def close(self) -> None:
        pybullet.disconnect(self.client)


def _clear_pose(robot: str, base: np.ndarray, yaw: float, centre: np.ndarray, rng: np.random.Generator,
                taken: list[np.ndarray], checker: _ClearanceChecker) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_sample_pose`, resampled until the arm clears every arm already placed in ``checker``."""
    for _ in range(100):
        q, ee = _sample_pose(robot, base, yaw, centre, rng, taken)
        body = checker.place(robot, base, yaw, q)
        if checker.clear(body):
            checker.bodies.append(body)
            return q, ee
        pybullet.removeBody(body, physicsClientId=checker.client)
    raise LookupError(f"no collision-free pose of {robot}")


def spatial_scenario(seed: int) -> dict[str, Any]:
    """One random spatial scenario of the random-scenario study (``studies/random_scenarios.py`` describes the
    family); the same ``seed`` gives the same dict.

    A draw whose arms cannot all be posed clear of each other is redrawn (a seeded sequence of attempts).
    """
    for attempt in range(50):
        try:
            return _spatial_attempt(seed, np.random.default_rng([1, seed, attempt]))
        except LookupError:
            continue
    raise RuntimeError(f"spatial_scenario({seed}): no valid draw in 50 attempts")


def _spatial_attempt(seed: int, rng: np.random.Generator) -> dict[str, Any]:
    """One draw of :func:`spatial_scenario` (LookupError if its arms cannot be posed)."""
    n_agents = int(rng.integers(3, 5))
    robots = [str(name) for name in rng.choice(list(RANDOM_SPATIAL_ROBOTS), size=n_agents)]
    radius = float(rng.uniform(0.45, 0.65))
    offset = float(rng.uniform(-math.pi, math.pi))
    initial_checker, target_checker = _ClearanceChecker(), _ClearanceChecker()
    try:
        arms, targets = _pose_arms(robots, radius, offset, rng, initial_checker, target_checker)
    finally:
        initial_checker.close()
        target_checker.close()
    n_agents = len(robots)
    edges = [[i, j] for i in range(n_agents) for j in range(i + 1, n_agents)]
    return {"name": f"random_spatial_{seed}", "arms": arms, "edges": edges,
            "shape": [t.tolist() for t in targets], "formation": "distance", "dim": 3, "initial_q_noise": 0.0,
            "frame_skip": 5, "episode_seconds": SPATIAL_SECONDS}


def _pose_arms(robots: list[str], radius: float, offset: float, rng: np.random.Generator,
               initial_checker: _ClearanceChecker, target_checker: _ClearanceChecker) -> tuple[list[dict], list]:
    """Bases on the ring, collision-free initial poses and target vertices (LookupError if none found)."""
    n_agents = len(robots)
    centre = np.zeros(3)
    arms, initial_ee, targets = [], [], []
    for i, robot in enumerate(robots):
        angle = offset + 2 * math.pi * i / n_agents
        spec = RANDOM_SPATIAL_ROBOTS[robot]
        base = np.array([radius * math.cos(angle), radius * math.sin(angle), spec.random_base_height])
        yaw = float(rng.uniform(-math.pi, math.pi))
        q0, ee0 = _clear_pose(robot, base, yaw, centre, rng, initial_ee, initial_checker)
        _, target = _clear_pose(robot, base, yaw, centre, rng, targets, target_checker)
        initial_ee.append(ee0)
        targets.append(target)
        arm = {"base_position": base.tolist(), "base_rpy": [0.0, 0.0, yaw], "initial_q": q0.tolist()}
        arm.update({"robot": robot} if robot in ROBOTS else {"urdf": str(spec.urdf), "ee_link": spec.ee_link})
        arms.append(arm)
    return arms, targets


# -- scenario distributions (ee_formation_env.distribution): one validated draw per reset ------------------
def sample_task(scenario: Any, rng: np.random.Generator, accept: Callable[[Any], str | None] | None = None,
                deadline_seconds: float | None = None) -> Any:
    """One validated draw of ``scenario``'s distribution (:mod:`ee_formation_env.distribution`): a
    :class:`~ee_formation_env.task.FormationTask` of a fixed scenario with the same team. ``rng`` supplies every
    random number (the env's generator: the reset seed fixes the draw). ``accept(task)`` may reject a draw that
    passed the geometric checks (the env's start-contact check in its world): it returns the reason, or None.
    Rejected draws are redrawn; after ``max_tries``, or once ``deadline_seconds`` (wall clock; None: no
    deadline) have passed after a rejection, a ``ValueError`` names the distribution and the last reason.
    """
    config = scenario.distribution
    reason = ""
    started = time.monotonic()
    for tries in range(1, config.max_tries + 1):
        try:
            with warnings.catch_warnings():  # a non-minimal graph warns once at construction, not per draw
                warnings.simplefilter("ignore", UserWarning)
                task = build_task(load_scenario(draw_scenario(scenario, rng)))
            problem = _margin_problem(task, config) or (accept(task) if accept is not None else None)
        except (ValueError, LookupError) as error:
            problem = str(error)
        if problem is None:
            return task
        reason = problem
        if deadline_seconds is not None and time.monotonic() - started >= deadline_seconds:
            raise ValueError(f"distribution: no valid draw of {scenario.name!r} within {deadline_seconds:g} s "
                             f"({tries} of max_tries {config.max_tries} tries); last rejection: {reason}")
    raise ValueError(f"distribution: no valid draw of {scenario.name!r} in {config.max_tries} tries (max_tries); "
                     f"last rejection: {reason}")


def first_draw(scenario: Any, arm_set: Any) -> Any:
    """The env's draw at construction (generator seeded 0, start contacts checked in ``arm_set``'s world), within
    :data:`~ee_formation_env.distribution.FIRST_DRAW_DEADLINE_SECONDS`: it refuses an infeasible distribution."""
    return sample_task(scenario, np.random.default_rng(0), lambda task: start_problem(arm_set, task),
                       deadline_seconds=FIRST_DRAW_DEADLINE_SECONDS)


def draw_scenario(scenario: Any, rng: np.random.Generator) -> dict[str, Any]:
    """One unvalidated draw of ``scenario``'s distribution as plain scenario data (no ``distribution`` key);
    LookupError when a ``"reachable"`` vertex cannot be placed."""
    config = scenario.distribution
    data = scenario.to_dict()
    data.pop("distribution")
    n_agents, dim = scenario.n_agents, scenario.dim
    arms = data["arms"]
    models = [chain_model(arm.urdf, arm.ee_link) for arm in scenario.arms]
    offset = 0.0
    if config.ring_radius is not None:
        radius = float(rng.uniform(*config.ring_radius))
        offset = float(rng.uniform(*config.ring_offset))
        centre = np.zeros(2)
        for i, arm in enumerate(arms):
            angle = offset + 2 * math.pi * i / n_agents
            arm["base_position"] = [radius * math.cos(angle), radius * math.sin(angle), arm["base_position"][2]]
            arm["base_rpy"] = [arm["base_rpy"][0], arm["base_rpy"][1], angle + math.pi + float(rng.uniform(*config.base_yaw))]
    else:
        centre = np.asarray(scenario.shape)[:, :2].mean(axis=0)
        for arm in arms:
            arm["base_rpy"][2] += float(rng.uniform(*config.base_yaw))
    if config.initial_q == "random":
        for arm, model in zip(arms, models):
            arm["initial_q"] = _inner_configurations(model, 1, rng)[0].tolist()
    if config.shape == "reachable":
        data["shape"] = _reachable_shape(scenario, arms, models, centre, rng).tolist()
    else:
        data["shape"] = _placed_shape(scenario, centre, offset, rng).tolist()
    if config.graph == "trilateration":
        data["edges"] = trilateration_edges(n_agents, dim)
    elif config.graph == "complete":
        data["edges"] = [[i, j] for i in range(n_agents) for j in range(i + 1, n_agents)]
    data.pop("incidence", None)
    return data


def _inner_configurations(model: Any, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` configurations (rad) uniform within the joint limits less a 10 % margin at each end."""
    low = np.where(model.continuous, -math.pi, model.lower)
    high = np.where(model.continuous, math.pi, model.upper)
    span = high - low
    return rng.uniform(low + 0.1 * span, high - 0.1 * span, size=(count, model.n_joints))


def _placed_shape(scenario: Any, centre: np.ndarray, ring_offset: float, rng: np.random.Generator) -> np.ndarray:
    """The ``"scenario"`` or ``"regular"`` shape, scaled, stretched and turned, about the layout's centre."""
    config, dim, n_agents = scenario.distribution, scenario.dim, scenario.n_agents
    own = np.asarray(scenario.shape, dtype=np.float64)
    scale = float(rng.uniform(*config.shape_scale))
    aspect = float(rng.uniform(*config.shape_aspect))
    turn = float(rng.uniform(*config.shape_rotation))
    if config.shape == "scenario":
        points = (own - own.mean(axis=0)) * scale
    else:  # a regular polygon (or tetrahedron) of circumradius `scale`, vertex i towards arm i's ring angle
        angles = ring_offset + 2 * math.pi * np.arange(n_agents) / n_agents
        points = np.zeros((n_agents, dim))
        if dim == 3 and n_agents == 4:
            points = np.array([[1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]]) / math.sqrt(3)
            points *= scale
        else:
            points[:, 0], points[:, 1] = scale * np.cos(angles), scale * np.sin(angles)
    points[:, 0] *= aspect
    points[:, 1] /= aspect
    c, s = math.cos(turn), math.sin(turn)
    points[:, :2] = points[:, :2] @ np.array([[c, s], [-s, c]])
    placed = points.copy()
    placed[:, :2] += centre
    if dim == 3:
        height = own[:, 2].mean() if config.region_height is None else float(rng.uniform(*config.region_height))
        placed[:, 2] += height
    return placed


def _reachable_shape(scenario: Any, arms: list[dict], models: list[Any], centre: np.ndarray,
                     rng: np.random.Generator) -> np.ndarray:
    """Each vertex the end-effector of a random configuration of its own arm (world frame) inside the shared
    region, away from singularities and from the vertices before it; LookupError if one cannot be placed."""
    config, dim = scenario.distribution, scenario.dim
    vertices: list[np.ndarray] = []
    for i, (arm, model) in enumerate(zip(arms, models)):
        rotation = rpy_to_matrix(np.asarray(arm["base_rpy"], dtype=np.float64))
        base = np.asarray(arm["base_position"], dtype=np.float64)
        for _ in range(20):
            q = _inner_configurations(model, 256, rng)
            ee = base + model.forward_batch(q) @ rotation.T
            inside = np.linalg.norm(ee[:, :2] - centre, axis=1) <= config.region_radius
            if dim == 3 and config.region_height is not None:
                inside &= (ee[:, 2] >= config.region_height[0]) & (ee[:, 2] <= config.region_height[1])
            found = None
            for k in np.flatnonzero(inside):
                if all(np.linalg.norm(ee[k, :dim] - other) >= config.vertex_spacing for other in vertices):
                    if singularity_margins(model.jacobian(q[k])[None], dim)[0] >= config.singularity_margin:
                        found = ee[k, :dim]
                        break
            if found is not None:
                vertices.append(found)
                break
        else:
            raise LookupError(f"distribution: arms[{i}] reaches no vertex in the shared region (region_radius "
                              f"{config.region_radius} m about {centre.round(3).tolist()})")
    return np.array(vertices)


def _margin_problem(task: Any, config: Any) -> str | None:
    """Why a validated draw breaks the distribution's own margins (initial singularity margin, vertex
    spacing), or None."""
    for i, (model, q0) in enumerate(zip(task.models, task.initial_q)):
        margin = float(singularity_margins(model.jacobian(q0)[None], task.dim)[0])
        if margin < config.singularity_margin:
            return f"arms[{i}]: initial singularity margin {margin:.3f} m < singularity_margin {config.singularity_margin} m"
    shape = np.asarray(task.scenario.shape)
    gaps = np.linalg.norm(shape[:, None] - shape[None], axis=-1) + np.diag(np.full(len(shape), np.inf))
    if gaps.min() < config.vertex_spacing:
        return f"shape: two vertices {gaps.min():.3f} m apart < vertex_spacing {config.vertex_spacing} m"
    distances = np.linalg.norm(shape - task.base_positions[:, :task.dim], axis=1)
    for i, (distance, reach) in enumerate(zip(distances, task.reaches)):
        if distance > reach - config.reach_margin:
            return (f"shape: vertex {i} is {distance:.3f} m from its base, within reach_margin "
                    f"{config.reach_margin} m of the arm's reach {reach:.3f} m")
    return None


def distribution_bounds(scenario: Any, task: Any) -> tuple[float, float]:
    """Bounds (m) on |z_ij| and on end-effector coordinates over every draw of ``scenario``'s distribution
    (``task``: any draw; the team, so the reaches and base heights, is the same in all): the observation and
    state spaces are built from them, so they stay fixed while the layout changes."""
    config, dim = scenario.distribution, scenario.dim
    reaches = np.asarray(task.reaches)
    heights = task.base_positions[:, 2]
    if config.ring_radius is None:
        bases = task.base_positions  # base yaws may change, the positions do not
        spans = np.linalg.norm(bases[:, None] - bases[None], axis=-1)
        horizontal = float(np.max(np.abs(bases[:, :2])))
    else:
        radius = config.ring_radius[1]
        spans = np.hypot(2 * radius, heights[:, None] - heights[None])
        horizontal = radius
    z_bound = float(np.max(spans + reaches[:, None] + reaches[None]))
    coordinate = max(horizontal, float(np.max(np.abs(heights))) if dim == 3 else 0.0)
    return z_bound, max(coordinate + float(reaches.max()), 1.0)
