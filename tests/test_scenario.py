"""Scenario parsing: built-ins, files, overrides, round trips and field-level errors."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pybullet
import pytest
import yaml

import ee_formation_env
from ee_formation_env.scenario import (BUILTIN_SCENARIOS, ROBOTS, RewardConfig, Scenario, builtin_scenario,
                                       load_scenario)

from conftest import scenario_dict

PAPER_2D_INCIDENCE = [[1, 0, 0, -1, 1], [-1, 1, 0, 0, 0], [0, -1, 1, 0, -1], [0, 0, -1, 1, 0]]
PAPER_3D_INCIDENCE = [[1, 1, -1, 1, 0, 0], [-1, 0, 0, 0, 0, 1], [0, -1, 1, 0, 0, -1], [0, 0, 0, -1, -1, -1]]


# ------------------------------------------------------------------------------------------ built-ins
@pytest.mark.parametrize("name", sorted(BUILTIN_SCENARIOS))
def test_builtin_scenarios_parse(name):
    scenario = load_scenario(name)
    assert isinstance(scenario, Scenario) and scenario.name == name
    assert scenario.n_agents == 4
    assert len(scenario.shape) == 4 and all(len(row) == scenario.dim for row in scenario.shape)
    assert scenario.max_steps == round(scenario.episode_seconds * scenario.physics_hz / scenario.frame_skip)
    assert builtin_scenario(name) is not builtin_scenario(name)  # fresh copies


def test_planar_square_is_the_papers_set_up():
    scenario = load_scenario("planar_square")
    assert scenario.dim == 2 and scenario.formation == "distance"
    assert [arm.base_position for arm in scenario.arms] == [(0, 0, 0), (6, 0, 0), (6, 6, 0), (0, 6, 0)]
    q0 = [(0.0, math.pi / 3), (math.pi / 2, math.pi / 3), (math.pi, math.pi / 3), (3 * math.pi / 2, math.pi / 3)]
    for arm, q in zip(scenario.arms, q0):
        np.testing.assert_allclose(arm.initial_q, q)
        assert arm.robot == "planar_2link"
    assert scenario.edges == ((0, 1), (1, 2), (2, 3), (3, 0), (0, 2))
    shape = np.asarray(scenario.shape)
    sides = np.linalg.norm(shape - np.roll(shape, -1, axis=0), axis=1)
    np.testing.assert_allclose(sides, 3.0)
    np.testing.assert_allclose(shape.mean(axis=0), [3.0, 3.0])


def test_planar_square_initial_end_effectors(make_env):
    """The paper's initial q put the end-effectors at (2.25, 1.299), (4.701, 2.25), (3.75, 4.701), (1.299, 3.75)."""
    for name in ("planar_square", "planar_square_rotated"):  # rotated bases compensate q1: same positions
        env = make_env(name, initial_q_noise=0.0)
        env.reset(seed=0)
        client = env.world.client
        positions = np.array([pybullet.getLinkState(arm.body, pybullet.getNumJoints(arm.body, physicsClientId=client) - 1,
                                                    computeForwardKinematics=True, physicsClientId=client)[4]
                              for arm in env.arms])
        expected = [[2.25, 1.299], [4.701, 2.25], [3.75, 4.701], [1.299, 3.75]]
        np.testing.assert_allclose(positions[:, :2], expected, atol=1e-3)
        np.testing.assert_allclose(positions[:, 2], 0.0, atol=1e-9)


def test_spatial_tetrahedron_is_regular_with_side_0_4():
    scenario = load_scenario("spatial_tetrahedron")
    shape = np.asarray(scenario.shape)
    distances = [np.linalg.norm(shape[i] - shape[j]) for i in range(4) for j in range(i + 1, 4)]
    np.testing.assert_allclose(distances, 0.4, atol=1e-12)
    assert len({frozenset(e) for e in scenario.edges}) == 6  # K4
    assert all(arm.robot == "pera_arm" for arm in scenario.arms)


def test_robots_exist():
    for spec in ROBOTS.values():
        assert spec.urdf.is_file()


# ------------------------------------------------------------------------------------------ overrides
def test_overrides_replace_top_level_keys_and_merge_reward():
    scenario = load_scenario("planar_square", episode_seconds=2.0, frame_skip=4, reward={"in_tolerance": 0.5})
    assert scenario.episode_seconds == 2.0 and scenario.frame_skip == 4 and scenario.max_steps == 500
    assert scenario.reward == RewardConfig(formation=1.0, in_tolerance=0.5, team=False)
    merged = load_scenario(scenario_dict(reward={"formation": 0.3}), reward={"team": True})
    assert merged.reward == RewardConfig(formation=0.3, in_tolerance=1.0, team=True)
    with pytest.raises(ValueError, match="reward.error_floor: expected a value below error_ceiling"):
        load_scenario("planar_square", reward={"error_floor": 200.0})
    with pytest.raises(ValueError, match="reward.position_tolerance: expected a positive"):
        load_scenario("planar_square", reward={"position_tolerance": 0.0})


def test_env_accepts_a_scenario_object(make_env):
    scenario = load_scenario("planar_square", episode_seconds=0.3)
    env = make_env(scenario, episode_seconds=0.3)
    assert env.scenario == scenario
    same = ee_formation_env.parallel_env(scenario)
    try:
        assert same.scenario is scenario
    finally:
        same.close()
    # Overrides on a Scenario object re-parse it and keep its name.
    custom = load_scenario({**scenario_dict("planar_square", frame_skip=5), "name": "mine"})
    assert custom.name == "mine"
    changed = make_env(custom, episode_seconds=0.2, initial_q_noise=0.0)
    assert changed.scenario.name == "mine" and changed.scenario.frame_skip == 5
    assert changed.scenario.episode_seconds == 0.2 and changed.scenario.max_steps == 40


# ------------------------------------------------------------------------------------------ files and round trips
@pytest.mark.parametrize("name", sorted(BUILTIN_SCENARIOS))
def test_to_dict_round_trips(name):
    scenario = load_scenario(name, episode_seconds=1.5, reward={"team": True}, initial_q_noise=0.01)
    data = scenario.to_dict()
    json.dumps(data)  # plain data
    again = load_scenario(data)
    assert again == scenario
    assert again.to_dict() == data


@pytest.mark.parametrize("suffix", [".yaml", ".yml", ".json"])
def test_scenario_files_load(tmp_path, suffix):
    scenario = load_scenario("planar_square_displacement", episode_seconds=0.7)
    data = scenario.to_dict()
    data["name"] = "from_file"
    path = tmp_path / f"my_task{suffix}"
    path.write_text(json.dumps(data) if suffix == ".json" else yaml.safe_dump(data), encoding="utf-8")
    loaded = load_scenario(path)
    assert loaded.name == "from_file"
    assert loaded.episode_seconds == 0.7 and loaded.formation == "displacement"
    assert loaded.arms == scenario.arms and loaded.edges == scenario.edges and loaded.shape == scenario.shape
    # A file without a name takes its stem.
    del data["name"]
    path.write_text(json.dumps(data) if suffix == ".json" else yaml.safe_dump(data), encoding="utf-8")
    assert load_scenario(str(path)).name == "my_task"


def test_relative_urdf_resolves_against_the_scenario_file(tmp_path, monkeypatch, make_env):
    robots = tmp_path / "robots"
    robots.mkdir()
    shutil.copy(ROBOTS["planar_2link"].urdf, robots / "arm.urdf")
    data = scenario_dict("planar_square")
    for arm in data["arms"]:
        del arm["robot"]
        arm["urdf"] = "robots/arm.urdf"
        arm["ee_link"] = "ee_link"
    path = tmp_path / "task.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    scenario = load_scenario(str(path))
    assert all(arm.urdf == str((robots / "arm.urdf").resolve()) for arm in scenario.arms)
    env = make_env(str(path))
    observations, _ = env.reset(seed=0)
    assert observations["arm_0"].shape == (19,)


def test_yaml_written_by_hand(tmp_path):
    path = tmp_path / "pair.yaml"
    path.write_text(
        "arms:\n"
        "  - {robot: planar_2link, base_position: [0, 0, 0], initial_q: [0.0, 1.0]}\n"
        "  - {robot: planar_2link, base_position: [3, 0, 0], base_rpy: [0, 0, 3.14159], initial_q: [0.0, 1.0]}\n"
        "edges: [[0, 1]]\n"
        "shape: [[0, 0], [1, 0]]\n"
        "formation: displacement\n"
        "dim: 2\n"
        "reward: {formation: 0.5}\n",
        encoding="utf-8")
    scenario = load_scenario(path)
    assert scenario.name == "pair" and scenario.n_agents == 2 and scenario.edges == ((0, 1),)
    assert scenario.reward.formation == 0.5 and scenario.reward.in_tolerance == 1.0
    assert scenario.physics_hz == 1000.0 and scenario.frame_skip == 10  # defaults


# ------------------------------------------------------------------------------------------ incidence
def test_paper_2d_incidence_gives_planar_square_edges():
    data = scenario_dict("planar_square")
    del data["edges"]
    data["incidence"] = PAPER_2D_INCIDENCE
    assert load_scenario(data).edges == load_scenario("planar_square").edges


def test_paper_3d_incidence_is_rejected():
    data = scenario_dict("spatial_tetrahedron")
    del data["edges"]
    data["incidence"] = PAPER_3D_INCIDENCE
    with pytest.raises(ValueError, match=r"incidence: column 5 .* is not an edge"):
        load_scenario(data)


def test_edges_and_incidence_are_exclusive():
    data = scenario_dict("planar_square", incidence=PAPER_2D_INCIDENCE)
    with pytest.raises(ValueError, match="exactly one of 'edges'"):
        load_scenario(data)
    data = scenario_dict("planar_square")
    del data["edges"]
    with pytest.raises(ValueError, match="exactly one of 'edges'"):
        load_scenario(data)


def test_incidence_wrong_row_count():
    data = scenario_dict("planar_square")
    del data["edges"]
    data["incidence"] = PAPER_2D_INCIDENCE[:3]
    with pytest.raises(ValueError, match="incidence: expected 4 rows"):
        load_scenario(data)


# ------------------------------------------------------------------------------------------ field errors
def _with_arm(index: int, **arm_changes):
    data = scenario_dict("planar_square")
    data["arms"][index].update(arm_changes)
    return data


@pytest.mark.parametrize("data, pattern", [
    (_with_arm(1, robot="ur5"), r"arms\[1\]\.robot: unknown robot 'ur5'; available: \['pera_arm', 'planar_2link'\]"),
    ({**_with_arm(2), "arms": [*scenario_dict()["arms"][:2], {"urdf": "nowhere/robot.urdf", "ee_link": "x"},
                               scenario_dict()["arms"][3]]}, r"arms\[2\]\.urdf: URDF not found: 'nowhere/robot.urdf'"),
    (scenario_dict(edges=[[0, 1], [1, 2], [2, 3], [3, 0], [0, 4]]), r"edges\[4\] = \[0, 4\] references a missing agent"),
    (scenario_dict(edges=[[0, 1], [1, -1]]), r"edges\[1\] = \[1, -1\] references a missing agent"),
    (scenario_dict(shape=[[0.0, 0.0, 0.0]] * 4), r"shape: expected 4 rows of 2 coordinates .* got an array of shape \(4, 3\)"),
    (scenario_dict(shape=[[0.0, 0.0]] * 3), r"shape: expected 4 rows of 2 coordinates .* \(3, 2\)"),
    (scenario_dict(bogus=1), r"scenario: unknown key\(s\) \['bogus'\]"),
    (_with_arm(0, colour="red"), r"arms\[0\]: unknown key\(s\) \['colour'\]"),
    (scenario_dict(physics_hz=0), "physics_hz: expected a positive"),
    (scenario_dict(physics_hz=-100.0), "physics_hz: expected a positive"),
    (scenario_dict(physics_hz=30.0), "physics_hz: expected at least 60 Hz"),
    (scenario_dict(frame_skip=0), "frame_skip: expected an integer >= 1, got 0"),
    (scenario_dict(frame_skip=1.5), "frame_skip: expected an integer >= 1, got 1.5"),
    (scenario_dict(frame_skip=True), "frame_skip: expected an integer"),
    (scenario_dict(episode_seconds=-1.0), "episode_seconds: expected a positive"),
    (scenario_dict(episode_seconds=0.001), "episode_seconds: .* shorter than one control step"),
    (scenario_dict(torque_limits=-5.0), "torque_limits: expected a positive"),
    (scenario_dict(torque_limits=[10.0, -1.0]), "torque_limits: expected a positive"),
    (scenario_dict(torque_limits=[[10.0, 10.0]] * 3), r"torque_limits: expected one list per arm \(4\), got 3"),
    (scenario_dict(gravity=[0.0, -9.81]), r"gravity: expected 3 numbers"),
    (scenario_dict(gravity=[0.0, 0.0, float("nan")]), r"gravity: expected finite numbers"),
    (scenario_dict(initial_q_noise=-0.1), "initial_q_noise: expected a finite number >= 0"),
    (scenario_dict(reward={"speed": 1.0}), r"reward: unknown key\(s\) \['speed'\]"),
    (scenario_dict(reward={"formation": -1.0}), "reward.formation: expected a weight >= 0"),
    (scenario_dict(reward={"team": 1}), "reward.team: expected true or false"),
    (scenario_dict(dim=4), "dim: expected 2 or 3, got 4"),
    (scenario_dict(formation="bearing"), "formation: expected one of"),
    (scenario_dict(arm_collisions="yes"), "arm_collisions: expected true or false"),
    (scenario_dict(joint_damping=-0.1), "joint_damping: expected a finite number >= 0"),
    (scenario_dict(max_joint_velocity=0.0), "max_joint_velocity: expected a positive"),
    (_with_arm(1, base_position=[1.0, 2.0]), r"arms\[1\]\.base_position: expected \[x, y, z\]"),
    (_with_arm(3, base_rpy=[0.0, 0.0]), r"arms\[3\]\.base_rpy: expected \[roll, pitch, yaw\]"),
    ({**scenario_dict(), "arms": scenario_dict()["arms"][:1]}, "arms: expected a list of at least 2 arm dicts"),
])
def test_invalid_fields_raise_naming_the_field(data, pattern):
    with pytest.raises(ValueError, match=pattern):
        load_scenario(data)
    with pytest.raises(ValueError, match=pattern):  # the env raises the same error
        ee_formation_env.parallel_env(data)


def test_arm_needs_exactly_one_of_robot_and_urdf():
    with pytest.raises(ValueError, match=r"arms\[0\]: give exactly one of 'robot'"):
        load_scenario(_with_arm(0, urdf="kuka_iiwa/model.urdf"))
    data = scenario_dict()
    data["arms"][1] = {"urdf": "kuka_iiwa/model.urdf"}
    with pytest.raises(ValueError, match=r"arms\[1\]\.ee_link: required"):
        load_scenario(data)


def test_unknown_scenario_name_and_missing_file(tmp_path):
    with pytest.raises(ValueError, match="neither a built-in scenario"):
        load_scenario("planar_sqare")
    with pytest.raises(ValueError, match="scenario: file not found"):
        load_scenario(str(tmp_path / "missing.yaml"))
    bad = tmp_path / "list.yaml"
    bad.write_text("- 1\n- 2\n", encoding="utf-8")
    with pytest.raises(ValueError, match="must contain a mapping"):
        load_scenario(bad)
    with pytest.raises(TypeError):
        load_scenario(42)


# ------------------------------------------------------------------------------------------ refusals at the door
def test_a_null_name_is_a_type_error_naming_name_not_the_string_none():
    with pytest.raises(TypeError, match=r"^name: expected a string"):
        load_scenario({**scenario_dict(), "name": None})
    with pytest.raises(TypeError, match=r"^name: expected a string"):
        load_scenario("planar_square", name=None)


def test_a_name_override_is_the_scenario_name():
    assert load_scenario("planar_square", name="renamed").name == "renamed"


def test_a_directory_given_as_the_scenario_is_called_a_directory_not_a_missing_file(tmp_path):
    folder = tmp_path / "scenario.yaml"
    folder.mkdir()
    with pytest.raises(ValueError, match=r"^scenario: .*scenario\.yaml' is a directory, not a scenario file"):
        load_scenario(folder)
    with pytest.raises(ValueError, match=r"\(it is a directory\)"):
        load_scenario(tmp_path)


def test_more_arms_than_the_cap_are_refused_before_any_arm_is_parsed():
    from ee_formation_env.inputs import MAX_ARMS

    arms = [{"robot": "no_such_robot"}] * (MAX_ARMS + 1)  # never parsed: the count is refused first
    with pytest.raises(ValueError, match=rf"^arms: expected at most {MAX_ARMS} arms, got {MAX_ARMS + 1}"):
        load_scenario(scenario_dict(arms=arms))


def test_a_dict_nested_20000_deep_is_a_value_error_about_nesting_naming_the_key_not_a_recursion_error():
    from ee_formation_env.inputs import MAX_NESTING_DEPTH

    nested: list = []
    for _ in range(20_000):
        nested = [nested]
    with pytest.raises(ValueError, match=rf"^scenario: arms: lists and dicts nest more than {MAX_NESTING_DEPTH} levels"):
        load_scenario(scenario_dict(arms=nested))
    with pytest.raises(ValueError, match=rf"^scenario: shape: lists and dicts nest more than {MAX_NESTING_DEPTH} levels"):
        load_scenario(scenario_dict(shape=nested))
    with pytest.raises(ValueError, match=rf"^overrides: gravity: lists and dicts nest more than {MAX_NESTING_DEPTH} "):
        load_scenario("planar_square", gravity=nested)
    deep_arm = scenario_dict()
    deep_arm["arms"][1]["initial_q"] = nested
    with pytest.raises(ValueError, match=r"^scenario: arms\[1\]\.initial_q: lists and dicts nest more than"):
        load_scenario(deep_arm)


@pytest.mark.parametrize("data, hint", [
    (scenario_dict(shpe=[[0.0, 0.0]]), r"^scenario: unknown key\(s\) \['shpe'\] \(did you mean 'shape' for 'shpe'\?\)"),
    (_with_arm(0, base_positon=[0.0, 0.0, 0.0]), r"^arms\[0\]: unknown key\(s\) .*did you mean 'base_position'"),
    (scenario_dict(reward={"in_tolerence": 1.0}), r"^reward: unknown key\(s\) .*did you mean 'in_tolerance'"),
    (scenario_dict(sensing={"nosie": 0.01}), r"^sensing: unknown key\(s\) .*did you mean 'noise'"),
])
def test_a_misspelt_key_is_refused_with_the_key_it_likely_meant(data, hint):
    with pytest.raises(ValueError, match=hint):
        load_scenario(data)


def test_a_key_far_from_every_allowed_one_gets_no_guess():
    with pytest.raises(ValueError) as info:
        load_scenario(scenario_dict(zzzzzz=1))
    assert "did you mean" not in str(info.value) and "allowed: [" in str(info.value)


def test_a_misspelt_builtin_name_gets_a_did_you_mean():
    import pytest

    import ee_formation_env

    with pytest.raises(ValueError, match="did you mean 'planar_square'"):
        ee_formation_env.load_scenario("planar_sqare")


def test_neighbour_slots_beyond_the_most_neighbours_any_scenario_has_are_refused_before_allocating():
    from ee_formation_env.inputs import MAX_ARMS, MAX_NEIGHBOUR_SLOTS

    assert MAX_NEIGHBOUR_SLOTS == MAX_ARMS - 1
    assert load_scenario("planar_square", neighbour_slots=MAX_NEIGHBOUR_SLOTS).neighbour_slots == MAX_NEIGHBOUR_SLOTS
    for slots in (MAX_NEIGHBOUR_SLOTS + 1, 10**9, 0):
        with pytest.raises(ValueError, match=rf"^neighbour_slots: expected null or an integer from 1 to "
                                             rf"{MAX_NEIGHBOUR_SLOTS} \(neighbour slots per agent.*got {slots}$"):
            load_scenario("planar_square", neighbour_slots=slots)


def test_initial_q_noise_beyond_a_full_turn_is_refused_naming_the_key_instead_of_overflowing_the_draw():
    assert load_scenario("planar_square", initial_q_noise=2 * math.pi).initial_q_noise == 2 * math.pi
    for noise in (2 * math.pi + 0.01, 1e308):
        with pytest.raises(ValueError, match=r"^initial_q_noise: expected at most 2 pi rad \(a full turn of a joint"):
            load_scenario("planar_square", initial_q_noise=noise)
