"""Observation features with resolution near the goal, for a learned torque policy.

The raw observation holds edge errors in formation units (m^2 for distance formations: up to tens) and
joint angles in rad. Normalized by their running statistics, the last centimetre (the success tolerance: 1 cm
on 3 m edges, ~0.3 % of the scale) is invisible to a policy network. :func:`log_error_features` appends
quantities computed from the agent's *own* observation only, so that a shared policy stays decentralized:

- per neighbour slot, the edge error in success tolerances ``r = e / tol`` through ``sign(r) log1p(|r|)``
  (0 for padding slots); ``tol = 2 d* delta`` (distance) or ``delta`` (displacement, per axis), as in the
  reward and :func:`ee_formation_env.baselines.learned.residual.error_gate`;
- the direction in which the end-effector should move, ``g = -sum_j r_ij u_ij`` (``u_ij`` the unit vector
  of ``z_ij``, distance formations) or ``g = -sum_j r_ij`` (displacement), in the agent's base frame, as
  ``g / |g| * log1p(|g|)``: the gradient of the formation potential in tolerance units, log-scaled;
- ``sin q`` and ``cos q`` of every joint (the Jacobian is a trigonometric function of q);
- every joint velocity as ``sign(dq) log1p(|dq| / velocity_scale)``, so that damping near rest is resolved.

``"invariant"`` is ``"log-error"`` computed on the observation *in the agent's first-link frame*
(:func:`first_link_frame_stack`): every vector (``z_ij``, and ``z*_ij`` and ``e_ij`` of displacement slots)
turned about the base z axis by ``-q_1`` and ``q_1`` itself replaced by 0. A base yaw changes an agent's raw
inputs (its z_ij turn, its q_1 shifts) but not this observation, and joint torques mean the same in either
pose, so a policy on it acts the same on any base yaw: the same physical problem gets the same actions. It
needs arms whose first joint turns about their base z axis (:func:`check_invariant_arms`).

One transform (:class:`FeatureRows`) runs in training (the training env's K x N rows) and evaluation (the
learned per-agent policy, one row); ``train.py`` saves the set's name in the run's config.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import gymnasium
import numpy as np

from ee_formation_env.observation import ObservationLayout
from ee_formation_env.reward import DEFAULT_POSITION_TOLERANCE

FEATURE_SETS = ("none", "log-error", "invariant")
VELOCITY_SCALE = 0.05  # rad/s: joint speeds below this are resolved linearly by the log feature


def feature_size(layout: ObservationLayout, features: str) -> int:
    """How many entries ``features`` appends to an observation of ``layout``."""
    _check(features)
    if features == "none":
        return 0
    return layout.n_slots * layout.error_width + layout.dim + 3 * layout.n_joints


def error_ratios(layout: ObservationLayout, observation: np.ndarray,
                 position_tolerance: float = DEFAULT_POSITION_TOLERANCE) -> tuple[np.ndarray, np.ndarray]:
    """Each neighbour slot's edge error in success tolerances, ``(slots, w)`` (0 for padding), and the mask of
    real slots, read from one observation (:meth:`ObservationLayout.error_ratios`)."""
    return layout.error_ratios(observation, position_tolerance)


def log_error_features(layout: ObservationLayout, observation: np.ndarray,
                       position_tolerance: float = DEFAULT_POSITION_TOLERANCE) -> np.ndarray:
    """The appended entries of the ``"log-error"`` set (module docstring) for one observation."""
    return log_error_feature_stack(layout, np.asarray(observation)[None], position_tolerance)[0]


def log_error_feature_stack(layout: ObservationLayout, observations: np.ndarray,
                            position_tolerance: float = DEFAULT_POSITION_TOLERANCE) -> np.ndarray:
    """:func:`log_error_features` of a stack (k, size) of observations of one layout: (k, extra)."""
    parts = layout.split(observations)
    ratios, _ = layout.error_ratios(observations, position_tolerance)  # (k, slots, w)
    if layout.error_width == 1:
        lengths = np.linalg.norm(parts.relative_positions, axis=2, keepdims=True)
        units = parts.relative_positions / np.maximum(lengths, 1e-9)
        gradients = -np.sum(ratios * units, axis=1)  # (k, dim)
    else:
        gradients = -np.sum(ratios, axis=1)
    norms = np.linalg.norm(gradients, axis=1, keepdims=True)
    moving = norms > 0
    directions = np.where(moving, gradients / np.where(moving, norms, 1.0) * np.log1p(norms), 0.0)
    flat = ratios.reshape(len(ratios), -1)
    return np.concatenate([
        np.sign(flat) * np.log1p(np.abs(flat)),
        directions,
        np.sin(parts.q), np.cos(parts.q),
        np.sign(parts.dq) * np.log1p(np.abs(parts.dq) / VELOCITY_SCALE),
    ], axis=1)


def first_link_frame_stack(layout: ObservationLayout, observations: np.ndarray) -> np.ndarray:
    """A stack (k, size) of observations in each agent's first-link frame (module docstring), float64: the
    slot vectors turned by ``-q_1`` about the base z axis, ``q_1`` set to 0; masks, distances, distance
    errors and the other joints' states unchanged."""
    out = np.array(observations, dtype=np.float64)
    parts = layout.split(out)  # views into ``out``
    angle = parts.q[:, 0].copy()
    cos, sin = np.cos(angle)[:, None], np.sin(angle)[:, None]
    vectors = [parts.relative_positions] + ([parts.desired, parts.edge_errors] if layout.error_width > 1 else [])
    for vector in vectors:
        x, y = vector[..., 0].copy(), vector[..., 1].copy()
        vector[..., 0] = cos * x + sin * y
        vector[..., 1] = -sin * x + cos * y
    parts.q[:, 0] = 0.0
    return out


def check_invariant_arms(task: Any) -> None:
    """``ValueError`` naming ``obs_features`` unless every arm's first joint turns about its base z axis
    (+z, through the base origin: what the ``"invariant"`` set's frame needs)."""
    from ee_formation_env.kinematics import rpy_to_matrix

    for i, model in enumerate(task.models):
        rotation, origin = np.eye(3), np.zeros(3)
        for joint in model.joints:  # the fixed joints before the first movable one, then that one
            origin = origin + rotation @ np.asarray(joint.origin_xyz, dtype=np.float64)
            rotation = rotation @ rpy_to_matrix(np.asarray(joint.origin_rpy, dtype=np.float64))
            if joint.movable:
                break
        axis = rotation @ np.asarray(joint.axis, dtype=np.float64)
        if not (np.allclose(axis, [0.0, 0.0, 1.0], atol=1e-9) and np.allclose(origin[:2], 0.0, atol=1e-9)):
            raise ValueError(f"obs_features: 'invariant' needs arms whose first joint turns about their base z axis; "
                             f"arms[{i}] joint {joint.name!r} turns about {np.round(axis, 6).tolist()} through "
                             f"{np.round(origin, 6).tolist()} m in its base frame")


def transform_stack(layout: ObservationLayout, features: str) -> Callable[[np.ndarray], np.ndarray]:
    """``observations -> observations with the features appended`` for a stack (k, size) of observations of one
    layout: (k, size + extra) float32; the identity for ``"none"``."""
    _check(features)
    if features == "none":
        return lambda observations: observations

    def apply(observations: np.ndarray) -> np.ndarray:
        if features == "invariant":
            observations = first_link_frame_stack(layout, observations)
        extra = log_error_feature_stack(layout, observations)
        return np.concatenate([np.asarray(observations, dtype=np.float32), extra.astype(np.float32)], axis=1)

    return apply


def feature_space(space: gymnasium.spaces.Box, layout: ObservationLayout, features: str) -> gymnasium.spaces.Box:
    """The observation space with the features' bounds appended (``"invariant"``: unbounded, as its turned
    vectors leave the raw observation's per-axis bounds)."""
    n = feature_size(layout, features)
    if n == 0:
        return space
    raw_low, raw_high = (space.low, space.high) if features != "invariant" else (
        np.full(space.shape, -np.inf, dtype=np.float32), np.full(space.shape, np.inf, dtype=np.float32))
    low = np.concatenate([raw_low, np.full(n, -np.inf, dtype=np.float32)]).astype(np.float32)
    high = np.concatenate([raw_high, np.full(n, np.inf, dtype=np.float32)]).astype(np.float32)
    return gymnasium.spaces.Box(low, high, dtype=np.float32)


class FeatureRows:
    """The features of a stack of R agent rows: row r's observation (of layout ``layouts[r]``) with the set
    ``features[r]`` appended, the rows of one layout and set in one call. The training env's K x N rows and an
    evaluated per-agent policy's one row both go through it.

    Called with fewer rows than R (``observations`` (R', size), R' < R), it treats them as the first R' rows:
    with copy-major rows, the first copies' agents (the copies that ended a step, say).
    """

    def __init__(self, layouts: Sequence[ObservationLayout | None], features: Sequence[str]):
        for name in features:
            _check(name)
        self.identity = all(name == "none" for name in features)
        self.size: int | None = None  # the featured size; None where every row has none (any layout)
        if self.identity:
            return
        groups: dict[tuple[ObservationLayout, str], list[int]] = {}
        for row, key in enumerate(zip(layouts, features)):
            groups.setdefault(key, []).append(row)
        self._groups = [(np.array(rows), transform_stack(layout, name)) for (layout, name), rows in groups.items()]
        sizes = {layout.size + feature_size(layout, name) for layout, name in groups}
        if len(sizes) > 1:
            raise ValueError(f"obs_features: rows of one stack must have one featured size, got {sorted(sizes)}")
        self.size = sizes.pop()

    def __call__(self, observations: np.ndarray) -> np.ndarray:
        """(R', size) raw observations -> (R', featured size) (float32; unchanged where every row has none)."""
        if self.identity:
            return observations
        if len(self._groups) == 1:
            return self._groups[0][1](observations)
        out = np.empty((len(observations), self.size), dtype=np.float32)
        for rows, apply in self._groups:
            rows = rows[rows < len(observations)]
            out[rows] = apply(observations[rows])
        return out


def _check(features: str) -> None:
    if features not in FEATURE_SETS:
        raise ValueError(f"obs_features: expected one of {FEATURE_SETS}, got {features!r}")
