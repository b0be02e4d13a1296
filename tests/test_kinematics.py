"""Tests of ee_formation_env.kinematics against PyBullet, closed forms and the regressor identity.

PyBullet facts these tests rely on (checked with pybullet 3.2.7):
- ``getLinkState(...)[4]`` (worldLinkFramePosition) is only float32-accurate (errors ~1e-7 m);
  the COM pose ``[0]``, ``[1]`` and the local inertial frame ``[2]``, ``[3]`` are double, so the
  URDF link frame is rebuilt from them for 1e-9 comparisons.
- ``calculateJacobian``'s localPosition is relative to the URDF link frame origin (not the COM),
  and its result is expressed in the axes of the base's inertial (COM) frame, not the world
  frame and not the URDF root link frame: the two differ when the root's <inertial> has an rpy.
- Within one client, loadURDF caches by file path: rewriting a file and loading it again gives
  the old model, so every generated URDF here gets its own path.
- ``loadURDF``'s basePosition/baseOrientation place the URDF root link frame (not the COM).
"""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pybullet
import pybullet_data
import pytest

REPO = Path(__file__).resolve().parents[1]

try:
    from ee_formation_env.kinematics import SerialChain
except Exception:  # the package __init__ may not be importable yet: load the module file itself
    _spec = importlib.util.spec_from_file_location(
        "_ee_formation_kinematics", REPO / "ee_formation_env" / "kinematics.py")
    _module = importlib.util.module_from_spec(_spec)
    sys.modules[_spec.name] = _module
    _spec.loader.exec_module(_module)
    SerialChain = _module.SerialChain

DATA = Path(pybullet_data.getDataPath())
ARMS = {
    "planar": (REPO / "assets" / "planar_2link.urdf", "ee_link"),
    "kuka": (DATA / "kuka_iiwa" / "model.urdf", "lbr_iiwa_link_7"),
    "panda": (DATA / "franka_panda" / "panda.urdf", "panda_hand"),
    "pera": (REPO / "assets" / "pera_arm.urdf", "ee_link"),
}
ARM_IDS = list(ARMS)


def _chain(arm: str) -> SerialChain:
    path, ee_link = ARMS[arm]
    if not path.is_file():
        pytest.skip(f"{path} does not exist yet")
    return SerialChain.from_urdf(path, ee_link)


@pytest.fixture(scope="module")
def client():
    cid = pybullet.connect(pybullet.DIRECT)
    yield cid
    pybullet.disconnect(cid)


class Body:
    """A PyBullet body of an arm plus the index maps between it and a SerialChain."""

    def __init__(self, cid: int, chain: SerialChain, position=(0.0, 0.0, 0.0),
                 orientation=(0.0, 0.0, 0.0, 1.0)) -> None:
        self.cid = cid
        self.id = pybullet.loadURDF(str(chain.urdf_path), list(position), list(orientation),
                                    useFixedBase=True, flags=pybullet.URDF_USE_INERTIA_FROM_FILE,
                                    physicsClientId=cid)
        infos = [pybullet.getJointInfo(self.id, i, physicsClientId=cid)
                 for i in range(pybullet.getNumJoints(self.id, physicsClientId=cid))]
        names = [info[1].decode() for info in infos]
        links = [info[12].decode() for info in infos]
        self.ee = links.index(chain.ee_link)
        self.model_joints = [names.index(name) for name in chain.joint_names]
        self.dofs = [i for i, info in enumerate(infos) if info[2] != pybullet.JOINT_FIXED]
        # chain column j <-> column of calculateJacobian (which spans every movable DOF)
        self.dof_columns = [self.dofs.index(i) for i in self.model_joints]

    def set_q(self, q: np.ndarray) -> None:
        for index, value in zip(self.model_joints, q):
            pybullet.resetJointState(self.id, index, float(value), physicsClientId=self.cid)

    def link_state(self):
        return pybullet.getLinkState(self.id, self.ee, computeForwardKinematics=True,
                                     physicsClientId=self.cid)

    def ee_frame_position(self) -> np.ndarray:
        """World position of the ee's URDF link frame, in double precision (from the COM pose)."""
        state = self.link_state()
        com_rot = np.array(pybullet.getMatrixFromQuaternion(state[1])).reshape(3, 3)
        inertial_rot = np.array(pybullet.getMatrixFromQuaternion(state[3])).reshape(3, 3)
        return np.array(state[0]) - com_rot @ inertial_rot.T @ np.array(state[2])

    def base_frame(self) -> tuple[np.ndarray, np.ndarray]:
        """World position and rotation of the URDF root link frame."""
        com_pos, com_orn = pybullet.getBasePositionAndOrientation(self.id, physicsClientId=self.cid)
        info = pybullet.getDynamicsInfo(self.id, -1, physicsClientId=self.cid)
        com_rot = np.array(pybullet.getMatrixFromQuaternion(com_orn)).reshape(3, 3)
        inertial_rot = np.array(pybullet.getMatrixFromQuaternion(info[4])).reshape(3, 3)
        rot = com_rot @ inertial_rot.T
        return np.array(com_pos) - rot @ np.array(info[3]), rot

    def base_inertial_rotation(self) -> np.ndarray:
        """Rotation of the root link's inertial frame relative to its URDF link frame."""
        info = pybullet.getDynamicsInfo(self.id, -1, physicsClientId=self.cid)
        return np.array(pybullet.getMatrixFromQuaternion(info[4])).reshape(3, 3)

    def raw_jacobian(self, local_position=(0.0, 0.0, 0.0)) -> np.ndarray:
        """Translational calculateJacobian restricted to the chain's joints (3, n), as returned:
        in the axes of the base's inertial (COM) frame."""
        q = [float(pybullet.getJointState(self.id, i, physicsClientId=self.cid)[0])
             for i in self.dofs]
        zeros = [0.0] * len(q)
        jac_t, _ = pybullet.calculateJacobian(self.id, self.ee, [float(v) for v in local_position],
                                              q, zeros, zeros, physicsClientId=self.cid)
        return np.array(jac_t)[:, self.dof_columns]

    def jacobian(self, local_position=(0.0, 0.0, 0.0)) -> np.ndarray:
        """calculateJacobian rotated into the URDF root link frame (3, n)."""
        return self.base_inertial_rotation() @ self.raw_jacobian(local_position)


def _random_params(chain: SerialChain, rng: np.random.Generator) -> np.ndarray:
    return chain.nominal_params * rng.uniform(-2.0, 2.0, chain.n_params) + rng.normal(
        0.0, 0.1, chain.n_params)


# ---------------------------------------------------------------- agreement with PyBullet
def _posed_in_pybullet(arm: str, client: int, seed: int):
    """The chain and 20 random configurations q, each set on the PyBullet body before it is yielded."""
    chain = _chain(arm)
    body = Body(client, chain)
    for q in chain.sample_configurations(20, np.random.default_rng(seed)):
        body.set_q(q)
        yield chain, body, q


@pytest.mark.parametrize("arm", ARM_IDS)
def test_forward_matches_pybullet_link_frame(arm, client):
    for chain, body, q in _posed_in_pybullet(arm, client, seed=1):
        position = chain.forward(q)
        np.testing.assert_allclose(position, body.ee_frame_position(), rtol=0, atol=1e-9)
        # getLinkState's worldLinkFramePosition itself is float32-accurate only
        np.testing.assert_allclose(position, body.link_state()[4], rtol=0, atol=1e-6)


@pytest.mark.parametrize("arm", ARM_IDS)
def test_jacobian_matches_pybullet(arm, client):
    for chain, body, q in _posed_in_pybullet(arm, client, seed=2):
        np.testing.assert_allclose(chain.jacobian(q), body.jacobian(), rtol=0, atol=1e-9)


def _finite_difference_jacobian(body: "Body", q: np.ndarray, point, step: float = 1e-6) -> np.ndarray:
    """Central differences (3, n) of ``point()`` (a world position read from PyBullet) over the joints;
    leaves the body at ``q``."""
    fd = np.empty((3, len(q)))
    for j in range(len(q)):
        positions = []
        for sign in (1.0, -1.0):
            shifted = q.copy()
            shifted[j] += sign * step
            body.set_q(shifted)
            positions.append(np.asarray(point()))
        fd[:, j] = (positions[0] - positions[1]) / (2 * step)
    body.set_q(q)
    return fd


def test_calculate_jacobian_local_position_is_from_link_frame(client):
    """kuka link 7 has its COM 0.02 m off the link frame: localPosition = that offset gives
    the Jacobian of the COM, so localPosition is measured from the URDF link frame."""
    chain = _chain("kuka")
    body = Body(client, chain)
    q = chain.sample_configurations(1, np.random.default_rng(3))[0]
    body.set_q(q)
    state = body.link_state()
    assert np.linalg.norm(state[2]) > 0.01
    fd = _finite_difference_jacobian(body, q, lambda: np.array(body.link_state()[0]))
    np.testing.assert_allclose(body.jacobian(state[2]), fd, rtol=0, atol=1e-7)
    assert np.abs(body.jacobian() - fd).max() > 1e-3


def test_calculate_jacobian_is_in_base_frame(client):
    """With a yawed and pitched base, R_base @ J (model or PyBullet) is the world Jacobian."""
    chain = _chain("kuka")
    orientation = pybullet.getQuaternionFromEuler([0.0, 0.4, 1.0])
    body = Body(client, chain, position=(0.3, -0.2, 0.5), orientation=orientation)
    base_pos, base_rot = body.base_frame()
    rng = np.random.default_rng(4)
    for q in chain.sample_configurations(3, rng):
        fd = _finite_difference_jacobian(body, q, body.ee_frame_position)
        position, jac = chain.forward_and_jacobian(q)
        np.testing.assert_allclose(base_pos + base_rot @ position, body.ee_frame_position(),
                                   rtol=0, atol=1e-9)
        np.testing.assert_allclose(base_rot @ jac, fd, rtol=0, atol=1e-7)
        np.testing.assert_allclose(body.jacobian(), jac, rtol=0, atol=1e-9)
        assert np.abs(jac - fd).max() > 1e-2  # the base-frame Jacobian is not the world one
        com_orientation = pybullet.getBasePositionAndOrientation(body.id, physicsClientId=client)[1]
        com_rot = np.array(pybullet.getMatrixFromQuaternion(com_orientation)).reshape(3, 3)
        np.testing.assert_allclose(com_rot @ body.raw_jacobian(), fd, rtol=0, atol=1e-7)


# ---------------------------------------------------------------- linearity in the parameters
@pytest.mark.parametrize("arm", ARM_IDS)
def test_regressor_identity_for_any_params(arm):
    chain = _chain(arm)
    rng = np.random.default_rng(5)
    for q in chain.sample_configurations(20, rng):
        zeta = rng.normal(size=3)
        for params in (chain.nominal_params, _random_params(chain, rng)):
            jac = chain.jacobian(q, params)
            np.testing.assert_allclose(chain.regressor(q, zeta) @ params, jac.T @ zeta,
                                       rtol=0, atol=1e-9)


@pytest.mark.parametrize("arm", ARM_IDS)
def test_batched_regressor_is_the_regressor_of_each_configuration(arm):
    chain = _chain(arm)
    rng = np.random.default_rng(6)
    q = chain.sample_configurations(7, rng)
    zeta = rng.normal(size=(7, 3))
    regressors = chain.regressor_batch(q, zeta)
    assert regressors.shape == (7, chain.n_joints, chain.n_params)
    for k in range(len(q)):
        np.testing.assert_allclose(regressors[k], chain.regressor(q[k], zeta[k]), rtol=0, atol=1e-12)
    planar = chain.regressor_batch(q, zeta[:, :2])  # (k, 2): z = 0
    np.testing.assert_array_equal(planar, chain.regressor_batch(q, np.c_[zeta[:, :2], np.zeros(7)]))
    with pytest.raises(ValueError, match="zeta_batch"):
        chain.regressor_batch(q, zeta[:3])


@pytest.mark.parametrize("arm", ARM_IDS)
def test_jacobian_with_params_is_derivative_of_forward(arm):
    chain = _chain(arm)
    rng = np.random.default_rng(6)
    step = 1e-6
    for q in chain.sample_configurations(5, rng):
        params = _random_params(chain, rng)
        position, jac = chain.forward_and_jacobian(q, params)
        np.testing.assert_allclose(position, chain.forward(q, params), rtol=0, atol=1e-12)
        fd = np.stack([(chain.forward(q + step * e, params) - chain.forward(q - step * e, params))
                       / (2 * step) for e in np.eye(chain.n_joints)], axis=1)
        np.testing.assert_allclose(jac, fd, rtol=0, atol=1e-7)


@pytest.mark.parametrize("arm", ARM_IDS)
def test_forward_is_linear_in_params(arm):
    chain = _chain(arm)
    rng = np.random.default_rng(7)
    q = chain.sample_configurations(1, rng)[0]
    a, b = _random_params(chain, rng), _random_params(chain, rng)
    np.testing.assert_allclose(chain.forward(q, 2.0 * a - b),
                               2.0 * chain.forward(q, a) - chain.forward(q, b), rtol=0, atol=1e-12)
    np.testing.assert_allclose(chain.forward(q, chain.nominal_params), chain.forward(q),
                               rtol=0, atol=0)


@pytest.mark.parametrize("arm", ARM_IDS)
def test_forward_batch_matches_forward(arm):
    chain = _chain(arm)
    rng = np.random.default_rng(8)
    q_batch = chain.sample_configurations(50, rng)
    params = _random_params(chain, rng)
    for given in (None, params):
        batch = chain.forward_batch(q_batch, given)
        assert batch.shape == (50, 3)
        expected = np.stack([chain.forward(q, given) for q in q_batch])
        np.testing.assert_allclose(batch, expected, rtol=0, atol=1e-12)


# ---------------------------------------------------------------- planar arm closed forms
def test_planar_parameters():
    chain = _chain("planar")
    assert chain.base_link == "base_link"
    assert chain.joint_names == ("joint_1", "joint_2")
    assert [j.name for j in chain.joints] == ["joint_1", "joint_2", "ee_joint"]
    assert chain.param_names == ("joint_2.x", "ee_joint.x")
    np.testing.assert_array_equal(chain.nominal_params, [1.5, 1.5])
    assert chain.continuous.tolist() == [True, True]
    assert np.all(np.isinf(chain.lower)) and np.all(np.isinf(chain.upper))
    np.testing.assert_array_equal(chain.effort_limits, [50.0, 50.0])


def test_planar_closed_forms():
    chain = _chain("planar")
    rng = np.random.default_rng(9)
    for q in chain.sample_configurations(20, rng):
        l1, l2 = rng.uniform(0.5, 2.0, 2)
        c1, s1 = math.cos(q[0]), math.sin(q[0])
        c12, s12 = math.cos(q[0] + q[1]), math.sin(q[0] + q[1])
        np.testing.assert_allclose(chain.forward(q, [l1, l2]),
                                   [l1 * c1 + l2 * c12, l1 * s1 + l2 * s12, 0.0], rtol=0, atol=1e-12)
        zx, zy = rng.normal(size=2)
        expected = np.array([[zy * c1 - zx * s1, zy * c12 - zx * s12],
                             [0.0, zy * c12 - zx * s12]])
        np.testing.assert_allclose(chain.regressor(q, [zx, zy]), expected, rtol=0, atol=1e-12)
        np.testing.assert_allclose(chain.regressor(q, [zx, zy]), chain.regressor(q, [zx, zy, 0.0]),
                                   rtol=0, atol=0)
        np.testing.assert_allclose(chain.regressor(q, [zx, zy]) @ [l1, l2],
                                   chain.jacobian(q, [l1, l2])[:2].T @ [zx, zy], rtol=0, atol=1e-12)


# ---------------------------------------------------------------- limits, sampling, metadata
def test_kuka_limits_and_dynamics_fields():
    chain = _chain("kuka")
    assert chain.n_joints == 7 and chain.n_params == 7
    np.testing.assert_allclose(chain.upper, -chain.lower)
    np.testing.assert_array_equal(chain.effort_limits, 300.0)
    np.testing.assert_array_equal(chain.velocity_limits, 10.0)
    np.testing.assert_array_equal(chain.joint_damping, 0.5)
    assert not chain.continuous.any()


def test_panda_ignores_joints_off_the_path():
    chain = _chain("panda")
    assert chain.joint_names == tuple(f"panda_joint{i}" for i in range(1, 8))
    assert [j.name for j in chain.joints][-2:] == ["panda_joint8", "panda_hand_joint"]
    assert all(j.joint_type != "prismatic" for j in chain.joints)


@pytest.mark.parametrize("arm", ARM_IDS)
def test_sample_configurations_within_limits(arm):
    chain = _chain(arm)
    q = chain.sample_configurations(1000, np.random.default_rng(10))
    assert q.shape == (1000, chain.n_joints)
    low = np.where(chain.continuous, -math.pi, chain.lower)
    high = np.where(chain.continuous, math.pi, chain.upper)
    assert np.all(q >= low) and np.all(q < high)


@pytest.mark.parametrize("arm", ARM_IDS)
def test_batch_forward_and_jacobian_is_bit_identical_to_single(arm):
    chain = _chain(arm)
    q = chain.sample_configurations(50, np.random.default_rng(11))
    positions, jacobians = chain.forward_and_jacobian_batch(q)
    assert positions.shape == (50, 3) and jacobians.shape == (50, 3, chain.n_joints)
    for k in range(len(q)):
        position, jacobian = chain.forward_and_jacobian(q[k])
        assert np.array_equal(position, positions[k]) and np.array_equal(jacobian, jacobians[k])


def test_repeated_evaluation_at_the_same_q_is_consistent():
    """The chain keeps its last evaluation; every call still answers for its own q and params."""
    chain = _chain("kuka")
    rng = np.random.default_rng(12)
    q1, q2 = chain.sample_configurations(2, rng)
    params = chain.nominal_params * 1.1
    zeta = rng.normal(size=3)
    first = (chain.forward(q1), chain.jacobian(q1, params), chain.regressor(q1, zeta))
    chain.forward(q2)
    again = (chain.forward(q1.copy()), chain.jacobian(list(q1), params), chain.regressor(q1, zeta))
    for a, b in zip(first, again):
        assert np.array_equal(a, b)
    assert not np.array_equal(chain.forward(q2), first[0])
    q = q1.copy()
    chain.forward(q)
    q[0] += 0.1  # mutating the caller's array must not reuse the stale evaluation
    assert np.array_equal(chain.forward(q), SerialChain.from_urdf(*ARMS["kuka"]).forward(q))


def test_bad_shapes_are_rejected():
    chain = _chain("planar")
    with pytest.raises(ValueError, match="q"):
        chain.forward([0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="params"):
        chain.jacobian([0.0, 0.0], [1.0])
    with pytest.raises(ValueError, match="zeta"):
        chain.regressor([0.0, 0.0], [1.0])
    with pytest.raises(ValueError, match="q_batch"):
        chain.forward_batch(np.zeros(2))
    with pytest.raises(ValueError, match="q_batch"):
        chain.forward_and_jacobian_batch(np.zeros((4, 3)))


# ---------------------------------------------------------------- errors
_TINY_URDF = """<?xml version="1.0"?>
<robot name="tiny">
  <link name="base"/>
  <link name="a"/>
  <link name="tip"/>
  <joint name="j1" type="revolute">
    <parent link="base"/><child link="a"/>
    <origin xyz="0 0 0.1"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
  <joint name="slider" type="{second_type}">
    <parent link="a"/><child link="tip"/>
    <origin xyz="0.2 0 0"/><axis xyz="1 0 0"/>
    <limit lower="0" upper="0.1" effort="1" velocity="1"/>
  </joint>
</robot>
"""


def test_missing_file(tmp_path):
    with pytest.raises(ValueError, match="urdf file not found"):
        SerialChain.from_urdf(tmp_path / "nope.urdf", "tip")


def test_unparseable_file(tmp_path):
    path = tmp_path / "bad.urdf"
    path.write_text("<robot><link name='a'></robot>")
    with pytest.raises(ValueError, match="not parseable"):
        SerialChain.from_urdf(path, "a")


def test_unknown_ee_link_lists_links():
    path, _ = ARMS["planar"]
    with pytest.raises(ValueError, match="ee_link") as error:
        SerialChain.from_urdf(path, "gripper")
    for link in ("base_link", "link_1", "link_2", "ee_link"):
        assert link in str(error.value)


def test_prismatic_joint_on_path(tmp_path):
    path = tmp_path / "tiny.urdf"
    path.write_text(_TINY_URDF.format(second_type="prismatic"))
    with pytest.raises(ValueError, match="slider.*prismatic"):
        SerialChain.from_urdf(path, "tip")
    chain = SerialChain.from_urdf(path, "a")  # the prismatic joint is off this path
    assert chain.joint_names == ("j1",)


def test_no_movable_joint_on_path(tmp_path):
    path = tmp_path / "tiny.urdf"
    path.write_text(_TINY_URDF.format(second_type="fixed"))
    with pytest.raises(ValueError, match="no path"):
        SerialChain.from_urdf(path, "base")
    chain = SerialChain.from_urdf(path, "tip")
    np.testing.assert_allclose(chain.forward([0.5]), [0.2 * math.cos(0.5), 0.2 * math.sin(0.5), 0.1])


_GENERAL_URDF = """<?xml version="1.0"?>
<robot name="general">
  <link name="root"><inertial><origin xyz="0.01 0.02 0.03" rpy="0.1 0.2 0.3"/><mass value="1"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  {links}
  <joint name="mount" type="fixed">
    <parent link="root"/><child link="l0"/><origin xyz="0.05 -0.02 0.1" rpy="0.3 -0.2 0.7"/>
  </joint>
  {joints}
</robot>
"""


def _general_urdf(rng: np.random.Generator) -> str:
    """Three revolute joints with general rpy, oblique non-unit axes and offset inertials."""
    links, joints = [], []
    for i in range(4):
        xyz = " ".join(f"{v:.6f}" for v in rng.uniform(-0.1, 0.1, 3))
        rpy = " ".join(f"{v:.6f}" for v in rng.uniform(-math.pi, math.pi, 3))
        links.append(f'<link name="l{i}"><inertial><origin xyz="{xyz}" rpy="{rpy}"/>'
                     '<mass value="0.5"/><inertia ixx="0.002" ixy="0" ixz="0" iyy="0.003" '
                     'iyz="0" izz="0.004"/></inertial></link>')
    links.append('<link name="tool"/>')
    for i in range(3):
        xyz = " ".join(f"{v:.6f}" for v in rng.uniform(-0.4, 0.4, 3))
        rpy = " ".join(f"{v:.6f}" for v in rng.uniform(-math.pi, math.pi, 3))
        axis = " ".join(f"{v:.6f}" for v in rng.uniform(-2.0, 2.0, 3))
        joints.append(f'<joint name="j{i}" type="revolute"><parent link="l{i}"/>'
                      f'<child link="l{i + 1}"/><origin xyz="{xyz}" rpy="{rpy}"/>'
                      f'<axis xyz="{axis}"/><limit lower="-3" upper="3" effort="5" velocity="2"/>'
                      '</joint>')
    joints.append('<joint name="tool_joint" type="fixed"><parent link="l3"/><child link="tool"/>'
                  '<origin xyz="0.1 0.05 -0.2" rpy="1.1 0.4 -0.9"/></joint>')
    return _GENERAL_URDF.format(links="\n  ".join(links), joints="\n  ".join(joints))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_general_rpy_and_oblique_axes_match_pybullet(seed, client, tmp_path):
    path = tmp_path / "general.urdf"
    path.write_text(_general_urdf(np.random.default_rng(seed)))
    rng = np.random.default_rng(100 + seed)
    for ee_link in ("tool", "l3"):
        chain = SerialChain.from_urdf(path, ee_link)
        assert chain.joint_names == ("j0", "j1", "j2")
        assert all(abs(np.linalg.norm(j.axis) - 1.0) < 1e-12 for j in chain.joints if j.movable)
        body = Body(client, chain)
        for q in chain.sample_configurations(10, rng):
            body.set_q(q)
            position, jac = chain.forward_and_jacobian(q)
            np.testing.assert_allclose(position, body.ee_frame_position(), rtol=0, atol=1e-9)
            np.testing.assert_allclose(jac, body.jacobian(), rtol=0, atol=1e-9)
            # the root's inertial frame is rotated here: raw calculateJacobian is in its axes
            np.testing.assert_allclose(body.base_inertial_rotation().T @ jac, body.raw_jacobian(),
                                       rtol=0, atol=1e-9)
            assert np.abs(jac - body.raw_jacobian()).max() > 1e-3
            zeta = rng.normal(size=3)
            params = _random_params(chain, rng)
            np.testing.assert_allclose(chain.regressor(q, zeta) @ params,
                                       chain.jacobian(q, params).T @ zeta, rtol=0, atol=1e-9)
