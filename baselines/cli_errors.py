"""How the command-line tools report errors: ``error: <field>: <what>`` and exit status 2.

The library raises ``ValueError``/``TypeError`` whose message starts with the field at fault; the tools print it
without a traceback (``--debug`` shows it). The message is one line, except for a scenario file that does not
parse, whose message ends with the parser's own lines (where, and the line with a caret). A run that stopped
before its end (:class:`~ee_formation_env.baselines.learned.interruption.RunStopped`) prints its one line, which
says how to continue it: stopped by SIGINT/SIGTERM, it exits with 128 + the signal's number; stopped by a fault
outside its input (a worker process died, the disk is full), with ``error: `` before the line and status 1. A
file the file system refuses to write (:class:`~ee_formation_env.baselines.atomic_files.WriteRefused`) is
``error: cannot write <file> (<why>)`` and status 1.
"""

from __future__ import annotations

import sys
from typing import Callable

#: What the library raises for bad input (a message that starts with the field): a command prints it in one line.
INPUT_ERRORS = (ValueError, TypeError)


def report_errors(command: Callable[[], int], debug: bool) -> int:
    """Run ``command``; bad input prints ``error: <field>: <what>`` to stderr and returns 2 (``debug``: raise it,
    with its traceback). A run that stopped before its end prints how to continue it and returns its exit code
    (a signal's, 128 + its number, even with ``debug``); a refused write prints its one line and returns 1."""
    from ee_formation_env.baselines.atomic_files import WriteRefused
    from ee_formation_env.baselines.learned.interruption import RunStopped

    try:
        return command()
    except RunStopped as stopped:
        if debug and stopped.signal_name is None:
            raise
        print(str(stopped) if stopped.signal_name else f"error: {stopped}", file=sys.stderr)
        return stopped.exit_code
    except WriteRefused as error:
        if debug:
            raise
        print(f"error: {error}", file=sys.stderr)
        return 1
    except INPUT_ERRORS as error:
        if debug:
            raise
        print(f"error: {error}", file=sys.stderr)
        return 2
