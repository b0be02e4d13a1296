"""Stopping a run cleanly on SIGINT (Ctrl-C) or SIGTERM: the backend finishes its step and saves.

While :func:`stop_on_signals` is active, the first SIGINT or SIGTERM sets its :class:`StopRequest`; the training
loop checks it at every step, stops within a step (an update at most, well under a second at the presets), and
saves the final model and its normalization as a complete checkpoint; the run can then be continued with
``--resume``. A second signal while stopping is handled as usual (SIGINT raises ``KeyboardInterrupt``). The
env worker processes ignore SIGINT, so a Ctrl-C sent to the whole process group does not kill them first.
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


class TrainingInterrupted(Exception):
    """A run stopped by a signal after saving its model; ``run_dir`` continues with ``--resume``. ``command`` is
    the program the message tells to run (the command that trained sets its own name)."""

    def __init__(self, run_dir: object, signal_name: str, agent_steps: int, command: str = "python train.py"):
        super().__init__(run_dir, signal_name, agent_steps)
        self.run_dir, self.signal_name, self.agent_steps, self.command = run_dir, signal_name, agent_steps, command

    def __str__(self) -> str:
        return (f"training: stopped by {self.signal_name} at {self.agent_steps} agent steps; the model and its "
                f"normalization are saved in {self.run_dir}: `{self.command} --resume {self.run_dir}` continues it")

    @property
    def exit_code(self) -> int:
        return 128 + int(getattr(signal, self.signal_name))


@contextmanager
def stop_on_signals() -> Iterator[StopRequest]:
    """Within the block, the first SIGINT/SIGTERM sets the yielded request instead of ending the process
    (outside the main thread, where handlers cannot be set, the request simply never comes)."""
    request = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield request
        return
    previous = {number: signal.getsignal(number) for number in SIGNALS}

    def handle(number: int, frame: object) -> None:
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

    for number in SIGNALS:
        signal.signal(number, handle)
    try:
        yield request
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
