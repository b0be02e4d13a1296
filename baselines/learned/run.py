"""A training run from its configuration: the run folder, training with the chosen backend, the comparison.

:func:`train` is what ``python train.py`` and ``ee-formation train`` do with a resolved
:class:`~ee_formation_env.baselines.learned.config.TrainConfig`; :func:`evaluate_saved_run` is their
``--eval-only``. A run folder holds ``config.json`` (the configuration, the parsed scenario and the package
versions), the model and its observation normalization, TensorBoard logs, checkpoints, ``learning_curve.csv``,
``reference_returns.json``, ``timing.json`` and the comparison (``comparison.json``, ``.md``, ``.png``).
"""

from __future__ import annotations

import dataclasses
import platform
import shutil
import time
from pathlib import Path
from typing import Any

import ee_formation_env
from ee_formation_env.baselines.extras import require
from ee_formation_env.baselines.learned.checkpoint import checkpoints, read_json, write_json
from ee_formation_env.baselines.learned.compare import compare, reference_returns, saved_scenario
from ee_formation_env.baselines.learned.config import TrainConfig
from ee_formation_env.baselines.learned.interruption import TrainingInterrupted, stop_on_signals
from ee_formation_env.baselines.learned.policy import MODEL_FOLDER


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
    return (f"{scenario}-{config.mode}-{config.algo}-{config.backend}-seed{config.seed}-"
            f"{time.strftime('%Y%m%d-%H%M%S')}")


def train(config: TrainConfig) -> Path:
    """Train ``config`` (resolved), write every artefact of the run and compare it with the references;
    returns the run folder. ``config.resume`` continues a saved run instead (:func:`resume`).

    Everything is checked before the run folder is made: the scenario builds and validates, a folder that already
    holds files is refused unless ``overwrite`` (then replaced once the rest has validated). A SIGINT or SIGTERM
    stops training within a step, saves the model and raises :class:`TrainingInterrupted`."""
    if config.resume:
        return resume(config)
    started = time.time()
    run_dir = Path(config.out) if config.out else Path("runs") / run_name(config)
    if run_dir.exists() and (not run_dir.is_dir() or any(run_dir.iterdir())) and not config.overwrite:
        hint = (f"--resume {run_dir} continues it, " if (run_dir / "config.json").is_file() else "")
        raise ValueError(f"--out: {run_dir} already holds files: {hint}--overwrite replaces it, or choose another "
                         "--out")
    scenario = _validated_scenario(config)
    require_training_extras(config)
    if config.overwrite and run_dir.exists():
        shutil.rmtree(run_dir) if run_dir.is_dir() else run_dir.unlink()
    run_dir.mkdir(parents=True)
    saved = config.to_dict()
    saved["scenario_data"] = scenario.to_dict()
    saved["versions"] = package_versions()
    write_json(run_dir / "config.json", saved)
    print(f"training {config.algo} ({config.backend}, mode {config.mode}) on {config.scenario} for "
          f"{config.total_timesteps} agent steps -> {run_dir}")
    return _train_and_compare(config, saved, run_dir, started)


def resume(config: TrainConfig) -> Path:
    """Continue the run in ``config.resume`` from its newest complete checkpoint (or its saved final model, if an
    interruption saved one later) to its budget, with its saved configuration; then compare as a fresh run does."""
    started = time.time()
    run_dir = Path(config.resume)
    saved = read_json(run_dir / "config.json", "--resume")
    settings = dataclasses.replace(TrainConfig.from_dict(saved), resume=str(run_dir), out=str(run_dir),
                                   **{name: getattr(config, name) for name in TrainConfig.EVALUATION_FIELDS})
    settings = settings.resolved()
    if settings.backend != "sb3" or settings.algo != "ppo":
        raise ValueError(f"--resume: runs of --backend sb3 --algo ppo only (this one: {settings.backend} "
                         f"{settings.algo}; SAC's replay buffer and RLlib's state are not checkpointed)")
    candidates = [*checkpoints(run_dir), run_dir / MODEL_FOLDER]
    states = [(read_json(path / "state.json", "--resume")["agent_steps"], path) for path in candidates
              if (path / "state.json").is_file()]
    if not states:
        raise ValueError(f"--resume: {run_dir} holds no complete checkpoint to continue from")
    steps, newest = max(states, key=lambda item: item[0])
    if steps >= settings.total_timesteps and (run_dir / "comparison.json").is_file():
        raise ValueError(f"--resume: {run_dir} is complete ({steps} of {settings.total_timesteps} agent steps)")
    require_training_extras(settings)
    print(f"resuming {run_dir} from {newest.name} at {steps} of {settings.total_timesteps} agent steps")
    settings = dataclasses.replace(settings, scenario=saved_scenario(saved))  # as saved, not as the file is now
    return _train_and_compare(settings, saved, run_dir, started, resume_from=newest)


def _validated_scenario(config: TrainConfig) -> Any:
    """The parsed scenario, after building the training env once: every geometric check runs here, before any
    folder or process exists."""
    scenario = ee_formation_env.load_scenario(config.scenario)
    ee_formation_env.parallel_env(scenario, **config.training_overrides()).close()
    return scenario


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
    write_json(run_dir / "reference_returns.json", reference_returns(saved))
    compare(config, saved, run_dir)
    timing["total_seconds"] = time.time() - started  # training, reference lines and evaluation
    write_json(run_dir / "timing.json", timing)
    print(f"wrote {run_dir}/comparison.md, comparison.json, comparison.png")
    return run_dir


def evaluate_saved_run(config: TrainConfig) -> dict[str, Any]:
    """``--eval-only RUN_DIR``: the comparison of a saved run on the scenario saved with it, with the evaluation
    settings of ``config``, written into ``RUN_DIR/evaluations/<date>-<time>/`` (the run's own results stay)."""
    run_dir = Path(config.eval_only)
    if not (run_dir / "config.json").is_file():
        raise ValueError(f"--eval-only: {run_dir / 'config.json'} not found")
    saved = read_json(run_dir / "config.json", "--eval-only")
    require_training_extras(config, saved)
    results_dir = run_dir / "evaluations" / time.strftime("%Y%m%d-%H%M%S")
    suffix = 1
    while results_dir.exists():
        suffix += 1
        results_dir = results_dir.with_name(f"{results_dir.name.split('.')[0]}.{suffix}")
    comparison = compare(config, saved, run_dir, results_dir)
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
