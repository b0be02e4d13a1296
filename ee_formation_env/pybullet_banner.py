"""PyBullet's first import, without its banner.

PyBullet's C extension prints ``pybullet build time: <date>`` (on standard error) when it is first imported, which
lands in every command's output (``--help`` included) and in every child process's. :func:`import_pybullet_quietly`
is that first import, made by the package's ``__init__`` before any module imports PyBullet: file descriptors 1
and 2 are pointed at the null device around it, and the C library's buffers are flushed before they are
restored, so the banner goes nowhere. Where descriptors cannot be redirected, it is a plain import.
"""

from __future__ import annotations

import ctypes
import os
import sys

_SILENCED_FDS = (1, 2)  # standard output and standard error


def import_pybullet_quietly() -> None:
    """Import ``pybullet`` (once per process) with the C-level standard output and error silenced."""
    if "pybullet" in sys.modules:
        return
    try:
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
        saved = [os.dup(fd) for fd in _SILENCED_FDS]
    except (AttributeError, OSError, ValueError):  # no standard streams, or their descriptors closed
        import pybullet  # noqa: F401
        return
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        for fd in _SILENCED_FDS:
            os.dup2(null, fd)
        import pybullet  # noqa: F401

        _flush_c_streams()
    finally:
        for fd, copy in zip(_SILENCED_FDS, saved):
            os.dup2(copy, fd)
            os.close(copy)
        os.close(null)


def _flush_c_streams() -> None:
    """Flush the C library's stream buffers (where the banner waits when a stream is a pipe or a file)."""
    try:
        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError, TypeError):  # no C library handle on this platform
        pass
