"""Helpers of the run tests: the tiny training flags, and trainers run as real processes (``train.py`` in its own
process group), so that signals, kills and worker faults reach them as they reach a user's."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Sequence

REPO = Path(__file__).resolve().parents[3]
EVAL_FAST = ["--eval-episodes", "1", "--eval-seconds", "0.2", "--no-progress", "--eval-workers", "0"]
FAST = ["--n-envs", "1", "--n-workers", "0", "--train-episode-seconds", "0.5", *EVAL_FAST]
TINY = ["--mode", "torque", "--total-timesteps", "300", *FAST]  # a whole run in a few seconds
#: A torque-mode trainer with short rollouts; the tests add the layout, budget and --out.
TRAIN = [sys.executable, str(REPO / "train.py"), "--mode", "torque", "--n-steps", "64", "--train-episode-seconds",
         "0.5", "--no-progress", *EVAL_FAST]
#: Two envs, one of them in a worker process.
WITH_A_WORKER = ["--n-envs", "2", "--n-workers", "1", "--in-process-envs", "1"]


def start_trainer(flags: Sequence[str], cwd: Path) -> subprocess.Popen:
    """``train.py`` with ``flags`` after :data:`TRAIN`, in a new session (its own process group)."""
    return subprocess.Popen([*TRAIN, *flags], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=cwd,
                            start_new_session=True)


def finish(process: subprocess.Popen, timeout: float = 90) -> tuple[str, str]:
    """The trainer's stdout and stderr once it ended; killed (its whole group) if it does not end in time."""
    try:
        return process.communicate(timeout=timeout)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.communicate(timeout=30)


def training_started(run_dir: Path) -> Callable[[], bool]:
    """True once the trainer has logged a few training episodes (its monitor file)."""
    monitor = Path(run_dir) / "monitor.csv"
    return lambda: monitor.is_file() and monitor.stat().st_size > 200


def children(pid: int, spawned_workers_only: bool = False) -> list[int]:
    """Process ids whose parent is ``pid`` (from /proc); ``spawned_workers_only``: those started by
    multiprocessing's spawn (``spawn_main``), not its resource tracker."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            command = (stat.parent / "cmdline").read_bytes()
        except OSError:
            continue
        if int(fields[1]) == pid and (not spawned_workers_only or b"spawn_main" in command):
            found.append(int(stat.parent.name))
    return found


def gone(pid: int) -> bool:
    """No such process any more, or only its zombie."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except OSError:
        return True


def wait_for(condition: Callable[[], bool], seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.1)
    return False


def error_lines(stderr: str) -> list[str]:
    """The lines of ``stderr`` a command printed as its error or stop message (progress notes aside)."""
    return [line for line in stderr.splitlines() if line.startswith(("error:", "training:", "comparison:"))]
