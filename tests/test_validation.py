"""Geometric validation with the arms' kinematic models: links, joint limits, planarity, rigidity,
reachability and singularities, all before any physics starts."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import ee_formation_env
import ee_formation_env.world
from ee_formation_env.scenario import ROBOTS, load_scenario
from ee_formation_env.task import build_task
from ee_formation_env.validation import find_reachable_placement

from benchmarks.soak import connected_clients
from conftest import scenario_dict

KUKA = {"urdf": "kuka_iiwa/model.urdf", "ee_link": "lbr_iiwa_link_7"}


def _square(side: float, centre=(3.0, 3.0)) -> list[list[float]]:
    h = side / 2
    cx, cy = centre
    return [[cx - h, cy - h], [cx + h, cy - h], [cx + h, cy + h], [cx - h, cy + h]]


@pytest.fixture
def no_physics(monkeypatch):
    """Fail the test if a PhysicsWorld is created (validation must reject before physics starts)."""

    def forbidden(self, *args, **kwargs):
        raise AssertionError("PhysicsWorld created for an invalid scenario")

    monkeypatch.setattr(ee_formation_env.world.PhysicsWorld, "__init__", forbidden)


def _rejects(data, pattern: str) -> str:
    """The ValueError message, checked against ``pattern``, from both build_task and the env."""
    with pytest.raises(ValueError, match=pattern) as caught:
        build_task(load_scenario(data))
    with pytest.raises(ValueError, match=pattern):
        ee_formation_env.parallel_env(data)
    return str(caught.value)


def _arm(data, index, **changes):
    data["arms"][index].update(changes)
    return data


# ------------------------------------------------------------------------------------------ links and joints
def test_unknown_ee_link_lists_available_links(no_physics):
    data = _arm(scenario_dict(), 2, ee_link="gripper")
    message = _rejects(data, r"arms\[2\]")
    assert "gripper" in message
    for link in ("base_link", "link_1", "link_2", "ee_link"):
        assert link in message


def test_unknown_ee_link_on_a_pybullet_data_urdf(no_physics):
    data = scenario_dict("planar_square", dim=2)
    data["arms"][0] = dict(KUKA, ee_link="tool0")
    message = _rejects(data, r"arms\[0\]")
    assert "tool0" in message and "lbr_iiwa_link_7" in message


def test_initial_q_wrong_length(no_physics):
    message = _rejects(_arm(scenario_dict(), 1, initial_q=[0.1, 0.2, 0.3]), r"arms\[1\]\.initial_q: expected 2 values")
    assert "joint_1" in message and "got 3" in message


def test_initial_q_outside_joint_limits(no_physics):
    # PERA joint_2 (shoulder pitch) has limits [0, 1.57].
    q = [-0.45, -0.1, 0.0, 1.15, 0.0, 0.3, 0.0]
    message = _rejects(_arm(scenario_dict("spatial_tetrahedron"), 1, initial_q=q),
                       r"arms\[1\]\.initial_q: joint joint_2 = -0\.1000 rad is outside its limits")
    assert "[0.0000, 1.5700]" in message


def test_torque_limit_list_of_wrong_length(no_physics):
    _rejects(scenario_dict(torque_limits=[10.0, 10.0, 10.0]), r"torque_limits: arms\[0\] has 2 joints, got 3")


def test_urdf_without_effort_limits_needs_torque_limits(no_physics, tmp_path, make_env):
    text = ROBOTS["planar_2link"].urdf.read_text(encoding="utf-8").replace('effort="50.0" ', "")
    assert "effort" not in text
    urdf = tmp_path / "no_effort.urdf"
    urdf.write_text(text, encoding="utf-8")
    data = scenario_dict()
    for arm in data["arms"]:
        del arm["robot"]
        arm.update(urdf=str(urdf), ee_link="ee_link")
    with pytest.raises(ValueError, match=r"torque_limits: arms\[0\] URDF has joints without a positive effort limit"):
        ee_formation_env.parallel_env(data)


def test_initial_configuration_at_singularity(no_physics):
    message = _rejects(_arm(scenario_dict(), 3, initial_q=[0.5, 0.0]), r"arms\[3\]\.initial_q: .* kinematic singularity")
    assert "singularity_threshold" in message


def test_singularity_threshold_is_honoured(make_env):
    near = _arm(scenario_dict(), 0, initial_q=[0.0, 0.02])  # smallest singular value ~ 1.5 * sin(0.02) / ...
    _rejects(scenario_dict(**{**near, "singularity_threshold": 0.1}), "kinematic singularity")
    env = make_env(near, singularity_threshold=1e-3)
    assert env.scenario.arms[0].initial_q == (0.0, 0.02)


# ------------------------------------------------------------------------------------------ planar scenarios
def test_planar_needs_yaw_only_bases(no_physics):
    _rejects(_arm(scenario_dict(), 1, base_rpy=[0.1, 0.0, 0.0]), r"arms\[1\]\.base_rpy: .* yaw-only bases")
    _rejects(_arm(scenario_dict(), 2, base_rpy=[0.0, -0.2, 1.0]), r"arms\[2\]\.base_rpy: .* yaw-only bases")


def test_planar_needs_planar_robots(no_physics):
    data = scenario_dict()
    data["arms"][1] = dict(KUKA, base_position=[6.0, 0.0, 0.0], initial_q=[0.0, 0.5, 0.0, -1.2, 0.0, 0.8, 0.0])
    _rejects(data, r"arms\[1\]: robot 'lbr_iiwa' does not move in its base x-y plane; use dim = 3")


# ------------------------------------------------------------------------------------------ graphs
def test_graph_not_connected(no_physics):
    data = scenario_dict("planar_square_displacement", edges=[[0, 1], [2, 3]])
    _rejects(data, "edges: the formation graph is not connected")


def test_square_without_diagonal_is_not_rigid(no_physics):
    data = scenario_dict(edges=[[0, 1], [1, 2], [2, 3], [3, 0]])
    message = _rejects(data, "edges: the graph is not infinitesimally rigid")
    assert "rank 4 < 5" in message
    # A displacement formation does not need rigidity.
    load = load_scenario(scenario_dict("planar_square_displacement", edges=[[0, 1], [1, 2], [2, 3], [3, 0]]))
    build_task(load)


def test_tetrahedron_missing_an_edge_is_not_rigid(no_physics):
    data = scenario_dict("spatial_tetrahedron", edges=[[0, 1], [0, 2], [2, 3], [0, 3], [1, 3]])
    _rejects(data, r"not infinitesimally rigid .*rank 5 < 6 needed in 3D")


def test_degenerate_shape_is_not_rigid(no_physics):
    # Four collinear points: no graph makes a distance formation of them infinitesimally rigid in 2D.
    data = scenario_dict(shape=[[1.5, 3.0], [2.5, 3.0], [3.5, 3.0], [4.5, 3.0]],
                         edges=[[0, 1], [1, 2], [2, 3], [3, 0], [0, 2], [1, 3]])
    _rejects(data, "not infinitesimally rigid")


def test_rigid_but_not_minimal_warns_and_builds(make_env):
    data = scenario_dict(edges=[[0, 1], [1, 2], [2, 3], [3, 0], [0, 2], [1, 3]])  # K4: 6 edges, 5 suffice
    with pytest.warns(UserWarning, match="rigid but not minimally rigid"):
        env = make_env(data)
    observations, _ = env.reset(seed=0)
    assert env.graph.max_degree == 3
    assert observations["arm_0"].shape == (3 * (1 + 2 + 1 + 1) + 2 + 2,)  # 3 slots of (mask, z, d*, e), q, dq
    # The minimally rigid built-in does not warn.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        make_env("planar_square")


def test_duplicate_and_self_loop_edges(no_physics):
    _rejects(scenario_dict(edges=[[0, 1], [1, 2], [2, 3], [3, 0], [0, 2], [2, 0]]), "duplicate edge")
    _rejects(scenario_dict(edges=[[0, 1], [1, 2], [2, 3], [3, 3], [0, 2]]), "self-loop")


# ------------------------------------------------------------------------------------------ reachability
def test_papers_square_is_out_of_reach(no_physics):
    message = _rejects(scenario_dict(shape=_square(0.4)), "out of reach")
    assert "shape" in message and "3.0" in message  # the arms' reach is reported


@pytest.mark.parametrize("side", [0.4, 1.0, 10.5, 12.0])
def test_infeasible_squares_rejected(no_physics, side):
    # Feasible sides (vertices in base order): 6 - 3 sqrt 2 = 1.757 m to 6 + 3 sqrt 2 = 10.243 m.
    _rejects(scenario_dict(shape=_square(side)), "out of reach")


@pytest.mark.parametrize("side", [1.8, 3.0, 4.0, 10.0])
def test_feasible_squares_accepted(make_env, side):
    data = scenario_dict(shape=_square(side, centre=(-50.0, 20.0)))  # any translation of the shape is a goal
    placement = find_reachable_placement(load_scenario(data))
    assert placement is not None
    # The placement is the shape moved rigidly: same pairwise distances, every vertex within reach.
    shape = np.asarray(data["shape"])
    pairwise = lambda p: np.linalg.norm(p[:, None] - p[None], axis=2)  # noqa: E731
    np.testing.assert_allclose(pairwise(placement), pairwise(shape), atol=1e-9)
    bases = np.array([arm["base_position"][:2] for arm in data["arms"]])
    assert np.all(np.linalg.norm(placement - bases, axis=1) <= 3.0 + 0.25)
    env = make_env(data)
    assert env.scenario.shape == tuple(map(tuple, shape.tolist()))


def test_displacement_formation_may_not_rotate(no_physics):
    """A displacement shape only translates: a square tilted so that diagonal vertices swap sides is out of reach."""
    rotated = np.asarray(_square(4.0)) - 3.0
    rotated = rotated @ np.array([[-1.0, 0.0], [0.0, -1.0]]).T + 3.0  # 180 degrees: vertex 0 goes near base 2
    data = scenario_dict("planar_square_displacement", shape=rotated.tolist())
    _rejects(data, r"out of reach: no placement of the shape \(translations\)")
    load_scenario(scenario_dict("planar_square", shape=rotated.tolist()))  # fine as a distance formation
    assert find_reachable_placement(load_scenario(scenario_dict("planar_square", shape=rotated.tolist()))) is not None


def test_spatial_shape_out_of_reach(no_physics):
    data = scenario_dict("spatial_tetrahedron")
    data["shape"] = (np.asarray(data["shape"]) * 10.0).tolist()  # a 4 m tetrahedron for 0.5 m-reach arms
    _rejects(data, "out of reach")


# ------------------------------------------------------------------------------------------ order of checks
def test_validation_happens_before_physics(no_physics):
    """The fixture makes any PhysicsWorld creation fail: every rejection above came before physics."""
    with pytest.raises(AssertionError, match="PhysicsWorld created"):
        ee_formation_env.parallel_env("planar_square")  # a valid scenario does reach the physics
    with pytest.raises(ValueError, match="out of reach"):
        ee_formation_env.parallel_env("planar_square", shape=_square(0.4))


def test_valid_builtins_pass_validation():
    for name in ("planar_square", "planar_square_rotated", "spatial_tetrahedron", "spatial_tetrahedron_displacement"):
        models = build_task(load_scenario(name)).models
        assert len(models) == 4
        assert all(model.n_joints == (2 if name.startswith("planar") else 7) for model in models)
        assert find_reachable_placement(load_scenario(name)) is not None


# ------------------------------------------------------------------------------------------ validate_scenario
def _stretched(index: int) -> dict:
    data = scenario_dict()
    data["arms"][index]["initial_q"] = [0.0, 0.0]
    return data


def _touching() -> dict:
    data = scenario_dict()
    data["arms"][1]["base_position"] = [0.3, 0.0, 0.0]
    data["arms"][1]["initial_q"] = data["arms"][0]["initial_q"]
    return data


@pytest.mark.parametrize("data, pattern", [
    (scenario_dict(shape=_square(0.4)), r"^shape: the formation is out of reach"),
    (_stretched(2), r"^arms\[2\]\.initial_q: .* kinematic singularity"),
    (_touching(), r"^arms: arm_0 and arm_1 are in contact at their initial configurations"),
    (scenario_dict("planar_random", distribution={"shape_scale": [40.0, 50.0], "max_tries": 3}),
     r"^distribution: no valid draw of 'custom'"),
])
def test_validate_scenario_refuses_what_parallel_env_refuses_without_a_physics_step(data, pattern, monkeypatch):
    """``load_scenario`` checks the format only: these pass it, and both validate_scenario and the env refuse
    them with the same message; validate_scenario never steps physics and leaves no client connected."""
    import pybullet

    from ee_formation_env import validate_scenario

    load_scenario(data)  # the format is fine
    with pytest.raises(ValueError, match=pattern) as from_env:
        ee_formation_env.parallel_env(data)

    def no_step(*args, **kwargs):
        raise AssertionError("validate_scenario stepped physics")

    monkeypatch.setattr(pybullet, "stepSimulation", no_step)
    before = connected_clients()
    with pytest.raises(ValueError, match=pattern) as from_validate:
        validate_scenario(data)
    assert str(from_validate.value) == str(from_env.value)
    assert connected_clients() == before


def test_validate_scenario_returns_the_parsed_scenario_of_a_valid_one():
    from ee_formation_env import validate_scenario

    assert validate_scenario("planar_random") == load_scenario("planar_random")
    assert validate_scenario("planar_square", episode_seconds=2.0).episode_seconds == 2.0


@pytest.mark.parametrize("name", ["planar_square", "spatial_tetrahedron", "planar_square_rotated"])
def test_the_pair_distance_bound_never_refuses_a_reachable_shape(name):
    from ee_formation_env.validation import _pairs_can_reach
    from ee_formation_env.workspace import workspace

    scenario = load_scenario(name)
    spaces = [workspace(arm.urdf, arm.ee_link, scenario.dim) for arm in scenario.arms]
    bases = np.array([arm.base_position[:scenario.dim] for arm in scenario.arms])
    assert _pairs_can_reach(np.asarray(scenario.shape), bases, spaces)
    assert find_reachable_placement(scenario) is not None


def _all_arms_at(data, q):
    for arm in data["arms"]:
        arm["initial_q"] = list(q)
    return data


def _robot_scenario(name):
    """Three arms of registry robot ``name`` (four planar_2links for planar_square), every one at all zeros."""
    from ee_formation_env.robots import PYBULLET_DATA_ROBOTS

    if name == "planar_2link":
        return _all_arms_at(scenario_dict(), [0.0, 0.0])
    spec = {**ROBOTS, **PYBULLET_DATA_ROBOTS}[name]
    arm = {"robot": name} if name in ROBOTS else {"urdf": str(spec.urdf), "ee_link": spec.ee_link}
    bases = [[0.0, 0.0, 0.0], [1.2, 0.0, 0.0], [0.6, 1.0, 0.0]]
    data = {"arms": [{**arm, "base_position": base} for base in bases], "edges": [[0, 1], [1, 2], [2, 0]],
            "shape": [[0.4, 0.2, 0.5], [0.8, 0.2, 0.5], [0.6, 0.5, 0.5]], "dim": 3}
    return _all_arms_at(data, [0.0] * len(spec.start_q))


@pytest.mark.parametrize("name", ["planar_2link", "pera_arm", "kuka_iiwa", "franka_panda"])
def test_the_singular_start_suggestion_is_itself_accepted_for_every_registry_robot(no_physics, name):
    import json
    import re

    from ee_formation_env.robots import PYBULLET_DATA_ROBOTS
    from ee_formation_env.kinematics import chain_model, singularity_margins
    from ee_formation_env.validation import nonsingular_pose

    assert set(ROBOTS) | set(PYBULLET_DATA_ROBOTS) == {"planar_2link", "pera_arm", "kuka_iiwa", "franka_panda"}
    data = _robot_scenario(name)
    # A threshold that the all-zeros start fails, for every robot (some are not singular at zeros by 1e-3 m).
    scenario = load_scenario(data)
    model = chain_model(scenario.arms[0].urdf, scenario.arms[0].ee_link)
    dim = scenario.dim
    threshold = max(1e-3, 1.5 * float(singularity_margins(model.jacobian(np.zeros(model.n_joints))[None], dim)[0]))
    data["singularity_threshold"] = threshold
    message = _rejects(data, r"^arms\[0\]\.initial_q: \[0\.0(, 0\.0)+\] is at a kinematic singularity .* e\.g\. "
                             r"initial_q: \[")
    suggestion = json.loads(re.search(r"e\.g\. initial_q: (\[[^\]]*\])", message).group(1))
    assert float(singularity_margins(model.jacobian(np.array(suggestion))[None], dim)[0]) >= threshold
    try:
        build_task(load_scenario(_all_arms_at(data, suggestion)))
    except ValueError as error:  # the start is accepted; a later check (reach) may still refuse the layout
        assert "singularity" not in str(error) and "initial_q" not in str(error), str(error)
    # The search alone (without the robot's default start) also finds a start that passes.
    pose = nonsingular_pose(model, np.zeros(model.n_joints), dim, threshold)
    assert pose is not None and float(singularity_margins(model.jacobian(np.array(pose))[None], dim)[0]) >= threshold
    assert np.all(np.array(pose) >= model.lower) and np.all(np.array(pose) <= model.upper)


def test_the_rigidity_warning_is_warned_once_per_build_at_the_user_s_line(closer):
    from ee_formation_env.validation import RigidityWarning

    data = scenario_dict(edges=[[0, 1], [1, 2], [2, 3], [3, 0], [0, 2], [1, 3]])  # K4: 6 edges, 5 suffice
    builds = [lambda: closer(ee_formation_env.parallel_env(data)),
              lambda: closer(ee_formation_env.vector_env(data, num_envs=2)),
              lambda: ee_formation_env.validate_scenario(data),
              lambda: build_task(load_scenario(data))]
    for build in builds:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            build()
        rigidity = [w for w in caught if issubclass(w.category, RigidityWarning)]
        assert len(rigidity) == 1 and issubclass(rigidity[0].category, UserWarning)
        assert rigidity[0].filename == __file__, rigidity[0].filename
        assert "rigid but not minimally rigid (6 edges, 5 suffice)" in str(rigidity[0].message)
