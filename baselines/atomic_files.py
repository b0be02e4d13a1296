"""Files written whole or not at all, and a refused write said in one line naming the file.

The files the tools write (a run's comparison and logs it rewrites, an evaluation's ``--json``, the scoreboard's
cells and tables) go through a temporary file beside the target (``.<name>.partial``), renamed into place with
``os.replace`` once complete: a full disk, a file-size limit or a kill never leaves a truncated file under its
name, and what was there stays as it was. A write the file system refuses, or a folder standing where the file
goes, is a :class:`WriteRefused` naming the file; the command-line tools print it in one line
(:func:`~ee_formation_env.baselines.cli_errors.report_errors`).
"""

from __future__ import annotations

import errno
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

#: Why a write was refused, in words that say what to do, by ``errno``; others keep the system's words.
_REASONS = {
    errno.ENOSPC: "no space left on the device: free some room",
    errno.EDQUOT: "disk quota exceeded: free some room",
    errno.EFBIG: "file too large: over this process's file-size limit (ulimit -f): raise it",
    errno.EROFS: "read-only file system",
    errno.EISDIR: "a folder stands at that path: move it away",
    errno.ENOTDIR: "a file stands where a folder of that path is expected: move it away",
}


class WriteRefused(OSError):
    """The file ``path`` could not be written (``errno`` and ``reason`` say why); nothing was written under its
    name and what was there is unchanged. Its message is one line: ``cannot write PATH (reason)``."""

    def __init__(self, path: Path, code: int | None, reason: str):
        super().__init__(code, reason, str(path))
        self.path, self.reason = Path(path), reason

    def __str__(self) -> str:
        return f"cannot write {self.path} ({self.reason})"


def refused(path: Path, error: OSError) -> WriteRefused:
    """``error``, raised while writing ``path``, as a :class:`WriteRefused` naming ``path``."""
    if isinstance(error, WriteRefused):
        return error
    reason = _REASONS.get(error.errno) or error.strerror or str(error) or type(error).__name__
    return WriteRefused(path, error.errno, reason)


@contextmanager
def replacing(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` to write the file into; when the block ends without an error it
    replaces ``path`` (``os.replace``). An ``OSError`` in the block or in the rename is a :class:`WriteRefused`
    naming ``path``; on any error the temporary file is removed and ``path`` is as it was."""
    path = Path(path)
    if path.is_dir() and not path.is_symlink():  # os.replace would say so only after the whole write
        raise refused(path, IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR)))
    temporary = path.with_name(f".{path.name}.partial")
    try:
        yield temporary
        os.replace(temporary, path)
    except OSError as error:
        _remove(temporary)
        raise refused(path, error) from None
    except BaseException:
        _remove(temporary)
        raise


def write_text(path: Path, text: str) -> None:
    """Write ``text`` (UTF-8) into ``path`` whole or not at all (:func:`replacing`)."""
    with replacing(path) as temporary:
        temporary.write_text(text, encoding="utf-8")


def make_folder(path: Path) -> None:
    """``mkdir -p path``; an ``OSError`` is a :class:`WriteRefused` naming ``path``."""
    try:
        Path(path).mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise refused(path, error) from None


def _remove(temporary: Path) -> None:
    try:
        temporary.unlink(missing_ok=True)
    except OSError:  # a folder of that name, or the file system refusing even that: nothing of ours to keep
        pass
