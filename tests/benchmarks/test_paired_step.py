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
