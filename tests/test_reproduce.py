"""Smoke test of ``python -m baselines.reproduce`` (planar study, 2 s horizons)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from baselines.reproduce import main

PLANAR_FIGURES = ("planar_trajectories", "planar_edge_errors", "planar_estimates", "planar_joints")


def test_quick_planar_reproduction(tmp_path: Path) -> None:
    out, figures = tmp_path / "out", tmp_path / "figures"
    rows = main(["--quick", "--only", "planar", "--out", str(out), "--figures-dir", str(figures)])

    summary = json.loads((out / "summary.json").read_text())
    assert [row["run"] for row in summary] == ["planar_paper", "planar_defaults"] == [row["run"] for row in rows]
    for row in summary:
        assert row["physics_fault"] == ""
        assert row["sim_time_s"] == 2.0
        assert np.isfinite(row["final_max_abs_edge_error"]) and row["wall_time_s"] > 0
        assert len(row["final_a_hat"]) == 4 and all(len(a) == 2 for a in row["final_a_hat"].values())
    paper, defaults = summary
    assert paper["peak_torque"] > 1e3 > defaults["peak_torque"] == 50.0  # lifted vs the 50 N m limit
    assert paper["final_max_abs_edge_error"] < 1e-6  # the paper's gains converge within 2 s on the 3.0 m square

    for run in ("planar_paper", "planar_defaults"):
        with open(out / f"{run}.csv", newline="") as handle:
            table = list(csv.reader(handle))
        header, body = table[0], np.array(table[1:], dtype=float)
        expected = ["t", *(f"e{k}" for k in range(5)), *(f"a_hat{i}" for i in range(4)), "q0", "dq0", "ee0_x"]
        assert all(any(name == column or column.startswith(name + "_") for column in header) for name in expected)
        assert body.shape[1] == len(header) == 1 + 5 + 8 + 8 + 8 + 12
        assert body.shape[0] > 100 and body[0, 0] == 0.0 and body[-1, 0] == 2.0
        assert np.all(np.isfinite(body))
        assert np.ptp(body[:, header.index("q0_0")]) > 0  # the arms moved

    for name in PLANAR_FIGURES:
        for folder in (out, figures):
            path = folder / f"{name}.png"
            assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
            assert 10_000 < path.stat().st_size < 200_000
