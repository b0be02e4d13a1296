"""A saved run's files, checked against the run's own configuration before anything uses them.

``config.json`` is checked against the ``SHA256SUMS`` of the run folder (written with it: an edited file is
refused) and then key by key (:meth:`~ee_formation_env.baselines.learned.config.TrainConfig.from_saved`);
checkpoints against their own ``SHA256SUMS`` (:func:`~ee_formation_env.baselines.learned.checkpoint.verify_checksums`),
the newest intact one chosen when a newer one is damaged (:func:`newest_intact_checkpoint`, said in one line).
A folder without the project's marker or its checksums is refused: every run the project writes has both.
Every fault is one ``ValueError`` naming the file and the fix.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path
from typing import Any

import numpy as np

from ee_formation_env.baselines.learned.checkpoint import (CHECKSUMS, TRAINING_STATE_FILES, atomic_directory,
                                                           checkpoint_state, checkpoints, read_json,
                                                           verify_checksums, write_checksums, write_json)
from ee_formation_env.baselines.learned.config import TrainConfig
from ee_formation_env.baselines.learned.policy import MODEL_FOLDER, ObservationNormalizer
from ee_formation_env.baselines.learned.run_folder import require_project_run

CONFIG = "config.json"


def write_saved_config(run_dir: Path, saved: dict[str, Any]) -> None:
    """``config.json`` and the run folder's ``SHA256SUMS`` (its sha256), written together."""
    write_json(Path(run_dir) / CONFIG, saved)
    write_checksums(run_dir, [CONFIG])


def load_saved_config(run_dir: Path, flag: str) -> tuple[dict[str, Any], TrainConfig]:
    """The saved ``config.json`` of ``run_dir`` (as read) and its configuration, checked: the file the run
    wrote (its sha256), each saved setting present and of its type, the whole in range. ``flag``: the command's
    flag (``--resume``, ``--eval-only``), named when the run folder has no ``config.json``."""
    run_dir = Path(run_dir)
    path = run_dir / CONFIG
    if not path.is_file():
        raise ValueError(f"{flag}: {path} not found")
    require_project_run(run_dir, flag)
    verify_checksums(run_dir, [CONFIG], "restore the config.json the run wrote (to change the budget, give "
                     "--resume RUN --total-timesteps N instead of editing it)")
    saved = read_json(path, str(path))
    return saved, TrainConfig.from_saved(saved, str(path))


def newest_intact_checkpoint(run_dir: Path) -> tuple[int, Path] | None:
    """The newest complete, intact training state of ``run_dir`` (a checkpoint or its final ``model/``) as
    (agent steps, folder), or None if it has none. A newer one that is damaged (a file whose sha256 differs, a
    file or ``state.json`` missing) is passed over, said in one line on stderr."""
    run_dir = Path(run_dir)
    required = True  # every run folder the project writes has checksums
    candidates = list(checkpoints(run_dir))
    if (run_dir / MODEL_FOLDER / "state.json").is_file():
        candidates.append(run_dir / MODEL_FOLDER)
    states: list[tuple[int, Path]] = []
    damaged: list[str] = []
    for folder in candidates:
        try:
            states.append((int(checkpoint_state(folder)["agent_steps"]), folder))
        except ValueError as error:
            damaged.append(_reason(error, run_dir))
    chosen = None
    for steps, folder in sorted(states, key=lambda item: item[0], reverse=True):
        try:
            verify_checksums(folder, TRAINING_STATE_FILES, _PASSED_OVER, required=required)
        except ValueError as error:
            damaged.append(_reason(error, run_dir))
            continue
        chosen = (steps, folder)
        break
    if damaged:
        instead = (f"resuming from {chosen[1].relative_to(run_dir)} ({chosen[0]} agent steps), the newest intact "
                   "checkpoint" if chosen else "no intact checkpoint is left")
        print(f"note: {run_dir}: passed over, damaged: {'; '.join(damaged)}; {instead}", file=sys.stderr, flush=True)
    return chosen


_PASSED_OVER = "passed over"


def _reason(error: ValueError, run_dir: Path) -> str:
    """A checksum or state error, its paths relative to the run folder, without its fix."""
    text = str(error).replace(f"{run_dir}/", "")
    return text[: -len(_PASSED_OVER) - 2] if text.endswith(f": {_PASSED_OVER}") else text


def verify_model(run_dir: Path, backend: str) -> None:
    """Check the files of ``run_dir``'s final model that the evaluation reads against its ``SHA256SUMS``."""
    run_dir = Path(run_dir)
    names = (("policy.json", "policy.pt") if backend == "sb3" else ("rllib_module.json", "rllib_module.pt"))
    verify_checksums(run_dir / MODEL_FOLDER, (*names, "obs_normalizer.json"),
                     "the model is damaged: `--resume RUN` trains it again from the newest intact checkpoint")


def model_from_checkpoint(run_dir: Path, checkpoint: Path) -> None:
    """Make ``checkpoint`` (an intact one of ``run_dir``) the run's final model, unless it is ``model/`` already:
    its files copied into ``model/`` atomically, with the observation normalization the evaluation applies
    (from its ``vecnormalize.json`` where a checkpoint written before it held one lacks it). For a run whose
    training ended at that checkpoint and was killed before it saved its model."""
    run_dir, checkpoint = Path(run_dir), Path(checkpoint)
    target = run_dir / MODEL_FOLDER
    if checkpoint.resolve() == target.resolve():
        return
    with atomic_directory(target) as partial:
        for path in checkpoint.iterdir():
            if path.is_file() and path.name != CHECKSUMS:
                shutil.copy2(path, partial / path.name)
        if not (partial / "obs_normalizer.json").is_file():
            statistics = read_json(partial / "vecnormalize.json", "vecnormalize.json")
            ObservationNormalizer(np.asarray(statistics["obs_mean"], dtype=np.float64),
                                  np.asarray(statistics["obs_var"], dtype=np.float64), float(statistics["clip_obs"]),
                                  float(statistics["epsilon"])).save(partial / "obs_normalizer.json")
