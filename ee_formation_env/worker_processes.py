"""What every worker process of the project shares: the ``spawn`` start method, stop signals left to the parent,
and the main script's ``if __name__ == "__main__":`` guard.

Workers (the SB3 VecEnv's env workers, the comparison's evaluation workers) start with ``spawn``: each is a fresh
interpreter that builds its own PyBullet clients. Two consequences are handled here, in one place:

- **Stop signals.** A Ctrl-C reaches the whole process group. Workers ignore SIGINT
  (:func:`ignore_interrupts`), blocked from before their start until then (:func:`interrupts_blocked`), so that
  the parent alone decides how to stop (it can finish its step and save first).
- **The main-script guard.** ``spawn`` re-imports the parent's main script in every child. A script that trains
  at its top level, without ``if __name__ == "__main__":``, would train again in each child. A child that
  reaches training code while it is still importing the parent's script exits at once with
  :data:`REIMPORTED_MAIN_EXIT_CODE` (:func:`exit_if_reimporting_main`), touching nothing; the parent, seeing a
  worker die during its start-up, explains it in one line with the fix (:func:`unguarded_main_hint`).
"""

from __future__ import annotations

import ast
import multiprocessing
import signal
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

#: The exit status of a spawned child that reached training code while importing the parent's main script.
REIMPORTED_MAIN_EXIT_CODE = 3
#: The signals a worker leaves to its parent (SIGTERM stays default: a worker that is sent it alone ends).
INTERRUPT_SIGNALS = (signal.SIGINT,)


@contextmanager
def interrupts_blocked() -> Iterator[None]:
    """Within the block this thread has SIGINT blocked, and a process spawned meanwhile starts with it blocked
    (the mask is inherited): a Ctrl-C during a worker's start-up cannot end it. A SIGINT meant for this process
    stays pending and is delivered after the block."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, set(INTERRUPT_SIGNALS))
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def ignore_interrupts() -> None:
    """A worker's first call: ignore SIGINT from now on, then unblock it (started by :func:`interrupts_blocked`)."""
    for number in INTERRUPT_SIGNALS:
        signal.signal(number, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, set(INTERRUPT_SIGNALS))


def importing_parent_main() -> bool:
    """True in a ``spawn`` child that is still importing its parent's main script (multiprocessing's own test,
    the one behind its "bootstrapping phase" error)."""
    return bool(getattr(multiprocessing.current_process(), "_inheriting", False))


def exit_if_reimporting_main() -> None:
    """Called first by code that trains or starts workers: in a child re-running the parent's unguarded main
    script, exit at once with :data:`REIMPORTED_MAIN_EXIT_CODE`, before anything is built or written (the
    parent reports it, :func:`unguarded_main_hint`)."""
    if importing_parent_main():
        raise SystemExit(REIMPORTED_MAIN_EXIT_CODE)


def unguarded_main_script() -> Path | None:
    """The parent's main script if ``spawn`` re-runs its top level in every child: a file (run as a path or as
    ``-m package.module``) without an ``if __name__ == "__main__":`` block at its top level; else None."""
    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    module = getattr(getattr(main, "__spec__", None), "name", None)
    if path is None or (module is not None and module.split(".")[-1] == "__main__"):
        return None  # nothing re-run: -c, an interactive session, `-m package` (spawn skips a __main__ module)
    try:
        tree = ast.parse(Path(path).read_text(encoding="utf-8"))
    except (OSError, SyntaxError, UnicodeDecodeError, ValueError):
        return None
    return None if any(_is_main_guard(node) for node in tree.body) else Path(path)


def _is_main_guard(node: ast.stmt) -> bool:
    """``if __name__ == "__main__":`` (either order of the comparison)."""
    if not isinstance(node, ast.If) or not isinstance(node.test, ast.Compare) or len(node.test.comparators) != 1:
        return False
    sides = [node.test.left, node.test.comparators[0]]
    return (isinstance(node.test.ops[0], ast.Eq)
            and any(isinstance(side, ast.Name) and side.id == "__name__" for side in sides)
            and any(isinstance(side, ast.Constant) and side.value == "__main__" for side in sides))


def unguarded_main_hint(exit_code: int | None) -> str | None:
    """Why a worker that died during its start-up did, if it was the missing main guard: one sentence with the
    fix, or None. ``exit_code``: the worker's."""
    script = unguarded_main_script()
    if script is None and exit_code != REIMPORTED_MAIN_EXIT_CODE:
        return None
    where = f"the main script {script}" if script is not None else "the main script"
    return (f"the spawn start method re-imports {where} in every worker process, and it has no "
            "`if __name__ == \"__main__\":` guard, so the worker ran its training code again; put the code that "
            "trains (or starts workers) under that guard")
