"""How a run stops before its end: on SIGINT (Ctrl-C) or SIGTERM, or on a fault outside its input (a worker
process, the disk), always with one line that says what stopped it and the command that continues it.

While :func:`stop_on_signals` is active (training), the first SIGINT or SIGTERM sets its :class:`StopRequest`;
the training loop checks it at every step, stops within a step (an update at most, well under a second at the
presets), and saves the final model and its normalization as a complete checkpoint; the run can then be
continued with ``--resume``. A second signal while stopping is handled as usual (SIGINT raises
``KeyboardInterrupt``). During the comparison, which has no step to stop at, :func:`raise_on_signals` turns
either signal into :class:`StopSignal` at once; training is complete by then, and ``--resume`` runs the
comparison alone. The env worker processes ignore SIGINT, so a Ctrl-C sent to the whole process group does not
kill them first; a SIGTERM sent to the whole group ends them, and the trainer, stopping for the same signal,
takes their end as part of its stop.

Every such stop is a :class:`RunStopped`: its message is one line, and the command-line tools print it without a
traceback and exit with its ``exit_code`` (128 + the signal's number for a signal, 1 for a fault).
"""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator

SIGNALS = (signal.SIGINT, signal.SIGTERM)


@dataclass
class StopRequest:
    """Set when a stop was asked for, with the signal's name."""

    signal_name: str | None = None

    @property
    def requested(self) -> bool:
        return self.signal_name is not None


class RunStopped(Exception):
    """A run that stopped before its end for a reason other than its input: ``message`` (one line) says what
    stopped it and what is saved; with ``run_dir`` the line ends with the ``--resume`` command and what it does
    (``continues``). ``command`` is the program the message tells to run (the command that trained sets its own
    name). ``details``: more lines (a worker's traceback), shown with ``--debug``. ``signal_name``: the signal
    that stopped it, if one did (the exit status is then 128 + its number, else 1)."""

    def __init__(self, message: str, run_dir: object = None, continues: str = "continues it",
                 command: str = "python train.py", details: str | None = None, signal_name: str | None = None):
        super().__init__(message)
        self.message, self.run_dir, self.continues, self.command, self.details = (message, run_dir, continues,
                                                                                  command, details)
        self.signal_name = signal_name

    def __str__(self) -> str:
        if self.run_dir is None:
            return self.message
        return f"{self.message}: `{self.command} --resume {self.run_dir}` {self.continues}"

    @property
    def exit_code(self) -> int:
        return 1 if self.signal_name is None else 128 + int(getattr(signal, self.signal_name))


class TrainingInterrupted(RunStopped):
    """A run stopped by a signal after saving its model (``phase`` "training"), or during its comparison, with
    training complete (``phase`` "comparison"); ``run_dir`` continues with ``--resume``."""

    def __init__(self, run_dir: object, signal_name: str, agent_steps: int, command: str = "python train.py",
                 phase: str = "training"):
        if phase == "comparison":
            message = (f"comparison: stopped by {signal_name}; training is complete ({agent_steps} agent steps, the "
                       f"model saved in {run_dir})")
            continues = "runs the comparison"
        else:
            message = (f"training: stopped by {signal_name} at {agent_steps} agent steps; the model and its "
                       f"normalization are saved in {run_dir}")
            continues = "continues it"
        super().__init__(message, run_dir, continues, command, signal_name=signal_name)
        self.agent_steps, self.phase = agent_steps, phase


class StopSignal(KeyboardInterrupt):
    """SIGINT or SIGTERM inside :func:`raise_on_signals`; ``signal_name`` says which."""

    def __init__(self, signal_name: str):
        super().__init__(signal_name)
        self.signal_name = signal_name


@contextmanager
def stop_on_signals() -> Iterator[StopRequest]:
    """Within the block, the first SIGINT/SIGTERM sets the yielded request instead of ending the process
    (outside the main thread, where handlers cannot be set, the request simply never comes)."""
    request = StopRequest()

    def handle(number: int, frame: object, previous: dict) -> None:
        if request.requested:  # a second signal: the usual behaviour
            handler = previous[number]
            if callable(handler):
                handler(number, frame)
            elif number == signal.SIGINT:
                raise KeyboardInterrupt
            else:
                raise SystemExit(128 + number)
            return
        request.signal_name = signal.Signals(number).name

    with _handlers(handle):
        yield request


@contextmanager
def raise_on_signals() -> Iterator[None]:
    """Within the block, SIGINT and SIGTERM raise :class:`StopSignal` in the main thread (the comparison, which
    has no step to stop at); outside the main thread nothing changes."""

    def handle(number: int, frame: object, previous: dict) -> None:
        raise StopSignal(signal.Signals(number).name)

    with _handlers(handle):
        yield


@contextmanager
def _handlers(handle) -> Iterator[None]:
    """``handle(number, frame, previous handlers)`` for :data:`SIGNALS` within the block, restored after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {number: signal.getsignal(number) for number in SIGNALS}
    for number in SIGNALS:
        signal.signal(number, lambda number, frame: handle(number, frame, previous))
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
