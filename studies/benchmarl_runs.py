"""BenchMARL runs on the training tasks: train for a wall-clock budget, evaluate with the project's metrics, export.

    python -m studies.benchmarl_runs --algorithm mappo --mode torque --minutes 30 --seed 0
    python -m studies.benchmarl_runs --algorithm mappo --mode torque --settings sb3 --minutes 30 --seed 0
    python -m studies.benchmarl_runs --algorithm ippo --mode torque --settings project --minutes 30 --seed 0
    python -m studies.benchmarl_runs --algorithm ippo --mode residual --minutes 10 --scenario planar_square
    python -m studies.benchmarl_runs --algorithm mappo --mode torque --settings project --frames 1900000 --seed 0
    python -m studies.benchmarl_runs --algorithm ippo --settings project --frames 750000 --task-set train_episode_seconds=30
    python -m studies.benchmarl_runs --algorithm masac --mode torque --minutes 30 --out results/benchmarl/masac
    python -m studies.benchmarl_runs --plot RUN_DIR [RUN_DIR ...] --figure curves.png   (no training)
    python -m studies.benchmarl_runs --plot RUN_DIR [RUN_DIR ...] --bands --figure curves.png   (median, band over seeds)

Needs the ``torchrl`` extra. The task is
:class:`~ee_formation_env.baselines.learned.benchmarl_task.EEFormationTrainingTask` with ``--mode`` and its
presets (the options of ``docs/training.md``, "The training options in BenchMARL"); the experiment uses the
recommended on-policy layout of that page (64 natively batched copies, 8,000 frames per batch) and the learning
settings ``--settings`` (:data:`SETTINGS`: BenchMARL's defaults, 4 epochs over minibatches of 2,000 frames; or
``sb3``, train.py's torque preset's where BenchMARL has the knob; off-policy algorithms keep BenchMARL's layout;
or ``project``: every config from the project's YAML files,
:mod:`~ee_formation_env.baselines.learned.benchmarl_configs`, with the task's observation normalization and
reward scale, advantage normalization and the mode preset's learning-rate decay), csv logging, no BenchMARL
evaluation (its test env is a training env). Training stops at the first batch collected after ``--minutes``
of wall time, or ``--frames`` frames, before that batch's update (:class:`BudgetStop`); then the deterministic policy runs the held-out seeds 10,000 + k through
:func:`~ee_formation_env.baselines.learned.benchmarl_task.evaluate_benchmarl_policy`, and the folder ``--out``
gets ``evaluation.json`` (the summary, every episode, budget and wall time), the learning curve
``curve.csv`` (frames, mean training return per batch) and the exported actor (``policy/``).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence



@dataclass(frozen=True)
class RunSettings:
    """The learning settings a run changes from BenchMARL's YAML defaults (the rest stay BenchMARL's).
    ``epochs``, ``minibatch_frames``, ``frames_per_batch`` and ``n_envs`` apply to on-policy algorithms only
    (off-policy ones keep BenchMARL's layout); ``lmbda`` too."""

    lr: float = 5e-5  # Adam learning rate (BenchMARL's default)
    lmbda: float = 0.9  # GAE lambda (BenchMARL's default)
    initial_std: float = 1.0  # the actor's initial standard deviation before the tanh squash (biased softplus)
    epochs: int = 4  # passes over each collected batch
    minibatch_frames: int = 2_000  # frames (env steps, all agents) per gradient step
    frames_per_batch: int = 8_000  # frames collected per iteration
    n_envs: int = 64  # natively batched env copies
    lr_decay: bool = False  # decay the learning rate linearly to 0 over the wall-clock budget (SB3's schedule)

    def __post_init__(self) -> None:
        if not isinstance(self.lr_decay, bool):
            raise TypeError(f"lr_decay: expected True or False, got {self.lr_decay!r}")
        for name, expected, valid in (("lr", "a learning rate > 0", lambda x: x > 0),
                                      ("lmbda", "a value in [0, 1]", lambda x: 0 <= x <= 1),
                                      ("initial_std", "a standard deviation > 0", lambda x: x > 0)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise TypeError(f"{name}: expected a number ({expected}), got {type(value).__name__} {value!r}")
            if not (math.isfinite(value) and valid(value)):
                raise ValueError(f"{name}: expected {expected}, got {value!r}")
        for name in ("epochs", "minibatch_frames", "frames_per_batch", "n_envs"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name}: expected an integer >= 1, got {value!r}")
        if self.minibatch_frames > self.frames_per_batch:
            raise ValueError(f"minibatch_frames: expected at most frames_per_batch ({self.frames_per_batch}), "
                             f"got {self.minibatch_frames}")


#: Named settings: ``benchmarl``, BenchMARL's defaults with the recommended batched layout; ``sb3``, the
#: settings of train.py's torque preset where BenchMARL has the knob (Adam 3e-4, GAE 0.95, initial standard
#: deviation e^-2 ~ 0.14, 10 epochs over small minibatches), on the same layout, at a constant learning rate;
#: ``sb3-decay``, those with the preset's linear decay of the learning rate to 0 (over the wall-clock budget).
#: Differences that remain: no observation, reward or advantage normalization, the tanh squash. The fourth name,
#: :data:`PROJECT_SETTINGS`, is not a RunSettings: its values live in the project's BenchMARL YAML files.
SETTINGS: dict[str, RunSettings] = {
    "benchmarl": RunSettings(),
    "sb3": RunSettings(lr=3e-4, lmbda=0.95, initial_std=0.14, epochs=10, minibatch_frames=400),
    "sb3-decay": RunSettings(lr=3e-4, lmbda=0.95, initial_std=0.14, epochs=10, minibatch_frames=400, lr_decay=True),
}


PROJECT_SETTINGS = "project"
SETTINGS_NAMES = (*SETTINGS, PROJECT_SETTINGS)

try:  # the torchrl extra; without it the module imports, and run() fails on its own imports
    from benchmarl.experiment.callback import Callback as _Callback
except ImportError:  # pragma: no cover
    _Callback = object


class BudgetStop(Exception):
    """Raised by :class:`BudgetCallback` to end ``Experiment.run`` at a batch boundary."""


class BudgetCallback(_Callback):
    """A BenchMARL callback that records (frames, mean reward per agent step of the batch, wall s) per batch in
    ``curve`` (the env's reward: the batch's divided by the task's ``reward_scale``, or the task's tally under
    ``reward_normalization``) and stops the run at the
    first batch collected after the budget: ``seconds`` of wall time, or, with ``frames`` given, that many frames
    (then ``seconds`` is not used). With ``lr`` given, it sets every optimizer's learning rate to
    ``lr * (1 - spent)`` before each batch's update, ``spent`` the budget's used fraction: of the frames (the
    same schedule on any machine, so a seed's run is repeatable) or of the wall time (a schedule that follows
    the machine's speed and load, so two runs of one seed differ from the first update on). Module-level,
    because BenchMARL pickles an experiment's callbacks."""

    def __init__(self, seconds: float, curve: list[tuple[int, float, float]], lr: float | None = None,
                 reward_scale: float = 1.0, frames: int | None = None):
        super().__init__()
        self.seconds, self.curve, self.started, self.lr = seconds, curve, time.time(), lr
        self.reward_scale, self.frames = reward_scale, frames

    def on_setup(self) -> None:
        self.started = time.time()

    def on_batch_collected(self, batch: Any) -> None:
        experiment = self.experiment
        env_reward = experiment.task.take_env_reward()  # with reward normalization: the env's, tallied
        if env_reward is None:
            rewards = [batch.get(("next", group, "reward")).float().mean().item() / self.reward_scale
                       for group in experiment.group_map]
            env_reward = sum(rewards) / len(rewards)
        elapsed = time.time() - self.started
        self.curve.append((int(experiment.total_frames), env_reward, elapsed))
        if self.frames is not None:
            spent = experiment.total_frames / self.frames
            if spent >= 1.0:
                raise BudgetStop(f"frame budget of {self.frames:,} frames reached")
        else:
            spent = elapsed / self.seconds
            if spent >= 1.0:
                raise BudgetStop(f"wall-clock budget of {self.seconds:.0f} s reached")
        if self.lr is not None:
            for optimizers in experiment.optimizers.values():
                for optimizer in optimizers.values():
                    for group in optimizer.param_groups:
                        group["lr"] = self.lr * (1.0 - spent)


#: The actor models a run can use: BenchMARL's MLP on the flat observation, or the project's masked Deepsets on
#: the task's set observations (``observation_sets``, without the observation normalization, whose statistics
#: are per agent), which acts for any team size; the critic is the MLP either way.
MODELS = ("mlp", "deepsets")


def _configs(algorithm: str, mode: str, settings: RunSettings | str, model: str = "mlp"
             ) -> tuple[Any, Any, Any, dict[str, Any], Any]:
    """(experiment config, algorithm config, actor model config, task config, learning rate to decay or None) of
    a run: the project's YAML files for :data:`PROJECT_SETTINGS`, else BenchMARL's defaults with ``settings``;
    ``model`` (:data:`MODELS`) ``deepsets`` needs the project's settings."""
    if model not in MODELS:
        raise ValueError(f"model: expected one of {list(MODELS)}, got {model!r}")
    if model != "mlp" and settings != PROJECT_SETTINGS:
        raise ValueError(f"model: {model!r} is the project's model; it runs with settings {PROJECT_SETTINGS!r}")
    from benchmarl.experiment import ExperimentConfig
    from benchmarl.models.mlp import MlpConfig

    from ee_formation_env.baselines.learned import benchmarl_configs
    from ee_formation_env.baselines.learned.modes import training_mode

    on_policy = benchmarl_configs.benchmarl_algorithm(algorithm).on_policy
    if settings == PROJECT_SETTINGS:
        config = benchmarl_configs.experiment_config(algorithm)
        decays = training_mode(mode).preset.ppo.learning_rate_decay and on_policy
        task = benchmarl_configs.task_config(mode)
        if model == "deepsets":
            task.update(observation_normalization=False, observation_sets=True,
                        global_state=True)  # the MLP critic reads the flat state, not the nested set observations
        return (config, benchmarl_configs.algorithm_config(algorithm), benchmarl_configs.model_config(model), task,
                config.lr if decays else None)
    if not isinstance(settings, RunSettings):
        raise ValueError(f"settings: expected a RunSettings or {PROJECT_SETTINGS!r}, got {settings!r}")
    config = ExperimentConfig.get_from_yaml()
    config.lr = settings.lr
    if on_policy:
        config.on_policy_n_envs_per_worker = settings.n_envs
        config.on_policy_collected_frames_per_batch = settings.frames_per_batch
        config.on_policy_n_minibatch_iters = settings.epochs
        config.on_policy_minibatch_size = settings.minibatch_frames
    algorithm_config = benchmarl_configs.algorithm_config_class(algorithm, project=False).get_from_yaml()
    algorithm_config.scale_mapping = f"biased_softplus_{settings.initial_std}"
    if on_policy:
        algorithm_config.lmbda = settings.lmbda
    return (config, algorithm_config, MlpConfig.get_from_yaml(), {"mode": mode},
            settings.lr if settings.lr_decay else None)


def run(algorithm: str, scenario: str, mode: str, minutes: float | None, seed: int, out: Path, episodes: int = 10,
        episode_seconds: float | None = None, settings: RunSettings | str = SETTINGS["benchmarl"],
        frames: int | None = None, model: str = "mlp", task_overrides: Mapping[str, Any] | None = None,
        algorithm_overrides: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Train, evaluate and export one run into ``out``; the evaluation record. The budget: ``minutes`` of wall
    time, or ``frames`` frames (then ``minutes`` is None: :class:`BudgetCallback`). ``episode_seconds``: the
    evaluation episodes' length (default: the scenario's; training uses the mode's training length);
    ``settings``: the learning settings (:data:`SETTINGS`, or :data:`PROJECT_SETTINGS`); ``model``: the actor's
    (:data:`MODELS`); ``task_overrides``: task config keys set over the settings' (training options such as
    ``train_episode_seconds``, transforms, scenario overrides), checked with the task before training starts;
    ``algorithm_overrides``: fields of the algorithm's config set over the settings' (e.g. ``orthogonal_init``),
    each checked to be one of its fields."""
    if (minutes is None) == (frames is None):
        raise ValueError(f"budget: expected minutes or frames, not both or neither (got {minutes!r}, {frames!r})")
    import torch
    from benchmarl.experiment import Experiment

    from ee_formation_env.baselines.learned.benchmarl_task import (EEFormationTrainingTask, evaluate_benchmarl_policy,
                                                                   export_benchmarl_policy)
    from ee_formation_env.scenario_sets import HELD_OUT_SEED_OFFSET

    config, algorithm_config, actor_model, task_config, decayed_lr = _configs(algorithm, mode, settings, model)
    if task_overrides is not None:
        if not isinstance(task_overrides, Mapping):
            raise TypeError(f"task_overrides: expected a dict of task config keys, got {type(task_overrides).__name__}")
        if "mode" in task_overrides:
            raise ValueError("task_overrides: 'mode' is the run's mode argument, not an override")
        task_config = {**task_config, **task_overrides}
    if algorithm_overrides is not None:
        if not isinstance(algorithm_overrides, Mapping):
            raise TypeError(f"algorithm_overrides: expected a dict of {type(algorithm_config).__name__} fields, got "
                            f"{type(algorithm_overrides).__name__}")
        fields = {field.name for field in dataclasses.fields(algorithm_config)}
        unknown = sorted(set(algorithm_overrides) - fields)
        if unknown:
            raise ValueError(f"algorithm_overrides: {unknown[0]!r} is not a field of {type(algorithm_config).__name__} "
                             f"(fields: {sorted(fields)})")
        algorithm_config = dataclasses.replace(algorithm_config, **algorithm_overrides)
    task = EEFormationTrainingTask[scenario.upper()].get_task(  # checked before any env is built
        {**task_config, **({} if episode_seconds is None else {"episode_seconds": episode_seconds})})
    torch.set_num_threads(1)  # the env copies and the update share the 2 cores better this way
    from ee_formation_env.baselines.learned import benchmarl_configs

    critic_model = benchmarl_configs.model_config("mlp") if model != "mlp" else actor_model
    config.max_n_frames, config.max_n_iters = 10**10, None  # the budget callback stops it
    config.loggers, config.evaluation, config.render = ["csv"], False, False
    config.checkpoint_at_end, config.create_json = False, False
    out.mkdir(parents=True, exist_ok=True)
    config.save_folder = str(out)
    curve: list[tuple[int, float, float]] = []
    experiment = Experiment(task=task, algorithm_config=algorithm_config, model_config=actor_model,
                            critic_model_config=critic_model, seed=seed, config=config,
                            callbacks=[BudgetCallback(math.inf if minutes is None else minutes * 60.0, curve,
                                                      decayed_lr, task.transforms().reward_scale, frames)])
    started = time.time()
    try:
        experiment.run()
    except BudgetStop as stop:  # BenchMARL closes the run and prints "Experiment failed ...": this stop
        print(f"training stopped: {stop} (BenchMARL's 'Experiment failed' line above is this stop)", flush=True)
    train_seconds = time.time() - started
    n_agents = sum(len(agents) for agents in experiment.group_map.values())
    evaluation = evaluate_benchmarl_policy(experiment, episodes=episodes, seed=HELD_OUT_SEED_OFFSET)
    evaluation["per_episode"] = [{k: v for k, v in e.items() if k != "trajectory"} for e in evaluation["per_episode"]]
    export_benchmarl_policy(experiment, out / "policy")
    with (out / "curve.csv").open("w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(["frames", "agent_steps", "mean_reward_per_step", "wall_seconds"])
        writer.writerows((frames, frames * n_agents, reward, wall) for frames, reward, wall in curve)
    record = {"algorithm": algorithm, "scenario": scenario, "mode": mode, "model": model, "seed": seed,
              "minutes": minutes,
              "frame_budget": frames,
              "settings": settings if isinstance(settings, str) else asdict(settings),
              "task_config": task.config, "algorithm_overrides": dict(algorithm_overrides or {}),
              "train_seconds": train_seconds, "frames": int(experiment.total_frames),
              "agent_steps": int(experiment.total_frames) * n_agents, "iterations": experiment.n_iters_performed,
              "evaluation": evaluation}
    (out / "evaluation.json").write_text(json.dumps(record, indent=1, default=float), encoding="utf-8")
    return record


#: The BenchMARL scalars a learning-curve figure shows: (csv-logger file pattern, axis label, log scale).
CURVE_SCALARS = (("collection_*_info_formation_error.csv", "training formation error (m² or m)", True),
                 ("train_*_entropy.csv", "policy entropy (nats)", False))


def _scalar(run_dir: Path, pattern: str) -> list[float]:
    """A BenchMARL csv-logger scalar of the run in ``run_dir``, one value per iteration (empty if absent)."""
    files = sorted(path for path in run_dir.glob(f"*/*/scalars/{pattern}") if "_loss_" not in path.name)
    if not files:
        return []
    with files[0].open(newline="", encoding="utf-8") as handle:
        return [float(row[1]) for row in csv.reader(handle)]


def _run_label(record: Mapping[str, Any]) -> str:
    """A run's algorithm, mode and settings (the name of its :data:`SETTINGS` entry, or ``custom``)."""
    saved = record.get("settings", {})
    if isinstance(saved, str):
        settings = saved
    else:
        used = {**asdict(RunSettings()), **saved}  # a knob a run predates: its default
        settings = next((name for name, named in SETTINGS.items() if asdict(named) == used), "custom")
    return f"{record['algorithm']} {record['mode']}, {settings} settings"


def seed_band(steps: Sequence[float], curves: Sequence[Sequence[float]]) -> tuple[Any, Any, Any, Any] | None:
    """One quantity of several runs (seeds) as (steps, median, smallest, largest) over the runs, each run first
    averaged over a running window of 2 % of its values (batch-to-batch noise would hide the band) and all cut
    to the shortest; None when a run has no values."""
    import numpy as np

    length = min(len(curve) for curve in curves)
    if length == 0:
        return None
    window = max(1, length // 50)
    kernel = np.ones(window) / window
    values = np.array([np.convolve(np.asarray(curve[:length], dtype=float), kernel, mode="valid") for curve in curves])
    return np.asarray(steps[window - 1:length]), np.median(values, axis=0), values.min(axis=0), values.max(axis=0)


def plot_runs(run_dirs: Sequence[Path], figure: Path, bands: bool = False) -> Path:
    """The learning curves of finished runs (their ``curve.csv`` and BenchMARL scalars) against agent steps:
    the mean reward per agent step, the training formation error and the policy's entropy. One line per run,
    labelled with its algorithm, settings, seed and held-out success; with ``bands``, one line per
    algorithm/mode/settings, the median over its runs (seeds) with the band from their smallest to their
    largest value, labelled with the seeds and each one's held-out success (runs of one group are cut to
    the shortest; each run's values first averaged over a running window of 2 % of its batches)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from studies._common import save_figure

    groups: dict[str, list[tuple[dict[str, Any], list[float], list[list[float]]]]] = {}
    for run_dir in run_dirs:
        record = json.loads((run_dir / "evaluation.json").read_text(encoding="utf-8"))
        with (run_dir / "curve.csv").open(newline="", encoding="utf-8") as handle:
            rows = list(csv.DictReader(handle))
        steps = [int(row["agent_steps"]) / 1e6 for row in rows]
        curves = [[float(row["mean_reward_per_step"]) for row in rows]]
        curves += [_scalar(run_dir, pattern)[:len(steps)] for pattern, _, _ in CURVE_SCALARS]
        key = _run_label(record) if bands else str(len(groups))  # a run given twice: drawn twice
        groups.setdefault(key, []).append((record, steps, curves))
    fig, axes = plt.subplots(1, 1 + len(CURVE_SCALARS), figsize=(5 * (1 + len(CURVE_SCALARS)), 3.8))
    for key, runs in groups.items():
        if not bands:
            ((record, steps, curves),) = runs
            label = (f"{_run_label(record)}, seed {record['seed']}: "
                     f"{record['evaluation']['success_rate']:.0%} success")
            for axis, values in zip(axes, curves):
                axis.plot(steps[:len(values)], values, label=label)
            continue
        ordered = sorted(runs, key=lambda run: run[0]["seed"])
        label = (f"{key}: seeds {', '.join(str(run[0]['seed']) for run in ordered)}, success "
                 f"{' / '.join(format(100 * run[0]['evaluation']['success_rate'], '.0f') for run in ordered)} %")
        for index, axis in enumerate(axes):
            banded = seed_band(runs[0][1], [curves[index] for _, _, curves in runs])
            if banded is None:
                continue
            steps, median, low, high = banded
            line, = axis.plot(steps, median, label=label)
            axis.fill_between(steps, low, high, color=line.get_color(), alpha=0.2)
    axes[0].set(ylabel="mean reward per agent step")
    for axis, (_, title, log) in zip(axes[1:], CURVE_SCALARS):
        axis.set(ylabel=title, yscale="log" if log else "linear")
    for axis in axes:
        axis.set(xlabel="agent steps (millions)")
    axes[0].legend(fontsize=6, loc="lower right")
    figure.parent.mkdir(parents=True, exist_ok=True)
    return save_figure(fig, figure)


def main(argv: Sequence[str] | None = None) -> int:
    from ee_formation_env.baselines.learned.algorithms import algorithm_names
    from ee_formation_env.scenario_sets import HELD_OUT_SEED_OFFSET

    parser = argparse.ArgumentParser(prog="python -m studies.benchmarl_runs", description=__doc__.split("\n\n")[0])
    parser.add_argument("--algorithm", default="mappo", choices=algorithm_names("benchmarl"),
                        help="the MARL algorithm (default mappo)")
    parser.add_argument("--scenario", default="planar_square", help="built-in scenario")
    from ee_formation_env.baselines.learned.modes import mode_names

    parser.add_argument("--mode", default="torque", choices=mode_names(), help="training mode (default torque)")
    budget = parser.add_mutually_exclusive_group()
    budget.add_argument("--minutes", type=float, default=None, help="wall-clock training budget (default 30)")
    budget.add_argument("--frames", type=int, default=None,
                        help="a frame budget instead (frames = env steps of all copies; agent steps = frames x "
                             "agents): the learning-rate decay follows it, so a seed's run repeats on any machine")
    parser.add_argument("--seed", type=int, default=0, help="training seed")
    parser.add_argument("--settings", default="benchmarl", choices=sorted(SETTINGS_NAMES),
                        help="learning settings: benchmarl (its defaults), sb3 (train.py's torque preset's), "
                             "sb3-decay (those with its linear learning-rate decay) or project (the project's "
                             "BenchMARL YAML files: normalized observations and advantages, scaled rewards)")
    parser.add_argument("--model", default="mlp", choices=MODELS,
                        help="the actor: mlp, or deepsets (the project's set model on the neighbour slots, for any team "
                             "size; with --settings project)")
    parser.add_argument("--task-set", nargs="+", default=[], metavar="KEY=VALUE",
                        help="task config keys over the settings' (VALUE in JSON), e.g. --task-set "
                             "train_episode_seconds=30 reward_normalization=false: training options, transforms "
                             "or scenario overrides, checked before training")
    parser.add_argument("--algorithm-set", nargs="+", default=[], metavar="KEY=VALUE",
                        help="fields of the algorithm's config over the settings' (VALUE in JSON), e.g. "
                             "--algorithm-set orthogonal_init=true share_param_critic=false")
    parser.add_argument("--episodes", type=int, default=10, help=f"held-out evaluation episodes (seeds {HELD_OUT_SEED_OFFSET}+)")
    parser.add_argument("--out", type=Path, default=None, help="default results/benchmarl/<algorithm>-<mode>-<scenario>[-<settings>]-seed<k>")
    parser.add_argument("--plot", type=Path, nargs="+", default=None, metavar="RUN_DIR",
                        help="no training: draw the learning curves of these finished runs into --figure")
    parser.add_argument("--figure", type=Path, default=Path("results/benchmarl/curves.png"), help="with --plot")
    parser.add_argument("--bands", action="store_true",
                        help="with --plot: one median curve per algorithm/mode/settings, the band over its seeds")
    args = parser.parse_args(argv)
    if args.bands and args.plot is None:
        parser.error("--bands: draws finished runs, so only with --plot RUN_DIR ...")
    if args.plot is not None:
        missing = [str(d) for d in args.plot if not (d / "evaluation.json").is_file() or not (d / "curve.csv").is_file()]
        if missing:
            parser.error(f"--plot: not a finished run (no evaluation.json and curve.csv): {missing}")
        print(f"wrote {plot_runs(args.plot, args.figure, bands=args.bands)}")
        return 0
    from ee_formation_env.builtin import BUILTIN_SCENARIOS

    if args.scenario not in BUILTIN_SCENARIOS:
        parser.error(f"--scenario: unknown {args.scenario!r}; available: {sorted(BUILTIN_SCENARIOS)}")
    if args.frames is None and args.minutes is None:
        args.minutes = 30.0
    if args.minutes is not None and not args.minutes > 0:
        parser.error("--minutes: expected a duration > 0")
    if args.frames is not None and args.frames < 1:
        parser.error("--frames: expected an integer >= 1")
    if args.episodes < 1:
        parser.error("--episodes: expected an integer >= 1")
    if args.model != "mlp" and args.settings != PROJECT_SETTINGS:
        parser.error(f"--model: {args.model} runs with --settings {PROJECT_SETTINGS}")
    from ee_formation_env.baselines.evaluate import parse_key_values

    try:
        overrides = {flag: parse_key_values(pairs, flag)
                     for flag, pairs in (("--task-set", args.task_set), ("--algorithm-set", args.algorithm_set))}
    except ValueError as error:
        parser.error(str(error))
    tag = ("" if args.settings == "benchmarl" else f"-{args.settings}") + ("" if args.model == "mlp" else f"-{args.model}")
    out = args.out or Path("results/benchmarl") / f"{args.algorithm}-{args.mode}-{args.scenario}{tag}-seed{args.seed}"
    record = run(args.algorithm, args.scenario, args.mode, args.minutes, args.seed, out, args.episodes,
                 settings=SETTINGS.get(args.settings, args.settings), frames=args.frames, model=args.model,
                 task_overrides=overrides["--task-set"] or None,
                 algorithm_overrides=overrides["--algorithm-set"] or None)
    from ee_formation_env.baselines.metrics import format_table

    print(format_table({f"{args.algorithm} ({args.mode})": record["evaluation"]}))
    print(f"{record['agent_steps']:,} agent steps in {record['train_seconds']:.0f} s; wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
