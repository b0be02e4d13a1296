"""Smoke test of ``python -m benchmarks.engines --quick``: both engines timed, the table with its ratios.

No timing is asserted (the machines vary): the figures are the benchmark's to report.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

pytest.importorskip("mujoco")

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))  # benchmarks/ is a top-level folder of the repository, not an installed package

from benchmarks.engines import main  # noqa: E402


def test_quick_run_prints_both_engines_and_their_ratios(capsys) -> None:
    assert main(["--quick", "--scenarios", "planar_square"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].startswith("| scenario | floor PyBullet (physics steps/s) | floor MuJoCo | ratio |")
    cells = [cell.strip() for cell in lines[2].strip("|").split("|")]
    assert cells[0] == "planar_square" and len(cells) == 7
    assert cells[3].endswith("x") and float(cells[3][:-1]) > 0 and float(cells[6][:-1]) > 0
