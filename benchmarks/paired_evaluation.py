"""Paired before/after timing of ``train.py --eval-only RUN`` (the held-out comparison: every policy x
``--eval-episodes`` episodes), two source trees run alternately on the same saved runs, with the numbers
checked equal.

    python -m benchmarks.paired_evaluation --before OLD_TREE RUN_DIR [RUN_DIR ...]

``OLD_TREE``: an export of the old code (``git archive <commit> | tar -x -C OLD_TREE``) with the two
symlinks ``OLD_TREE/ee_formation_env/baselines -> ../baselines`` and ``.../assets -> ../assets``, so that
``PYTHONPATH=OLD_TREE`` imports the old package (worker processes included) ahead of the editable install.
Each run's ``comparison.json`` of both trees must agree number for number (the per-episode metrics).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]


def _newest(run_dir: Path) -> Path:
    return max((run_dir / "evaluations").iterdir(), key=lambda path: path.stat().st_mtime) / "comparison.json"


def timed(tree: Path, run_dir: Path, extra: list[str]) -> tuple[float, dict]:
    env = dict(os.environ)
    if tree != HERE:
        env["PYTHONPATH"] = str(tree)
    command = [sys.executable, str(tree / "train.py"), "--eval-only", str(run_dir), "--no-progress", *extra]
    start = time.perf_counter()
    subprocess.run(command, env=env, cwd=tree, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - start, json.loads(_newest(run_dir).read_text())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", type=Path, required=True)
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("runs", type=Path, nargs="+")
    args, extra = parser.parse_known_args()
    for run_dir in args.runs:
        for _ in range(args.repeats):
            before, old = timed(args.before.resolve(), run_dir.resolve(), extra)
            after, new = timed(HERE, run_dir.resolve(), extra)
            same = json.dumps(old["results"]) == json.dumps(new["results"])
            print(f"{run_dir.name}: before {before:.1f} s, after {after:.1f} s, speed-up {before / after:.2f}x, "
                  f"results identical: {same}", flush=True)


if __name__ == "__main__":
    main()
