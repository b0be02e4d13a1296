"""Training modes: what a learned action means, one class per mode, registered once.

A mode is a :class:`TrainingMode` subclass with a ``name``, a ``help`` line, a ``preset`` (the defaults of
its runs, :class:`ModePreset`) and :meth:`TrainingMode.action_rows`, its action rule over a stack of agent
rows (:class:`ActionRows`). The training env (every backend) and the evaluated policy both apply that one
rule, so a mode is written once. :func:`register_mode` adds a mode; :func:`training_mode` looks one up by the
name the options carry (``TrainingOptions.mode``), and nothing else compares mode names. The built-in modes
are ``residual`` (:mod:`~ee_formation_env.baselines.learned.residual`), ``torque``
(:mod:`~ee_formation_env.baselines.learned.torque`), ``velocity``
(:mod:`~ee_formation_env.baselines.learned.velocity`) and ``position``
(:mod:`~ee_formation_env.baselines.learned.position`); adding one is shown in docs/extending.md. A mode of
another package is a plugin: its module, named in that package's entry points under :data:`PLUGIN_GROUP`, is
imported (and so registers its modes) on the first lookup, or on the lookup of a name not yet registered.
"""

from __future__ import annotations

import importlib
import importlib.metadata
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Mapping, Sequence

import numpy as np

if TYPE_CHECKING:
    from ee_formation_env.baselines.learned.options import TrainingOptions

#: The built-in modes and their modules, imported (and so registered) on the first lookup; they come first, in
#: this order, in :func:`mode_names` (the default mode first).
BUILTIN_MODES = {"residual": "ee_formation_env.baselines.learned.residual",
                 "torque": "ee_formation_env.baselines.learned.torque",
                 "velocity": "ee_formation_env.baselines.learned.velocity",
                 "position": "ee_formation_env.baselines.learned.position"}

#: The entry-point group of mode plugins: each entry point names a module that registers modes when imported.
PLUGIN_GROUP = "ee_formation.training_modes"


@dataclass(frozen=True)
class PPOSettings:
    """PPO's network and optimizer settings of a mode (the settings every mode shares: algorithm_conf/ppo.yaml)."""

    net_arch: tuple[int, ...]  # hidden layer widths of the actor and the critic
    n_epochs: int  # passes over each rollout
    learning_rate: float
    learning_rate_decay: bool  # linear decay to 0 over the run


@dataclass(frozen=True)
class ModePreset:
    """The defaults of one training mode: what every ``None`` setting of a run becomes (docs/training.md gives
    the evidence for each value)."""

    total_timesteps: int  # agent steps (all agents count)
    train_episode_seconds: float  # s: short episodes give many starts per budget
    train_initial_q_noise: float | None  # rad, half-width; None: the scenario's
    obs_features: str  # features appended to each agent's observation (features.py)
    gamma: float  # discount per control step
    hold_penalty: float  # training-only shaping (shaping.py)
    log_std_init: float  # initial log standard deviation of the Gaussian policy
    ppo: PPOSettings
    n_envs: int  # envs, each with all its agents
    n_steps: int  # PPO steps per env slot per update
    n_workers: int  # worker processes for the envs
    in_process_envs: int  # with worker processes: envs the learner's process steps itself
    #: sb3: a run stops when more than this share of its last 100 training episodes faulted. A mode that learns
    #: from scratch passes through an exploration phase of many faults and learns after it (docs/training.md).
    max_fault_fraction: float = 0.5
    #: sb3: the share of the agent-step budget done before that judgment starts: a run learning from scratch can
    #: fault in every episode for a while early on and recover (docs/training.md); a setup the arms cannot be
    #: driven in still stops, a quarter of the way in.
    fault_guard_start: float = 0.0


class ActionRows:
    """A mode's action rule over R agent rows (copy-major: row ``k * N + i`` is agent i of copy k).

    ``rows(observations, learned)``: the rows' raw observations (R, size) and learned actions (R, n) ->
    the applied normalized actions (R, n) and each row's reward factor (R,), or None where the rule leaves
    rewards as they are. ``reset(rows)`` starts new episodes for those rows (default: all), for a rule with
    state (the residual rule's reference controllers). :meth:`split` gives one rule per row and
    :meth:`concatenate` stacks rules of one ``stack_key`` back into one: a per-agent policy holds a rule of one
    row, and a stack of them acts as one rule of many.
    """

    def reset(self, rows: Sequence[int] | np.ndarray | None = None) -> None:
        pass

    def __call__(self, observations: np.ndarray, learned: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        raise NotImplementedError

    def split(self) -> list["ActionRows"]:
        """One rule per row, in order (sharing this rule's state objects)."""
        raise NotImplementedError

    @classmethod
    def concatenate(cls, parts: Sequence["ActionRows"]) -> "ActionRows":
        """One rule over the rows of ``parts`` in order (all of one :attr:`stack_key`)."""
        raise NotImplementedError

    @property
    def stack_key(self) -> Any:
        """Rules with equal keys can be concatenated (default: rules of one class)."""
        return type(self)


class RowJointStates:
    """Each row's own joint positions and velocities, read from its observation: the rows grouped by layout so
    that a stack of one layout (every homogeneous team) is split in one call."""

    def __init__(self, layouts: Sequence[Any]):
        groups: dict[Any, list[int]] = {}
        for row, layout in enumerate(layouts):
            groups.setdefault(layout, []).append(row)
        self._groups = [(layout, np.array(rows)) for layout, rows in groups.items()]

    def __call__(self, observations: np.ndarray, n_joints: int) -> tuple[np.ndarray, np.ndarray]:
        """``q`` (R, n), rad, and ``dq`` (R, n), rad/s, of the rows' observations (R, size)."""
        if len(self._groups) == 1:
            parts = self._groups[0][0].split(observations)
            return parts.q, parts.dq
        q, dq = np.empty((len(observations), n_joints)), np.empty((len(observations), n_joints))
        for layout, rows in self._groups:
            parts = layout.split(observations[rows])
            q[rows], dq[rows] = parts.q, parts.dq
        return q, dq


class TrainingMode:
    """A training mode (module docstring). Subclasses set the class attributes and implement
    :meth:`action_rows`; :meth:`check` may refuse options the mode cannot use."""

    name: ClassVar[str]
    help: ClassVar[str]  # one line: what the learned action is
    preset: ClassVar[ModePreset]
    imitation: ClassVar[bool] = False  # whether --imitate may start its policy as a copy of a reference
    #: Scenario settings every env the mode's policy acts in gets, training and evaluation (its action
    #: convention, e.g. ``{"gravity_compensation": True}``); the reference laws act without them.
    env_settings: ClassVar[Mapping[str, Any]] = {}

    def check(self, options: "TrainingOptions") -> None:
        """Raise ``ValueError`` naming the field for options this mode cannot use (before any env is built)."""

    def action_rows(self, options: "TrainingOptions", copies: Sequence[Any], agents: Sequence[str],
                    joint_scales: Mapping[str, np.ndarray] | None) -> ActionRows:
        """The rule over the rows of ``agents`` in each env of ``copies`` (copy-major). ``joint_scales``: agent
        -> the normalized env action of one unit of learned action, per joint
        (:func:`~ee_formation_env.baselines.learned.action_scale.rescaling`); None where every scale is 1."""
        raise NotImplementedError


_MODES: dict[str, TrainingMode] = {}
_builtins_loaded = False
_plugins_loaded: set[str] = set()  # the plugin modules imported so far


def register_mode(mode_class: type[TrainingMode]) -> type[TrainingMode]:
    """Register ``mode_class`` under its ``name`` (usable as a class decorator); ``ValueError`` if the name is
    taken."""
    name = mode_class.name
    if not isinstance(name, str) or not name:
        raise ValueError(f"mode: a registered mode needs a non-empty name, got {name!r}")
    if name in _MODES:
        raise ValueError(f"mode: {name!r} is already registered ({type(_MODES[name]).__name__})")
    _MODES[name] = mode_class()
    return mode_class


def unregister_mode(name: str) -> None:
    """Remove the mode ``name`` (a mode registered for a test, say)."""
    _MODES.pop(name, None)


def mode_names() -> tuple[str, ...]:
    """The registered modes' names: the built-ins (:data:`BUILTIN_MODES`' order), then the others as registered."""
    _load_builtins()
    builtin = [name for name in BUILTIN_MODES if name in _MODES]
    return (*builtin, *(name for name in _MODES if name not in BUILTIN_MODES))


def training_mode(name: Any) -> TrainingMode:
    """The registered mode ``name``; ``ValueError`` naming ``mode`` for an unknown one."""
    _load_builtins()
    if isinstance(name, str) and name not in _MODES:
        _load_plugins()  # a plugin installed since the first lookup
    if not isinstance(name, str) or name not in _MODES:
        raise ValueError(f"mode: expected one of {list(mode_names())}, got {name!r}")
    return _MODES[name]


def _load_builtins() -> None:
    global _builtins_loaded
    if not _builtins_loaded:
        _builtins_loaded = True
        for module in BUILTIN_MODES.values():
            importlib.import_module(module)
        _load_plugins()


def _load_plugins() -> None:
    """Import the modules of :data:`PLUGIN_GROUP`'s entry points not imported yet; one that fails is a
    ``ValueError`` naming the entry point."""
    for entry in importlib.metadata.entry_points(group=PLUGIN_GROUP):
        if entry.value in _plugins_loaded:
            continue
        _plugins_loaded.add(entry.value)  # tried once: a failing plugin is not retried on every lookup
        try:
            entry.load()
        except Exception as error:  # noqa: BLE001 - any fault of foreign code, reported as one line
            raise ValueError(f"mode: the plugin {entry.name!r} ({PLUGIN_GROUP}: {entry.value}) failed to load: "
                             f"{type(error).__name__}: {error}") from None
