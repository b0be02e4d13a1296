"""Paired before/after SB3 training throughput (agent steps/s, PPO updates included), two source trees run
alternately.

    python -m benchmarks.paired_training --before OLD_TREE [--pairs 3] [--quick]

``OLD_TREE``: an export of the old code with the two symlinks of :mod:`benchmarks.paired_evaluation`. Each
measurement is a fresh process per tree running that tree's own ``benchmarks.run.bench_training`` (the
``sb3_training`` section: ``train.py``'s model built from its flags, one untimed update, then the fastest of
three timed runs of four updates; ``--quick``: one run of one update, a smoke test) with the case's flags; a tree whose ``TrainConfig`` has a ``recipe`` field
also gets ``--recipe none``, so that both trees train with their flat defaults. The trees alternate, pair after
pair, so that both see the same phase of the machine. The table gives agent steps/s of each tree (median over
pairs) and the ratio after / before of each pair.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]
CASES = (("--mode", "residual"), ("--mode", "torque"))

# Run in the child process (cwd: the tree): agent steps/s of one case, printed as JSON.
CHILD = """
import dataclasses, json, sys
from benchmarks.run import FULL, QUICK, bench_training
from ee_formation_env.baselines.learned.config import TrainConfig
budget, extra = (QUICK if sys.argv[1] == "quick" else FULL), sys.argv[2:]
if "recipe" in {field.name for field in dataclasses.fields(TrainConfig)}:
    extra = [*extra, "--recipe", "none"]
print(json.dumps(bench_training(budget, extra)[0]["agent_steps_per_s"]))
"""


def agent_steps_per_second(tree: Path, case: tuple[str, ...], quick: bool = False) -> float:
    env = dict(os.environ, PYTHONPATH=str(tree))
    result = subprocess.run([sys.executable, "-c", CHILD, "quick" if quick else "full", *case], env=env, cwd=str(tree), check=True,
                            capture_output=True, text=True)
    return float(json.loads(result.stdout.strip().splitlines()[-1]))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.paired_training", description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", type=Path, required=True, help="the old source tree (module docstring)")
    parser.add_argument("--pairs", type=int, default=3, help="before/after pairs per case")
    parser.add_argument("--quick", action="store_true", help="one timed update per run (a smoke test, not a figure)")
    args = parser.parse_args(argv)
    before_tree = args.before.resolve()
    if not (before_tree / "benchmarks" / "run.py").is_file():
        raise ValueError(f"--before: {before_tree} holds no benchmarks/run.py")
    if args.pairs < 1:
        raise ValueError("--pairs: expected an integer >= 1")
    print("| train.py flags | before, agent steps/s | after, agent steps/s | after / before, each pair | median |")
    print("|---|---:|---:|---|---:|")
    for case in CASES:
        before, after = [], []
        for _ in range(args.pairs):
            before.append(agent_steps_per_second(before_tree, case, args.quick))
            after.append(agent_steps_per_second(HERE, case, args.quick))
        ratios = [a / b for a, b in zip(after, before)]
        print(f"| `{' '.join(case)}` | {statistics.median(before):,.0f} | {statistics.median(after):,.0f} | "
              f"{', '.join(f'{r:.2f}' for r in ratios)} | {statistics.median(ratios):.2f} |", flush=True)


if __name__ == "__main__":
    main()
