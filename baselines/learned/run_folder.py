"""The folder of a training run: which ``--out`` is accepted, how it is made, and what ``--overwrite`` may remove.

Every refusal comes before anything is created (:func:`check_out`, then the configuration and the scenario,
then :func:`created_run_folder`). The folder is made holding the marker file :data:`MARKER` (what wrote it)
and its lock (:mod:`~ee_formation_env.baselines.learned.run_lock`), held until the command ends.
``--overwrite`` removes only a folder the project wrote (it holds the marker), never a symlink, a file, a FIFO,
a device or a foreign folder; and never a folder another trainer holds. A run that fails before anything could
be continued from (no checkpoint, no model: a worker that died at start-up, a full disk at the first
checkpoint) leaves no folder behind (:func:`created_run_folder`), so the same command can simply be run again.
"""

from __future__ import annotations

import json
import os
import shutil
import stat
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from ee_formation_env.baselines.learned.checkpoint import checkpoints
from ee_formation_env.baselines.learned.run_lock import LOCK_NAME, RunLocked, lock_holder, run_lock

MARKER = ".ee-formation-run"  # in every run folder: what wrote it and when (JSON)


def is_project_run(run_dir: Path) -> bool:
    """Whether ``run_dir`` holds the marker of a run folder the project wrote (runs written before the marker
    existed hold none)."""
    return (Path(run_dir) / MARKER).is_file()


def require_project_run(run_dir: Path, what: str) -> None:
    """``ValueError`` starting with ``what`` unless ``run_dir`` holds the project's marker: every path that reads a
    run refuses a folder whose files cannot be checked, in these words."""
    if not is_project_run(run_dir):
        raise ValueError(f"{what}: {run_dir} has no {MARKER}: not a run folder train.py wrote (or its marker was "
                         "removed), so its files cannot be checked")


def check_out(run_dir: Path, overwrite: bool) -> None:
    """Refuse ``--out run_dir`` (a ``ValueError`` naming ``--out`` and why) unless it is free to train into: it
    does not exist, or it is an empty folder, or, with ``overwrite``, a run folder the project wrote that no live
    process holds. Nothing is changed."""
    run_dir = Path(run_dir)
    try:
        info = os.lstat(run_dir)
    except FileNotFoundError:
        return
    except NotADirectoryError as error:
        blocking = next((parent for parent in run_dir.parents if parent.exists() and not parent.is_dir()), None)
        raise ValueError(f"--out: cannot create {run_dir} ({error.strerror}: {blocking or run_dir.parent} is a "
                         "file)") from None
    except OSError as error:
        raise ValueError(f"--out: {run_dir}: cannot be read ({error.strerror})") from None
    if stat.S_ISLNK(info.st_mode):
        raise ValueError(f"--out: {run_dir} is a symbolic link: refused (a run folder is never written or replaced "
                         "through a link); give the folder itself, or another --out")
    if not stat.S_ISDIR(info.st_mode):
        raise ValueError(f"--out: {run_dir} is {_kind(info.st_mode)}, not a folder: refused (--overwrite replaces "
                         "only a run folder this project wrote); choose another --out")
    holder = lock_holder(run_dir)
    if holder is not None:
        raise RunLocked("--out", run_dir, holder)
    try:
        empty = not any(run_dir.iterdir())
    except OSError as error:
        raise ValueError(f"--out: {run_dir}: cannot be read ({error.strerror})") from None
    if empty:
        return
    if not overwrite:
        hint = f"--resume {run_dir} continues it, " if (run_dir / "config.json").is_file() else ""
        raise ValueError(f"--out: {run_dir} already holds files: {hint}--overwrite replaces it, or choose another "
                         "--out")
    if not is_project_run(run_dir):
        raise ValueError(f"--out: {run_dir} holds files but no {MARKER} marker, so it is not a run folder this "
                         "project wrote (runs written before the marker existed hold none either): --overwrite "
                         "refuses to remove it; remove it yourself, or choose another --out")


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"), (stat.S_ISREG, "a file")):
        if test(mode):
            return name
    return "not a folder"


@contextmanager
def created_run_folder(run_dir: Path, overwrite: bool, version: str) -> Iterator[Path]:
    """Make the run folder ``run_dir`` (checked by :func:`check_out`) and hold its lock within the block: a new
    folder (with any missing parents), an empty one, or, with ``overwrite``, a run folder whose contents are
    removed once its lock is taken. The marker is written first. A folder that cannot be made is a
    ``ValueError`` naming ``--out`` and the path. If the block fails before the run holds anything to continue
    from (:func:`has_resumable_state`), what it wrote is removed, and the folder too if this call made it: the
    same command can run again."""
    run_dir = Path(run_dir)
    check_out(run_dir, overwrite)  # again: the folder may have changed since the first check
    made = _make_folders(run_dir)
    unstarted = True
    try:
        with run_lock(run_dir, "--out"):
            try:
                if overwrite:
                    _clear(run_dir)
                (run_dir / MARKER).write_text(json.dumps({"written_by": f"ee-formation-env {version}",
                                                          "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")}),
                                              encoding="utf-8")
            except OSError as error:
                raise ValueError(f"--out: cannot write into {run_dir} ({error.strerror})") from None
            try:
                yield run_dir
            except BaseException:
                unstarted = not has_resumable_state(run_dir)
                if unstarted:
                    _clear(run_dir)
                raise
            unstarted = False
    finally:
        if unstarted and made:  # the lock file is gone with the lock: the folders made are empty
            _remove_made(made)


def _clear(run_dir: Path) -> None:
    """Remove everything in ``run_dir`` but its lock (held by this process)."""
    for entry in run_dir.iterdir():
        if entry.name == LOCK_NAME and not entry.is_symlink():  # a link named as the lock is never the lock
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry)
        else:
            entry.unlink()


def _make_folders(run_dir: Path) -> list[Path]:
    """Make ``run_dir`` and its missing parents; returns those made, outermost first. An ``OSError`` (a
    read-only place, a file on the path, a name too long) is a ``ValueError`` naming ``--out``, and what was
    made is removed."""
    missing = []
    path = run_dir
    while not os.path.lexists(path):
        missing.append(path)
        if path.parent == path:
            break
        path = path.parent
    made: list[Path] = []
    try:
        for folder in reversed(missing):
            try:
                folder.mkdir()
            except FileExistsError:
                if folder == run_dir:
                    raise ValueError(f"--out: {run_dir} was made by another command meanwhile: choose another "
                                     "--out") from None
                continue  # a parent another command made meanwhile: not this one's to remove
            made.append(folder)
    except OSError as error:
        _remove_made(made)
        raise ValueError(f"--out: cannot create {run_dir} ({error.strerror}: {error.filename or folder})") from None
    except ValueError:
        _remove_made(made)
        raise
    return made


def _remove_made(made: list[Path]) -> None:
    """Remove the folders of ``made`` (outermost first), the innermost with its contents."""
    if not made:
        return
    shutil.rmtree(made[-1], ignore_errors=True)
    for folder in reversed(made[:-1]):
        try:
            folder.rmdir()
        except OSError:
            pass


def has_resumable_state(run_dir: Path) -> bool:
    """Whether ``run_dir`` holds anything a ``--resume`` could continue from: a checkpoint or a model (a folder
    whose ``checkpoints/`` holds something stray counts too: nothing in it is removed unread)."""
    model = Path(run_dir) / "model"
    if (model / "state.json").is_file() or (model / "rllib_module.pt").is_file():
        return True
    try:
        return bool(checkpoints(run_dir))
    except ValueError:
        return True
