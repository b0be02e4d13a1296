"""The per-agent reward: how close the agent's incident edges are to their lengths, in units of the success
tolerance, on a log scale; plus a bonus on steps where all of them are within the tolerance.

``r_i = formation * closeness(x_i) + in_tolerance * [every incident edge k has |e_k| <= tol_k]
        + tracking * closeness(y_i)``,  ``closeness(x) = clip(log10(ceiling / (x + floor)) / log10(ceiling / floor), 0, 1)``

with ``x_i = mean_k |e_k| / tol_k`` over agent i's incident edges, ``tol_k = 2 d*_k delta`` (distance
formations, m^2: ``|z|^2 - d^2 ~ 2 d (|z| - d)``) or ``delta`` (displacement formations, m), ``delta =
position_tolerance``. With the defaults, ``r_i`` is 1 at zero error, ~0.65 at one tolerance, 0.33 at ten,
0 from a hundred on, plus 1 inside the tolerance: in [0, 2]. Every reward is >= 0, and there is no velocity
or torque penalty.

The tracking term (off by default: ``tracking = 0``; a scenario with a manoeuvre only): ``y_i = |p_i - p*_i| /
tracking_tolerance``, agent i's end-effector distance to its place in the moving reference, ``p*_i(t) = c*(t)
+ R(theta*(t)) Q0 (x*_i - x*_mean)``: the formation's shape placed as the end-effectors stood when the motion
started, carried along the motion (m; :meth:`ee_formation_env.manoeuvre.ReferenceMotion.agent_targets`), 0
before the motion starts. Without it a reward of the shape alone holds in any place and orientation, so it
asks nothing of the motion.

Why this shape, with the measurements: see docs/spaces.md ("Why this reward").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, Mapping

import numpy as np

from ee_formation_env.inputs import check_known_keys, excerpt

DEFAULT_POSITION_TOLERANCE = 0.01  # m: the edge-length accuracy that counts as "in formation"
DEFAULT_TRACKING_TOLERANCE = 0.02  # m: the manoeuvre study's centroid target (docs/manoeuvres.md)


@dataclass(frozen=True)
class RewardConfig:
    """Weights and scales of the per-agent reward (see the module docstring for the formula).

    ``formation``: weight of the log-scaled error term (>= 0); ``in_tolerance``: bonus on steps where all
    the agent's incident edges are within tolerance (>= 0); ``position_tolerance``: edge accuracy, m;
    ``error_floor`` < ``error_ceiling``: the errors, in tolerances, at which the log term saturates at 1
    and reaches 0; ``team``: every agent receives the mean of all agents' rewards; ``tracking``: weight of the
    manoeuvre tracking term (>= 0; > 0 needs a manoeuvre); ``tracking_tolerance``: its unit of distance, m.
    """

    formation: float = 1.0
    in_tolerance: float = 1.0
    position_tolerance: float = DEFAULT_POSITION_TOLERANCE
    error_floor: float = 0.1
    error_ceiling: float = 100.0
    team: bool = False
    tracking: float = 0.0
    tracking_tolerance: float = DEFAULT_TRACKING_TOLERANCE

    def __post_init__(self) -> None:
        if not self.error_floor < self.error_ceiling:
            raise ValueError(f"reward.error_floor: expected a value below error_ceiling ({self.error_ceiling}), "
                             f"got {self.error_floor}")


def parse_reward(value: Any) -> RewardConfig:
    """``reward`` from scenario data (a dict of :class:`RewardConfig` fields, missing ones at their
    defaults); ``ValueError`` naming the field on bad input."""
    if isinstance(value, RewardConfig):
        return value
    if value is None:
        return RewardConfig()
    if not isinstance(value, Mapping):
        raise ValueError(f"reward: expected a dict of RewardConfig fields, got {excerpt(value)}")
    allowed = sorted(f.name for f in fields(RewardConfig))
    check_known_keys("reward", value, allowed)
    parsed: dict[str, Any] = {}
    for key, number in value.items():
        if key == "team":
            if not isinstance(number, bool):
                raise ValueError(f"reward.team: expected true or false, got {excerpt(number)}")
            parsed[key] = number
            continue
        if isinstance(number, bool) or not isinstance(number, (int, float, np.integer, np.floating)) \
                or not math.isfinite(number):
            raise ValueError(f"reward.{key}: expected a finite number, got {excerpt(number)}")
        if key in ("formation", "in_tolerance", "tracking") and number < 0:
            raise ValueError(f"reward.{key}: expected a weight >= 0, got {excerpt(number)}")
        if key in ("position_tolerance", "error_floor", "error_ceiling", "tracking_tolerance") and number <= 0:
            raise ValueError(f"reward.{key}: expected a positive number, got {excerpt(number)}")
        parsed[key] = float(number)
    return RewardConfig(**parsed)


def edge_tolerances(kind: str, desired_lengths: np.ndarray, position_tolerance: float) -> np.ndarray:
    """Each edge's success tolerance in formation units: ``2 d*_k delta`` (m^2, ``kind="distance"``) or
    ``delta`` (m, ``"displacement"``), for an edge accuracy ``delta = position_tolerance`` (m).

    ``desired_lengths``: ``d*_k = |z*_k|`` per edge (m).
    """
    lengths = np.asarray(desired_lengths, dtype=np.float64)
    if kind == "distance":
        return 2.0 * lengths * position_tolerance
    if kind == "displacement":
        return np.full(lengths.shape, float(position_tolerance))
    raise ValueError(f"kind: expected 'distance' or 'displacement', got {excerpt(kind)}")


def edge_length_errors(kind: str, desired_lengths: np.ndarray, edge_errors: np.ndarray) -> np.ndarray:
    """Each edge's length error in metres from its edge error ``e_k``: ``| |z_k| - d*_k |`` for
    ``kind="distance"`` (``e_k = |z_k|^2 - d*_k^2`` m^2, so ``|z_k| = sqrt(e_k + d*_k^2)``), ``|z_k - z*_k|`` for
    ``"displacement"`` (``e_k`` the error vector, m, on the last axis). ``desired_lengths``: ``d*_k`` (m),
    broadcast against ``edge_errors`` (..., E) or (..., E, dim). (..., E) m."""
    errors = np.asarray(edge_errors, dtype=np.float64)
    if kind == "distance":
        lengths = np.asarray(desired_lengths, dtype=np.float64)
        return np.abs(np.sqrt(np.maximum(errors + lengths**2, 0.0)) - lengths)
    if kind == "displacement":
        return np.linalg.norm(errors, axis=-1)
    raise ValueError(f"kind: expected 'distance' or 'displacement', got {excerpt(kind)}")


def agent_error_ratios(edge_abs_errors: np.ndarray, tolerances: np.ndarray, slot_edges: np.ndarray,
                       slot_starts: np.ndarray, degrees: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per agent: the mean over its incident edges of ``|e_k| / tol_k``, and whether all are ``<= tol_k``.

    ``edge_abs_errors``, ``tolerances``: (E,) per edge; ``slot_edges`` (S,): the edge of each agent slot,
    agent by agent; ``slot_starts`` (N,): where each agent's slots start; ``degrees`` (N,): slot counts
    (every agent has at least one edge). Leading axes of ``edge_abs_errors`` (K copies: (K, E)) carry over
    to the results ((K, N)).
    """
    ratios = edge_abs_errors / tolerances
    slot_ratios = ratios[..., slot_edges]
    mean_ratios = np.add.reduceat(slot_ratios, slot_starts, axis=-1) / degrees
    all_within = np.logical_and.reduceat(slot_ratios <= 1.0, slot_starts, axis=-1)
    return mean_ratios, all_within


def closeness(ratios: np.ndarray, config: RewardConfig) -> np.ndarray:
    """The log term (module docstring) of errors ``ratios`` in tolerances: 1 at 0, 0 from ``error_ceiling`` on."""
    span = np.log10(config.error_ceiling / config.error_floor)
    near = np.log10(config.error_ceiling / (ratios + config.error_floor)) / span
    return np.minimum(np.maximum(near, 0.0, out=near), 1.0, out=near)  # np.clip, without its overhead


def rewards_from_ratios(mean_ratios: np.ndarray, all_within: np.ndarray, config: RewardConfig,
                        tracking_ratios: np.ndarray | None = None) -> np.ndarray:
    """Every agent's reward (N,) from :func:`agent_error_ratios`' outputs (or (K, N) from stacked ones; the
    team mean is then taken per copy); ``tracking_ratios`` (same shape): the tracking term's ``y_i``, or None
    without it."""
    rewards = config.formation * closeness(mean_ratios, config) + config.in_tolerance * all_within
    if tracking_ratios is not None:
        rewards += config.tracking * closeness(tracking_ratios, config)
    if config.team:  # every agent gets its copy's mean (np.mean's arithmetic, without its overhead)
        rewards[...] = np.add.reduce(rewards, axis=-1, keepdims=True) / rewards.shape[-1]
    return rewards


def task_edge_tolerances(task: Any) -> np.ndarray:
    """The per-edge tolerances (:func:`edge_tolerances`) of a task's formation, at its scenario's
    ``reward.position_tolerance``."""
    formation = task.formation
    return edge_tolerances(formation.kind, np.linalg.norm(formation.desired_vectors, axis=1),
                           task.scenario.reward.position_tolerance)
