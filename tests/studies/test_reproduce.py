"""Smoke test of ``python -m studies.reproduce`` (planar study, 2 s horizons)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import matplotlib.image
import numpy as np

from studies.reproduce import main

# Pixel size (width, height) of each planar figure: its figsize in inches x DPI (100; 75 for the joint
# figure, one row per arm and a q and a dq column per preset), two preset columns.
PLANAR_FIGURES = {"planar_trajectories": (1000, 490), "planar_edge_errors": (1100, 650),
                  "planar_estimates": (1100, 900), "planar_joints": (1110, 660)}


def _read_png(path: Path) -> np.ndarray:
    """The decoded image (height, width, channels), floats in [0, 1]; fails if the file is not a PNG."""
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", path
    return matplotlib.image.imread(path)


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

    for name, (width, height) in PLANAR_FIGURES.items():
        images = [_read_png(folder / f"{name}.png") for folder in (out, figures)]
        np.testing.assert_array_equal(images[0], images[1])  # the same figure in both places
        image = images[0]
        assert image.shape[:2] == (height, width), name  # figsize (inches) x DPI, two presets side by side
        rgb = image[..., :3]
        drawn = np.any(rgb < 0.9, axis=-1)  # anything visibly darker than the white background
        assert 0.01 < drawn.mean() < 0.5, name  # axes, text and curves, not a blank or a filled canvas
        colours = {tuple(pixel) for pixel in np.round(rgb[drawn] * 8).astype(int)}
        assert len(colours) >= 10, name  # coloured curves, not only black axes and text
