"""The README's scenario-key table agrees with the one definition of the keys (the Scenario dataclass)."""

from __future__ import annotations

import re
from dataclasses import fields
from pathlib import Path

import pytest

from ee_formation_env.scenario import Scenario, _default, scenario_keys_table

README = Path(__file__).resolve().parent.parent / "README.md"
_DOCUMENTED_ELSEWHERE = {"name", "arms", "edges", "shape", "formation", "dim"}  # the YAML example shows them


def _readme_key_rows() -> dict[str, str]:
    rows = {}
    for line in README.read_text(encoding="utf-8").splitlines():
        match = re.match(r"\| `(\w+)` \| ([^|]*) \|", line)
        if match and match.group(1) in {spec.name for spec in fields(Scenario)}:
            rows.setdefault(match.group(1), match.group(2).strip())
    return rows


def test_readme_lists_every_scenario_key():
    documented = set(_readme_key_rows())
    assert {spec.name for spec in fields(Scenario)} - _DOCUMENTED_ELSEWHERE <= documented


@pytest.mark.parametrize("key", ["physics_hz", "initial_q_noise", "joint_damping", "max_joint_velocity",
                                 "singularity_threshold"])
def test_readme_numeric_defaults_match_the_dataclass(key):
    assert float(_readme_key_rows()[key]) == _default(key)


def test_generated_table_has_a_row_per_key():
    table = scenario_keys_table()
    for spec in fields(Scenario):
        if spec.name != "name":
            assert f"``{spec.name}``" in table


def test_scenario_docs_name_every_builtin():
    """docs/scenarios.md documents the built-ins: every YAML file of ee_formation_env/builtin/ is named there."""
    from ee_formation_env.builtin import BUILTIN_SCENARIOS

    page = README.parent / "docs" / "scenarios.md"
    if not page.is_file():
        pytest.skip("docs/scenarios.md is not written yet")
    text = page.read_text(encoding="utf-8")
    assert [name for name in BUILTIN_SCENARIOS if f"`{name}`" not in text] == []
