"""Paired before/after timing of the parallel env's ``step`` (zero actions), two source trees run alternately.

    python -m benchmarks.paired_step --before OLD_TREE [--pairs 5] [--steps 4000] [--num-envs K]
    python -m benchmarks.paired_step --before OLD_TREE --counter instructions [--steps 1000]

``OLD_TREE``: an export of the old code with the two symlinks of :mod:`benchmarks.paired_evaluation`, so that
``PYTHONPATH=OLD_TREE`` imports the old package. Each measurement is a fresh process per tree that builds the
env through the public API (``ee_formation_env.parallel_env(name, frame_skip=...)``, the same call in both
trees), steps it 200 times to warm up, then times ``--steps`` steps from a fixed reset three times and keeps
the fastest; the trees alternate, pair after pair, so that both see the same phase of the machine. The table
gives env steps/s of each tree (median over pairs) and the ratio after / before of each pair. ``--num-envs K``
times the batched env of K copies instead (``ee_formation_env.vector_env``, autoreset), at the scenarios' own
frame_skip.

``--counter instructions`` counts instead of timing: each tree's child runs under valgrind's callgrind (with
``PYTHONHASHSEED=0``) twice, with ``--steps`` and with twice as many, and the difference of the two instruction
totals over the extra steps is the instructions per env step, setup and warm-up cancelled. The count is the
same whatever else the machine runs (one pair is enough); it is work, not time: cache misses are not in it.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]
CASES = (("planar_square", 1), ("planar_square", 10), ("spatial_tetrahedron", 1), ("spatial_tetrahedron", 5))

# Run in the child process: the steps/s of one (scenario, frame_skip) case, printed as JSON.
CHILD = """
import json, sys, time
import numpy as np
import ee_formation_env
name, frame_skip, steps, num_envs = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
if num_envs:  # the batched env: K copies, autoreset, batched zero actions
    env = ee_formation_env.vector_env(name, num_envs=num_envs, frame_skip=frame_skip)
    zero = {a: np.zeros(env.batched_action_space(a).shape, dtype=np.float32) for a in env.possible_agents}
else:
    env = ee_formation_env.parallel_env(name, frame_skip=frame_skip)
    zero = {a: np.zeros(env.action_space(a).shape, dtype=np.float32) for a in env.possible_agents}
best = float("inf")
for repeat in range(4):
    env.reset(seed=0)
    count = 200 if repeat == 0 else steps
    start = time.perf_counter()
    for _ in range(count):
        env.step(zero)
        if not num_envs and not env.agents:
            env.reset(seed=0)
    if repeat:
        best = min(best, time.perf_counter() - start)
env.close()
print(json.dumps(steps * max(num_envs, 1) / best))
"""


def steps_per_second(tree: Path, name: str, frame_skip: int, steps: int, num_envs: int = 0) -> float:
    """Env steps/s of ``tree``'s parallel env (``num_envs`` 0) or batched env of ``num_envs`` copies (all copies'
    steps counted)."""
    env = dict(os.environ)
    if tree != HERE:
        env["PYTHONPATH"] = str(tree)
    result = subprocess.run([sys.executable, "-c", CHILD, name, str(frame_skip), str(steps), str(num_envs)], env=env,
                            cwd=str(tree), check=True, capture_output=True, text=True)
    return float(json.loads(result.stdout.strip().splitlines()[-1]))


def instructions_per_step(tree: Path, name: str, frame_skip: int, steps: int) -> float:
    """Instructions per env step of ``tree``'s env (module docstring, ``--counter instructions``)."""
    env = dict(os.environ, PYTHONHASHSEED="0")
    if tree != HERE:
        env["PYTHONPATH"] = str(tree)
    totals = []
    for count in (steps, 2 * steps):
        result = subprocess.run(["valgrind", "--tool=callgrind", "--callgrind-out-file=/dev/null", sys.executable,
                                 "-c", CHILD, name, str(frame_skip), str(count), "0"], env=env, cwd=str(tree),
                                check=True, capture_output=True, text=True)
        totals.append(int(re.findall(r"Collected : (\d+)", result.stderr)[-1]))
    return (totals[1] - totals[0]) / (3 * steps)  # the child times three repeats of ``steps``


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.paired_step", description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", type=Path, required=True, help="the old source tree (module docstring)")
    parser.add_argument("--pairs", type=int, default=5, help="before/after pairs per case")
    parser.add_argument("--steps", type=int, default=4000, help="env steps per timed run")
    parser.add_argument("--num-envs", type=int, default=0, metavar="K",
                        help="time the batched env of K copies at each scenario's own frame_skip instead (env steps "
                             "of all copies per s)")
    parser.add_argument("--counter", choices=("time", "instructions"), default="time",
                        help="wall-clock steps/s, or instructions per step under callgrind (module docstring)")
    args = parser.parse_args(argv)
    before_tree = args.before.resolve()
    if not (before_tree / "ee_formation_env" / "__init__.py").is_file():
        raise ValueError(f"--before: {before_tree} holds no ee_formation_env package")
    if args.pairs < 1 or args.steps < 1:
        raise ValueError("--pairs and --steps: expected integers >= 1")
    if args.num_envs < 0 or (args.num_envs and args.counter != "time"):
        raise ValueError("--num-envs: expected an integer >= 1, with the time counter")
    if args.counter == "instructions":
        if shutil.which("valgrind") is None:
            raise ValueError("--counter instructions: needs valgrind on the PATH")
        print("| case | before, instructions/step | after, instructions/step | before / after (speed ratio) |")
        print("|---|---:|---:|---:|")
        for name, frame_skip in CASES:
            before = instructions_per_step(before_tree, name, frame_skip, args.steps)
            after = instructions_per_step(HERE, name, frame_skip, args.steps)
            print(f"| {name}, frame_skip {frame_skip} | {before:,.0f} | {after:,.0f} | {before / after:.3f} |",
                  flush=True)
        return
    print("| case | before, steps/s | after, steps/s | after / before, each pair | median |")
    print("|---|---:|---:|---|---:|")
    cases = CASES if not args.num_envs else tuple(case for case in CASES if case[1] > 1)
    for name, frame_skip in cases:
        before, after = [], []
        for _ in range(args.pairs):
            before.append(steps_per_second(before_tree, name, frame_skip, args.steps, args.num_envs))
            after.append(steps_per_second(HERE, name, frame_skip, args.steps, args.num_envs))
        ratios = [a / b for a, b in zip(after, before)]
        batched = f", K = {args.num_envs}" if args.num_envs else ""
        print(f"| {name}, frame_skip {frame_skip}{batched} | {statistics.median(before):,.0f} | "
              f"{statistics.median(after):,.0f} | {', '.join(f'{r:.2f}' for r in ratios)} | "
              f"{statistics.median(ratios):.2f} |", flush=True)


if __name__ == "__main__":
    main()
