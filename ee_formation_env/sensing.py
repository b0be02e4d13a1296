"""Imperfect sensing: what each agent measures of its neighbour displacements z_ij.

Scenario key ``sensing`` = ``{"noise": s, "delay": d, "bias": b, "yaw": a, "seed": k}``. Agent i observes, in
its own base frame, for every neighbour j:

``z_ij measured(t) = R_z(a_i) z_ij(t - d) + b_i + n_ij(t)``

- ``delay`` d (control steps): the displacement of d steps ago; after a reset the sensor holds the start
  displacement for d steps;
- ``yaw`` a_i (rad): a frame misalignment, a rotation about the agent's base z axis; a number gives every
  agent the same angle, a list one per agent;
- ``bias`` b_i (m): a constant offset in the agent's own frame; a number gives each agent a vector of that
  length in a direction drawn once from ``seed`` (in the formation's plane for ``dim`` 2), a list gives the
  N vectors;
- ``noise`` (m): n_ij, independent Gaussian noise of this standard deviation on every component at every
  step, drawn from the env's generator (so a reset seed fixes it; a batched copy draws from its own).

The observation's edge errors are computed from the measured z (distance: |z|^2 - d_k^2; displacement:
z - z*_ij in the agent's frame), as a sensor-fed controller would compute them. The reward, the infos
(``formation_error``, ``edge_errors``) and every metric use the true displacements. All knobs at zero (the
default) leave the observations exactly the true ones.

How the reference laws stand each knob: docs/sensing.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from ee_formation_env.inputs import check_known_keys, excerpt

SENSING_KEYS = ("noise", "delay", "bias", "yaw", "seed")
MAX_DELAY_STEPS = 1000


@dataclass(frozen=True)
class SensingConfig:
    """The sensing knobs (module docstring); units m, control steps, m, rad."""

    noise: float = 0.0
    delay: int = 0
    bias: float | tuple[tuple[float, ...], ...] = 0.0
    yaw: float | tuple[float, ...] = 0.0
    seed: int = 0

    @property
    def active(self) -> bool:
        """Whether any agent measures anything but the true displacement."""
        return bool(self.noise > 0 or self.delay > 0 or np.any(np.asarray(self.bias) != 0)
                    or np.any(np.asarray(self.yaw) != 0))

    def agent_yaws(self, n_agents: int) -> np.ndarray:
        """Each agent's misalignment (N,), rad."""
        return np.broadcast_to(np.asarray(self.yaw, dtype=np.float64), (n_agents,)).copy()

    def agent_biases(self, n_agents: int, dim: int) -> np.ndarray:
        """Each agent's bias vector (N, dim) in its own frame, m."""
        if not isinstance(self.bias, (int, float)):
            return np.asarray(self.bias, dtype=np.float64).reshape(n_agents, dim)
        directions = np.random.default_rng(self.seed).normal(size=(n_agents, dim))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        return float(self.bias) * directions


def parse_sensing(value: Any, n_agents: int, dim: int) -> SensingConfig:
    """``sensing`` from scenario data, for ``n_agents`` agents in ``dim`` dimensions; ``ValueError`` naming
    the field on bad input."""
    if isinstance(value, SensingConfig):
        value = {"noise": value.noise, "delay": value.delay, "bias": value.bias, "yaw": value.yaw,
                 "seed": value.seed}
    if value is None:
        return SensingConfig()
    if not isinstance(value, Mapping):
        raise ValueError(f"sensing: expected a dict with keys {list(SENSING_KEYS)}, got {excerpt(value)}")
    check_known_keys("sensing", value, list(SENSING_KEYS))
    parsed: dict[str, Any] = {}
    if "noise" in value:
        parsed["noise"] = _number("sensing.noise", value["noise"], "a standard deviation >= 0 (m)", lambda x: x >= 0)
    for key, limit in (("delay", MAX_DELAY_STEPS), ("seed", None)):
        if key in value:
            number = value[key]
            if isinstance(number, bool) or not isinstance(number, (int, np.integer)) or number < 0 or (
                    limit is not None and number > limit):
                bound = f"an integer in [0, {limit}] (control steps)" if limit else "an integer >= 0"
                raise ValueError(f"sensing.{key}: expected {bound}, got {excerpt(number)}")
            parsed[key] = int(number)
    if "yaw" in value:
        parsed["yaw"] = _per_agent("sensing.yaw", value["yaw"], (n_agents,), "rad")
    if "bias" in value:
        bias = value["bias"]
        if isinstance(bias, (int, float)) and not isinstance(bias, bool):
            parsed["bias"] = _number("sensing.bias", bias, "a length >= 0 (m) or a list of N vectors",
                                     lambda x: x >= 0)
        else:
            parsed["bias"] = _per_agent("sensing.bias", bias, (n_agents, dim), "m")
    return SensingConfig(**parsed)


def _number(name: str, value: Any, expected: str, valid: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and valid(value)):
        raise ValueError(f"{name}: expected {expected}, got {excerpt(value)}")
    return float(value)


def _per_agent(name: str, value: Any, shape: tuple[int, ...], unit: str) -> Any:
    """A number (every agent the same) or an array of ``shape`` (one entry per agent), finite, as plain data."""
    if isinstance(value, (int, float)) and not isinstance(value, bool) and len(shape) == 1:
        return _number(name, value, f"a number ({unit}) or a list of {shape[0]}", lambda x: True)
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        array = None
    if array is None or array.shape != shape or not np.all(np.isfinite(array)):
        wanted = f"{shape[0]} numbers" if len(shape) == 1 else f"{shape[0]} vectors of {shape[1]} numbers"
        raise ValueError(f"{name}: expected {wanted} ({unit}), one per agent, got {excerpt(value)}")
    return tuple(array.tolist()) if len(shape) == 1 else tuple(tuple(row) for row in array.tolist())


class Sensor:
    """The measured neighbour displacements and edge errors of K copies of one task (module docstring).

    ``reset(slot_z, rows)`` starts copies ``rows`` from their true in-frame displacements ``slot_z`` (k, S, m);
    ``sense(slot_z, rows, generators)`` pushes the copies' new true displacements and returns what they
    measure, (k, S, m) and the edge errors computed from it ((k, S) or (k, S, m)), drawing each copy's noise
    from its generator.
    """

    def __init__(self, config: SensingConfig, task: Any, observer: Any, num_envs: int = 1):
        self.config = config
        m, slot_agent = task.dim, observer.slot_agent
        yaws = config.agent_yaws(task.n_agents)[slot_agent]
        cos, sin = np.cos(yaws), np.sin(yaws)
        rotations = np.zeros((len(slot_agent), m, m))
        rotations[:, 0, 0], rotations[:, 0, 1], rotations[:, 1, 0], rotations[:, 1, 1] = cos, sin, -sin, cos
        if m == 3:
            rotations[:, 2, 2] = 1.0
        self._rotations = rotations  # row vector @ R = (R_z(a) z)^T
        self._bias = config.agent_biases(task.n_agents, m)[slot_agent]  # (S, m)
        self._kind, self._desired = observer.kind, observer.slot_desired  # (S,) d^2 or (S, m) own-frame z*
        self._buffer = np.zeros((num_envs, config.delay + 1, len(slot_agent), m))

    def reset(self, slot_z: np.ndarray, rows: Sequence[int] | np.ndarray) -> None:
        self._buffer[rows] = np.asarray(slot_z)[:, None]

    def sense(self, slot_z: np.ndarray, rows: Sequence[int] | np.ndarray,
              generators: Sequence[np.random.Generator]) -> tuple[np.ndarray, np.ndarray]:
        rows = np.asarray(rows, dtype=np.intp)
        if self.config.delay:
            self._buffer[rows, :-1] = self._buffer[rows, 1:]
        self._buffer[rows, -1] = slot_z
        measured = (self._buffer[rows, 0][..., None, :] @ self._rotations)[..., 0, :] + self._bias
        if self.config.noise > 0:
            shape = measured.shape[1:]
            measured = measured + np.stack([generators[k].normal(0.0, self.config.noise, shape) for k in rows])
        if self._kind == "distance":
            errors = np.einsum("ksd,ksd->ks", measured, measured) - self._desired
        else:
            errors = measured - self._desired
        return measured, errors
