"""The lab's command: ``python -m studies COMMAND [flags]`` from the root of a checkout; ``python -m studies
COMMAND --help`` lists a command's flags.

The lab (``studies/``) produces the project's own evidence: the paper's figures, the studies, the gain tuning and
the scoreboard. It is not installed with the library (``ee-formation`` holds the library's commands: train,
evaluate, validate); each command here is ``python -m studies.<module>`` under one name.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import Sequence

from ee_formation_env.baselines.cli_errors import report_errors

#: Each lab command: its module in ``studies`` and what it does.
COMMANDS: dict[str, tuple[str, str]] = {
    "reproduce": ("reproduce", "the paper's figures from the three laws"),
    "robustness": ("robustness", "the laws under model mismatch, stalls and windup"),
    "random-scenarios": ("random_scenarios", "the laws on random planar and spatial scenarios"),
    "sensing": ("sensing", "the laws against noisy, delayed, biased and misaligned measurements"),
    "manoeuvres": ("manoeuvres", "the laws carrying and turning a formation: shape and tracking errors"),
    "tune-gains": ("tune_gains", "a seeded search of the laws' gains per built-in, written as data"),
    "tuned-perturbations": ("tuned_perturbations", "the tuned gains under the studies' perturbations"),
    "scoreboard": ("scoreboard", "every built-in scenario x method over training seeds, with intervals"),
    "team-size": ("team_size", "one set policy trained on 4 arms, zero-shot on teams of 3 to 8"),
    "learning-curves": ("learning_curves", "held-out success and settling against agent steps, with intervals"),
    "benchmarl-runs": ("benchmarl_runs", "BenchMARL runs on the training tasks, with the project's metrics"),
    "gallery": ("gallery", "images of every built-in scenario"),
}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m studies", description="The lab: studies, tuning and the "
                                     "scoreboard of ee-formation-env (from the root of a checkout).")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (_, help) in COMMANDS.items():
        commands.add_parser(name, help=help, add_help=False)  # each study parses (and documents) its own flags
    known, rest = parser.parse_known_args(argv)

    def run() -> int:  # the import inside: a study's missing extra is reported in one line like bad input
        status = importlib.import_module(f"studies.{COMMANDS[known.command][0]}").main(list(rest))  # a study returns its results, the scoreboard its exit status
        return status if isinstance(status, int) else 0

    return report_errors(run, "--debug" in rest)


if __name__ == "__main__":
    sys.exit(main())
