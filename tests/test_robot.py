"""Physics set-up of the arms: true torque control, no hidden motors, damping or velocity clamps, and
the planar arm's dynamics equal the paper's closed form (Wu et al., Table I; Slotine & Li Ex. 6.2)."""

from __future__ import annotations

import math

import numpy as np
import pybullet
import pytest

from conftest import apply_torques, read_state, scenario_dict


def _set_state(arm, q, dq) -> None:
    for j, position, velocity in zip(arm.joint_indices, q, dq):
        pybullet.resetJointState(arm.body, j, float(position), float(velocity), physicsClientId=arm.world.client)


def _mass_matrix(arm, q) -> np.ndarray:
    return np.array(pybullet.calculateMassMatrix(arm.body, [float(v) for v in q], physicsClientId=arm.world.client))


def _bias(arm, q, dq) -> np.ndarray:
    """C(q, dq) dq + g(q): inverse dynamics at zero acceleration."""
    zero = [0.0] * len(q)
    return np.array(pybullet.calculateInverseDynamics(arm.body, [float(v) for v in q], [float(v) for v in dq], zero,
                                                      physicsClientId=arm.world.client))


def _kinetic_energy(arm) -> float:
    q, dq = read_state(arm)
    return 0.5 * float(dq @ _mass_matrix(arm, q) @ dq)


def _zero_torques(env) -> None:
    """Zero torque on every arm for the next physics step."""
    for arm in env.arms:
        apply_torques(arm, [0.0] * arm.n_joints)


# ------------------------------------------------------------------------------------------ planar arm model
PLANAR_Q = [(0.0, 0.0), (0.4, 0.3), (-1.0, 1.0), (2.0, 2.5), (0.7, -1.7), (3.0, math.pi)]


@pytest.mark.parametrize("q", PLANAR_Q)
def test_planar_mass_matrix_closed_form(make_env, q):
    env = make_env("planar_square")
    arm = env.arms[0]
    c2 = math.cos(q[1])
    expected = np.array([[3.9 + 2.25 * c2, 0.75 + 1.125 * c2], [0.75 + 1.125 * c2, 0.75]])
    np.testing.assert_allclose(_mass_matrix(arm, q), expected, rtol=0, atol=1e-12)
    # Every arm of the scenario is the same robot, whatever its base yaw.
    rotated = make_env("planar_square_rotated")
    np.testing.assert_allclose(_mass_matrix(rotated.arms[2], q), expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize("q, dq", [((0.4, 0.3), (0.7, -1.3)), ((-1.0, 1.0), (2.0, 0.5)), ((2.0, 2.5), (-3.0, 4.0)),
                                   ((0.7, -1.7), (1.1, 1.1)), ((0.0, 0.0), (5.0, -2.0))])
def test_planar_coriolis_closed_form(make_env, q, dq):
    env = make_env("planar_square")  # gravity is along -z, the joint axes: g(q) = 0
    h = 1.125 * math.sin(q[1])  # m2 l1 lc2 sin q2
    coriolis = np.array([[-h * dq[1], -h * (dq[0] + dq[1])], [h * dq[0], 0.0]])
    np.testing.assert_allclose(_bias(env.arms[1], q, dq), coriolis @ np.asarray(dq), rtol=0, atol=1e-12)


# ------------------------------------------------------------------------------------------ torque control
def test_one_physics_step_follows_forward_dynamics(make_env):
    """(dq' - dq) / dt = M(q)^-1 (tau - C(q, dq) dq - g(q)) under gravity; q' = q + dt dq' (semi-implicit).

    Arm collisions are off: random configurations of neighbouring arms can interpenetrate, and a
    contact impulse is not part of this equation.
    """
    env = make_env("spatial_tetrahedron", arm_collisions=False)
    env.reset(seed=0)
    dt = env.world.time_step
    assert dt == pytest.approx(1.0 / env.scenario.physics_hz)
    rng = np.random.default_rng(0)
    worst = 0.0
    for trial in range(12):
        i = trial % len(env.arms)
        arm = env.arms[i]
        model = arm.model
        q = rng.uniform(model.lower + 0.05, model.upper - 0.05)
        dq = rng.uniform(-1.0, 1.0, model.n_joints)
        tau = rng.uniform(-0.3, 0.3, model.n_joints) * env.torque_limits[i]
        _set_state(arm, q, dq)
        acceleration = np.linalg.solve(_mass_matrix(arm, q), tau - _bias(arm, q, dq))
        for other in env.arms:
            apply_torques(other, tau.tolist() if other is arm else [0.0] * other.n_joints)
        env.world.step()
        q_new, dq_new = read_state(arm)
        measured = (dq_new - dq) / dt
        error = np.max(np.abs(measured - acceleration)) / np.max(np.abs(acceleration))
        worst = max(worst, error)
        np.testing.assert_allclose(q_new, q + dt * dq_new, rtol=0, atol=1e-12)
    assert worst < 1e-9, worst  # measured: ~2e-15


@pytest.mark.parametrize("name, action_scale", [("planar_square", 0.5), ("spatial_tetrahedron", 0.0),
                                                ("spatial_tetrahedron", 0.2)])
def test_env_step_holds_torque_for_every_physics_step(make_env, name, action_scale):
    """One env step = frame_skip semi-implicit Euler steps of the forward dynamics with the same torque.

    With action 0 under gravity this is free fall: no motor holds the arm.
    """
    env = make_env(name, arm_collisions=False, initial_q_noise=0.0)
    env.reset(seed=0)
    rng = np.random.default_rng(1)
    actions = {a: (action_scale * rng.uniform(-1, 1, env.action_space(a).shape)).astype(np.float32)
               for a in env.agents}
    dt, skip = env.world.time_step, env.scenario.frame_skip
    predicted = []
    for i, (agent, arm) in enumerate(zip(env.agents, env.arms)):
        q, dq = read_state(arm)
        tau = actions[agent].astype(np.float64) * env.torque_limits[i]
        for _ in range(skip):
            dq = dq + dt * np.linalg.solve(_mass_matrix(arm, q), tau - _bias(arm, q, dq))
            q = q + dt * dq
        predicted.append((q, dq))
    env.step(actions)
    for arm, (q, dq) in zip(env.arms, predicted):
        q_sim, dq_sim = read_state(arm)
        np.testing.assert_allclose(dq_sim, dq, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(q_sim, q, rtol=0, atol=1e-10)
        assert np.max(np.abs(dq_sim)) > 1e-3  # it moved


def test_zero_torque_under_gravity_moves_the_arm(make_env):
    env = make_env("spatial_tetrahedron", initial_q_noise=0.0, episode_seconds=0.2)
    observations, _ = env.reset(seed=0)
    q0 = [read_state(arm)[0] for arm in env.arms]
    zero = {a: np.zeros(7, np.float32) for a in env.agents}
    for _ in range(20):  # 0.1 s
        env.step(zero)
    for arm, start in zip(env.arms, q0):
        q, dq = read_state(arm)
        assert np.max(np.abs(q - start)) > 1e-3
        assert np.max(np.abs(dq)) > 1e-2
    # ... and gravity is what moves it: in zero gravity the arms stay put.
    still = make_env("spatial_tetrahedron", initial_q_noise=0.0, episode_seconds=0.2, gravity=[0.0, 0.0, 0.0])
    still.reset(seed=0)
    for _ in range(20):
        still.step(zero)
    for arm, start in zip(still.arms, q0):
        q, dq = read_state(arm)
        np.testing.assert_allclose(q, start, atol=1e-12)
        np.testing.assert_allclose(dq, 0.0, atol=1e-12)


# ------------------------------------------------------------------------------------------ no hidden damping
def _spin_straight_planar_arm(env, rate: float, seconds: float) -> tuple[float, float, np.ndarray]:
    """A straight planar arm (q2 = 0) spinning rigidly about joint 1: energy (before, after), final dq."""
    arm = env.arms[0]
    _set_state(arm, [0.3, 0.0], [rate, 0.0])
    before = _kinetic_energy(arm)
    for _ in range(int(round(seconds * env.scenario.physics_hz))):
        _zero_torques(env)
        env.world.step()
    return before, _kinetic_energy(arm), read_state(arm)[1]


def test_no_link_damping(make_env):
    env = make_env("planar_square", gravity=[0.0, 0.0, 0.0])
    env.reset(seed=0)
    before, after, dq = _spin_straight_planar_arm(env, 2.0, 2.0)
    assert before > 1.0
    assert abs(after - before) / before < 1e-6
    np.testing.assert_allclose(dq, [2.0, 0.0], atol=1e-6)
    # The check can fail: PyBullet's default link damping (0.04) loses a lot over the same 2 s.
    for link in range(-1, pybullet.getNumJoints(env.arms[0].body, physicsClientId=env.world.client)):
        pybullet.changeDynamics(env.arms[0].body, link, linearDamping=0.04, angularDamping=0.04,
                                physicsClientId=env.world.client)
    env.reset(seed=0)
    before, after, _ = _spin_straight_planar_arm(env, 2.0, 2.0)
    assert (before - after) / before > 0.05


def test_velocity_clamp_is_lifted(make_env):
    """PyBullet clamps joint speeds at 100 rad/s by default; the env lifts it to see runaways itself."""
    env = make_env("planar_square", gravity=[0.0, 0.0, 0.0], max_joint_velocity=1000.0)
    env.reset(seed=0)
    before, after, dq = _spin_straight_planar_arm(env, 150.0, 0.05)
    np.testing.assert_allclose(dq, [150.0, 0.0], rtol=1e-9, atol=1e-6)
    assert abs(after - before) / before < 1e-9


def _two_kukas(**changes) -> dict:
    kuka = {"urdf": "kuka_iiwa/model.urdf", "ee_link": "lbr_iiwa_link_7", "initial_q": [0.0, 0.5, 0.0, -1.2, 0.0, 0.8, 0.0]}
    data = {
        "arms": [dict(kuka, base_position=[0.0, 0.0, 0.0]), dict(kuka, base_position=[1.0, 0.0, 0.0])],
        "edges": [[0, 1]], "shape": [[0.5, 0.0, 0.6], [1.5, 0.0, 0.6]], "formation": "displacement", "dim": 3,
        "gravity": [0.0, 0.0, 0.0], "initial_q_noise": 0.0, "arm_collisions": False,
    }
    data.update(changes)
    return data


def _coast(env, seconds: float) -> tuple[float, float]:
    """Give arm 0 a joint velocity, coast with zero torque; kinetic energy before and after."""
    env.reset(seed=0)
    arm = env.arms[0]
    q, _ = read_state(arm)
    _set_state(arm, q, 0.5 * np.array([1.0, -0.8, 0.6, 1.2, -1.0, 0.7, 0.5]))
    before = _kinetic_energy(arm)
    for _ in range(int(round(seconds * env.scenario.physics_hz))):
        _zero_torques(env)
        env.world.step()
    return before, _kinetic_energy(arm)


def test_urdf_joint_damping_is_zeroed_by_default(make_env):
    env = make_env(_two_kukas())
    assert all(d == 0.5 for d in env.arms[0].model.joint_damping)  # the URDF does have damping
    before, after = _coast(env, 0.5)
    # Semi-implicit Euler on a 7-DOF chain drifts a little (measured ~6e-5); damping 0.5 would lose > 30 %.
    assert abs(after - before) / before < 1e-3


@pytest.mark.parametrize("damping, lost_at_least", [("urdf", 0.15), (0.1, 0.03)])
def test_joint_damping_applied_when_asked(make_env, damping, lost_at_least):
    env = make_env(_two_kukas(joint_damping=damping))
    before, after = _coast(env, 0.5)
    assert (before - after) / before > lost_at_least


def test_extra_joints_are_not_agent_joints(make_env):
    panda = {"urdf": "franka_panda/panda.urdf", "ee_link": "panda_hand", "initial_q": [0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.8]}
    env = make_env({
        "arms": [dict(panda, base_position=[0.0, 0.0, 0.0]), dict(panda, base_position=[1.0, 0.0, 0.0])],
        "edges": [[0, 1]], "shape": [[0.4, 0.0, 0.6], [1.4, 0.0, 0.6]], "formation": "displacement", "dim": 3,
    })
    arm = env.arms[0]
    client = env.world.client
    names = [pybullet.getJointInfo(arm.body, j, physicsClientId=client)[1].decode() for j in arm.joint_indices]
    extra = [pybullet.getJointInfo(arm.body, j, physicsClientId=client)[1].decode() for j in arm.extra_joint_indices]
    assert names == [f"panda_joint{k}" for k in range(1, 8)]
    assert sorted(extra) == ["panda_finger_joint1", "panda_finger_joint2"]
    assert arm.n_joints == 7 and env.action_space("arm_0").shape == (7,)


def test_planar_joints_are_continuous(make_env):
    """The planar arm's joints have no limits: q may wind past pi (observed wrapped to [-pi, pi))."""
    env = make_env(scenario_dict("planar_square"), gravity=[0.0, 0.0, 0.0], max_joint_velocity=100.0)
    assert all(arm.model.continuous.all() for arm in env.arms)
    env.reset(seed=0)
    _set_state(env.arms[0], [3.0, 0.0], [20.0, 0.0])
    for _ in range(100):  # 0.1 s at 20 rad/s: q1 goes from 3.0 to 5.0 rad, no limit stops it
        _zero_torques(env)
        env.world.step()
    q, dq = read_state(env.arms[0])
    assert q[0] == pytest.approx(5.0, abs=1e-6) and dq[0] == pytest.approx(20.0, abs=1e-6)
