"""Smoke test of ``python -m benchmarks.paired_training``: a row per case, a tree against itself (no timing is
asserted: speed targets live in the benchmark's own output)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))  # benchmarks/ is a top-level folder of the repository, not an installed package

from benchmarks.paired_training import CASES, main  # noqa: E402


def test_paired_training_prints_a_row_per_case_for_a_tree_against_itself():
    pytest.importorskip("stable_baselines3")
    run = subprocess.run([sys.executable, "-m", "benchmarks.paired_training", "--before", str(REPO), "--pairs", "1",
                          "--quick"], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    rows = [line for line in run.stdout.splitlines() if line.startswith("| `")]
    assert [row.split("`")[1] for row in rows] == [" ".join(case) for case in CASES]
    ratios = [float(row.rstrip(" |").rsplit("|", 1)[1]) for row in rows]
    assert all(ratio > 0 for ratio in ratios)


def test_paired_training_refuses_a_before_tree_without_the_benchmarks(tmp_path):
    with pytest.raises(ValueError, match="--before"):
        main(["--before", str(tmp_path)])
