"""Formation manoeuvres: a time-varying reference for the formation's centroid and orientation (transport).

Scenario key ``manoeuvre`` = ``{"start": t0, "duration": T, "translation": A, "rotation": r, "axis": u}``:

- ``start`` t0 (s, default 5, at most :data:`~ee_formation_env.inputs.MAX_EPISODE_SECONDS`): the hold time
  before the motion starts;
- ``duration`` T (s, default 20, at most :data:`~ee_formation_env.inputs.MAX_EPISODE_SECONDS`): the length of the
  motion, at least :data:`MIN_DURATION_CONTROL_STEPS` control periods (``frame_skip / physics_hz`` s each), so
  that the arms are commanded along it rather than shown a jump (an episode shorter than t0 + T ends during it);
- ``translation`` A (m, ``dim`` numbers, default zeros): the out-and-back displacement amplitude; the peak speed
  ``pi |A| / T`` is at most :data:`MAX_REFERENCE_SPEED` m/s, and |A| at most twice the shortest arm's reach (the
  diameter of its workspace: no end-effector can follow farther), checked with the robots' models
  (:func:`ee_formation_env.validation.check_task`);
- ``rotation`` r (rad, default 0): the amplitude of the out-and-back turn about the centroid; distance
  formations only (a displacement formation's shape is fixed in the world's orientation); at the peak turn rate
  ``pi |r| / T`` the reference turns at most half a turn (pi rad) per control period, i.e. ``|r| <= T /
  control_dt``: the reference is sampled once per control period, and a turn of more than half a revolution
  between two samples reads as one the other way;
- ``axis`` u (``dim`` 3 only; world frame, default [0, 0, 1]): the turn's axis (normalized).

Each bound is refused at parse time naming its key, so that every number the reference produces (positions,
speeds, turn rates, the observation bounds) is finite.

Profile: ``s(t) = (1 - cos(2 pi (t - t0) / T)) / 2`` for t0 <= t <= t0 + T, 0 otherwise (out and back, at rest
at both ends). Reference centroid ``c*(t) = c0 + s(t) A``, with c0 the centroid of the end-effectors at the motion's
start (measured by the env at the last control step with t <= t0; until then c* is the current centroid:
the formation forms where its arms take it, and the transport starts from there); reference orientation: the turn ``theta*(t) = s(t) r`` about u through c*(t). Peak
speed ``pi |A| / T`` (m/s) and peak turn rate ``pi |r| / T`` (rad/s), both at t0 + T / 4 and t0 + 3T / 4.

With a manoeuvre, every agent's observation ends with the reference in its own base frame
(:mod:`ee_formation_env.observation`): ``c*(t) - b_i`` (m), ``dc*/dt`` (m/s) and the reference angular
velocity ``omega* = ds/dt r u`` (rad/s: one number, about z, for ``dim`` 2; a 3-vector for ``dim`` 3).
Without one (the default, or zero translation and rotation) nothing changes.

Tracking errors (:meth:`ReferenceMotion.orientation_errors`): the centroid error is ``|c(t) - c*(t)|`` (m);
the orientation error is the angle (rad) of the best-fit rotation (Kabsch) taking the end-effector
positions about their centroid at the motion's start (the last step with t <= t0), turned by theta*(t),
onto the current ones about theirs; 0 before the motion starts.

The reference laws' velocity feedforward and its measurements: docs/manoeuvres.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from ee_formation_env.inputs import MAX_EPISODE_SECONDS, check_known_keys, excerpt

MANOEUVRE_KEYS = ("start", "duration", "translation", "rotation", "axis")
DEFAULT_START_SECONDS = 5.0
DEFAULT_DURATION_SECONDS = 20.0
#: Shortest manoeuvre, in control periods: 4 steps sample the profile at its start, peak speed (T/4), turning
#: point (T/2) and return (3T/4); at fewer the arms are shown a jump, not a motion to follow.
MIN_DURATION_CONTROL_STEPS = 4
#: Fastest reference centroid, m/s (peak speed pi |A| / T): no arm's end-effector moves at a kilometre per second
#: (at the default max_joint_velocity, 50 rad/s, it would take an arm 20 m long).
MAX_REFERENCE_SPEED = 1000.0
_BOUND_MARGIN = 1.001  # observation bounds: a little above the largest value the reference can take


@dataclass(frozen=True)
class ManoeuvreConfig:
    """The reference motion (module docstring); units s, s, m, rad, unit vector."""

    start: float = DEFAULT_START_SECONDS
    duration: float = DEFAULT_DURATION_SECONDS
    translation: tuple[float, ...] = ()  # () or zeros: no translation
    rotation: float = 0.0
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)

    @property
    def active(self) -> bool:
        """Whether the reference moves at all (else the env is exactly the plain hold task)."""
        return bool(any(a != 0 for a in self.translation) or self.rotation != 0)

    @property
    def peak_speed(self) -> float:
        """The reference centroid's peak speed ``pi |A| / T``, m/s."""
        return math.pi * float(np.linalg.norm(self.translation)) / self.duration if self.translation else 0.0

    @property
    def peak_angular_speed(self) -> float:
        """The reference turn's peak rate ``pi |r| / T``, rad/s."""
        return math.pi * abs(self.rotation) / self.duration

    def profile(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``s(t)`` and ``ds/dt`` (1/s) at times ``t`` (s), any shape."""
        t = np.asarray(t, dtype=np.float64)
        phase = 2.0 * math.pi * (t - self.start) / self.duration
        moving = (t >= self.start) & (t <= self.start + self.duration)
        s = np.where(moving, 0.5 * (1.0 - np.cos(phase)), 0.0)
        rate = np.where(moving, (math.pi / self.duration) * np.sin(phase), 0.0)
        return s, rate

    def to_dict(self) -> dict[str, Any] | None:
        """Plain data that :func:`parse_manoeuvre` accepts back; None when inactive."""
        if not self.active:
            return None
        data = {"start": self.start, "duration": self.duration, "translation": list(self.translation),
                "rotation": self.rotation}
        if self.axis != (0.0, 0.0, 1.0):  # only a spatial formation may name one
            data["axis"] = list(self.axis)
        return data


def parse_manoeuvre(value: Any, dim: int, formation_kind: str, control_dt: float) -> ManoeuvreConfig:
    """``manoeuvre`` from scenario data, for a ``dim``-dimensional formation of kind ``formation_kind`` whose
    env steps last ``control_dt`` s; ``ValueError`` naming the field on bad input."""
    if isinstance(value, ManoeuvreConfig):
        value = value.to_dict()
    if value is None:
        return ManoeuvreConfig()
    if not isinstance(value, Mapping):
        raise ValueError(f"manoeuvre: expected a dict with keys {list(MANOEUVRE_KEYS)} or null, got {excerpt(value)}")
    check_known_keys("manoeuvre", value, list(MANOEUVRE_KEYS))
    start = _number("manoeuvre.start", value.get("start", DEFAULT_START_SECONDS),
                    f"a time >= 0 (s), at most {MAX_EPISODE_SECONDS:g} (the longest episode)",
                    lambda x: 0 <= x <= MAX_EPISODE_SECONDS)
    duration = _number("manoeuvre.duration", value.get("duration", DEFAULT_DURATION_SECONDS),
                       f"a time > 0 (s), at most {MAX_EPISODE_SECONDS:g} (the longest episode)",
                       lambda x: 0 < x <= MAX_EPISODE_SECONDS)
    if duration < MIN_DURATION_CONTROL_STEPS * control_dt:
        raise ValueError(f"manoeuvre.duration: expected at least {MIN_DURATION_CONTROL_STEPS} control periods "
                         f"({MIN_DURATION_CONTROL_STEPS * control_dt:g} s at {control_dt:g} s per env step) for the "
                         f"arms to follow the motion, got {duration:g} s")
    translation = _vector("manoeuvre.translation", value.get("translation", [0.0] * dim), dim, "m")
    amplitude = math.hypot(*translation)  # inf rather than an overflow warning for huge components
    if math.pi * amplitude / duration > MAX_REFERENCE_SPEED:
        raise ValueError(f"manoeuvre.translation: expected a peak speed pi |A| / T of at most {MAX_REFERENCE_SPEED:g} "
                         f"m/s, got |A| = {amplitude:g} m over T = {duration:g} s")
    rotation = _number("manoeuvre.rotation", value.get("rotation", 0.0), "an angle (rad)", lambda x: True)
    if abs(rotation) > duration / control_dt:
        raise ValueError(f"manoeuvre.rotation: expected at most half a turn (pi rad) per control period at the peak "
                         f"turn rate pi |r| / T, i.e. |r| <= T / control_dt = {duration / control_dt:g} rad, got "
                         f"{rotation:g} rad")
    if rotation != 0 and formation_kind != "distance":
        raise ValueError(f"manoeuvre.rotation: a {formation_kind} formation's shape is fixed in orientation; "
                         f"only distance formations can turn, got rotation {rotation:g} rad")
    axis = (0.0, 0.0, 1.0)
    if "axis" in value:
        if dim != 3:
            raise ValueError(f"manoeuvre.axis: only for dim 3 (a planar formation turns about z), got "
                             f"{excerpt(value['axis'])}")
        vector = np.asarray(_vector("manoeuvre.axis", value["axis"], 3, "a direction"))
        norm = float(np.linalg.norm(vector))
        if not (norm > 1e-9 and math.isfinite(norm)):
            raise ValueError(f"manoeuvre.axis: expected a nonzero direction, got {excerpt(value['axis'])}")
        axis = tuple((vector / norm).tolist())
    config = ManoeuvreConfig(start=start, duration=duration, translation=translation, rotation=rotation, axis=axis)
    return config if config.active else ManoeuvreConfig()  # one form of "no manoeuvre": equal scenarios compare equal


def _finite_number(value: Any) -> bool:
    """Whether ``value`` is a finite int or float (not a bool; an int too large for a float is not)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def _number(name: str, value: Any, expected: str, valid: Any) -> float:
    if not (_finite_number(value) and valid(value)):
        raise ValueError(f"{name}: expected {expected}, got {excerpt(value)}")
    return float(value)


def _vector(name: str, value: Any, length: int, unit: str) -> tuple[float, ...]:
    ok = isinstance(value, (list, tuple, np.ndarray)) and len(value) == length and all(
        _finite_number(v) for v in value)
    if not ok:
        raise ValueError(f"{name}: expected {length} finite numbers ({unit}), got {excerpt(value)}")
    return tuple(float(v) for v in value)


def rotation_about(axis: np.ndarray, angles: np.ndarray, dim: int) -> np.ndarray:
    """Rotations (K, dim, dim) by ``angles`` (K,) rad about ``axis`` (world, unit; about z for ``dim`` 2)."""
    c, s = np.cos(angles), np.sin(angles)
    if dim == 2:
        return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    u = np.asarray(axis, dtype=np.float64)
    skew = np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])
    return (c[:, None, None] * np.eye(3) + s[:, None, None] * skew
            + (1.0 - c)[:, None, None] * np.outer(u, u))


def best_fit_angle(source: np.ndarray, target: np.ndarray) -> float:
    """The angle (rad, >= 0) of the proper rotation that best takes the centred points ``source`` (N, d)
    onto the centred points ``target`` (Kabsch)."""
    a, b = source - source.mean(axis=0), target - target.mean(axis=0)
    u, _, vt = np.linalg.svd(a.T @ b)
    correction = np.ones(len(u))
    correction[-1] = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rotation = vt.T @ np.diag(correction) @ u.T  # target ~ rotation @ source
    if rotation.shape == (2, 2):
        return abs(float(np.arctan2(rotation[1, 0], rotation[0, 0])))
    return float(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)))


class ReferenceMotion:
    """The reference of one task's manoeuvre for K copies: the world signal, each agent's observation block
    and the tracking errors (module docstring). Every function takes K copies' arrays (a single env is K = 1),
    so a batched copy's numbers are the single env's bit for bit."""

    def __init__(self, config: ManoeuvreConfig, task: Any):
        self.config = config
        m = self.dim = task.dim
        self.omega_size = 1 if m == 2 else 3
        self.size = 2 * m + self.omega_size  # per agent: c* - b_i, dc*/dt, omega*
        self._translation = np.asarray(config.translation or (0.0,) * m, dtype=np.float64)
        self._axis = np.asarray(config.axis, dtype=np.float64)
        self._rotations = np.ascontiguousarray(task.base_rotations[:, :m, :m])  # (N, m, m) base -> world
        self._bases = task.base_positions[:, :m]  # (N, m)
        # A planar agent's turn rate about its own z: the sign of its base z axis along the world's.
        self._z_signs = task.base_rotations[:, 2, 2][None, :, None]  # (1, N, 1)
        self._full_rotations = task.base_rotations  # (N, 3, 3)
        shape = np.asarray(task.formation.shape, dtype=np.float64)
        self._centred_shape = shape - shape.mean(axis=0)  # (N, m): the tracking term's shape (agent_targets)
        self._shape_turns = task.formation.kind == "distance"  # a displacement shape keeps the world's orientation
        self.n_agents = task.n_agents
        self.bound = self._bound(task)

    def _bound(self, task: Any) -> np.ndarray:
        """One agent's block bound (size,): |c* - b_i| at most the farthest end-effector from b_i plus |A|."""
        bases, reaches = self._bases, np.asarray(task.reaches)
        farthest = max(float(np.linalg.norm(bases[j] - bases[i])) + reaches[j]
                       for i in range(len(bases)) for j in range(len(bases)))
        position = farthest + float(np.linalg.norm(self._translation))
        return _BOUND_MARGIN * np.concatenate([np.full(self.dim, position), np.full(self.dim, self.config.peak_speed),
                                               np.full(self.omega_size, self.config.peak_angular_speed)])

    def world(self, t: np.ndarray, c0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """At times ``t`` (K,) s from reset centroids ``c0`` (K, m): c* (K, m) m, dc*/dt (K, m) m/s,
        theta* (K,) rad and omega* (K, 3) rad/s (world frame)."""
        s, rate = self.config.profile(t)
        centroid = c0 + s[:, None] * self._translation
        velocity = rate[:, None] * self._translation
        omega = (rate * self.config.rotation)[:, None] * self._axis
        return centroid, velocity, s * self.config.rotation, omega

    def observation_block(self, t: np.ndarray, c0: np.ndarray) -> np.ndarray:
        """Every agent's reference block in its own base frame (K, N * size): c* - b_i, dc*/dt, omega*."""
        centroid, velocity, _, omega = self.world(t, c0)
        offsets = centroid[:, None, :] - self._bases  # (K, N, m), world
        offsets = (offsets[..., None, :] @ self._rotations)[..., 0, :]  # row vector @ R = R^T v: own frame
        velocities = (velocity[:, None, None, :] @ self._rotations)[..., 0, :]
        if self.dim == 2:
            omegas = omega[:, None, 2:3] * self._z_signs
        else:
            omegas = (omega[:, None, None, :] @ self._full_rotations)[..., 0, :]
        block = np.concatenate([offsets, velocities, omegas], axis=-1)
        return block.reshape(len(block), -1)

    def agent_targets(self, t: np.ndarray, start_points: np.ndarray) -> np.ndarray:
        """Every end-effector's place in the moving reference (K, N, m), world, m: ``c*(t) + R(theta*(t)) Q0
        (x*_i - x*_mean)``, the formation's shape ``x*`` placed as the end-effectors stood at the motion's start
        ``start_points`` (K, N, m; c0 their centroid) and carried along the motion. ``Q0``: the orthogonal
        matrix that best takes the centred shape onto the centred start points (orthogonal Procrustes; a
        reflection too, since a distance formation's mirror image has its edge lengths), the identity for a
        displacement formation, whose shape keeps the world's orientation. Whether the shape had formed by the
        start or not, the targets are the shape."""
        c0 = start_points.mean(axis=-2)
        centroid, _, theta, _ = self.world(t, c0)
        turns = rotation_about(self._axis, theta, self.dim)  # (K, m, m)
        placed = np.broadcast_to(self._centred_shape, start_points.shape)
        if self._shape_turns:  # Q0 = V U^T of svd(A^T B) maps the shape's rows a_i onto the start's b_i
            u, _, vt = np.linalg.svd(self._centred_shape.T @ (start_points - c0[:, None, :]))
            placed = placed @ (u @ vt)  # rows: (Q0 a_i)^T = a_i^T U V^T
        return centroid[:, None, :] + placed @ turns.transpose(0, 2, 1)

    def tracking_ratios(self, t: np.ndarray, start_points: np.ndarray, ee_world: np.ndarray,
                        tolerance: float) -> np.ndarray:
        """``|p_i - p*_i| / tolerance`` (K, N) (:meth:`agent_targets`; ``ee_world`` (K, N, 3)), 0 until the motion
        starts: the reward's tracking term (:mod:`ee_formation_env.reward`)."""
        distances = np.linalg.norm(ee_world[..., :self.dim] - self.agent_targets(t, start_points), axis=-1)
        return np.where((t > self.config.start)[:, None], distances / tolerance, 0.0)

    def centroid_errors(self, t: np.ndarray, c0: np.ndarray, ee_world: np.ndarray) -> np.ndarray:
        """|c - c*| (K,), m, of end-effector positions ``ee_world`` (K, N, 3)."""
        centroid = self.world(t, c0)[0]
        return np.linalg.norm(ee_world[..., :self.dim].mean(axis=-2) - centroid, axis=-1)

    def orientation_errors(self, t: np.ndarray, start_points: np.ndarray, ee_world: np.ndarray) -> np.ndarray:
        """The orientation error (K,), rad (module docstring) from the end-effector positions at the motion's
        start ``start_points`` (K, N, m) and the current ones ``ee_world`` (K, N, 3)."""
        theta = self.world(t, np.zeros((len(t), self.dim)))[2]
        turns = rotation_about(self._axis, theta, self.dim)  # (K, m, m)
        centred = start_points - start_points.mean(axis=-2, keepdims=True)
        references = centred @ turns.transpose(0, 2, 1)
        current = ee_world[..., :self.dim]
        return np.array([0.0 if t_k <= self.config.start else best_fit_angle(ref, cur)
                         for t_k, ref, cur in zip(t, references, current)])
