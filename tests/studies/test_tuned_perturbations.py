"""The tuned sets under the sensing and mismatch perturbations (studies/tuned_perturbations.py): each case runs
the defaults and the tuned set on the same seeds, and every loss of success is listed."""

from __future__ import annotations

from conftest import write_tuned_file

from ee_formation_env.baselines.reference import tuned
from studies import tuned_perturbations


def test_quick_run_compares_each_tuned_law_with_its_defaults_and_lists_losses(tmp_path, monkeypatch):
    monkeypatch.setattr(tuned, "TUNED_DIR", tmp_path / "tuned")
    write_tuned_file(tmp_path / "tuned")
    records = tuned_perturbations.main(["--quick", "--out", str(tmp_path / "out")])
    assert [(r["scenario"], r["law"], r["knob"]) for r in records] == [("planar_square", "gradient", "noise")]
    assert {"default", "tuned"} <= set(records[0])
    text = (tmp_path / "out" / "perturbations.md").read_text()
    assert "| planar_square | gradient | noise 0.002 |" in text and "The tuned set loses success in" in text
    lost = [{**records[0], "default": {**records[0]["default"], "success": 1.0},
             "tuned": {**records[0]["tuned"], "success": 0.5}}]
    assert tuned_perturbations.losses(lost) == lost
    assert "loses success in 1 of 1 cases: planar_square / gradient / noise 0.002" in tuned_perturbations.table(lost)


def test_scenario_selects_the_cases_run(tmp_path, monkeypatch):
    monkeypatch.setattr(tuned, "TUNED_DIR", tmp_path / "tuned")
    write_tuned_file(tmp_path / "tuned")
    write_tuned_file(tmp_path / "tuned", "planar_square_displacement")
    records = tuned_perturbations.main(["--quick", "--out", str(tmp_path / "out"), "--scenario",
                                        "planar_square_displacement"])
    assert [(r["scenario"], r["law"]) for r in records] == [("planar_square_displacement", "gradient")]
