"""The tuned sets under the sensing and mismatch perturbations (studies/tuned_perturbations.py): each case runs
the defaults and the tuned set on the same seeds, and every loss of success is listed."""

from __future__ import annotations

import json

from ee_formation_env.baselines.reference import tuned
from ee_formation_env.builtin import builtin_scenario
from studies import tuned_perturbations


def test_quick_run_compares_each_tuned_law_with_its_defaults_and_lists_losses(tmp_path, monkeypatch):
    monkeypatch.setattr(tuned, "TUNED_DIR", tmp_path / "tuned")
    (tmp_path / "tuned").mkdir()
    point = {"kp_scale": 2.0, "kd_scale": 1.0, "saturated": False, "spring_scale": 1.0, "rate_steps": 0.0}
    (tmp_path / "tuned" / "planar_square.json").write_text(json.dumps({
        "schema": tuned.TUNED_SCHEMA, "scenario": "planar_square",
        "scenario_digest": tuned.scenario_digest(builtin_scenario("planar_square")),
        "laws": {"gradient": {"point": point, "improved": True}}}))
    records = tuned_perturbations.main(["--quick", "--out", str(tmp_path / "out")])
    assert [(r["scenario"], r["law"], r["knob"]) for r in records] == [("planar_square", "gradient", "noise")]
    assert {"default", "tuned"} <= set(records[0])
    text = (tmp_path / "out" / "perturbations.md").read_text()
    assert "| planar_square | gradient | noise 0.002 |" in text and "The tuned set loses success in" in text
    lost = [{**records[0], "default": {**records[0]["default"], "success": 1.0},
             "tuned": {**records[0]["tuned"], "success": 0.5}}]
    assert tuned_perturbations.losses(lost) == lost
    assert "loses success in 1 of 1 cases: planar_square / gradient / noise 0.002" in tuned_perturbations.table(lost)
