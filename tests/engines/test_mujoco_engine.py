"""The MuJoCo engine against PyBullet's: the same rigid-body model, the same first steps, contacts between arms
only, and a world that resets to the same state."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("mujoco")

import ee_formation_env  # noqa: E402
from ee_formation_env.engines import make_engine, rigid_body_model  # noqa: E402
from ee_formation_env.kinematics import SerialChain  # noqa: E402
from ee_formation_env.robots import ROBOTS  # noqa: E402


@pytest.mark.parametrize("robot", ["planar_2link", "pera_arm"])
def test_gravity_torques_and_mass_matrix_are_pybullets(robot):
    urdf = str(ROBOTS[robot].urdf)
    chain = SerialChain.from_urdf(urdf, ROBOTS[robot].ee_link)
    bullet, mujoco = (rigid_body_model(name, urdf, chain.joint_names) for name in ("pybullet", "mujoco"))
    rng = np.random.default_rng(0)
    lower = np.where(np.isfinite(chain.lower), chain.lower, -np.pi)
    upper = np.where(np.isfinite(chain.upper), chain.upper, np.pi)
    for _ in range(20):
        q = rng.uniform(lower, upper)
        gravity = rng.normal(size=3) * 5.0  # any direction: the base-frame gravity of a tilted mounting
        expected_g, expected_h = bullet.gravity_torque(q, gravity), bullet.mass_matrix(q)
        np.testing.assert_allclose(mujoco.gravity_torque(q, gravity), expected_g, rtol=0,
                                   atol=1e-6 * np.abs(expected_g).max())
        np.testing.assert_allclose(mujoco.mass_matrix(q), expected_h, rtol=0, atol=1e-6 * np.abs(expected_h).max())


def _trajectory(scenario: str, engine: str, steps: int) -> np.ndarray:
    """Joint positions and velocities after each of ``steps`` env steps under constant actions."""
    with ee_formation_env.parallel_env(scenario, engine=engine) as env:
        env.reset(seed=3)
        actions = {agent: np.full(env.action_space(agent).shape, 0.3, dtype=np.float32) for agent in env.agents}
        states = []
        for _ in range(steps):
            env.step(actions)
            states.append(np.concatenate([np.concatenate(arm.read_state_lists()) for arm in env.arms]))
    return np.array(states)


# Measured: the two engines' first ten env steps (100 physics steps on planar_square, 50 under gravity on
# spatial_tetrahedron) agree to 5e-16 rad and 5e-15 rad/s: both integrate semi-implicitly, without contacts.
@pytest.mark.parametrize("scenario", ["planar_square", "spatial_tetrahedron"])
def test_the_first_ten_steps_follow_pybullets_trajectory(scenario):
    bullet, mujoco = _trajectory(scenario, "pybullet", 10), _trajectory(scenario, "mujoco", 10)
    assert np.abs(bullet[-1] - bullet[0]).max() > 1e-3  # the arms moved
    np.testing.assert_allclose(mujoco, bullet, rtol=0, atol=1e-12)


def test_a_reset_returns_the_world_to_the_same_state():
    first, second = (_trajectory("spatial_tetrahedron", "mujoco", 5) for _ in range(2))
    np.testing.assert_array_equal(first, second)
    with ee_formation_env.parallel_env("spatial_tetrahedron", engine="mujoco") as env:
        runs = []
        for _ in range(2):  # the same env reset twice: restored from its snapshot
            env.reset(seed=3)
            env.step({agent: np.full(env.action_space(agent).shape, 0.3, dtype=np.float32) for agent in env.agents})
            runs.append(np.concatenate([np.concatenate(arm.read_state_lists()) for arm in env.arms]))
    np.testing.assert_array_equal(runs[0], runs[1])


def _two_pera_arms(engine: str, gap: float, collide: bool = True):
    urdf = str(ROBOTS["pera_arm"].urdf)
    chain = SerialChain.from_urdf(urdf, "ee_link")
    world = make_engine(engine, 1000.0, (0.0, 0.0, -9.81))
    arms = [world.load_arm(urdf, (x, 0.0, 0.0), (0.0, 0.0, yaw), chain.joint_names, np.zeros(chain.n_joints), collide)
            for x, yaw in ((0.0, 0.0), (gap, np.pi))]  # facing each other
    for arm in arms:
        world.reset_joints(arm, np.array(ROBOTS["pera_arm"].start_q))
    return world, arms


def test_closest_distance_between_arms_matches_pybullet_within_a_millimetre():
    for gap in (0.8, 0.6):
        distances = []
        for engine in ("pybullet", "mujoco"):
            world, arms = _two_pera_arms(engine, gap)
            distances.append(world.closest_distance(arms[0], arms[1], 1.0))
            assert world.closest_distance(arms[0], arms[1], distances[-1] - 1e-3) is None  # beyond the bound
            world.close()
        assert distances[0] > 0 and abs(distances[1] - distances[0]) < 1e-3, distances


def test_contacts_are_between_arms_only_and_off_with_arm_collisions_off():
    for engine in ("pybullet", "mujoco"):  # bases 5 cm apart: the first links overlap on both engines
        world, arms = _two_pera_arms(engine, 0.05)
        world.step_torques(np.zeros(2 * len(arms[0].joint_indices)), 1)
        assert world.closest_distance(arms[0], arms[1], 0.0) < -0.05
        pairs = world.contact_bodies()
        assert pairs and all({a, b} == {arms[0].body, arms[1].body} for a, b in pairs), (engine, pairs)
        world.close()
    world, arms = _two_pera_arms("mujoco", 0.05, collide=False)
    world.step_torques(np.zeros(2 * len(arms[0].joint_indices)), 1)
    assert world.contact_bodies() == []
    world.close()


def test_arms_touching_at_the_start_are_refused_as_on_pybullet():
    arms = [{"robot": "pera_arm", "base_position": [x, 0.0, 0.0], "base_rpy": [0.0, 0.0, yaw]}
            for x, yaw in ((0.0, 0.0), (0.1, np.pi))]  # the bases overlap by 2 cm
    scenario = {"arms": arms, "edges": [[0, 1]], "shape": [[0.0, 0.0, -0.5], [0.2, 0.0, -0.5]]}
    with pytest.raises(ValueError, match=r"^arms: arm_0 and arm_1 are in contact at their initial configurations"):
        ee_formation_env.parallel_env(scenario, engine="mujoco")


def test_pybullet_data_robots_load_with_their_package_meshes_and_held_fingers():
    """``franka_panda`` names its meshes ``package://...`` (resolved from the URDF's folder, as PyBullet does)
    and has two finger joints off the chain, held where they are loaded: the arms follow PyBullet's closely
    (measured after ten steps under gravity compensation: 4e-6 rad, 1.4e-5 rad/s; PyBullet holds the fingers by
    motors)."""
    from ee_formation_env.robots import PYBULLET_DATA_ROBOTS

    spec = PYBULLET_DATA_ROBOTS["franka_panda"]
    scenario = {"arms": [{"urdf": str(spec.urdf), "ee_link": spec.ee_link, "base_position": [x, 0.0, 0.0],
                          "initial_q": list(spec.start_q)} for x in (0.0, 1.5)],
                "edges": [[0, 1]], "shape": [[0.3, 0.0, 0.5], [1.2, 0.0, 0.5]], "gravity_compensation": True}
    states = []
    for engine in ("pybullet", "mujoco"):
        with ee_formation_env.parallel_env(scenario, engine=engine) as env:
            env.reset(seed=0)
            assert len(env.arms[0].extra_joint_indices) == 2
            actions = {agent: np.full(env.action_space(agent).shape, 0.05, dtype=np.float32) for agent in env.agents}
            for _ in range(10):
                env.step(actions)
            states.append(np.concatenate([np.concatenate(arm.read_state_lists()) for arm in env.arms]))
    np.testing.assert_allclose(states[1], states[0], rtol=0, atol=1e-4)


def test_a_urdf_mujoco_cannot_read_is_refused_in_one_line_naming_the_arm(tmp_path):
    """A Collada mesh (PyBullet reads it, MuJoCo has no decoder for it): a ValueError naming the arm and the
    file, on one line."""
    (tmp_path / "part.dae").write_text("")
    inertial = '<inertial><origin xyz="0.5 0 0"/><mass value="1"/><inertia ixx="0.01" ixy="0" ixz="0" iyy="0.1" iyz="0" izz="0.1"/></inertial>'
    (tmp_path / "arm.urdf").write_text(f"""<robot name="dae_arm">
  <link name="base_link">{inertial}</link>
  <joint name="j1" type="continuous"><parent link="base_link"/><child link="l1"/><axis xyz="0 0 1"/></joint>
  <link name="l1">{inertial}<collision><geometry><mesh filename="part.dae"/></geometry></collision></link>
  <joint name="j2" type="continuous"><parent link="l1"/><child link="l2"/><origin xyz="1 0 0"/><axis xyz="0 0 1"/></joint>
  <link name="l2">{inertial}</link>
  <joint name="tip" type="fixed"><parent link="l2"/><child link="ee"/><origin xyz="1 0 0"/></joint>
  <link name="ee"/>
</robot>""")
    arms = [{"urdf": str(tmp_path / "arm.urdf"), "ee_link": "ee", "base_position": [x, 0.0, 0.0], "initial_q": [0.3, 0.5]}
            for x in (0.0, 3.0)]
    scenario = {"arms": arms, "edges": [[0, 1]], "shape": [[1.6, 1.0], [4.4, 1.0]], "dim": 2, "arm_collisions": False,
                "torque_limits": 5.0}
    with pytest.raises(ValueError, match=r"^arms\[0\]\.urdf: MuJoCo could not load .*arm\.urdf \(.*no decoder found "
                                         r"for mesh file .*part\.dae") as caught:
        ee_formation_env.parallel_env(scenario, engine="mujoco")
    assert "\n" not in str(caught.value)
