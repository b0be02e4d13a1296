"""The lock of a run folder: one process at a time trains, resumes or replaces a run.

The lock is the file :data:`LOCK_NAME` inside the run folder, holding the pid and host of its holder, and an
exclusive ``fcntl.flock`` on it for as long as the holder runs. The kernel drops the ``flock`` when the holder
ends, however it ends (a SIGKILL included), so a lock file whose ``flock`` can be taken is stale whatever pid it
names: it is taken over, and the takeover is said in one line. A holder that ends normally removes the file
(its ``flock`` still held, then the inode checked after taking it, so that two processes never both hold the
lock through an old and a new file). Where ``fcntl`` is missing the file alone is the lock: created
exclusively, a file left by a holder that was killed has to be removed by hand, as the refusal says.
"""

from __future__ import annotations

import errno
import json
import os
import socket
import stat
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

try:
    import fcntl
except ImportError:  # not POSIX
    fcntl = None  # type: ignore[assignment]

LOCK_NAME = ".ee-formation-run.lock"


class RunLocked(ValueError):
    """The run folder is locked by a live process (``pid`` on ``host``; None where the lock file does not say,
    e.g. empty, or written by another program): a ``ValueError`` naming ``flag``."""

    def __init__(self, flag: str, run_dir: Path, holder: dict):
        self.pid, self.host = holder_pid(holder), holder.get("host")
        lock = Path(run_dir) / LOCK_NAME
        if self.pid is None:
            super().__init__(f"{flag}: {run_dir} is in use by an unknown process (the lock file {lock} is held but "
                             "has no pid): wait for it to end or stop it (`fuser` or `lsof` on the lock file names "
                             "it), or choose another folder")
            return
        where = f"pid {self.pid}" + (f" on {self.host}" if self.host and self.host != socket.gethostname() else "")
        super().__init__(f"{flag}: {run_dir} is in use by another trainer ({where}, its lock "
                         f"{lock}): wait for it to end, stop it, or choose another folder")


def holder_pid(holder: dict | None) -> int | None:
    """The pid a lock holder's record names: a positive integer, else None (unknown)."""
    pid = (holder or {}).get("pid")
    return pid if isinstance(pid, int) and not isinstance(pid, bool) and pid > 0 else None


def lock_holder(run_dir: Path) -> dict | None:
    """Who holds the lock of ``run_dir`` now, ``{"pid": ..., "host": ...}``, or None if nobody does (no lock
    file, or a stale one). Nothing is changed."""
    path = Path(run_dir) / LOCK_NAME
    if path.is_symlink() or not path.is_file():
        return None
    if fcntl is None:
        return _read_holder(path) or {}
    try:
        descriptor = os.open(path, os.O_RDONLY | _NO_FOLLOW)
    except OSError:
        return None
    try:
        try:
            fcntl.flock(descriptor, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return _read_holder(path) or {}
        fcntl.flock(descriptor, fcntl.LOCK_UN)
        return None
    finally:
        os.close(descriptor)


@contextmanager
def run_lock(run_dir: Path, flag: str) -> Iterator[None]:
    """Hold the lock of the existing folder ``run_dir`` within the block: :class:`RunLocked` (naming ``flag``)
    if a live process holds it; a stale lock is taken over, said in one line on stderr. Released on every way
    out of the block."""
    path = Path(run_dir) / LOCK_NAME
    try:
        descriptor = _acquire(path, Path(run_dir), flag)
    except OSError as error:  # a read-only folder, a vanished one
        raise ValueError(f"{flag}: cannot lock {run_dir} ({error.strerror}: {error.filename or path})") from None
    try:
        yield
    finally:
        _release(path, descriptor)


#: The lock is never opened through a link: a link named as the lock would have its target truncated.
_NO_FOLLOW = getattr(os, "O_NOFOLLOW", 0)


def _open_lock(path: Path, flags: int, flag: str) -> int:
    """Open the lock file ``path`` without following a link; ``ValueError`` naming ``flag`` unless it is a
    regular file."""
    try:
        descriptor = os.open(path, flags | _NO_FOLLOW, 0o644)
    except OSError as error:
        if error.errno == errno.ELOOP:
            raise ValueError(f"{flag}: {path} is a link, not a lock file: nothing was written through it; remove "
                             "it (a run folder's lock is a regular file)") from None
        raise
    if not stat.S_ISREG(os.fstat(descriptor).st_mode):
        os.close(descriptor)
        raise ValueError(f"{flag}: {path} is not a regular file: remove it (a run folder's lock is one)")
    return descriptor


def _acquire(path: Path, run_dir: Path, flag: str) -> int:
    me = {"pid": os.getpid(), "host": socket.gethostname()}
    if fcntl is None:
        try:
            descriptor = _open_lock(path, os.O_CREAT | os.O_EXCL | os.O_RDWR, flag)
        except FileExistsError:
            raise RunLocked(flag, run_dir, _read_holder(path) or {}) from None
        _write_holder(descriptor, me)
        return descriptor
    while True:
        descriptor = _open_lock(path, os.O_CREAT | os.O_RDWR, flag)
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(descriptor)
            raise RunLocked(flag, run_dir, _read_holder(path) or {}) from None
        try:
            same_file = os.path.samestat(os.fstat(descriptor), os.stat(path))
        except FileNotFoundError:
            same_file = False
        if same_file:
            break
        os.close(descriptor)  # its holder removed the file as we opened it: try the new one
    previous = _read_holder(path)
    if holder_pid(previous) is not None:
        host = f" on {previous['host']}" if previous.get("host") and previous["host"] != me["host"] else ""
        print(f"note: {path}: took over the stale lock of pid {previous['pid']}{host}, which ended without "
              "releasing it", file=sys.stderr, flush=True)
    _write_holder(descriptor, me)
    return descriptor


def _release(path: Path, descriptor: int) -> None:
    try:
        path.unlink(missing_ok=True)  # while still holding it: whoever opens it next finds a new file
    except OSError:
        pass
    try:
        if fcntl is not None:
            fcntl.flock(descriptor, fcntl.LOCK_UN)
    finally:
        os.close(descriptor)


def _write_holder(descriptor: int, holder: dict) -> None:
    os.ftruncate(descriptor, 0)
    os.lseek(descriptor, 0, os.SEEK_SET)
    os.write(descriptor, json.dumps(holder).encode())
    os.fsync(descriptor)


def _read_holder(path: Path) -> dict | None:
    try:
        if path.is_symlink():
            return None
        holder = json.loads(path.read_text(encoding="utf-8") or "null")
    except (OSError, ValueError):
        return None
    return holder if isinstance(holder, dict) else None
