"""Bounded inputs and clear errors: each test guards one guarantee, so that none of these bugs can come back.

Every refusal is a ``ValueError`` / ``TypeError`` whose message starts with the field's name, raised with no
PyBullet client left connected, and a refused action or seed leaves the env bit-identical.
"""

from __future__ import annotations

import re
import shutil
import sys
import types
from pathlib import Path

import gymnasium
import numpy as np
import pybullet
import pytest
import yaml

import ee_formation_env
from benchmarks.soak import connected_clients
from ee_formation_env.builtin import BUILTIN_SCENARIOS
from ee_formation_env.inputs import MAX_EPISODE_SECONDS, MAX_EXCERPT_CHARS, MAX_SCENARIO_FILE_BYTES, MAX_SCENARIO_NODES
from ee_formation_env.scenario_file import BoundedSafeLoader, expanded_node_count
from ee_formation_env.kinematics import chain_model, singularity_margins
from ee_formation_env.robots import ROBOTS
from ee_formation_env.scenario import SCENARIO_FIELDS, builtin_scenario, load_scenario, resolve_urdf

from conftest import scenario_dict

REPO = Path(__file__).resolve().parents[1]
PLANAR_URDF = ROBOTS["planar_2link"].urdf
DOCS = REPO / "docs"


def _planar_urdf_arm(urdf: Path | str, index: int = 0) -> dict:
    arm = dict(builtin_scenario("planar_square")["arms"][index])
    arm.pop("robot")
    return {**arm, "urdf": str(urdf), "ee_link": "ee_link"}


def _refused(error_type, match: str, build):
    """``build()`` raises ``error_type`` matching ``match`` with no PyBullet client left connected."""
    before = connected_clients()
    with pytest.raises(error_type, match=match) as info:
        build()
    assert connected_clients() == before
    return info.value


# ------------------------------------------------------------------------------------ A: YAML size and aliases
def _alias_file(path: Path, extra_scalars: int) -> Path:
    """``{shape: x, arms: [&a [x]*999, *a x 98, x * extra]}``: 5 + 99 * 1000 + extra nodes, aliases expanded."""
    items = ["&a [" + ", ".join(["x"] * 999) + "]"] + ["*a"] * 98 + ["x"] * extra_scalars
    path.write_text("shape: x\narms: [" + ", ".join(items) + "]\n", encoding="utf-8")
    return path


def test_yaml_files_are_bounded_in_size_and_alias_expansion_before_anything_expands(tmp_path):
    # The node bound, exactly at and one past it (counted on the composed document, aliases expanded).
    at_bound = _alias_file(tmp_path / "at.yaml", MAX_SCENARIO_NODES - 5 - 99_000)
    over_bound = _alias_file(tmp_path / "over.yaml", MAX_SCENARIO_NODES - 5 - 99_000 + 1)
    assert expanded_node_count(yaml.compose(at_bound.read_text()), MAX_SCENARIO_NODES) == MAX_SCENARIO_NODES
    with pytest.raises(ValueError, match=r"^arms") as under:  # parsed, then refused for what it is
        load_scenario(at_bound)
    assert len(str(under.value)) < 2 * MAX_EXCERPT_CHARS + 200  # a short excerpt of the 99,000-item list
    with pytest.raises(ValueError, match=rf"^scenario: the YAML document expands to more than {MAX_SCENARIO_NODES}"):
        load_scenario(over_bound)

    # The "billion laughs": nine levels of nine aliases, ~500 bytes, 9^9 scalars if expanded.
    levels = ["&l0 [x, x, x, x, x, x, x, x, x]"] + [f"&l{i} [" + ", ".join([f"*l{i - 1}"] * 9) + "]" for i in range(1, 9)]
    laughs = tmp_path / "laughs.yaml"
    laughs.write_text("arms: [{robot: planar_2link}, {robot: planar_2link}]\nedges: [[0, 1]]\nshape: ["
                      + ",\n  ".join(levels) + "]\n", encoding="utf-8")
    assert laughs.stat().st_size < 700
    with pytest.raises(ValueError, match=r"^scenario: the YAML document expands to more than") as info:
        load_scenario(laughs)
    assert len(str(info.value)) < MAX_EXCERPT_CHARS
    recursive = tmp_path / "recursive.yaml"
    recursive.write_text("arms: &r [*r]\n", encoding="utf-8")
    with pytest.raises(ValueError, match=r"^scenario: "):
        load_scenario(recursive)

    # The size bound: a valid scenario padded to exactly the bound loads; one byte more is refused unread.
    text = yaml.safe_dump(builtin_scenario("planar_square"))
    exact = tmp_path / "exact.yaml"
    exact.write_text(text + "#" * (MAX_SCENARIO_FILE_BYTES - len(text.encode()) - 1) + "\n", encoding="utf-8")
    assert exact.stat().st_size == MAX_SCENARIO_FILE_BYTES
    assert load_scenario(exact).n_agents == 4
    exact.write_text(exact.read_text() + "#", encoding="utf-8")
    with pytest.raises(ValueError, match=rf"^scenario: .* is {MAX_SCENARIO_FILE_BYTES + 1} bytes"):
        load_scenario(exact)

    # Messages quote a short excerpt, never the value: a huge dict value stays under the cap.
    with pytest.raises(ValueError, match=r"^shape: ") as info:
        load_scenario(scenario_dict(shape=[["x"] * 10_000] * 100))
    assert len(str(info.value)) < MAX_EXCERPT_CHARS + 100

    # The format needs no aliases: the built-ins use none, and are far below the bound.
    for name in BUILTIN_SCENARIOS:
        text = (REPO / "ee_formation_env" / "builtin" / f"{name}.yaml").read_text(encoding="utf-8")
        assert not any(isinstance(event, yaml.AliasEvent) or getattr(event, "anchor", None)
                       for event in yaml.parse(text)), name
        assert expanded_node_count(yaml.compose(text, Loader=BoundedSafeLoader), MAX_SCENARIO_NODES) < 300


# ------------------------------------------------------------------------------------ B: URDF lookup order
def test_relative_urdf_paths_are_looked_up_in_the_scenario_folder_before_anything_else(tmp_path, monkeypatch):
    folder, cwd = tmp_path / "scenario", tmp_path / "cwd"
    folder.mkdir()
    cwd.mkdir()
    shutil.copy(PLANAR_URDF, folder / "arm.urdf")
    (cwd / "arm.urdf").write_text(PLANAR_URDF.read_text().replace("ee_link", "tip"), encoding="utf-8")
    data = scenario_dict(arms=[_planar_urdf_arm("arm.urdf", i) for i in range(4)])
    data.pop("controller_gains")
    (folder / "scenario.yaml").write_text(yaml.safe_dump(data), encoding="utf-8")
    monkeypatch.chdir(cwd)
    scenario = load_scenario(folder / "scenario.yaml")
    assert {arm.urdf for arm in scenario.arms} == {str((folder / "arm.urdf").resolve())}
    # Then pybullet_data; a dict scenario's folder is the current directory.
    assert resolve_urdf("kuka_iiwa/model.urdf", folder).endswith("pybullet_data/kuka_iiwa/model.urdf")
    assert resolve_urdf("arm.urdf", Path.cwd()) == str((cwd / "arm.urdf").resolve())
    docs = (DOCS / "scenarios.md").read_text(encoding="utf-8")
    assert "looked up in the scenario file's folder first" in docs and "then in `pybullet_data`" in docs


# ------------------------------------------------------------------------------------ C: time bounds
def test_time_fields_are_bounded_at_parse_time_so_no_step_overflows():
    for overrides, field in [({"episode_seconds": 1e308}, "episode_seconds"),
                             ({"episode_seconds": 10 ** 400}, "episode_seconds"),
                             ({"episode_seconds": MAX_EPISODE_SECONDS * 1.0001}, "episode_seconds"),
                             ({"physics_hz": 1e308}, "physics_hz"),
                             ({"frame_skip": 10 ** 30}, "frame_skip")]:
        _refused(ValueError, rf"^{field}: ", lambda: ee_formation_env.parallel_env("planar_square", **overrides))
    longest = load_scenario("planar_square", episode_seconds=MAX_EPISODE_SECONDS)
    assert isinstance(longest.max_steps, int) and longest.max_steps == 100_000_000


# ------------------------------------------------------------------------------------ D: URDFs PyBullet rejects
def test_a_urdf_with_a_missing_mesh_is_refused_naming_urdf_and_mesh_before_any_client_connects(tmp_path,
                                                                                                monkeypatch):
    """PyBullet ends the whole process on a missing visual mesh, so the check runs before it is asked."""
    urdf = tmp_path / "mesh_arm.urdf"
    urdf.write_text(PLANAR_URDF.read_text().replace('<geometry><box size="1.3 0.08 0.08"/></geometry>',
                                                    '<geometry><mesh filename="meshes/missing.stl"/></geometry>'))
    arms = [_planar_urdf_arm(urdf, 0)] + builtin_scenario("planar_square")["arms"][1:]

    def no_connect(*args, **kwargs):
        raise AssertionError("a PyBullet client was asked for before the mesh check")

    monkeypatch.setattr(pybullet, "connect", no_connect)
    error = _refused(ValueError, r"^arms\[0\]\.urdf: .*names mesh files that do not exist next to it",
                     lambda: ee_formation_env.parallel_env(scenario_dict(arms=arms)))
    assert str(urdf) in str(error) and "meshes/missing.stl" in str(error)


def test_negative_masses_and_indefinite_inertias_are_refused_before_physics(tmp_path):
    text = PLANAR_URDF.read_text()
    cases = {
        "mass": (text.replace('<mass value="1.2"/>', '<mass value="-1"/>'), r"link link_1 has mass '-1'"),
        "inertia": (text.replace('ixx="0.002" ixy="0" ixz="0" iyy="0.2250"', 'ixx="-0.5" ixy="0" ixz="0" iyy="0.2250"'),
                    r"link link_1 has an inertia tensor that is not positive semi-definite"),
        "nan": (text.replace('<mass value="1.0"/>', '<mass value="nan"/>'), r"link link_2 has mass 'nan'"),
    }
    for name, (urdf_text, message) in cases.items():
        urdf = tmp_path / f"{name}.urdf"
        urdf.write_text(urdf_text, encoding="utf-8")
        arms = builtin_scenario("planar_square")["arms"][:3] + [_planar_urdf_arm(urdf, 3)]
        _refused(ValueError, r"^arms\[3\]\.urdf: " + message,
                 lambda: ee_formation_env.parallel_env(scenario_dict(arms=arms)))


# ------------------------------------------------------------------------------------ E: numbers are numbers
def test_strings_and_booleans_are_not_numbers_in_scenario_arrays():
    def with_arm_field(key, value):
        data = scenario_dict()
        data["arms"][1][key] = value
        return data

    for data, field in [(with_arm_field("base_position", ["1", True, 0]), r"arms\[1\]\.base_position"),
                        (with_arm_field("base_position", [6.0, True, 0.0]), r"arms\[1\]\.base_position"),
                        (with_arm_field("initial_q", ["0", 1.0]), r"arms\[1\]\.initial_q"),
                        (scenario_dict(shape=[[1.5, 1.5], [4.5, 1.5], [4.5, 4.5], [1.5, "4.5"]]), "shape"),
                        (scenario_dict(gravity=[0, 0, False]), "gravity"),
                        (scenario_dict(edges=[[0, 1], [1, 2], [2, 3], [3, 0], [0, True]]), "edges")]:
        _refused((ValueError, TypeError), rf"^{field}: ", lambda: ee_formation_env.parallel_env(data))
    # numpy numbers are numbers
    data = scenario_dict()
    data["arms"][1]["base_position"] = np.array([6.0, 0.0, 0.0], dtype=np.float32)
    assert load_scenario(data).arms[1].base_position == (6.0, 0.0, 0.0)


def test_string_action_arrays_are_refused_naming_the_agent_and_change_nothing(make_env):
    env, reference = make_env("planar_square"), make_env("planar_square")
    env.reset(seed=2)
    reference.reset(seed=2)
    zeros = {agent: np.zeros(2, np.float32) for agent in env.agents}
    for bad in (np.array(["0.1", "0.2"]), ["0.1", "0.2"], np.array([0.1 + 1j, 0.2]), np.array([0.1, None])):
        actions = {**zeros, "arm_2": bad}
        with pytest.raises((ValueError, TypeError), match=r"^actions\['arm_2'\]: "):
            env.step(actions)
    for _ in range(2):
        got, expected = env.step(zeros), reference.step(zeros)
        for agent in env.agents:
            np.testing.assert_array_equal(got[0][agent], expected[0][agent])
    # the centralized env passes the raw parts on: strings are refused there too
    central = gymnasium.make("EEFormation/PlanarSquare-v0", episode_seconds=0.2)
    try:
        central.reset(seed=0)
        with pytest.raises(ValueError, match=r"^actions\['arm_0'\]: "):
            central.step(np.array(["0.1"] * 8))
    finally:
        central.close()


# ------------------------------------------------------------------------------------ G: seeds
def test_numpy_integer_seeds_are_accepted_and_negative_seeds_refused_naming_seed(make_env):
    env, reference = make_env("planar_square"), make_env("planar_square")
    observations, _ = env.reset(seed=np.int64(3))
    expected, _ = reference.reset(seed=3)
    for agent in observations:
        np.testing.assert_array_equal(observations[agent], expected[agent])
    for bad, error in [(-1, ValueError), (np.int64(-5), ValueError), (1.5, TypeError), (True, TypeError)]:
        with pytest.raises(error, match=r"^seed: "):
            env.reset(seed=bad)
    zeros = {agent: np.zeros(2, np.float32) for agent in env.agents}
    np.testing.assert_array_equal(env.step(zeros)[0]["arm_1"], reference.step(zeros)[0]["arm_1"])

    central = gymnasium.make("EEFormation/PlanarSquare-v0", episode_seconds=0.2)
    central_reference = gymnasium.make("EEFormation/PlanarSquare-v0", episode_seconds=0.2)
    try:
        np.testing.assert_array_equal(central.reset(seed=np.int32(4))[0], central_reference.reset(seed=4)[0])
        with pytest.raises(ValueError, match=r"^seed: "):
            central.reset(seed=-1)
        action = np.zeros(8, np.float32)
        np.testing.assert_array_equal(central.step(action)[0], central_reference.step(action)[0])
    finally:
        central.close()
        central_reference.close()


# ------------------------------------------------------------------------------------ H: the AEC form
def test_aec_env_refuses_a_bad_action_at_that_call_naming_that_agent_and_stays_usable(closer):
    env = closer(ee_formation_env.env("planar_square", episode_seconds=0.1))
    reference = closer(ee_formation_env.env("planar_square", episode_seconds=0.1))
    env.reset(seed=0)
    reference.reset(seed=0)
    zero = np.zeros(2, np.float32)
    for agent in ("arm_0", "arm_2"):
        while env.agent_selection != agent:
            env.step(zero)
            reference.step(zero)
        for bad in (np.array([np.nan, 0.0], np.float32), np.zeros(3, np.float32), np.array(["0.1", "0.2"])):
            with pytest.raises(ValueError, match=rf"^actions\['{agent}'\]: "):
                env.step(bad)
            assert env.agent_selection == agent  # nothing buffered, the turn stays
    steps = 0
    for agent in env.agent_iter(max_iter=200):
        observation, reward, termination, truncation, _ = env.last()
        expected = reference.last()
        assert reference.agent_selection == agent
        np.testing.assert_array_equal(observation, expected[0])
        assert (reward, termination, truncation) == expected[1:4]
        action = None if termination or truncation else zero
        env.step(action)
        reference.step(action)
        steps += 1
    assert steps > 8 and not env.agents  # the episode ran to its end


# ------------------------------------------------------------------------------------ I: newcomer items
def test_shipped_robots_start_away_from_singularities_when_no_initial_q_is_given(make_env):
    for name, robot in ROBOTS.items():
        model = chain_model(str(robot.urdf), robot.ee_link)
        q = np.asarray(robot.start_q)
        assert q.shape == (model.n_joints,)
        dim = 2 if name == "planar_2link" else 3
        assert singularity_margins(model.jacobian(q)[None], dim)[0] > 0.05, name  # 50x the default threshold
    data = scenario_dict()
    for arm in data["arms"]:
        arm.pop("initial_q")
    env = make_env(data)
    for q0 in env.task.initial_q:
        np.testing.assert_array_equal(q0, ROBOTS["planar_2link"].start_q)
    env.reset(seed=0)
    # A singular initial_q given explicitly: the error suggests a concrete bent-elbow initial_q.
    data["arms"][2]["initial_q"] = [0.0, 0.0]
    _refused(ValueError, r"^arms\[2\]\.initial_q: .* singularity.* initial_q: \[0\.0, 1\.0472\] \(the robot's default start\)",
             lambda: ee_formation_env.parallel_env(data))
    # The built-ins give theirs: unchanged.
    assert all(arm.initial_q is not None for name in BUILTIN_SCENARIOS for arm in load_scenario(name).arms)


def test_arms_in_contact_at_start_are_refused_unless_arm_collisions_is_off(make_env):
    data = scenario_dict()
    data["arms"][1]["base_position"] = [0.3, 0.0, 0.0]
    data["arms"][1]["initial_q"] = data["arms"][0]["initial_q"]
    _refused(ValueError, r"^arms: arm_0 and arm_1 are in contact at their initial configurations",
             lambda: ee_formation_env.parallel_env(data))
    make_env({**data, "arm_collisions": False}).reset(seed=0)  # allowed: no contact forces
    for name in BUILTIN_SCENARIOS:
        make_env(name)
    docs = (DOCS / "scenarios.md").read_text(encoding="utf-8")
    assert "arms in contact at their initial configurations are an error" in docs


def test_custom_scenarios_get_the_documented_rate_and_length_defaults():
    data = builtin_scenario("spatial_tetrahedron")
    assert (data.pop("frame_skip"), data.pop("episode_seconds")) == (5, 50.0)  # the built-in's own
    custom = load_scenario(data)
    frame_skip, seconds = SCENARIO_FIELDS["frame_skip"].default, SCENARIO_FIELDS["episode_seconds"].default
    assert (custom.frame_skip, custom.episode_seconds) == (frame_skip, seconds) == (10, 30.0)
    docs = " ".join((DOCS / "scenarios.md").read_text(encoding="utf-8").split())
    assert f"A scenario of your own gets the defaults of the [keys table](#keys) ({seconds:.0f} s at `frame_skip` {frame_skip}" in docs
    for page in ("scenarios.md", "spaces.md", "performance.md"):
        text = " ".join((DOCS / page).read_text(encoding="utf-8").split())
        assert not re.search(r"(200 Hz|5) \(?spatial\)? by default|default frame_skip \(10 planar, 5 spatial\)", text), page


# ------------------------------------------------------------------------------------ F: video file names
def test_video_files_stay_inside_their_folder_whatever_the_scenario_name(tmp_path, monkeypatch):
    from ee_formation_env.baselines.evaluate import evaluate_policy, file_stem

    # A changed name keeps its readable part and gets a hash suffix (two names never share a stem).
    assert re.fullmatch(r"_escaped_dir_owned-[0-9a-f]{8}", file_stem("../escaped_dir/owned"))
    assert re.fullmatch(r"_etc_passwd-[0-9a-f]{8}", file_stem("/etc/passwd"))
    assert re.fullmatch(r"scenario-[0-9a-f]{8}", file_stem("...")) and file_stem(".hidden").startswith("hidden-")
    assert file_stem("planar_square") == "planar_square" and file_stem("v1.2-run") == "v1.2-run"
    written: list[Path] = []
    stub = types.ModuleType("imageio")
    stub.mimwrite = lambda path, frames, **kwargs: (written.append(Path(path)), Path(path).write_bytes(b"video"))
    monkeypatch.setitem(sys.modules, "imageio", stub)
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # the GIF branch
    videos = tmp_path / "deep" / "videos"
    for name in ("../escaped_dir/owned", str(tmp_path / "absolute" / "owned"), "..", "my.scenario"):
        evaluate_policy({**scenario_dict(), "name": name}, "zero", 1, 0, overrides={"episode_seconds": 0.05}, video_dir=videos)
    assert len(written) == 4
    assert all(path.resolve().parent == videos.resolve() for path in written), written
    assert sorted(p.name for p in videos.iterdir()) == sorted(p.name for p in written)
    assert {p.name for p in tmp_path.rglob("*.gif")} == {p.name for p in written}
    assert (videos / "my.scenario-zero-seed0.gif").is_file()
