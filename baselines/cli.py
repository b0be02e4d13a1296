"""The ``ee-formation`` command: ``ee-formation COMMAND [flags]``; ``ee-formation COMMAND --help`` lists a command's flags.

- ``train``: train a shared policy and compare it with the reference controllers (the flags of ``train.py``);
- ``evaluate``: run reference policies, or a ``train.py`` run folder's policy, on seeded episodes and print the
  metrics table;
- ``validate SCENARIO``: run every check the env runs on a scenario (:func:`ee_formation_env.validate_scenario`),
  without stepping physics: one ``OK`` line and exit status 0, or the error and exit status 2;

The lab's studies, gain tuning and scoreboard are not part of the installed library: they run from the root of a
checkout as ``python -m studies COMMAND`` (``studies/__main__.py``).
"""

from __future__ import annotations

import argparse
import sys
from typing import Callable, Sequence

import ee_formation_env
from ee_formation_env.baselines.cli_errors import report_errors

TRAIN_DESCRIPTION = "Train a shared formation policy and compare it with the reference controllers on the same metrics."


def train_command(argv: Sequence[str] | None = None, prog: str = "train.py") -> int:
    """``train.py`` / ``ee-formation train``: parse the flags into a run configuration, then train (or, with
    ``--eval-only RUN_DIR``, re-evaluate a saved run; ``--resume RUN_DIR``, continue one)."""
    from ee_formation_env.baselines.learned.config import TrainConfig
    from ee_formation_env.baselines.learned.interruption import RunStopped
    from ee_formation_env.baselines.learned.run import evaluate_saved_run, train

    config = TrainConfig.from_args(argv, prog=prog, description=TRAIN_DESCRIPTION)

    def run() -> int:
        try:
            if config.eval_only:
                evaluate_saved_run(config)
            else:
                train(config)
        except RunStopped as stopped:  # its message names the program that was run, to resume it
            stopped.command = f"python {prog}" if prog.endswith(".py") else prog
            raise
        return 0

    return report_errors(run, config.debug)


def _evaluate(argv: Sequence[str]) -> int:
    from ee_formation_env.baselines.evaluate import main

    return report_errors(lambda: main(argv, prog="ee-formation evaluate"), "--debug" in argv)


def _validate(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(prog="ee-formation validate",
                                     description="Run every check the env runs on a scenario, without stepping physics.")
    parser.add_argument("scenario", metavar="SCENARIO", help="built-in scenario name or YAML/JSON file")
    parser.add_argument("--debug", action="store_true", help="on an error, show the traceback instead of the message")
    args = parser.parse_args(argv)

    def run() -> int:
        from ee_formation_env import validate_scenario

        scenario = validate_scenario(args.scenario)
        print(f"OK: {args.scenario}: {scenario.n_agents} arms, dim {scenario.dim}, {scenario.formation} formation, "
              f"{len(scenario.edges)} edges")
        return 0

    return report_errors(run, args.debug)


COMMANDS: dict[str, tuple[str, Callable[[Sequence[str]], int]]] = {
    "train": ("train a shared policy (residual or torque mode) and compare it with the references",
              lambda argv: train_command(argv, prog="ee-formation train")),
    "evaluate": ("evaluate reference policies or a trained run on seeded episodes: the metrics table", _evaluate),
    "validate": ("run every check the env runs on a scenario, without stepping physics", _validate),
}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="ee-formation", description="Formation control of manipulator end-effectors: train and evaluate policies, validate scenarios. The lab's studies run from a checkout: python -m studies --help.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {ee_formation_env.__version__}",
                        help="print the version of ee-formation-env and exit")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (help, _) in COMMANDS.items():
        commands.add_parser(name, help=help, add_help=False)  # each command parses (and documents) its own flags
    known, rest = parser.parse_known_args(argv)
    return COMMANDS[known.command][1](rest)


if __name__ == "__main__":
    sys.exit(main())
