"""A training run from its configuration: the run folder, training with the chosen backend, the comparison.

:func:`train` is what ``python train.py`` and ``ee-formation train`` do with a resolved
:class:`~ee_formation_env.baselines.learned.config.TrainConfig`; :func:`evaluate_saved_run` is their
``--eval-only``. A run folder holds ``config.json`` (the configuration, the parsed scenario and the package
versions), the model and its observation normalization, TensorBoard logs, checkpoints, ``learning_curve.csv``,
``reference_returns.json``, ``timing.json`` and the comparison (``comparison.json``, ``.md``, ``.png``).
"""

from __future__ import annotations

import json
import platform
import time
from pathlib import Path
from typing import Any

import ee_formation_env
from ee_formation_env.baselines.extras import require
from ee_formation_env.baselines.learned.compare import compare, reference_returns
from ee_formation_env.baselines.learned.config import TrainConfig


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
    returns the run folder."""
    started = time.time()
    ee_formation_env.load_scenario(config.scenario)  # fail fast on a bad scenario, before any process starts
    require_training_extras(config)
    run_dir = Path(config.out) if config.out else Path("runs") / run_name(config)
    run_dir.mkdir(parents=True, exist_ok=True)
    saved = config.to_dict()
    saved["scenario_data"] = ee_formation_env.load_scenario(config.scenario).to_dict()
    saved["versions"] = package_versions()
    (run_dir / "config.json").write_text(json.dumps(saved, indent=2, default=str))
    print(f"training {config.algo} ({config.backend}, mode {config.mode}) on {config.scenario} for "
          f"{config.total_timesteps} agent steps -> {run_dir}")
    if config.backend == "sb3":
        from ee_formation_env.baselines.learned.sb3_backend import train_sb3 as backend
    else:
        from ee_formation_env.baselines.learned.rllib_backend import train_rllib as backend
    backend(config, run_dir)
    (run_dir / "reference_returns.json").write_text(json.dumps(reference_returns(saved), indent=2))
    compare(config, saved, run_dir)
    timing = json.loads((run_dir / "timing.json").read_text())
    timing["total_seconds"] = time.time() - started  # training, reference lines and evaluation
    (run_dir / "timing.json").write_text(json.dumps(timing))
    print(f"wrote {run_dir}/comparison.md, comparison.json, comparison.png")
    return run_dir


def evaluate_saved_run(config: TrainConfig) -> dict[str, Any]:
    """``--eval-only RUN_DIR``: the comparison of a saved run, with the evaluation settings of ``config``."""
    run_dir = Path(config.eval_only)
    config_path = run_dir / "config.json"
    if not config_path.is_file():
        raise SystemExit(f"--eval-only: {config_path} not found")
    saved = json.loads(config_path.read_text())
    require_training_extras(config, saved)
    return compare(config, saved, run_dir)


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
