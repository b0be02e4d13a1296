"""A saved run's files, checked against the run's own configuration before anything uses them.

``config.json`` is checked against the ``SHA256SUMS`` of the run folder (written with it: an edited file is
refused) and then key by key (:meth:`~ee_formation_env.baselines.learned.config.TrainConfig.from_saved`);
checkpoints against their own ``SHA256SUMS`` (:func:`~ee_formation_env.baselines.learned.checkpoint.verify_checksums`),
the newest intact one chosen when a newer one is damaged (:func:`newest_intact_checkpoint`, said in one line)
and its stamp checked against the run's configuration (:func:`resume_checkpoint`; the stamp:
:mod:`~ee_formation_env.baselines.learned.run_files`). A folder without the project's marker or its checksums is
refused: every run the project writes has both. Every fault is one ``ValueError`` naming the file and the fix.
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
from ee_formation_env.baselines.learned.policy import ObservationNormalizer, load_model, open_run
from ee_formation_env.baselines.learned.run_files import CONFIG, MODEL_FOLDER, STAMP


def write_saved_config(run_dir: Path, saved: dict[str, Any]) -> None:
    """``config.json`` and the run folder's ``SHA256SUMS`` (its sha256), written together."""
    write_json(Path(run_dir) / CONFIG, saved)
    write_checksums(run_dir, [CONFIG])


def load_saved_config(run_dir: Path, flag: str, final_model: bool) -> tuple[dict[str, Any], TrainConfig]:
    """The saved ``config.json`` of ``run_dir`` (as read) and its configuration, checked: the run opened by
    :func:`~ee_formation_env.baselines.learned.policy.open_run` (the file the run wrote, its final model with
    ``final_model``), each saved setting present and of its type, the whole in range. ``flag``: the command's
    flag (``--resume``, ``--eval-only``), which each refusal starts with."""
    saved = open_run(run_dir, flag, final_model)
    path = Path(run_dir) / CONFIG
    try:
        return saved, TrainConfig.from_saved(saved, str(path))
    except (TypeError, ValueError) as error:
        raise ValueError(f"{flag}: {error}") from None


def resume_checkpoint(run_dir: Path, saved: dict[str, Any], flag: str = "--resume") -> tuple[int, Path]:
    """The checkpoint ``--resume`` continues ``run_dir`` from: the newest intact one
    (:func:`newest_intact_checkpoint`, a damaged newer one passed over in a note), loaded by
    :func:`~ee_formation_env.baselines.learned.policy.load_model`, so that its stamp must be of this run's
    configuration (``saved``: config.json, whose budget ``--resume`` may have changed: the stamp's digest leaves
    the budget out) and of its own model. None intact is one ``ValueError`` naming the newest damage."""
    chosen, damaged = _intact_checkpoint(Path(run_dir))
    if chosen is None:
        found = f": {damaged[0]}" if damaged else ""
        raise ValueError(f"{flag}: {run_dir} holds no intact checkpoint to continue from{found}")
    _note_passed_over(Path(run_dir), chosen, damaged)
    load_model(chosen[1], saved, flag)
    return chosen


def newest_intact_checkpoint(run_dir: Path) -> tuple[int, Path] | None:
    """The newest complete, intact training state of ``run_dir`` (a checkpoint or its final ``model/``) as
    (agent steps, folder), or None if it has none. A newer one that is damaged (a file whose sha256 differs, a
    file, its stamp or ``state.json`` missing) is passed over, said in one line on stderr."""
    chosen, damaged = _intact_checkpoint(Path(run_dir))
    _note_passed_over(Path(run_dir), chosen, damaged)
    return chosen


def _intact_checkpoint(run_dir: Path) -> tuple[tuple[int, Path] | None, list[str]]:
    """The newest intact training state of ``run_dir`` (or None), and why each newer one was passed over, newest
    first."""
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
    for steps, folder in sorted(states, key=lambda item: item[0], reverse=True):
        try:  # every run folder the project writes has checksums, and every checkpoint its stamp
            verify_checksums(folder, (*TRAINING_STATE_FILES, STAMP), _PASSED_OVER)
        except ValueError as error:
            damaged.append(_reason(error, run_dir))
            continue
        return (steps, folder), damaged
    return None, damaged


def _note_passed_over(run_dir: Path, chosen: tuple[int, Path] | None, damaged: list[str]) -> None:
    if damaged:
        instead = (f"resuming from {chosen[1].relative_to(run_dir)} ({chosen[0]} agent steps), the newest intact "
                   "checkpoint" if chosen else "no intact checkpoint is left")
        print(f"note: {run_dir}: passed over, damaged: {'; '.join(damaged)}; {instead}", file=sys.stderr, flush=True)


_PASSED_OVER = "passed over"


def _reason(error: ValueError, run_dir: Path) -> str:
    """A checksum or state error, its paths relative to the run folder, without its fix."""
    text = str(error).replace(f"{run_dir}/", "")
    return text[: -len(_PASSED_OVER) - 2] if text.endswith(f": {_PASSED_OVER}") else text


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
