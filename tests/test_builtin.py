"""The built-in scenarios: YAML files parsing to exactly the data the env was pinned with, one registry."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

import ee_formation_env
from ee_formation_env import builtin, robots, scenario
from ee_formation_env.builtin import BUILTIN_SCENARIOS, builtin_scenario
from ee_formation_env.generators import square_vertices
from ee_formation_env.robots import SPATIAL_INITIAL_Q

# The built-ins as the Python code that defined them before they became YAML files produced them
# (json.dumps of each dict, generated once from that code): the YAML must parse to exactly these values,
# types (5 vs 5.0) and key order, so every episode is bit for bit what it was.
FIXTURE = Path(__file__).resolve().parent / "fixtures" / "builtin_scenarios.json"
BUILTIN_DIR = Path(builtin.__file__).resolve().parent / "builtin"


def _expected() -> dict:
    return json.loads(FIXTURE.read_text(encoding="utf-8"))


def test_registry_is_the_sorted_yaml_files():
    assert BUILTIN_SCENARIOS == tuple(sorted(path.stem for path in BUILTIN_DIR.glob("*.yaml")))
    # The pinned built-ins are all still there (built-ins added since are pinned by their own tests).
    assert set(_expected()) <= set(BUILTIN_SCENARIOS)


@pytest.mark.parametrize("name", sorted(json.loads(FIXTURE.read_text(encoding="utf-8"))))
def test_yaml_builtin_equals_the_former_python_builtin_exactly(name):
    # json.dumps writes floats with repr and keeps int/float and key order: equal text, identical data.
    assert json.dumps(builtin_scenario(name)) == json.dumps(_expected()[name])


@pytest.mark.parametrize("name", sorted(BUILTIN_SCENARIOS))
def test_each_file_says_what_it_is(name):
    text = (BUILTIN_DIR / f"{name}.yaml").read_text(encoding="utf-8")
    assert text.startswith(f"# {name}: ")


def test_builtin_scenario_is_a_fresh_copy():
    data = builtin_scenario("planar_square")
    data["arms"][0]["initial_q"][0] = 99.0
    data["shape"].append([0.0, 0.0])
    assert json.dumps(builtin_scenario("planar_square")) == json.dumps(_expected()["planar_square"])
    assert builtin_scenario("planar_square") is not builtin_scenario("planar_square")


def test_unknown_builtin_names_the_available_ones():
    with pytest.raises(ValueError, match="unknown built-in scenario 'nope'.*planar_square"):
        builtin_scenario("nope")


def test_planar_numbers_are_the_papers_expressions():
    """The written-out numbers are the expressions they stand for, to the last bit."""
    for name in ("planar_square", "planar_square_displacement", "planar_square_rotated"):
        data = builtin_scenario(name)
        assert data["shape"] == square_vertices(3.0)
        assert data["edges"] == [[0, 1], [1, 2], [2, 3], [3, 0], [0, 2]]
        yaws = [arm["base_rpy"][2] for arm in data["arms"]]
        for k, (arm, yaw) in enumerate(zip(data["arms"], yaws)):
            assert arm["initial_q"] == [[0.0, math.pi / 2, math.pi, 3 * math.pi / 2][k] - yaw, math.pi / 3]
    assert [arm["base_rpy"][2] for arm in builtin_scenario("planar_square_rotated")["arms"]] == [0.4, -1.1, 2.3, 0.9]


def test_spatial_numbers_are_their_expressions():
    half = 0.4 / (2 * math.sqrt(2))
    corners = [[-half, -half, -half], [half, -half, half], [half, half, -half], [-half, half, half]]
    shape = [[c + o for c, o in zip((0.25, 0.25, -0.5), corner)] for corner in corners]
    for name in ("spatial_tetrahedron", "spatial_tetrahedron_displacement"):
        data = builtin_scenario(name)
        assert data["shape"] == shape
        for i, arm in enumerate(data["arms"]):
            x, y, _ = arm["base_position"]
            assert arm["base_rpy"] == [0.0, 0.0, math.atan2(0.25 - y, 0.25 - x)]
            assert arm["initial_q"] == list(SPATIAL_INITIAL_Q[i % 2])


def test_old_names_are_plain_re_exports():
    assert scenario.BUILTIN_SCENARIOS is BUILTIN_SCENARIOS is ee_formation_env.BUILTIN_SCENARIOS
    assert scenario.builtin_scenario is builtin_scenario
    assert scenario.ROBOTS is robots.ROBOTS is ee_formation_env.ROBOTS
    assert scenario.RobotSpec is robots.RobotSpec
    assert scenario.SPATIAL_INITIAL_Q is SPATIAL_INITIAL_Q
