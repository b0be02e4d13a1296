"""Smoke test of ``python -m benchmarks.paired_step``: the table of every case, a tree against itself (no
timing is asserted: speed targets live in the benchmark's own output)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))  # benchmarks/ is a top-level folder of the repository, not an installed package

from benchmarks.paired_step import CASES, main  # noqa: E402


def test_paired_step_prints_a_row_per_case_for_a_tree_against_itself():
    run = subprocess.run([sys.executable, "-m", "benchmarks.paired_step", "--before", str(REPO), "--pairs", "1",
                          "--steps", "5"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    rows = [line for line in run.stdout.splitlines() if line.startswith("| ") and "frame_skip" in line]
    assert [row.split(" | ")[0][2:] for row in rows] == [f"{name}, frame_skip {fs}" for name, fs in CASES]


def test_paired_step_refuses_a_before_tree_without_the_package(tmp_path):
    with pytest.raises(ValueError, match="--before"):
        main(["--before", str(tmp_path)])


def test_the_instruction_counter_refuses_to_start_without_valgrind(monkeypatch):
    import benchmarks.paired_step as paired_step

    monkeypatch.setattr(paired_step.shutil, "which", lambda name: None)
    with pytest.raises(ValueError, match="--counter instructions: needs valgrind"):
        main(["--before", str(REPO), "--counter", "instructions"])


def test_the_instruction_count_per_step_is_the_difference_of_two_runs_over_the_extra_steps(monkeypatch):
    import benchmarks.paired_step as paired_step

    calls = []

    def fake_run(command, **kwargs):
        steps, num_envs = int(command[-2]), command[-1]
        assert num_envs == "0"  # the parallel env: the counter counts its steps only
        calls.append((command[:2], steps, kwargs["env"]["PYTHONHASHSEED"]))
        # 5,000,000 instructions of setup, 3 repeats of `steps` steps at 1,000 instructions each
        total = 5_000_000 + 3 * steps * 1_000
        return subprocess.CompletedProcess(command, 0, "", f"==1== Collected : {total}\n")

    monkeypatch.setattr(paired_step.subprocess, "run", fake_run)
    assert paired_step.instructions_per_step(REPO, "planar_square", 1, 10) == 1_000.0
    assert calls == [(["valgrind", "--tool=callgrind"], 10, "0"), (["valgrind", "--tool=callgrind"], 20, "0")]


def test_the_batched_child_counts_the_steps_of_every_copy():
    import benchmarks.paired_step as paired_step

    # a real child process on this tree: K = 2 copies, 5 timed steps
    rate = paired_step.steps_per_second(REPO, "planar_square", 10, 5, num_envs=2)
    single = paired_step.steps_per_second(REPO, "planar_square", 10, 5)
    assert rate > 0 and single > 0
    with pytest.raises(ValueError, match="--num-envs"):
        main(["--before", str(REPO), "--num-envs", "-1"])
