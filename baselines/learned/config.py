"""The configuration of a training run: one tree of typed objects, the CLI flags derived from it.

A :class:`TrainConfig` holds every setting of a run (``python train.py`` / ``ee-formation train``: each setting is
one flag, ``--n-envs`` for ``n_envs``): its own (scenario, budget, rollout layout, evaluation, output) and, nested as
its field ``options``, the training options (mode, features, shaping, action scale), which
:class:`~ee_formation_env.baselines.learned.options.TrainingOptions` declares and checks. Each setting is declared
in one of them; :meth:`TrainConfig.settings` lists them flat, as the flags, ``config.json``, ``--config FILE`` and
``--set key=value`` name them (:mod:`~ee_formation_env.baselines.learned.settings`). Fields left ``None`` take
their training mode's preset (:data:`PRESETS`, each registered mode's ``preset``) when :meth:`TrainConfig.resolved`
fills and checks them; a resolved configuration is what a run saves in its ``config.json`` and what
:meth:`TrainConfig.from_dict` reads back. The training design behind the presets (episode length, start noise, PPO
settings, rollout layout) is in docs/training.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import re
import typing
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Collection, Iterator, Mapping, Sequence

from ee_formation_env.baselines import MODEL_BASED_POLICIES
from ee_formation_env.baselines.learned.algorithms import AlgorithmNames, algorithm, algorithm_names
from ee_formation_env.baselines.learned.imitation import (IMITATION_EPISODES, IMITATION_ROUNDS, IMITATION_TIMESTEPS,
                                                         reference_features)
from ee_formation_env.baselines.learned.modes import ModePreset, PPOSettings, mode_names, training_mode
from ee_formation_env.baselines.learned.options import PRESET_FIELDS, TrainingOptions
from ee_formation_env.baselines.learned.recipes import RECIPE_CHOICES, recipe_for
from ee_formation_env.baselines.learned.settings import (Setting, agent_steps, flag_of, parse_assignment,
                                                        read_settings_file)
from ee_formation_env.scenario_sets import HELD_OUT_SEED_OFFSET


class _Presets(Mapping[str, ModePreset]):
    """Mode name -> its preset, read from the mode registry (a mode registered later is in it too)."""

    def __getitem__(self, name: str) -> ModePreset:
        if name not in mode_names():
            raise KeyError(name)
        return training_mode(name).preset

    def __iter__(self) -> Iterator[str]:
        return iter(mode_names())

    def __len__(self) -> int:
        return len(mode_names())


#: Per-mode presets: each mode's ``preset`` (docs/training.md gives the evidence for each value).
PRESETS: Mapping[str, ModePreset] = _Presets()
TRAIN_BACKENDS = ("sb3", "rllib")  # the libraries train.py trains with (the registry's backends of --algo)
FAULT_WINDOW = 100  # training episodes over which --max-fault-fraction is judged (all copies together)
IMITATION_NET_ARCH = (256, 256)  # a copy of a reference controller (--imitate) needs a wider actor


def _preset_text(name: str) -> str:
    return ", ".join(f"{mode}: {getattr(preset, name)}" for mode, preset in PRESETS.items())


def _flag(help: str, default: Any = None, **argparse_kwargs: Any) -> Any:
    """A field that is also a command-line flag: its help and any argparse keywords travel in its metadata."""
    return field(default=default, metadata={"help": help, **argparse_kwargs})


def _option_setting(spec: dataclasses.Field, kind: Any) -> Setting:
    """The setting of the training option ``spec`` (of type ``kind``): its default, meaning and choices are
    :class:`TrainingOptions`' (its one owner); its flag adds the unit and, for an option a mode's preset fills
    (``PRESET_FIELDS``), the presets' values to the help."""
    help = spec.metadata["meaning"] + (f", {spec.metadata['unit']}" if spec.metadata["unit"] else "")
    if spec.name in PRESET_FIELDS:
        help += f" (default {_preset_text(spec.name)})"
    flag: dict[str, Any] = {"help": help}
    if kind is bool:
        flag["action"] = argparse.BooleanOptionalAction
    elif kind in (int, float):
        flag["type"] = kind
    if spec.metadata["choices"]:
        flag["choices"] = spec.metadata["choices"]
    if not spec.metadata["flag"]:
        flag["by_name_only"] = True
    return Setting(spec.name, TrainingOptions, spec.default, flag)


def _flag_error(error: Exception) -> ValueError:
    """An owner's ``field: message`` error as the command line names it: ``--field: message`` (``field`` for a
    setting set by name only)."""
    name, _, rest = str(error).partition(": ")
    by_name = {setting.name for setting in TrainConfig.settings() if not setting.has_flag}
    return ValueError(f"{name if name in by_name else flag_of(name)}: {rest}")


@dataclass
class TrainConfig:
    """Every setting of a training run, the training options nested as ``options``; ``None`` fields take the
    mode's preset (:meth:`resolved`)."""

    scenario: Any = _flag("built-in name or YAML/JSON scenario file", "planar_square")
    recipe: str = _flag("board: a built-in scenario's preset (scenario_presets.yaml) sets every training flag not "
                        "given, unless --mode names another mode; none: the flat defaults", "board",
                        choices=RECIPE_CHOICES)
    #: The training options (mode, features, shaping, action scale): their own dataclass, which declares and
    #: checks them; their flags sit here, in its field order (:meth:`settings`).
    options: TrainingOptions = field(default_factory=TrainingOptions, metadata={"settings": TrainingOptions})
    imitate: str | None = _flag("torque mode: start the policy as a copy of this reference, learned from its "
                                "demonstrations (DAgger) before PPO: a reference law "
                                f"({', '.join(MODEL_BASED_POLICIES)}) or a run folder of the same scenario and env "
                                "settings, whose learned policy's applied torques are copied (default none: learn from "
                                "the reward alone); residual mode: none only", None, metavar="LAW|RUN_DIR|none")
    imitation_rounds: int = _flag("--imitate: demonstration rounds (the first driven by the reference, the next ones "
                                  "partly by the learner)", IMITATION_ROUNDS, type=int)
    imitation_episodes: int = _flag("--imitate: training episodes per demonstration round", IMITATION_EPISODES,
                                    type=int)
    algo: str = _flag("learning algorithm", "ppo", choices=AlgorithmNames(*TRAIN_BACKENDS))
    backend: str = _flag("training library", "sb3", choices=TRAIN_BACKENDS)
    total_timesteps: int | None = _flag(f"agent steps (all agents count; 400000, 4e5, 400k and 5M alike); default "
                                        f"{_preset_text('total_timesteps')}", type=agent_steps)
    n_envs: int | None = _flag(f"parallel envs (each with all its agents; default {_preset_text('n_envs')})", type=int)
    n_steps: int | None = _flag("ppo: steps per env slot per update (an update learns from n_steps x n_envs x agents "
                                "agent steps: 4,096 with either mode's defaults on 4 agents; default "
                                f"{_preset_text('n_steps')})", type=int)
    n_workers: int | None = _flag("worker processes for the envs (0 = step them in this process; default "
                                  f"{_preset_text('n_workers')})", type=int)
    in_process_envs: int | None = _flag("with worker processes: how many of the envs the learner's process steps "
                                        "while the workers step the others (default "
                                        f"{_preset_text('in_process_envs')}; 0 without workers)", type=int)
    gamma: float | None = _flag(f"discount per control step (default {_preset_text('gamma')})", type=float)
    log_std_init: float | None = _flag("initial log standard deviation of the Gaussian policy (ppo; default "
                                       f"{_preset_text('log_std_init')})", type=float)
    sde_sample_freq: int = _flag("ppo (sb3): 0 explores with white Gaussian action noise, drawn anew at each control "
                                 "step (the default); N >= 1 with generalized state-dependent exploration (gSDE): "
                                 "the noise is a function of the policy's features, its random matrix drawn anew "
                                 "every N control steps; -1: once per rollout", 0, type=int)
    max_train_seconds: float | None = _flag("stop training after this wall time, s, even if --total-timesteps is "
                                            "not reached (default: no limit)", type=float)
    max_fault_fraction: float | None = _flag("sb3: stop training with an error naming the fault when more than this "
                                             f"share of the last {FAULT_WINDOW} training episodes ended in a physics "
                                             f"fault (1: never stop; default {_preset_text('max_fault_fraction')})",
                                             type=float)
    fault_guard_start: float | None = _flag("sb3: the share of --total-timesteps done before --max-fault-fraction "
                                            "is judged (0: from the start), in [0, 1) (default "
                                            f"{_preset_text('fault_guard_start')})", type=float)
    seed: int = _flag(f"training seed, an integer >= 0; the first reset of env slot j uses seed + j, which stays below "
                      f"the held-out evaluation seeds ({HELD_OUT_SEED_OFFSET} and up)", 0, type=int)
    out: str | None = _flag("run directory (default runs/<name>); a folder that already holds files is refused "
                            "unless --overwrite or --resume")
    overwrite: bool = _flag("replace what --out holds, once the new configuration has validated", False,
                            action="store_true")
    resume: str | None = _flag("continue the interrupted or checkpointed run in RUN_DIR to its budget, with its saved "
                               "configuration (only evaluation flags and --total-timesteps, a new budget at least the "
                               "agent steps done, may be given beside it)", metavar="RUN_DIR")
    eval_only: str | None = _flag("evaluate a saved run only (its saved scenario; results in RUN_DIR/evaluations/)",
                                  metavar="RUN_DIR")
    eval_episodes: int = _flag("held-out episodes per policy in the comparison (20: enough for its 95-percent intervals)", 20,
                               type=int)
    eval_workers: int = _flag("processes for the evaluation episodes (0 = run them in this process)", 2, type=int)
    eval_seconds: float | None = _flag("episode length for the comparison, s (default: the scenario's)", type=float)
    address: str | None = _flag("rllib: address of an existing Ray cluster")
    no_progress: bool = _flag("no progress bars", False, action="store_true")
    debug: bool = _flag("on an error, show the traceback instead of one line", False, action="store_true")

    # ------------------------------------------------------------------------------------------ the settings
    @classmethod
    def settings(cls) -> tuple[Setting, ...]:
        """Every setting of a run, flat, in flag order: this class's own fields, with the fields of a nested
        dataclass (``options``) in place of the field that holds it. Each is declared in exactly one of them."""
        settings = []
        for spec in fields(cls):
            nested = spec.metadata.get("settings")
            if nested is None:
                settings.append(Setting(spec.name, cls, spec.default, dict(spec.metadata)))
                continue
            kinds = typing.get_type_hints(nested)
            for option in fields(nested):
                kind = kinds[option.name]
                kind = next((k for k in typing.get_args(kind) if k is not type(None)), kind)  # Optional[x]: x
                settings.append(_option_setting(option, kind))
        return tuple(settings)

    def values(self) -> dict[str, Any]:
        """Every setting's value, flat by name (:meth:`settings`' order)."""
        merged = {**{spec.name: getattr(self, spec.name) for spec in fields(self)},
                  **{spec.name: getattr(self.options, spec.name) for spec in fields(self.options)}}
        return {setting.name: merged[setting.name] for setting in self.settings()}

    def with_settings(self, values: Mapping[str, Any]) -> "TrainConfig":
        """A copy with the settings ``values`` (flat names, as the flags and config.json name them) replaced,
        each in the dataclass that owns it. Raises ``ValueError`` naming an unknown name, or the flag of an
        option its owner refuses (the options are checked together)."""
        owners = {setting.name: setting.owner for setting in self.settings()}
        unknown = [name for name in values if name not in owners]
        if unknown:
            raise ValueError(f"unknown setting(s) {', '.join(map(repr, unknown))}")
        own = {name: value for name, value in values.items() if owners[name] is not TrainingOptions}
        options = {name: value for name, value in values.items() if owners[name] is TrainingOptions}
        try:
            replaced = dataclasses.replace(self.options, **options) if options else self.options
        except (TypeError, ValueError) as error:
            raise _flag_error(error) from None
        return dataclasses.replace(self, options=replaced, **own)

    # ------------------------------------------------------------------------------------------ presets
    @property
    def registered_mode(self) -> Any:
        """The registered training mode of the options' ``mode``."""
        return self.options.training_mode

    @property
    def preset(self) -> ModePreset:
        return self.registered_mode.preset

    @property
    def ppo(self) -> PPOSettings:
        """The mode's PPO settings; an imitated policy gets the wider actor."""
        settings = self.preset.ppo
        if self.imitate not in (None, "none"):
            settings = dataclasses.replace(settings, net_arch=IMITATION_NET_ARCH)
        return settings

    def resolved(self) -> "TrainConfig":
        """A copy with every ``None`` field filled from the mode's preset, checked: raises ``ValueError``
        naming the flag of the first setting out of range (the options checked themselves when made)."""
        config = dataclasses.replace(self)
        preset = config.preset
        if config.imitate is None:
            config.imitate = "none"
        imitating = config.imitate != "none"
        if config.total_timesteps is None and not config.resume:  # a resumed run keeps its saved budget unless given
            config.total_timesteps = IMITATION_TIMESTEPS if imitating else preset.total_timesteps
        if config.options.obs_features is None and imitating:  # an imitated policy sees what its reference sees
            config = config.with_settings({"obs_features": reference_features(config.imitate)})
        config.options = config.options.resolved()  # the options' preset fields (PRESET_FIELDS)
        for name in ("gamma", "log_std_init", "n_envs", "n_steps", "n_workers", "max_fault_fraction",
                     "fault_guard_start"):
            if getattr(config, name) is None:
                setattr(config, name, getattr(preset, name))
        if config.in_process_envs is None:  # the mode's share, where it leaves the workers envs to step
            share = preset.in_process_envs
            config.in_process_envs = share if config.n_workers > 0 and share < config.n_envs else 0
        config.check()
        return config

    def check(self) -> None:
        """Raise ``ValueError`` naming the flag of the first setting out of range (a resolved configuration): this
        class's own settings and how they go with the options (which check themselves)."""
        imitating = self.imitate != "none"
        for name in ("out", "resume", "eval_only"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, (str, Path)) or not str(value).strip()):
                raise ValueError(f"{flag_of(name)}: expected a folder path, got {value!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int):
            raise TypeError(f"--seed: expected an integer, got {self.seed!r}")
        if not 0 <= self.seed < HELD_OUT_SEED_OFFSET:
            raise ValueError(f"--seed: expected an integer in [0, {HELD_OUT_SEED_OFFSET}) (training reset seeds stay "
                             f"below the held-out evaluation seeds), got {self.seed}")
        if self.total_timesteps is not None and (isinstance(self.total_timesteps, bool)
                                                 or not isinstance(self.total_timesteps, int)):
            raise TypeError(f"--total-timesteps: expected an integer, got {self.total_timesteps!r}")
        if self.total_timesteps is not None and self.total_timesteps < (0 if imitating else 1):
            raise ValueError("--total-timesteps must be >= 1 (>= 0 with --imitate: the imitated policy as it is)")
        if self.n_envs < 1 or self.n_steps < 1 or self.eval_episodes < 1:
            raise ValueError("--n-envs, --n-steps and --eval-episodes must be >= 1")
        if not isinstance(self.imitate, str):
            raise TypeError(f"--imitate: expected a reference law's name, a run folder or none, got {self.imitate!r}")
        if self.imitate in MODEL_BASED_POLICIES and self.options.obs_features != "none":
            raise ValueError("--obs-features: expected none with --imitate of a law (the policy sees what its "
                             "reference sees)")
        ppo = algorithm(self.algo, "--algo", TRAIN_BACKENDS).is_ppo
        if imitating and (not self.registered_mode.imitation or self.backend != "sb3" or not ppo):
            imitating_modes = [name for name in mode_names() if training_mode(name).imitation]
            raise ValueError(f"--imitate: expected none, except with --mode {' or '.join(imitating_modes)}, "
                             "--backend sb3 and --algo ppo")
        if self.imitation_rounds < 1 or self.imitation_episodes < 1:
            raise ValueError("--imitation-rounds and --imitation-episodes must be >= 1")
        if self.eval_seconds is not None and not (math.isfinite(self.eval_seconds) and self.eval_seconds > 0):
            raise ValueError("--eval-seconds: expected a duration > 0 s")
        if self.resume and (self.eval_only or self.overwrite):
            raise ValueError("--resume: give it alone, without --eval-only or --overwrite")
        if self.eval_only and self.overwrite:
            raise ValueError("--overwrite: not with --eval-only (an evaluation never replaces a run)")
        if self.n_workers < 0 or self.eval_workers < 0:
            raise ValueError("--n-workers and --eval-workers must be >= 0")
        if self.in_process_envs and not (self.n_workers > 0 and 0 < self.in_process_envs < self.n_envs):
            raise ValueError("--in-process-envs: expected 0, or with --n-workers >= 1 a number below --n-envs")
        if self.options.policy_network == "set" and (self.backend != "sb3" or not ppo or imitating):
            raise ValueError("--policy-network: set trains with --backend sb3 and --algo ppo, without --imitate")
        if self.backend not in algorithm(self.algo).backends:
            raise ValueError(f"--backend {self.backend} supports --algo {' or '.join(algorithm_names(self.backend))} "
                             "only")
        if self.backend == "rllib" and self.n_workers > 0 and self.n_envs % self.n_workers:
            raise ValueError(f"--n-envs: --backend rllib gives each of its --n-workers {self.n_workers} env runners "
                             f"the same number of copies; expected a multiple of {self.n_workers}, got {self.n_envs}")
        if not 0 < self.gamma <= 1:
            raise ValueError("--gamma: expected a value in (0, 1]")
        if not 0 < self.max_fault_fraction <= 1:
            raise ValueError("--max-fault-fraction: expected a value in (0, 1]")
        if not 0 <= self.fault_guard_start < 1:
            raise ValueError("--fault-guard-start: expected a value in [0, 1)")
        if self.max_train_seconds is not None and not self.max_train_seconds > 0:
            raise ValueError("--max-train-seconds: expected a value > 0")
        if not math.isfinite(self.log_std_init):
            raise ValueError("--log-std-init: expected a finite number")
        if isinstance(self.sde_sample_freq, bool) or not isinstance(self.sde_sample_freq, int):
            raise TypeError(f"--sde-sample-freq: expected an integer, got {self.sde_sample_freq!r}")
        if self.sde_sample_freq < -1:
            raise ValueError("--sde-sample-freq: expected -1, 0 or a number of steps >= 1, got "
                             f"{self.sde_sample_freq}")
        if self.sde_sample_freq and (self.backend != "sb3" or not ppo or imitating
                                     or self.options.policy_network == "set"):
            raise ValueError("--sde-sample-freq: gSDE trains with --backend sb3 and --algo ppo, an MLP policy and "
                             "no --imitate (0: off)")

    # ------------------------------------------------------------------------------------------ the env
    def training_overrides(self) -> dict[str, Any]:
        """Scenario overrides of the training env (:meth:`TrainingOptions.training_overrides`)."""
        return self.options.training_overrides()

    # ------------------------------------------------------------------------------------------ files
    #: Fields that say where a run is or how this command behaves, not what the run is: not in its config.json.
    UNSAVED_FIELDS = ("out", "eval_only", "overwrite", "resume", "debug")
    #: Fields that a command on a saved run (``--resume``, ``--eval-only``) may set: how it is evaluated.
    EVALUATION_FIELDS = ("eval_episodes", "eval_workers", "eval_seconds", "no_progress")

    def to_dict(self) -> dict[str, Any]:
        """The saved settings (every setting but :data:`UNSAVED_FIELDS`), flat by name, JSON-ready."""
        return {name: value for name, value in self.values().items() if name not in self.UNSAVED_FIELDS}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "TrainConfig":
        """The configuration a run saved (extra keys such as ``scenario_data`` and ``versions`` are ignored;
        settings a run saved before they existed take their defaults). Only the options are checked (by their
        owner, named by flag): :meth:`from_saved` checks the whole."""
        names = {setting.name for setting in cls.settings()}
        return cls().with_settings({key: value for key, value in data.items() if key in names})

    #: Saved settings that a run's ``config.json`` may lack: added after the first saved runs, their defaults
    #: are what those runs trained with. Every other saved setting must be in the file.
    LATER_SAVED_FIELDS = ("action_acceleration", "gravity_compensation", "contact_penalty", "max_fault_fraction",
                          "residual_gate_power", "joint_speed", "velocity_gain", "recipe", "policy_network",
                          "joint_reach", "position_gain", "target_smoothing", "reward_error_ceiling",
                          "reward_tracking", "fault_guard_start", "sde_sample_freq", "precision_bonus",
                          "precision_band")
    #: Saved settings that may be null in a resolved configuration (every other one has a value).
    NULLABLE_SAVED_FIELDS = ("train_initial_q_noise", "max_train_seconds", "eval_seconds", "address",
                             "reward_error_ceiling", "reward_tracking")

    @classmethod
    def from_saved(cls, data: Any, source: str = "config.json") -> "TrainConfig":
        """The configuration a run saved, checked before use: a JSON object holding every saved setting (but
        :data:`LATER_SAVED_FIELDS`), each of its setting's type, the whole in range as :meth:`resolved` checks
        it. A fault is a ``ValueError`` naming ``source`` and the key."""
        fix = "restore the config.json the run wrote (its sha256 is in the run's SHA256SUMS)"
        if not isinstance(data, Mapping):
            raise ValueError(f"{source}: expected a JSON object of settings, got {type(data).__name__}: {fix}")
        saved = [setting for setting in cls.settings() if setting.name not in cls.UNSAVED_FIELDS]
        missing = [s.name for s in saved if s.name not in data and s.name not in cls.LATER_SAVED_FIELDS]
        if missing:
            raise ValueError(f"{source}: {', '.join(missing)} missing (every setting of the run is saved): {fix}")
        for setting in saved:
            value = data.get(setting.name)
            nullable = setting.name in cls.NULLABLE_SAVED_FIELDS
            if setting.name in data and not (setting.fits(value) if value is not None else nullable):
                null = " or null" if nullable else ""
                raise ValueError(f"{source}: {setting.name}: {setting.expected()}{null}, got {value!r}: {fix}")
        try:
            return cls.from_dict(data).resolved()
        except (TypeError, ValueError) as error:
            raise ValueError(f"{source}: {error}: {fix}") from None

    @classmethod
    def load(cls, run_dir: str | Path) -> "TrainConfig":
        """The configuration saved in ``run_dir/config.json``."""
        return cls.from_dict(json.loads((Path(run_dir) / "config.json").read_text()))

    # ------------------------------------------------------------------------------------------ the CLI
    @classmethod
    def add_arguments(cls, parser: argparse.ArgumentParser, defaults: bool = True) -> None:
        """One flag per setting (``--n-envs`` for ``n_envs``), with its help, type and choices, and ``--config``
        and ``--set``, which read settings from a file or one ``key=value``; with ``defaults`` False a flag not
        given takes the parser's ``argument_default``."""
        for setting in cls.settings():
            if not setting.has_flag:
                continue
            kwargs = dict(setting.flag)
            if defaults and kwargs.get("action") != "store_true":
                kwargs["default"] = setting.default
            parser.add_argument(flag_of(setting.name), **kwargs)
        parser.add_argument("--config", metavar="FILE", help="a YAML or JSON file of settings, flat by name as a run's "
                            "config.json writes them (n_envs: 8); a flag or --set given beside it wins")
        parser.add_argument("--set", action="append", metavar="KEY=VALUE", help="one setting by name, its value as "
                            "its flag reads it (repeatable; null: its default); a flag given beside it wins, and it "
                            "wins over --config")

    @classmethod
    def flags_table(cls) -> str:
        """Every setting's flag with its default and meaning, as a Markdown table (docs/training.md shows it)."""
        lines = ["| flag | default | meaning |", "|---|---|---|"]
        for setting in cls.settings():
            flag = flag_of(setting.name) if setting.has_flag else f"--set {setting.name}=..."
            if setting.flag.get("action") is argparse.BooleanOptionalAction:
                flag = f"{flag}` / `--no-{flag[2:]}"
            default = "mode preset" if setting.default is None and setting.name in ModePreset.__dataclass_fields__ else (
                "-" if setting.default is None else setting.default)
            meaning = setting.flag["help"].replace("|", "\\|")
            choices = setting.flag.get("choices")
            if choices:
                meaning += f" (one of: {', '.join(map(str, choices))})"
            lines.append(f"| `{flag}` | {default} | {meaning} |")
        return "\n".join(lines)

    @classmethod
    def parser(cls, prog: str = "train.py", description: str | None = None) -> argparse.ArgumentParser:
        parser = argparse.ArgumentParser(prog=prog, description=description)
        cls.add_arguments(parser)
        return parser

    #: Fields that ``--resume`` may set besides the evaluation fields: the budget (a new one, not below the agent
    #: steps done: a finished run is extended).
    RESUME_FIELDS = ("total_timesteps",)
    #: The flags that say where settings come from rather than set one (:meth:`add_arguments`).
    SOURCE_FLAGS = ("config", "set")

    def with_recipe(self, given: Collection[str]) -> "TrainConfig":
        """This configuration with its scenario's recipe (:mod:`~ee_formation_env.baselines.learned.recipes`)
        for every setting not in ``given`` (those the command line, --set or --config set); itself where no
        recipe applies."""
        recipe = recipe_for(self.scenario) if self.recipe == "board" else None
        if recipe is None or ("mode" in given and self.options.mode != recipe.mode):
            return self
        return self.with_settings({name: value for name, value in recipe.settings.items() if name not in given})

    def recipe_used(self) -> str:
        """Which settings this configuration trains with, in words: its scenario's recipe (:meth:`with_recipe`
        applied it: the recipe is set and the mode is the recipe's) or the flat defaults, and why."""
        recipe = recipe_for(self.scenario)
        if recipe is None:
            return "flat defaults (no preset for this scenario)"
        if self.recipe == "none":
            return "flat defaults (--recipe none)"
        if self.options.mode != recipe.mode:
            return f"flat defaults (--mode {self.options.mode} is not the mode of its preset, {recipe.describe()})"
        return f"{self.scenario}'s preset ({recipe.describe()})"

    @classmethod
    def _given(cls, argv: Sequence[str] | None) -> set[str]:
        """The settings ``argv``'s flags set (parsed as :meth:`from_args` parses it, defaults left out)."""
        parser = argparse.ArgumentParser(argument_default=argparse.SUPPRESS, add_help=False)
        cls.add_arguments(parser, defaults=False)
        return set(vars(parser.parse_known_args(argv)[0])) - set(cls.SOURCE_FLAGS)

    @classmethod
    def from_args(cls, argv: Sequence[str] | None = None, prog: str = "train.py",
                  description: str | None = None) -> "TrainConfig":
        """Parse command-line flags into a resolved configuration; a bad value is a parser error naming its flag
        (and the ``--config`` file or ``--set`` it came from). A flag wins over ``--set``, which wins over
        ``--config``, which wins over the recipe and the mode's preset."""
        parser = cls.parser(prog, description)
        namespace = vars(parser.parse_args(argv))
        path, assignments = namespace.pop("config"), namespace.pop("set") or []
        sources: dict[str, str] = {}  # setting -> the --config file or --set that gave its value
        try:
            given, settings = cls._given(argv), {setting.name: setting for setting in cls.settings()}
            written = read_settings_file(path, settings) if path is not None else {}
            sources.update((name, f"--config {path}") for name in written)
            for text in assignments:  # in order: a later --set of a name wins
                name, value = parse_assignment(text, settings)
                written[name], sources[name] = value, f"--set {text}"
            sources = {name: source for name, source in sources.items() if name not in given}
            values = {**namespace, **{name: written[name] for name in sources}}
            config = cls().with_settings(values)
            if not (config.resume or config.eval_only):
                config = config.with_recipe(given | set(sources))
            if config.resume or config.eval_only:  # the saved run's settings decide; only evaluation flags may change
                defaults = vars(parser.parse_args([]))
                allowed = (*cls.UNSAVED_FIELDS, *cls.EVALUATION_FIELDS, *(cls.RESUME_FIELDS if config.resume else ()))
                changed = [name for name, value in values.items() if value != defaults[name] and name not in allowed]
                if changed:
                    flag = "--resume" if config.resume else "--eval-only"
                    raise ValueError(f"{flag}: the run's saved configuration is used; drop "
                                     + ", ".join(flag_of(name) for name in changed))
            return config.resolved()
        except ValueError as error:
            parser.error(_with_source(str(error), sources))
            raise  # parser.error exits; this line is never reached


def _with_source(message: str, sources: Mapping[str, str]) -> str:
    """``message`` (starting with the flag it is about) prefixed with the ``--config`` file or ``--set`` that
    gave that setting its value, if one did."""
    match = re.match(r"--([a-z0-9-]+)", message)
    name = match.group(1).replace("-", "_") if match else None
    return f"{sources[name]}: {message}" if name in sources else message
