"""Scenarios: the schema and parser of the declarative description of a formation task.

A scenario is plain data: a dict, a YAML/JSON file, or the name of a built-in scenario. It is parsed
into a frozen :class:`Scenario` by :func:`load_scenario`, which checks every field's type and range;
the geometric checks that need the robots' kinematic models (links, reachability, singularities,
rigidity) live in :mod:`ee_formation_env.validation`. Both run before any simulation starts.

This module holds the format only (the format is documented in ``docs/scenarios.md``). The built-in
scenarios are YAML files in that format (:mod:`ee_formation_env.builtin`), the built-in robots are in
:mod:`ee_formation_env.robots`; ``ROBOTS``, ``BUILTIN_SCENARIOS``, ``builtin_scenario`` and
``SPATIAL_INITIAL_Q`` are re-exported here for compatibility.

Top-level keys: see the table at the end of this docstring (generated from :class:`Scenario`'s fields,
the one place where their defaults, units and meanings are written). Every one can also be passed to
``parallel_env`` as an override.

Arm keys: exactly one of ``robot`` (a built-in robot, see :data:`ee_formation_env.robots.ROBOTS`) or
``urdf`` (a path: absolute, or relative: looked up in the scenario file's folder first (the current
directory for a dict), then in ``pybullet_data``); ``ee_link``
(required with ``urdf``); ``base_position`` [x, y, z] m (default 0); ``base_rpy`` [roll, pitch, yaw] rad
(default 0); ``initial_q`` rad (default: the robot's start pose ``ROBOTS[name].start_q``, a bent elbow;
all zeros for an arm given by ``urdf``).
"""

from __future__ import annotations

import copy
import math
import os
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path
from typing import Any, Mapping

import numpy as np

# Re-exported for compatibility (plain re-exports, defined once): the built-in scenarios live in
# ee_formation_env.builtin, the robots in ee_formation_env.robots.
from ee_formation_env.builtin import BUILTIN_SCENARIOS, builtin_scenario  # noqa: F401
from ee_formation_env.engines.base import ENGINES
from ee_formation_env.formation import FORMATION_KINDS
from ee_formation_env.inputs import (MAX_ARMS, MAX_EPISODE_SECONDS, MAX_FRAME_SKIP, MAX_NEIGHBOUR_SLOTS, MAX_PHYSICS_HZ,
                                     check_known_keys, check_nesting, excerpt, is_real_number)
from ee_formation_env.scenario_file import read_scenario_file
from ee_formation_env.manoeuvre import ManoeuvreConfig, parse_manoeuvre
from ee_formation_env.mismatch import MismatchConfig, parse_mismatch
from ee_formation_env.reward import RewardConfig, parse_reward
from ee_formation_env.distribution import DistributionConfig, parse_distribution
from ee_formation_env.sensing import SensingConfig, parse_sensing
from ee_formation_env.robots import ROBOTS, SPATIAL_INITIAL_Q, RobotSpec  # noqa: F401

@dataclass(frozen=True)
class ArmConfig:
    """One arm (one agent). ``urdf`` is resolved to an existing file."""

    urdf: str
    ee_link: str
    base_position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    base_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    initial_q: tuple[float, ...] | None = None  # None: the robot's start_q (all zeros for a URDF)
    robot: str | None = None  # built-in robot name, if the arm was given as one


@dataclass(frozen=True)
class ControllerGains:
    """Tuned gains of the reference controllers, carried by the scenario they were tuned for.

    ``kp`` formation gain, ``kd`` joint damping (N m s/rad), ``ki`` internal-model gain (1/s), ``alpha``
    adaptation rate. Used only while the physics they were tuned for is unchanged: :func:`load_scenario`
    drops them when an override changes a field outside :data:`GAIN_NEUTRAL_FIELDS`.
    """

    kp: float
    kd: float
    ki: float
    alpha: float


def _key(default: Any, meaning: str, unit: str = "", default_factory: Any = None) -> Any:
    """A scenario field: its default, unit and meaning in one place (the docs table is made from them)."""
    metadata = {"unit": unit, "meaning": meaning}
    if default_factory is not None:
        return field(default_factory=default_factory, metadata=metadata)
    return field(default=default, metadata=metadata)


@dataclass(frozen=True)
class Scenario:
    """A validated formation task. Build with :func:`load_scenario`; see the module docstring."""

    name: str = field(metadata={"meaning": "scenario name (a built-in name, the file stem, or 'custom')"})
    arms: tuple[ArmConfig, ...] = field(metadata={"meaning": "list of arm dicts (below); one agent per arm, "
                                                             "``arm_0 .. arm_{N-1}``"})
    edges: tuple[tuple[int, int], ...] = field(metadata={"meaning": "list of ``[tail, head]`` 0-based agent "
                                                                    "indices (or give ``incidence``: the paper's "
                                                                    "incidence matrix B, N x |E|)"})
    shape: tuple[tuple[float, ...], ...] = field(metadata={"unit": "m", "meaning": (
        "reference configuration x* (N x dim); any translation of it (and for distance formations any "
        "rotation/reflection) is a goal")})
    formation: str = _key("distance", '``"distance"`` (e_k = |z_k|^2 - d_k^2, m^2) or ``"displacement"`` '
                                      "(e_k = z_k - z*_k, m)")
    dim: int = _key(3, "2 (formation in the arms' base x-y plane; planar arms only) or 3")
    engine: str = _key("pybullet", '``"pybullet"`` or ``"mujoco"`` (the ``mujoco`` extra): the physics engine that '
                                   "simulates the arms (:mod:`ee_formation_env.engines`)")
    physics_hz: float = _key(1000.0, "physics rate (the engine's fixed step); at least 60", "Hz")
    frame_skip: int = _key(10, "physics steps per env step; control rate = physics_hz / frame_skip", "steps")
    episode_seconds: float = _key(30.0, "simulated time before truncation", "s")
    torque_limits: Any = _key(None, "``null`` = each URDF joint's effort; a number for every joint; a list "
                                    "per joint (same for every arm); or a list of such lists, one per arm", "N m")
    gravity: tuple[float, float, float] = _key((0.0, 0.0, -9.81), "world gravity vector", "m/s^2")
    initial_q_noise: float = _key(0.05, "half-width of the uniform noise added to each ``initial_q`` at reset, "
                                        "at most 2 pi (a full turn); 0 turns randomization off", "rad")
    arm_collisions: bool = _key(True, "simulate contacts between arms (contacts are always reported)")
    terminate_on_contact: bool = _key(False, "end the episode when two arms touch")
    gravity_compensation: bool = _key(False, "the env adds each arm's own gravity torque g(q) to the torque of "
                                             "its action (the joint-torque convention of robosuite; see "
                                             ":mod:`ee_formation_env.gravity`); the reference laws send raw "
                                             "torques and refuse it")
    joint_damping: float | str = _key(0.0, 'viscous joint damping (URDF damping is replaced); ``"urdf"`` keeps '
                                           "the URDF values", "N m s/rad")
    max_joint_velocity: float = _key(50.0, "|dq| above this is a physics fault that terminates the episode "
                                           "(PyBullet's own 100 rad/s clamp is lifted so it cannot hide it)", "rad/s")
    neighbour_slots: int | None = _key(None, "neighbour slots in every agent's observation: null = the graph's "
                                             "largest degree D; a number >= D (at most "
                                             f"{MAX_NEIGHBOUR_SLOTS}, the most neighbours an agent of {MAX_ARMS} arms "
                                             "has) pads every agent with empty slots "
                                             "(mask 0), so that teams of other sizes or graphs share one "
                                             "observation space (see :mod:`ee_formation_env.team_env`)")
    singularity_threshold: float = _key(1e-3, "smallest Jacobian singular value below which an initial "
                                              "configuration is rejected as singular", "m")
    reward: RewardConfig = _key(None, "reward weights and scales, see :class:`RewardConfig`",
                                default_factory=RewardConfig)
    model_mismatch: MismatchConfig = _key(None, '``{"length": L, "mass": M, "seed": s}``: simulate robots whose '
                                                "link lengths and masses differ from the nominal URDFs by up to "
                                                "+-L and +-M; default none (see :mod:`ee_formation_env.mismatch`)",
                                          "relative", default_factory=MismatchConfig)
    sensing: SensingConfig = _key(None, '``{"noise": s, "delay": d, "bias": b, "yaw": a, "seed": k}``: what the '
                                        "agents measure of z_ij: Gaussian noise (m), a delay (control steps), a bias "
                                        "(m) and a frame misalignment (rad) per agent; default exact (see "
                                        ":mod:`ee_formation_env.sensing`)", default_factory=SensingConfig)
    distribution: DistributionConfig = _key(None, "ranges sampled at every reset instead of fixed values: base "
                                                  "layout, shape, graph generator, initial configurations (see "
                                                  ":mod:`ee_formation_env.distribution`); default none (fixed)",
                                            default_factory=DistributionConfig)
    manoeuvre: ManoeuvreConfig = _key(None, '``{"start": t0, "duration": T, "translation": A, "rotation": r, '
                                            '"axis": u}``: the centroid follows c0 + s(t) A and a distance '
                                            "formation turns by s(t) r about u (dim 3) through it, s(t) out and "
                                            "back over [t0, t0 + T] (s, s, m, rad); peak speed pi abs(A) / T; "
                                            "default none (see :mod:`ee_formation_env.manoeuvre`)",
                                      default_factory=ManoeuvreConfig)
    controller_gains: ControllerGains | None = _key(None, "``{kp, kd, ki, alpha}``: tuned gains of the reference "
                                                          "controllers (built-in scenarios carry theirs); null = "
                                                          "derived from the robots, torque limits and rates")

    @property
    def n_agents(self) -> int:
        return len(self.arms)

    @property
    def control_hz(self) -> float:
        """Env steps per simulated second."""
        return self.physics_hz / self.frame_skip

    @property
    def control_dt(self) -> float:
        """Simulated seconds per env step."""
        return self.frame_skip / self.physics_hz

    @property
    def max_steps(self) -> int:
        """Env steps before truncation."""
        return int(round(self.episode_seconds * self.control_hz))

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (JSON/YAML serializable) that :func:`load_scenario` accepts back."""
        data: dict[str, Any] = {}
        for spec in fields(self):
            value = getattr(self, spec.name)
            if spec.name == "arms":
                value = [_arm_to_dict(arm) for arm in value]
            elif spec.name == "distribution":
                value = value.to_dict()
            elif spec.name in ("reward", "model_mismatch", "sensing") or (spec.name == "controller_gains" and value is not None):
                value = {f.name: getattr(value, f.name) for f in fields(value)}
            elif spec.name == "manoeuvre":
                value = value.to_dict()  # None when inactive: a scenario without one reads back the same
            elif spec.name == "engine" and value == _default("engine"):
                continue  # left out on PyBullet: its scenarios read (and digest) as they did before engines
            data[spec.name] = _plain(value)
        return data


def _arm_to_dict(arm: ArmConfig) -> dict[str, Any]:
    data: dict[str, Any] = {"robot": arm.robot} if arm.robot else {"urdf": arm.urdf, "ee_link": arm.ee_link}
    data.update(base_position=list(arm.base_position), base_rpy=list(arm.base_rpy))
    if arm.initial_q is not None:
        data["initial_q"] = list(arm.initial_q)
    return data


def _plain(value: Any) -> Any:
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value


def _default(name: str) -> Any:
    """The default of scenario field ``name`` (from :class:`Scenario`, the one place it is written)."""
    spec = SCENARIO_FIELDS[name]
    return spec.default_factory() if spec.default_factory is not MISSING else spec.default


def scenario_keys_table() -> str:
    """The reStructuredText table of the scenario's top-level keys (default, unit, meaning)."""
    rows = []
    for spec in fields(Scenario):
        if spec.name == "name":
            continue
        default = "required" if spec.default is MISSING and spec.default_factory is MISSING else (
            "see class" if spec.default_factory is not MISSING else repr(_plain(spec.default)))
        unit = spec.metadata.get("unit", "")
        rows.append((f"``{spec.name}``", default + (f" {unit}" if unit and default not in ("required", "see class") else ""),
                     spec.metadata["meaning"]))
    widths = [max(len(row[c]) for row in rows + [("key", "default", "meaning")]) for c in range(3)]
    rule = "  ".join("=" * w for w in widths)
    lines = [rule, "  ".join(h.ljust(w) for h, w in zip(("key", "default", "meaning"), widths)).rstrip(), rule]
    lines += ["  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip() for row in rows]
    return "\n".join(lines + [rule])


SCENARIO_FIELDS = {spec.name: spec for spec in fields(Scenario)}
# Fields whose change leaves tuned controller gains valid: everything but the physics (robots, bases, shape,
# graph, rates, torque limits, gravity, damping, contacts).
# The engine is neutral: both simulate the same physics (tests/engines/test_parity.py bounds the difference).
GAIN_NEUTRAL_FIELDS = frozenset({"name", "engine", "episode_seconds", "initial_q_noise", "terminate_on_contact",
                                 "max_joint_velocity", "neighbour_slots", "singularity_threshold", "reward", "model_mismatch",
                                 "sensing", "manoeuvre", "controller_gains"})
__doc__ += "\n" + scenario_keys_table() + "\n"


# --------------------------------------------------------------------------------------------------
# Parsing
# --------------------------------------------------------------------------------------------------

_TOP_LEVEL_KEYS = {f.name for f in fields(Scenario)} | {"incidence"}
_ARM_KEYS = {"robot", "urdf", "ee_link", "base_position", "base_rpy", "initial_q"}


def load_scenario(scenario: str | os.PathLike | Mapping[str, Any] | Scenario = "planar_square",
                  **overrides: Any) -> Scenario:
    """Parse a scenario (built-in name, YAML/JSON path, dict or parsed :class:`Scenario`) plus overrides.

    ``reward``, ``model_mismatch``, ``sensing``, ``distribution`` and ``manoeuvre`` overrides are merged into
    the scenario's. It checks the format: every field's type, range and the limits of
    :mod:`ee_formation_env.inputs` (file size, nesting, arm count), and that every URDF exists. It does not
    read the robots' models, so it does not check links, meshes, joint limits, reachability, rigidity,
    singular starts or start contacts: :func:`ee_formation_env.validate_scenario` runs those too (every check
    ``parallel_env`` runs, without stepping physics). Raises ``ValueError`` naming the
    offending field, or ``TypeError`` for an argument of the wrong type.
    """
    if isinstance(scenario, Scenario):
        if not overrides:
            return scenario
        scenario = scenario.to_dict()
    check_nesting("overrides", overrides)
    base_dir = Path.cwd()
    if isinstance(scenario, Mapping):
        check_nesting("scenario", scenario)
        data = copy.deepcopy(dict(scenario))
        name = _name(data.pop("name", "custom"))
    elif isinstance(scenario, (str, os.PathLike)):
        text = os.fspath(scenario)
        if text in BUILTIN_SCENARIOS:
            data, name = builtin_scenario(text), text
        elif text.endswith((".yaml", ".yml", ".json")):
            path = Path(text)
            if path.is_dir():
                raise ValueError(f"scenario: {excerpt(text)} is a directory, not a scenario file")
            if not path.is_file():
                raise ValueError(f"scenario: file not found: {excerpt(text)}")
            data = read_scenario_file(path)
            if not isinstance(data, dict):
                raise ValueError(f"scenario: {excerpt(text)} must contain a mapping, got {type(data).__name__}")
            check_nesting(f"scenario: {excerpt(text)}", data)
            name = _name(data.pop("name", path.stem))
            base_dir = path.resolve().parent
        else:
            import difflib

            close = difflib.get_close_matches(text, list(BUILTIN_SCENARIOS), n=1)
            raise ValueError(
                f"scenario: {excerpt(text)} is neither a built-in scenario {sorted(BUILTIN_SCENARIOS)} "
                "nor a .yaml/.yml/.json file" + (" (it is a directory)" if Path(text).is_dir() else "")
                + (f"; did you mean {close[0]!r}?" if close else "")
            )
    else:
        raise TypeError(f"scenario: expected a name, a path or a dict, got {type(scenario).__name__}")
    if "name" in overrides:
        name = _name(overrides["name"])
        overrides = {key: value for key, value in overrides.items() if key != "name"}

    physics_changed = any(
        key not in GAIN_NEUTRAL_FIELDS and _plain(value) != _plain(data.get(key, SCENARIO_FIELDS[key].default
                                                                        if key in SCENARIO_FIELDS else None))
        for key, value in overrides.items())
    for key, value in overrides.items():
        if key in ("reward", "model_mismatch", "sensing", "distribution", "manoeuvre") and isinstance(value, Mapping) and isinstance(data.get(key), Mapping):
            data[key] = {**data[key], **value}
        else:
            data[key] = value
    if physics_changed and "controller_gains" not in overrides:
        data.pop("controller_gains", None)  # tuned for other physics: the derived rule applies
    return _parse(name, data, base_dir)


def _name(value: Any) -> str:
    """The scenario's ``name``: a non-empty string."""
    if not isinstance(value, str):
        raise TypeError(f"name: expected a string (the scenario's name), got {type(value).__name__} {excerpt(value)}")
    if not value:
        raise ValueError("name: expected a non-empty string")
    return value


def _parse(name: str, data: dict[str, Any], base_dir: Path) -> Scenario:
    check_known_keys("scenario", data, sorted(_TOP_LEVEL_KEYS))
    for required in ("arms", "shape"):
        if required not in data:
            raise ValueError(f"scenario: missing required key {excerpt(required)}")

    arms_data = data["arms"]
    if not isinstance(arms_data, (list, tuple)) or len(arms_data) < 2:
        raise ValueError(f"arms: expected a list of at least 2 arm dicts, got {excerpt(arms_data)}")
    if len(arms_data) > MAX_ARMS:
        raise ValueError(f"arms: expected at most {MAX_ARMS} arms, got {len(arms_data)}")
    arms = tuple(_parse_arm(i, arm, base_dir) for i, arm in enumerate(arms_data))
    n_agents = len(arms)

    dim = data.get("dim", _default("dim"))
    if dim not in (2, 3) or isinstance(dim, bool):
        raise ValueError(f"dim: expected 2 or 3, got {excerpt(dim)}")
    formation = data.get("formation", _default("formation"))
    if formation not in FORMATION_KINDS:
        raise ValueError(f"formation: expected one of {list(FORMATION_KINDS)}, got {excerpt(formation)}")

    edges = _parse_edges(data, n_agents)
    shape = _float_array("shape", data["shape"], ndim=2)
    if shape.shape != (n_agents, dim):
        raise ValueError(
            f"shape: expected {n_agents} rows of {dim} coordinates (one per arm, dim = {dim}), "
            f"got an array of shape {shape.shape}"
        )

    kwargs: dict[str, Any] = {}
    engine = data.get("engine", _default("engine"))
    if engine not in ENGINES:
        raise ValueError(f"engine: expected one of {list(ENGINES)}, got {excerpt(engine)}")
    kwargs["engine"] = engine
    kwargs["physics_hz"] = _positive("physics_hz", data.get("physics_hz", _default("physics_hz")))
    frame_skip = data.get("frame_skip", _default("frame_skip"))
    if not isinstance(frame_skip, (int, np.integer)) or isinstance(frame_skip, (bool, np.bool_)) or frame_skip < 1:
        raise ValueError(f"frame_skip: expected an integer >= 1, got {excerpt(frame_skip)}")
    if frame_skip > MAX_FRAME_SKIP:
        raise ValueError(f"frame_skip: expected at most {MAX_FRAME_SKIP} physics steps per env step, got "
                         f"{excerpt(frame_skip)}")
    kwargs["frame_skip"] = int(frame_skip)
    if kwargs["physics_hz"] < 60.0:
        raise ValueError(f"physics_hz: expected at least 60 Hz for a stable torque-controlled arm, got {kwargs['physics_hz']}")
    if kwargs["physics_hz"] > MAX_PHYSICS_HZ:
        raise ValueError(f"physics_hz: expected at most {MAX_PHYSICS_HZ:g} Hz, got {kwargs['physics_hz']:g}")
    kwargs["episode_seconds"] = _positive("episode_seconds", data.get("episode_seconds", _default("episode_seconds")))
    if kwargs["episode_seconds"] > MAX_EPISODE_SECONDS:
        raise ValueError(f"episode_seconds: expected at most {MAX_EPISODE_SECONDS:g} s, got {kwargs['episode_seconds']:g}")
    if kwargs["episode_seconds"] * kwargs["physics_hz"] / kwargs["frame_skip"] < 1:
        raise ValueError(
            f"episode_seconds: {kwargs['episode_seconds']} s is shorter than one control step "
            f"({kwargs['frame_skip'] / kwargs['physics_hz']} s)"
        )
    kwargs["torque_limits"] = _parse_torque_limits(data.get("torque_limits"), n_agents)
    gravity = _float_array("gravity", data.get("gravity", _default("gravity")), ndim=1)
    if gravity.shape != (3,):
        raise ValueError(f"gravity: expected 3 numbers (m/s^2), got {excerpt(data.get('gravity'))}")
    kwargs["gravity"] = tuple(gravity.tolist())
    noise = data.get("initial_q_noise", _default("initial_q_noise"))
    kwargs["initial_q_noise"] = _non_negative("initial_q_noise", noise)
    if kwargs["initial_q_noise"] > 2 * math.pi:
        raise ValueError(f"initial_q_noise: expected at most 2 pi rad (a full turn of a joint; the noise is clipped to "
                         f"the joint limits), got {kwargs['initial_q_noise']:g} rad")
    for flag in ("arm_collisions", "terminate_on_contact", "gravity_compensation"):
        value = data.get(flag, _default(flag))
        if not isinstance(value, bool):
            raise ValueError(f"{flag}: expected true or false, got {excerpt(value)}")
        kwargs[flag] = value
    damping = data.get("joint_damping", _default("joint_damping"))
    kwargs["joint_damping"] = damping if damping == "urdf" else _non_negative("joint_damping", damping)
    kwargs["max_joint_velocity"] = _positive("max_joint_velocity", data.get("max_joint_velocity", _default("max_joint_velocity")))
    slots = data.get("neighbour_slots", _default("neighbour_slots"))
    if slots is not None and (not isinstance(slots, (int, np.integer)) or isinstance(slots, (bool, np.bool_))
                              or not 1 <= slots <= MAX_NEIGHBOUR_SLOTS):
        raise ValueError(f"neighbour_slots: expected null or an integer from 1 to {MAX_NEIGHBOUR_SLOTS} (neighbour "
                         f"slots per agent; an agent of {MAX_ARMS} arms has at most {MAX_NEIGHBOUR_SLOTS} "
                         f"neighbours), got {excerpt(slots)}")
    kwargs["neighbour_slots"] = None if slots is None else int(slots)
    kwargs["singularity_threshold"] = _non_negative("singularity_threshold", data.get("singularity_threshold", _default("singularity_threshold")))
    kwargs["reward"] = parse_reward(data.get("reward", {}))
    kwargs["model_mismatch"] = parse_mismatch(data.get("model_mismatch"))
    kwargs["sensing"] = parse_sensing(data.get("sensing"), len(arms), int(dim))
    kwargs["manoeuvre"] = parse_manoeuvre(data.get("manoeuvre"), int(dim), formation,
                                           kwargs["frame_skip"] / kwargs["physics_hz"])
    kwargs["distribution"] = parse_distribution(data.get("distribution"), int(dim))
    if kwargs["distribution"].active and kwargs["sensing"].active:
        raise ValueError("distribution: a scenario distribution cannot be combined with sensing imperfections "
                         "yet (the sensor's per-agent frames are built for one fixed layout)")
    if kwargs["reward"].tracking > 0 and not kwargs["manoeuvre"].active:
        raise ValueError(f"reward.tracking: the tracking term needs a manoeuvre to track (this scenario has none); "
                         f"got {kwargs['reward'].tracking}")
    if kwargs["distribution"].active and kwargs["manoeuvre"].active:
        raise ValueError("distribution: a scenario distribution cannot be combined with a manoeuvre yet (the "
                         "reference is built for one fixed layout)")
    kwargs["controller_gains"] = _parse_controller_gains(data.get("controller_gains"))

    return Scenario(
        name=name, arms=arms, edges=tuple((int(t), int(h)) for t, h in edges),
        shape=tuple(tuple(row) for row in shape.tolist()), formation=formation, dim=int(dim), **kwargs,
    )


def _parse_arm(index: int, arm: Any, base_dir: Path) -> ArmConfig:
    where = f"arms[{index}]"
    if not isinstance(arm, Mapping):
        raise ValueError(f"{where}: expected a dict, got {excerpt(arm)}")
    check_known_keys(where, arm, sorted(_ARM_KEYS))
    if ("robot" in arm) == ("urdf" in arm):
        raise ValueError(f"{where}: give exactly one of 'robot' (one of {sorted(ROBOTS)}) or 'urdf'")
    robot = arm.get("robot")
    if "robot" in arm:
        if not isinstance(robot, str) or robot not in ROBOTS:
            raise ValueError(f"{where}.robot: unknown robot {excerpt(robot)}; available: {sorted(ROBOTS)}")
        urdf = str(ROBOTS[robot].urdf)
        ee_link = arm.get("ee_link", ROBOTS[robot].ee_link)
    else:
        urdf = resolve_urdf(arm["urdf"], base_dir, where=f"{where}.urdf")
        if "ee_link" not in arm:
            raise ValueError(f"{where}.ee_link: required when the arm is given by 'urdf'")
        ee_link = arm["ee_link"]
    if not isinstance(ee_link, str) or not ee_link:
        raise ValueError(f"{where}.ee_link: expected a link name, got {excerpt(ee_link)}")
    position = _float_array(f"{where}.base_position", arm.get("base_position", [0.0, 0.0, 0.0]), ndim=1)
    rpy = _float_array(f"{where}.base_rpy", arm.get("base_rpy", [0.0, 0.0, 0.0]), ndim=1)
    if position.shape != (3,):
        raise ValueError(f"{where}.base_position: expected [x, y, z] in m, got {excerpt(arm.get('base_position'))}")
    if rpy.shape != (3,):
        raise ValueError(f"{where}.base_rpy: expected [roll, pitch, yaw] in rad, got {excerpt(arm.get('base_rpy'))}")
    initial_q = None
    if arm.get("initial_q") is not None:
        initial_q = tuple(_float_array(f"{where}.initial_q", arm["initial_q"], ndim=1).tolist())
    return ArmConfig(urdf=urdf, ee_link=ee_link, base_position=tuple(position.tolist()),
                     base_rpy=tuple(rpy.tolist()), initial_q=initial_q, robot=robot)


def resolve_urdf(value: Any, base_dir: Path, where: str = "urdf") -> str:
    """Resolve a URDF given as a path: absolute; or relative, looked up in ``base_dir`` (the scenario file's
    folder; the current directory for a scenario given as a dict or name) first, then in ``pybullet_data``."""
    if not isinstance(value, (str, os.PathLike)):
        raise ValueError(f"{where}: expected a path, got {excerpt(value)}")
    if Path(value).is_absolute():
        candidates = [Path(value)]
    else:
        import pybullet_data  # local import: only needed for pybullet_data names

        candidates = [base_dir / value, Path(pybullet_data.getDataPath()) / value]
    for candidate in candidates:
        if candidate.is_file():
            return str(candidate.resolve())
    raise ValueError(f"{where}: URDF not found: {excerpt(os.fspath(value))} (looked in {[str(c) for c in candidates]})")


def _parse_edges(data: Mapping[str, Any], n_agents: int) -> np.ndarray:
    if ("edges" in data) == ("incidence" in data):
        raise ValueError("scenario: give exactly one of 'edges' (list of [tail, head]) or 'incidence' (matrix B)")
    if "edges" in data:
        edges = np.asarray(data["edges"]) if _only_numbers(data["edges"], 2) else np.empty((0, 0), dtype=object)
        if edges.ndim != 2 or edges.shape[1] != 2 or len(edges) == 0 or not np.issubdtype(edges.dtype, np.integer):
            raise ValueError(f"edges: expected a non-empty list of [tail, head] integer pairs, got {excerpt(data['edges'])}")
        for k, (tail, head) in enumerate(edges.tolist()):
            if not (0 <= tail < n_agents and 0 <= head < n_agents):
                raise ValueError(
                    f"edges[{k}] = [{tail}, {head}] references a missing agent: there are {n_agents} arms "
                    f"(indices 0..{n_agents - 1})"
                )
        return edges
    return edges_from_incidence(data["incidence"], n_agents)


def edges_from_incidence(incidence: Any, n_agents: int) -> np.ndarray:
    """Edges (tail, head) from an incidence matrix B (+1 tail, -1 head per column)."""
    matrix = _float_array("incidence", incidence, ndim=2)
    if matrix.shape[0] != n_agents:
        raise ValueError(f"incidence: expected {n_agents} rows (one per arm), got {matrix.shape[0]}")
    edges = []
    for k in range(matrix.shape[1]):
        column = matrix[:, k]
        tails, heads = np.flatnonzero(column == 1), np.flatnonzero(column == -1)
        if len(tails) != 1 or len(heads) != 1 or np.count_nonzero(column) != 2:
            raise ValueError(
                f"incidence: column {k + 1} ({excerpt(column.tolist())}) is not an edge: each column needs exactly "
                "one +1 (tail) and one -1 (head)"
            )
        edges.append([int(tails[0]), int(heads[0])])
    return np.asarray(edges, dtype=np.int64)


def _parse_torque_limits(value: Any, n_agents: int) -> Any:
    if value is None:
        return None
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        _positive("torque_limits", value)
        return float(value)
    if isinstance(value, (list, tuple)) and value and all(isinstance(v, (list, tuple)) for v in value):
        if len(value) != n_agents:
            raise ValueError(f"torque_limits: expected one list per arm ({n_agents}), got {len(value)}")
        return tuple(tuple(_positive(f"torque_limits[{i}]", v) for v in row) for i, row in enumerate(value))
    if isinstance(value, (list, tuple)) and value:
        return tuple(_positive("torque_limits", v) for v in value)
    raise ValueError(
        "torque_limits: expected null (URDF efforts), a positive number (N m), a list per joint "
        f"or a list of lists per arm, got {excerpt(value)}"
    )


def _parse_controller_gains(value: Any) -> ControllerGains | None:
    if value is None or isinstance(value, ControllerGains):
        return value
    names = [f.name for f in fields(ControllerGains)]
    if not isinstance(value, Mapping) or set(value) != set(names):
        raise ValueError(f"controller_gains: expected null or a dict with keys {names}, got {excerpt(value)}")
    return ControllerGains(**{key: _non_negative(f"controller_gains.{key}", value[key]) for key in names})


def _only_numbers(value: Any, depth: int) -> bool:
    """Whether ``value`` is a number, or nested lists/tuples/arrays (at most ``depth`` deep) of numbers only
    (ints and floats; booleans and strings are not numbers here)."""
    if isinstance(value, np.ndarray):
        return value.dtype.kind in "iuf" and value.ndim <= depth
    if isinstance(value, (list, tuple)):
        return depth > 0 and all(_only_numbers(item, depth - 1) for item in value)
    return is_real_number(value)


def _float_array(name: str, value: Any, ndim: int) -> np.ndarray:
    if not _only_numbers(value, ndim):
        raise ValueError(f"{name}: expected numbers (not strings or booleans), got {excerpt(value)}")
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected numbers, got {excerpt(value)}") from None
    if array.ndim != ndim:
        raise ValueError(f"{name}: expected a {'list' if ndim == 1 else 'list of lists'} of numbers, got {excerpt(value)}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name}: expected finite numbers, got {excerpt(value)}")
    return array


def _positive(name: str, value: Any) -> float:
    if not is_real_number(value):
        raise ValueError(f"{name}: expected a positive number, got {excerpt(value)}")
    if not _finite(value) or value <= 0:
        raise ValueError(f"{name}: expected a positive finite number, got {excerpt(value)}")
    return float(value)


def _non_negative(name: str, value: Any) -> float:
    if not is_real_number(value):
        raise ValueError(f"{name}: expected a number >= 0, got {excerpt(value)}")
    if not _finite(value) or value < 0:
        raise ValueError(f"{name}: expected a finite number >= 0, got {excerpt(value)}")
    return float(value)


def _finite(value: Any) -> bool:
    """``math.isfinite`` that is False (instead of raising) for an int too large for a float."""
    try:
        return math.isfinite(value)
    except OverflowError:
        return False
