"""A training run from its configuration: the run folder, training with the chosen backend, the comparison.

:func:`train` is what ``python train.py`` and ``ee-formation train`` do with a resolved
:class:`~ee_formation_env.baselines.learned.config.TrainConfig`; :func:`evaluate_saved_run` is their
``--eval-only``. A run folder holds ``config.json`` (the configuration, the parsed scenario and the package
versions), the model and its observation normalization, TensorBoard logs, checkpoints, ``learning_curve.csv``,
``reference_returns.json``, ``timing.json`` and the comparison (``comparison.json``, ``.md``, ``.png``); its
marker and, while a command works on it, its lock (:mod:`~ee_formation_env.baselines.learned.run_folder`).
"""

from __future__ import annotations

import dataclasses
import platform
import shutil
import time
from pathlib import Path
from typing import Any

import ee_formation_env
from ee_formation_env.baselines.atomic_files import WriteRefused, refused
from ee_formation_env.baselines.learned.algorithms import algorithm
from ee_formation_env.baselines.extras import require
from ee_formation_env.baselines.learned.checkpoint import write_json
from ee_formation_env.baselines.learned.compare import compare, reference_gains, reference_returns, saved_scenario
from ee_formation_env.baselines.learned.config import TrainConfig
from ee_formation_env.baselines.learned.imitation import check_reference_run, reference_run
from ee_formation_env.baselines.learned.interruption import (RunStopped, StopSignal, TrainingInterrupted,
                                                             raise_on_signals, stop_on_signals)
from ee_formation_env.baselines.learned.run_folder import check_out, created_run_folder, has_resumable_state
from ee_formation_env.baselines.learned.run_lock import LOCK_NAME, holder_pid, lock_holder, run_lock
from ee_formation_env.baselines.learned.saved_run import (load_saved_config, model_from_checkpoint,
                                                          resume_checkpoint, write_saved_config)
from ee_formation_env.baselines.learned.segments import (TIMING, close_killed_segments, read_timing,
                                                         write_learning_curve, write_timing)
from ee_formation_env.baselines.learned.set_network import set_description
from ee_formation_env.baselines.learned.team import TEAM_PADDING_KEY, TeamPadding
from ee_formation_env.baselines.learned.training_env import EVAL_SEED_OFFSET, batched_env_factory
from ee_formation_env.worker_processes import exit_if_reimporting_main


def require_training_extras(config: TrainConfig, saved: dict[str, Any] | None = None) -> None:
    """Fail in one line naming the pip extra, before anything is created, if a needed package is missing.

    ``saved``: a saved run's configuration (``--eval-only``), whose backend decides what reloading its model needs.
    """
    backend = saved["backend"] if saved else config.backend
    modules = ["torch", "matplotlib"]  # the model, comparison.png
    if backend == "sb3":
        modules += ["stable_baselines3", "tensorboard"]  # SB3 logs to TensorBoard
        if not config.no_progress and not saved:
            modules += ["tqdm", "rich"]  # SB3's progress bar
        extras = "train"
    else:
        modules.append("ray.rllib")
        extras = "train,distributed"
    require(modules, extras, f"train.py (--backend {backend})")


def run_name(config: TrainConfig) -> str:
    """``<scenario>-<mode>-<algo>-<backend>-seed<seed>-<date>-<time>``: the default folder name under ``runs/``."""
    scenario = Path(str(config.scenario)).stem
    return (f"{scenario}-{config.options.mode}-{config.algo}-{config.backend}-seed{config.seed}-"
            f"{time.strftime('%Y%m%d-%H%M%S')}")


def train(config: TrainConfig) -> Path:
    """Train ``config`` (resolved), write every artefact of the run and compare it with the references;
    returns the run folder. ``config.resume`` continues a saved run instead (:func:`resume`).

    Everything is checked before the run folder is made: ``--out`` (:func:`~ee_formation_env.baselines.learned.
    run_folder.check_out`: a folder that holds files is refused unless ``overwrite``, which replaces only a run
    folder the project wrote and no live trainer holds), the scenario and the training env it builds (a mixed
    team trains with --backend sb3 only), the seeds, the extras. A run that fails before anything could be
    continued from leaves no folder behind. A SIGINT or SIGTERM stops training within a step, saves the model
    and raises :class:`TrainingInterrupted`; a worker or disk fault raises :class:`RunStopped`, one line."""
    exit_if_reimporting_main()  # a spawn child re-running an unguarded main script touches no run folder
    if config.resume:
        return resume(config)
    started = time.time()
    run_dir = Path(config.out) if config.out is not None else Path("runs") / run_name(config)
    check_out(run_dir, config.overwrite)
    scenario, padding = _validated_scenario(config)
    require_training_extras(config)
    saved = config.to_dict()
    saved["scenario_data"] = scenario.to_dict()
    if padding is not None:  # a mixed team: how evaluation pads each agent as training did
        saved[TEAM_PADDING_KEY] = padding.to_dict()
    saved["versions"] = package_versions()
    try:
        with created_run_folder(run_dir, config.overwrite, ee_formation_env.__version__):
            try:
                write_saved_config(run_dir, saved)
            except OSError as error:
                raise RunStopped(f"training: {refused(run_dir / 'config.json', error)}") from None
            print(f"training {config.algo} ({config.backend}, mode {config.options.mode}) on {config.scenario} for "
                  f"{config.total_timesteps} agent steps -> {run_dir}")
            print(f"recipe: {config.recipe_used()}; reference laws: {reference_gains(scenario)}", flush=True)
            return _train_and_compare(config, saved, run_dir, started)
    except RunStopped as stopped:
        if stopped.run_dir is not None or has_resumable_state(run_dir):
            raise
        left = "the run folder was left empty" if run_dir.exists() else "no run folder is left"
        raise RunStopped(f"{stopped.message}; nothing was saved, so {left}: the same command starts the run again",
                         details=stopped.details, signal_name=stopped.signal_name) from stopped


def resume(config: TrainConfig) -> Path:
    """Continue the run in ``config.resume`` from its newest intact checkpoint (or its saved final model, if an
    interruption saved one later) to its budget, with its saved configuration; then compare as a fresh run does.
    ``config.total_timesteps``, if given, is a new budget (not below the agent steps done): a finished run is
    extended to it, then compared again. A run whose training is complete but whose comparison is missing (a
    signal during the comparison) is compared only. The run folder is locked meanwhile."""
    started = time.time()
    run_dir = Path(config.resume)
    if not (run_dir / "config.json").is_file():
        raise ValueError(f"--resume: {run_dir / 'config.json'} not found")
    with run_lock(run_dir, "--resume"):
        saved, settings = load_saved_config(run_dir, "--resume", final_model=False)
        settings = dataclasses.replace(settings, resume=str(run_dir), out=str(run_dir),
                                       **{name: getattr(config, name) for name in TrainConfig.EVALUATION_FIELDS})
        if settings.backend != "sb3" or not algorithm(settings.algo).is_ppo:
            raise ValueError(f"--resume: runs of --backend sb3 --algo ppo only (this one: {settings.backend} "
                             f"{settings.algo}; SAC's replay buffer and RLlib's state are not checkpointed)")
        require_training_extras(settings)  # before the checkpoint's model is loaded
        steps, newest = resume_checkpoint(run_dir, saved)
        if config.total_timesteps is not None and config.total_timesteps != settings.total_timesteps:
            if config.total_timesteps < steps:
                raise ValueError(f"--total-timesteps: {config.total_timesteps} is below the {steps} agent steps "
                                 f"{run_dir} has done: a budget can only be lowered to the steps done, or raised")
            saved["total_timesteps"] = config.total_timesteps
            settings = dataclasses.replace(settings, total_timesteps=config.total_timesteps)
            extended = True
        else:
            extended = False
        read_timing(run_dir)  # a damaged timing.json is refused before anything runs
        if steps >= settings.total_timesteps and (run_dir / "comparison.json").is_file():
            raise ValueError(f"--resume: {run_dir} is complete ({steps} of {settings.total_timesteps} agent steps): "
                             "--total-timesteps N (more than that) extends it")
        if extended:  # the new budget is the run's own from now on, so that a later --resume keeps it
            write_saved_config(run_dir, saved)
        settings = dataclasses.replace(settings, scenario=saved_scenario(saved))  # as saved, not as the file is now
        if steps >= settings.total_timesteps:
            print(f"{run_dir}: training is complete ({steps} of {settings.total_timesteps} agent steps); running the "
                  "comparison", flush=True)
            model_from_checkpoint(run_dir, newest)
            # A kill after the last checkpoint but before the segment's end left it running and the learning
            # curve unwritten: end the segment as killed at the checkpoint, and draw the curve, as training would.
            timing = read_timing(run_dir)
            if timing["segments"] and timing["segments"][-1].get("running"):
                timing["segments"][-1]["agent_steps"] = steps  # the model's, saved after the segment's last write
            close_killed_segments(timing)
            write_timing(run_dir, timing)
            write_learning_curve(run_dir, timing["segments"])
            timing.setdefault("agent_steps", steps)
            return _compare_and_write(settings, saved, run_dir, timing, started)
        print(f"resuming {run_dir} from {newest.name} at {steps} of {settings.total_timesteps} agent steps")
        try:
            return _train_and_compare(settings, saved, run_dir, started, resume_from=newest)
        except RunStopped as stopped:
            if stopped.run_dir is not None:
                raise
            raise RunStopped(f"{stopped.message}; nothing new was saved", run_dir, "tries again",
                             details=stopped.details, signal_name=stopped.signal_name) from stopped


def _validated_scenario(config: TrainConfig) -> tuple[Any, TeamPadding | None]:
    """The parsed scenario and, for a mixed team, its padding (:mod:`~ee_formation_env.baselines.learned.team`),
    after building one copy of the training env: every geometric check runs here, before any folder or process
    exists. A mixed team trains with ``--backend sb3`` and without ``--imitate`` only. The training reset seeds
    must stay below the held-out evaluation seeds."""
    scenario = ee_formation_env.load_scenario(config.scenario)
    with batched_env_factory(dataclasses.replace(config, scenario=scenario))(num_envs=1) as probe:
        padding = probe.padding
    if padding is not None:
        team = f"scenario {scenario.name} is a mixed team ({', '.join(padding.kinds)})"
        if config.backend != "sb3":
            raise ValueError(f"--backend: {config.backend} cannot train a mixed team yet: {team}; use --backend sb3")
        if config.imitate not in (None, "none"):
            raise ValueError(f"--imitate: the imitation cannot start a mixed team's policy yet: {team}")
    run = reference_run(config.imitate or "none")
    if run is not None:
        check_reference_run(run, config, scenario)
        if config.out:  # before anything is removed: --overwrite of the reference would lose both runs
            reference, out = run.run_dir.resolve(), Path(config.out).resolve()
            if reference == out or reference in out.parents or out in reference.parents:
                raise ValueError(f"--imitate: {run.run_dir} is --out {config.out} or holds it (or is inside it): "
                                 "the reference run would be removed before it is read; choose another --out")
    if config.options.policy_network == "set":  # one robot and layout, slots kept by the features: refused here
        if padding is not None:
            raise ValueError(f"--policy-network: set shares one network over agents of one robot and layout; "
                             f"scenario {scenario.name} is a mixed team ({', '.join(padding.kinds)})")
        try:
            set_description(scenario, config.options.obs_features)
        except ValueError as error:
            raise ValueError(f"--policy-network: {str(error).partition(': ')[2]}") from None
    slots = config.n_envs * scenario.n_agents
    if slots > EVAL_SEED_OFFSET:  # too many whatever the seed: the env count is at fault
        seed = f" from --seed {config.seed}" if config.seed else ""
        raise ValueError(f"--n-envs: {config.n_envs} envs x {scenario.n_agents} agents = {slots} env slots, whose "
                         f"reset seeds{seed} would reach the held-out evaluation seeds ({EVAL_SEED_OFFSET} and up): "
                         f"expected at most {max((EVAL_SEED_OFFSET - config.seed) // scenario.n_agents, 1)}")
    if config.seed + slots > EVAL_SEED_OFFSET:
        raise ValueError(f"--seed: {config.seed} + {slots} env slots reaches the held-out evaluation seeds "
                         f"({EVAL_SEED_OFFSET} and up): expected at most {EVAL_SEED_OFFSET - slots}")
    return scenario, padding


def _train_and_compare(config: TrainConfig, saved: dict[str, Any], run_dir: Path, started: float,
                       resume_from: Path | None = None) -> Path:
    with stop_on_signals() as stop:
        if config.backend == "sb3":
            from ee_formation_env.baselines.learned.sb3_backend import train_sb3

            timing = train_sb3(config, run_dir, stop, resume_from)
        else:
            from ee_formation_env.baselines.learned.rllib_backend import train_rllib

            timing = train_rllib(config, run_dir, stop)
    if stop.requested:
        raise TrainingInterrupted(run_dir, stop.signal_name, int(timing.get("agent_steps", 0)))
    segment = (timing.get("segments") or [{}])[-1]
    if segment.get("faulted_training_episodes"):  # below the stop threshold, but never hidden
        reasons = "; ".join(f"{reason} ({count}x)" for reason, count in segment["fault_reasons"].items())
        print(f"{segment['faulted_training_episodes']} of {segment['training_episodes']} training episodes ended in "
              f"a physics fault: {reasons}", flush=True)
    return _compare_and_write(config, saved, run_dir, timing, started)


def _compare_and_write(config: TrainConfig, saved: dict[str, Any], run_dir: Path, timing: dict[str, Any],
                       started: float) -> Path:
    """The comparison phase, training complete: the reference lines, the comparison, ``timing.json``'s total.
    A SIGINT or SIGTERM here ends it at once (:class:`TrainingInterrupted`, phase "comparison"), and
    ``--resume`` then runs it alone; ``comparison.json`` is written last, so a run holding it is complete."""
    try:
        with raise_on_signals():
            references = run_dir / "reference_returns.json"
            try:
                write_json(references, reference_returns(saved))
            except OSError as error:
                raise refused(references, error) from None
            compare(config, saved, run_dir)
    except WriteRefused as error:
        raise RunStopped(f"comparison: {error}; training is complete", run_dir, "runs the comparison") from None
    except StopSignal as stopped:
        raise TrainingInterrupted(run_dir, stopped.signal_name, int(timing.get("agent_steps", 0)),
                                  phase="comparison") from None
    except RunStopped as stopped:
        if stopped.run_dir is not None:
            raise
        raise RunStopped(f"{stopped.message}; training is complete", run_dir, "runs the comparison",
                         details=stopped.details, signal_name=stopped.signal_name) from stopped
    timing["total_seconds"] = time.time() - started  # training, reference lines and evaluation
    write_json(run_dir / TIMING, timing)
    print(f"wrote {run_dir}/comparison.md, comparison.json, comparison.png")
    return run_dir


def evaluate_saved_run(config: TrainConfig) -> dict[str, Any]:
    """``--eval-only RUN_DIR``: the comparison of a saved run on the scenario saved with it, with the evaluation
    settings of ``config``, written into ``RUN_DIR/evaluations/<date>-<time>/`` (the run's own results stay).
    A run another process is training (its lock held) is refused, naming that process; the run's files are then
    checked (:mod:`~ee_formation_env.baselines.learned.saved_run`)."""
    exit_if_reimporting_main()
    run_dir = Path(config.eval_only)
    holder = lock_holder(run_dir)  # first: a run in training has no final model yet, which is no damage
    if holder is not None:
        pid = holder_pid(holder)
        trainer = (f"pid {pid}" if pid is not None else
                   f"an unknown process (its lock file {run_dir / LOCK_NAME} has no pid)")
        raise ValueError(f"--eval-only: {run_dir} is being trained by {trainer}: wait for it to end, or stop it "
                         "(its model is saved when it stops), then evaluate it")
    saved, _ = load_saved_config(run_dir, "--eval-only", final_model=True)
    require_training_extras(config, saved)
    results_dir = run_dir / "evaluations" / time.strftime("%Y%m%d-%H%M%S")
    suffix = 1
    while results_dir.exists():
        suffix += 1
        results_dir = results_dir.with_name(f"{results_dir.name.split('.')[0]}.{suffix}")
    try:
        comparison = compare(config, saved, run_dir, results_dir)
    except WriteRefused as error:  # the run's own files are only read: only the new evaluation folder goes
        shutil.rmtree(results_dir, ignore_errors=True)
        try:
            results_dir.parent.rmdir()  # evaluations/, if this was its first evaluation
        except OSError:
            pass
        raise RunStopped(f"--eval-only: {error}; the run is unchanged (its partial evaluation removed): the same "
                         "command evaluates it again") from None
    print(f"wrote {results_dir}/comparison.md, comparison.json, comparison.png")
    return comparison


def package_versions() -> dict[str, str]:
    """Versions of Python and the packages a run depends on, for its ``config.json``."""
    from importlib import metadata

    versions = {"python": platform.python_version()}
    for package in ("numpy", "pybullet", "pettingzoo", "gymnasium", "stable-baselines3", "torch", "ray"):
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            pass
    return versions
