"""The robustness study's building blocks: mismatched arms, the Prop. 4.1 quantities, a quick run."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ElementTree

import numpy as np
import pytest

from studies import robustness
from ee_formation_env.kinematics import chain_model
from ee_formation_env.scenario import ROBOTS


def _origin(path: str, joint: str) -> np.ndarray:
    for element in ElementTree.parse(path).getroot().iter("joint"):
        if element.get("name") == joint:
            return np.array([float(v) for v in element.find("origin").get("xyz").split()])
    raise AssertionError(joint)


@pytest.mark.parametrize("kind", robustness.KINDS)
def test_each_mismatch_kind_changes_the_arm_as_documented(kind, tmp_path):
    path = robustness.perturbed_planar_urdf(kind, 0.3, np.random.default_rng(0), str(tmp_path))
    nominal = str(ROBOTS["planar_2link"].urdf)
    tool, elbow = _origin(path, "ee_joint"), _origin(path, "joint_2")
    if kind == "uniform":
        assert np.isclose(tool[0], elbow[0]) and abs(tool[0] - 1.5) == pytest.approx(0.45)
    elif kind == "lengths":
        assert tool[1] == elbow[1] == 0.0 and not np.allclose([tool[0], elbow[0]], 1.5)
    elif kind == "offsets":
        assert np.linalg.norm(tool - _origin(nominal, "ee_joint")) == pytest.approx(0.45)
    else:  # zero_component: only the sideways tool offset, which the nominal parameter vector lacks
        assert abs(tool[1]) == pytest.approx(0.45) and tool[0] == 1.5 and elbow[0] == 1.5
        assert "ee_joint.y" not in chain_model(nominal, "ee_link").param_names
    truth = chain_model(path, "ee_link")
    assert not np.allclose(truth.forward([0.3, 0.7]), chain_model(nominal, "ee_link").forward([0.3, 0.7]))


def test_quick_study_writes_numbers_and_figures(tmp_path):
    results = robustness.main(["--quick", "--only", "separating", "--out", str(tmp_path)])
    rows = results["separating"]
    assert len(rows) == 3 * len(robustness.SEEDS)
    for row in rows:
        assert row["delta"] > 0 and row["delta_star"] > 0  # a_hat(0) = [2.7, 0.3] is not the truth
        assert 0.0 <= row["boundary_fraction"] <= 1.0
    assert json.loads((tmp_path / "robustness.json").read_text())["separating"]
    assert (tmp_path / "robustness_separating.png").stat().st_size > 0


def test_quick_spatial_study_runs_every_law_with_mismatch(tmp_path):
    results = robustness.main(["--quick", "--only", "spatial", "--out", str(tmp_path)])
    rows = results["spatial"]
    assert len(rows) == 3 * (1 + len(robustness.SPATIAL_KINDS))  # exact arms + one case per kind, 3 laws
    assert {row["kind"] for row in rows} == {"none", *robustness.SPATIAL_KINDS}
    for row in rows:
        assert row["fault"] == "" and np.isfinite(row["final_max_length_error"])
    # The mismatch reaches the simulated arms: law-I (nominal model, no internal model) ends elsewhere.
    law1 = {row["kind"]: row["final_max_length_error"] for row in rows if row["law"] == "law-I"}
    assert law1["length"] != law1["none"] and law1["mass"] != law1["none"]
    assert "| length | 0.5 |" in robustness.spatial_table(rows)
    assert (tmp_path / "robustness_spatial.png").stat().st_size > 0
