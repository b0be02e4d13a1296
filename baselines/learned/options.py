"""The training options: what a training mode, its features, its shaping and its action scale are, in one class.

:class:`TrainingOptions` is the one owner of these settings and their defaults. ``train.py``'s flags
(:class:`~ee_formation_env.baselines.learned.config.TrainConfig`), the BenchMARL task's options
(:mod:`~ee_formation_env.baselines.learned.benchmarl_task`) and the RLlib and SB3 builders all read it; the
training env (:class:`~ee_formation_env.baselines.learned.training_env.BatchedTrainingEnv`) and the evaluated
policy (:mod:`~ee_formation_env.baselines.learned.policy`) are built from it. Fields left ``None`` take the
mode's preset (:meth:`TrainingOptions.resolved`). docs/training.md's flags table lists them.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Optional

from ee_formation_env.baselines import MODEL_BASED_POLICIES
from ee_formation_env.baselines.learned.action_scale import DEFAULT_ACTION_ACCELERATION, check_action_acceleration
from ee_formation_env.baselines.learned.features import FEATURE_SETS
from ee_formation_env.baselines.learned.modes import TrainingMode, mode_names, training_mode
from ee_formation_env.baselines.learned.set_network import POLICY_NETWORKS
from ee_formation_env.baselines.learned.shaping import SPEED_SCALE

#: The fields a run's config.json may lack (saved before the option existed), and the value the run had then:
#: no gate, no features, the default action acceleration (which leaves the built-in robots as they were).
SAVED_RUN_DEFAULTS = {"residual_gate": False, "obs_features": "none", "hold_penalty": 0.0, "contact_penalty": 0.0,
                      "action_acceleration": DEFAULT_ACTION_ACCELERATION, "policy_network": "mlp",
                      "precision_bonus": 0.0}


def _option(default: Any, unit: str, meaning: str, choices: tuple[str, ...] | None = None,
            flag: bool = True) -> Any:
    """A field of :class:`TrainingOptions`: its unit ("" if none), meaning and, for a name among a fixed few, its
    choices travel in its metadata (the options table and ``train.py``'s flag); ``flag`` False: set by name only
    (``train.py --set name=value`` or ``--config``), with no flag of its own."""
    return dataclasses.field(default=default, metadata={"unit": unit, "meaning": meaning, "choices": choices,
                                                        "flag": flag})


@dataclass(frozen=True)
class TrainingOptions:
    """The training options (module docstring). Checked on construction: a bad value raises ``ValueError``
    (``TypeError`` for a wrong type) naming the field. Frozen and plain, so it pickles into worker processes."""

    mode: str = _option("residual", "", "what the learned action is: residual (a correction added to the "
                        "reference controller's torques), torque (the normalized joint torques), velocity (the "
                        "joint speeds, turned into torques by a damped loop with gravity compensation) or position "
                        "(joint target angles, held by a PD loop with gravity compensation); any "
                        "registered mode (modes.py)")
    reference: str = _option("adaptive_jacobian", "", "residual mode: the reference controller (a model-based one: "
                             + ", ".join(MODEL_BASED_POLICIES) + ")", MODEL_BASED_POLICIES)
    residual_scale: float = _option(0.3, "", "residual mode: the correction's share of one unit of learned action, "
                                    "in (0, 1]")
    residual_gate: bool = _option(True, "", "residual mode: scale the correction by min(1, the agent's error in "
                                  "success tolerances), so that it fades out at the goal")
    residual_gate_power: float = _option(1.0, "", "residual mode, with the gate: the gate is min(1, x)^this, >= 1; "
                                         "above 1 the correction fades faster than the reference's own pull near "
                                         "the goal, so that it cannot hold the formation off there")
    correction_penalty: float = _option(0.5, "", "residual mode: each agent's reward is multiplied by 1 - this * "
                                        "mean(correction^2), in [0, 1]")
    obs_features: Optional[str] = _option(None, "", "features appended to each agent's observation, from it alone "
                                          "(features.py): " + " or ".join(FEATURE_SETS), FEATURE_SETS)
    hold_penalty: Optional[float] = _option(None, "reward per step", "training only: subtract this times "
                                            f"min(1, joint speed / {SPEED_SCALE} rad/s) from an in-formation agent's "
                                            "reward (shaping.py), in [0, 1]")
    contact_penalty: float = _option(0.0, "reward per step", "training only: subtract this from an agent's reward on "
                                     "every step its arm touches another arm (shaping.py), >= 0")
    precision_bonus: float = _option(0.0, "reward per step", "training only: add this to an agent's reward on every "
                                     "step each of its edges is within precision_band of its length, a tight-band "
                                     "bonus that values precision beyond the success band (shaping.py; 0: off), "
                                     ">= 0", flag=False)
    precision_band: float = _option(1e-3, "m", "training only: the edge length error within which the precision "
                                    "bonus is paid, > 0", flag=False)
    reward_error_ceiling: Optional[float] = _option(None, "success tolerances", "training only: the error at which "
                                                    "the training reward's log term reaches 0 (None: the scenario's "
                                                    "reward.error_ceiling, 100 by default); a start farther out "
                                                    "than it earns nothing, so learning from such starts needs a "
                                                    "larger one (> 1; evaluation keeps the scenario's reward)")
    reward_tracking: Optional[float] = _option(None, "reward per step", "training only: the weight of the reward's "
                                               "manoeuvre tracking term, each end-effector's closeness to its place "
                                               "in the moving reference (reward.py; None: the scenario's "
                                               "reward.tracking, 0 by default), >= 0; a scenario with a manoeuvre")
    action_acceleration: float = _option(DEFAULT_ACTION_ACCELERATION, "rad/s²", "one unit of learned action (or "
                                         "correction) is the torque giving a joint this acceleration at the "
                                         "initial configuration, at most its torque limit (action_scale.py)")
    gravity_compensation: bool = _option(False, "", "the env adds each arm's own gravity torque g(q) to the "
                                         "learned torque, in training and evaluation (the scenario key of that "
                                         "name, docs/spaces.md); torque mode")
    joint_speed: float = _option(1.0, "rad/s", "velocity mode: the joint speed one unit of learned action commands")
    velocity_gain: float = _option(10.0, "1/s", "velocity mode: the velocity loop's gain, the inverse time constant "
                                   "of reaching the commanded speed; at most 1 / control period for a stable loop")
    joint_reach: float = _option(1.0, "rad", "position mode: the joint angle about the initial configuration that "
                                 "one unit of learned action targets")
    position_gain: float = _option(10.0, "1/s", "position mode: the PD loop's natural frequency (critically "
                                   "damped); at most 0.5 / control period for a stable loop")
    target_smoothing: float = _option(0.0, "s", "position mode: the time constant of a first-order low-pass filter "
                                      "on the joint targets (0: none); it stops a policy that switches its targets "
                                      "from step to step from chattering")
    train_episode_seconds: Optional[float] = _option(None, "s", "training episode length (evaluation: the "
                                                     "scenario's episode_seconds)")
    policy_network: str = _option("mlp", "", "the shared policy network: mlp (SB3's MLP on the whole observation, "
                                  "one team size) or set (a slot encoder shared over the neighbour slots, masked "
                                  "mean and max pooling and an own-state encoder: one policy for any team size of "
                                  "the same robot, set_network.py); set needs obs_features none", POLICY_NETWORKS)
    train_initial_q_noise: Optional[float] = _option(None, "rad", "half-width of the uniform noise on the initial "
                                                     "joint positions while training (None in a preset: the "
                                                     "scenario's; evaluation: the scenario's)")

    def __post_init__(self) -> None:
        training_mode(self.mode)  # ValueError naming mode
        if self.reference not in MODEL_BASED_POLICIES:
            raise ValueError(f"reference: expected a model-based controller {list(MODEL_BASED_POLICIES)}, "
                             f"got {self.reference!r}")
        for flag in ("residual_gate", "gravity_compensation"):
            if not isinstance(getattr(self, flag), bool):
                raise TypeError(f"{flag}: expected True or False, got {getattr(self, flag)!r}")
        if self.obs_features is not None and self.obs_features not in FEATURE_SETS:
            raise ValueError(f"obs_features: expected one of {list(FEATURE_SETS)} or None, got {self.obs_features!r}")
        if self.policy_network not in POLICY_NETWORKS:
            raise ValueError(f"policy_network: expected one of {list(POLICY_NETWORKS)}, got {self.policy_network!r}")
        features = self.training_mode.preset.obs_features if self.obs_features is None else self.obs_features
        if self.policy_network == "set" and features != "none":
            raise ValueError(f"policy_network: 'set' reads the observation's neighbour slots and needs obs_features "
                             f"none; {features!r} appends entries that mix slots with the own state")
        self._number("residual_scale", lambda x: 0 < x <= 1, "a value in (0, 1]")
        self._number("residual_gate_power", lambda x: 1 <= x <= 8, "a power in [1, 8]")
        self._number("correction_penalty", lambda x: 0 <= x <= 1, "a value in [0, 1]")
        self._number("hold_penalty", lambda x: 0 <= x <= 1, "a value in [0, 1] or None", optional=True)
        self._number("contact_penalty", lambda x: x >= 0, "a finite value >= 0")
        self._number("precision_bonus", lambda x: x >= 0, "a finite value >= 0")
        self._number("precision_band", lambda x: x > 0, "a length > 0 m")
        self._number("reward_error_ceiling", lambda x: x > 1, "a value > 1 or None", optional=True)
        self._number("reward_tracking", lambda x: x >= 0, "a weight >= 0 or None", optional=True)
        object.__setattr__(self, "action_acceleration", check_action_acceleration(self.action_acceleration))
        self._number("joint_speed", lambda x: 0 < x <= 100, "a speed in (0, 100] rad/s")
        self._number("velocity_gain", lambda x: 0 < x <= 1000, "a gain in (0, 1000] 1/s")
        self._number("joint_reach", lambda x: 0 < x <= math.pi, "an angle in (0, pi] rad")
        self._number("position_gain", lambda x: 0 < x <= 1000, "a gain in (0, 1000] 1/s")
        self._number("target_smoothing", lambda x: 0 <= x <= 10, "a time constant in [0, 10] s")
        self._number("train_episode_seconds", lambda x: x > 0, "a duration > 0 s or None", optional=True)
        self._number("train_initial_q_noise", lambda x: x >= 0, "a half-width >= 0 rad or None", optional=True)
        self.training_mode.check(self)

    def _number(self, name: str, valid: Callable[[float], bool], expected: str, optional: bool = False) -> None:
        """Check field ``name`` is a finite real number (or None if ``optional``) for which ``valid`` holds, and
        store it as a float."""
        value = getattr(self, name)
        if value is None and optional:
            return
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise TypeError(f"{name}: expected a number ({expected}), got {type(value).__name__} {value!r}")
        if not (math.isfinite(value) and valid(value)):
            raise ValueError(f"{name}: expected {expected}, got {value!r}")
        object.__setattr__(self, name, float(value))

    @property
    def training_mode(self) -> TrainingMode:
        """The registered mode these options name (:func:`~ee_formation_env.baselines.learned.modes.training_mode`)."""
        return training_mode(self.mode)

    def resolved(self) -> "TrainingOptions":
        """A copy with every ``None`` field filled from the mode's preset (``train_initial_q_noise`` stays None,
        the scenario's, where the preset says so)."""
        preset = self.training_mode.preset
        filled = {name: getattr(preset, name) for name in PRESET_FIELDS if getattr(self, name) is None}
        return dataclasses.replace(self, **filled) if filled else self

    def env_overrides(self) -> dict[str, Any]:
        """Scenario overrides of every env the learned policy acts in, training and evaluation: its action
        convention: the mode's own (:attr:`TrainingMode.env_settings`) and ``gravity_compensation`` when set.
        The reference laws act without them."""
        overrides = dict(self.training_mode.env_settings)
        if self.gravity_compensation:
            overrides["gravity_compensation"] = True
        return overrides

    def episode_overrides(self) -> dict[str, Any]:
        """Scenario overrides of the training episodes (options resolved): episode length and, if set, start
        noise and the training reward's error ceiling and tracking weight (what the learning curve's reference
        lines are also run with)."""
        options = self.resolved()
        overrides: dict[str, Any] = {"episode_seconds": options.train_episode_seconds}
        if options.train_initial_q_noise is not None:
            overrides["initial_q_noise"] = options.train_initial_q_noise
        reward = {key: value for key, value in (("error_ceiling", options.reward_error_ceiling),
                                                ("tracking", options.reward_tracking)) if value is not None}
        if reward:  # merged into the scenario's reward (load_scenario)
            overrides["reward"] = reward
        return overrides

    def training_overrides(self) -> dict[str, Any]:
        """Scenario overrides of the training env: :meth:`episode_overrides` and :meth:`env_overrides`."""
        return {**self.episode_overrides(), **self.env_overrides()}

    def to_dict(self) -> dict[str, Any]:
        """The options as plain values (JSON-ready): ``TrainingOptions(**options.to_dict())`` is a copy."""
        return dataclasses.asdict(self)

    @classmethod
    def fields(cls) -> tuple[str, ...]:
        """The option names, in order."""
        return tuple(spec.name for spec in dataclasses.fields(cls))

    @classmethod
    def from_saved(cls, saved: Mapping[str, Any]) -> "TrainingOptions":
        """The options of a run's saved ``config.json`` (the same keys as the fields; other keys are ignored):
        a key the run lacks takes :data:`SAVED_RUN_DEFAULTS`' value (what it had then), else the default."""
        defaults = {spec.name: spec.default for spec in dataclasses.fields(cls)}
        values = {name: saved[name] for name in cls.fields()
                  if name in saved and not (saved[name] is None and defaults[name] is not None)}
        for name, value in SAVED_RUN_DEFAULTS.items():
            values.setdefault(name, value)
        return cls(**values)


#: The options a mode's preset fills where they are ``None``.
PRESET_FIELDS = ("obs_features", "hold_penalty", "train_episode_seconds", "train_initial_q_noise")
