"""The parallel env: PettingZoo API, observation contents, determinism, rendering, local frames,
episode ends, action checks, contacts, other robots, copies and resources."""

from __future__ import annotations

import copy
import math
import os
import pickle
import subprocess
import sys

import numpy as np
import pybullet
import pytest
from pettingzoo.test import api_test, parallel_api_test
from pettingzoo.utils.conversions import parallel_to_aec

import ee_formation_env
from ee_formation_env.env import PHYSICS_FAULTS
from ee_formation_env import BUILTIN_SCENARIOS, FormationEnv
from ee_formation_env.kinematics import rpy_to_matrix as rpy_matrix

from conftest import CLOSING, random_actions, read_state, scenario_dict, two_planar_arms

BUILTINS = sorted(BUILTIN_SCENARIOS)


def _max_abs_diff(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> float:
    assert a.keys() == b.keys()
    return max(float(np.max(np.abs(a[k].astype(np.float64) - b[k].astype(np.float64)))) for k in a)


def _assert_obs_valid(env: FormationEnv, observations: dict[str, np.ndarray]) -> None:
    assert set(observations) == set(env.agents)
    for agent, obs in observations.items():
        space = env.observation_space(agent)
        assert obs.dtype == np.float32, (agent, obs.dtype)
        assert obs.shape == space.shape, (agent, obs.shape, space.shape)
        assert np.all(np.isfinite(obs)), agent
        assert space.contains(obs), agent


# ------------------------------------------------------------------------------------------ API
@pytest.mark.parametrize("name", BUILTINS)
def test_parallel_api(make_env, name):
    # 0.2 s: planar 20 steps, spatial 40 steps, so the 50 cycles cross an episode end.
    parallel_api_test(make_env(name, episode_seconds=0.2), num_cycles=50)


@pytest.mark.filterwarnings("ignore:Agents have different observation space sizes")  # bounds differ per agent
@pytest.mark.parametrize("name", BUILTINS)
def test_aec_api(make_env, name):
    # api_test checks observation dtype and space membership (parallel_api_test does not).
    api_test(parallel_to_aec(make_env(name, episode_seconds=0.2)), num_cycles=50)


@pytest.mark.parametrize("name", BUILTINS)
def test_observations_and_state_in_spaces(make_env, name):
    env = make_env(name, episode_seconds=1.0)
    rng = np.random.default_rng(0)
    observations, infos = env.reset(seed=0)
    _assert_obs_valid(env, observations)
    assert set(infos) == set(env.agents)
    state = env.state()
    assert state.dtype == np.float32 and env.state_space.contains(state)
    for _ in range(50):
        observations, rewards, terminations, truncations, infos = env.step(random_actions(env, rng))
        _assert_obs_valid(env, observations)
        assert all(isinstance(r, float) and math.isfinite(r) for r in rewards.values())
        state = env.state()
        assert state.dtype == np.float32 and state.shape == env.state_space.shape
        assert env.state_space.contains(state)
        assert not any(terminations.values()), infos
    assert env.agents == env.possible_agents  # 50 steps < 1 s episode


def _ee_link_index(body: int, link_name: str, client: int) -> int:
    for j in range(pybullet.getNumJoints(body, physicsClientId=client)):
        if pybullet.getJointInfo(body, j, physicsClientId=client)[12].decode() == link_name:
            return j
    raise AssertionError(link_name)


def _ee_world(env) -> np.ndarray:
    """End-effector positions (N, 3) in the world frame, as PyBullet computes them."""
    client = env.world.client
    return np.array([pybullet.getLinkState(arm.body, _ee_link_index(arm.body, arm.config.ee_link, client),
                                           computeForwardKinematics=True, physicsClientId=client)[4]
                     for arm in env.arms])


@pytest.mark.parametrize("name", ["planar_square_rotated", "spatial_tetrahedron", "spatial_tetrahedron_displacement"])
def test_observation_contents_match_simulator(make_env, name):
    """Slots hold x_i - x_j (PyBullet's own end-effector positions) in agent i's base frame."""
    env = make_env(name, episode_seconds=1.0)
    env.reset(seed=1)
    rng = np.random.default_rng(1)
    for _ in range(5):
        observations, _, _, _, infos = env.step(random_actions(env, rng, scale=0.5))
    m = env.dim
    client = env.world.client
    ee = _ee_world(env)
    shape = np.asarray(env.scenario.shape)
    w = 1 if env.scenario.formation == "distance" else m
    for i, agent in enumerate(env.agents):
        obs = observations[agent].astype(np.float64)
        parts = env.observation_layout(agent).split(obs)  # the layout itself is tested in test_observation.py
        arm = env.arms[i]
        rotation = rpy_matrix(env.scenario.arms[i].base_rpy)
        neighbours = [(t, h) for t, h in env.scenario.edges if i in (t, h)]
        slot_errors = []
        for s, (tail, head) in enumerate(neighbours):
            j = head if tail == i else tail
            z_world = ee[i] - ee[j]
            z_local = (rotation.T @ z_world)[:m]
            desired = shape[i] - shape[j]
            assert parts.mask[s] == 1.0
            np.testing.assert_allclose(parts.relative_positions[s], z_local, atol=2e-5)
            if w == 1:
                np.testing.assert_allclose(parts.desired[s, 0], np.linalg.norm(desired), atol=1e-5)
                error = z_world[:m] @ z_world[:m] - desired @ desired
                np.testing.assert_allclose(parts.edge_errors[s, 0], error, atol=1e-4)
                slot_errors.append(error)
            else:
                desired_local = (rotation.T @ np.append(desired, [0.0] * (3 - m)))[:m]
                np.testing.assert_allclose(parts.desired[s], desired_local, atol=1e-5)
                np.testing.assert_allclose(parts.edge_errors[s], z_local - desired_local, atol=2e-5)
                slot_errors.append(z_local - desired_local)
        padding = len(neighbours)
        padding_slots = env.graph.max_degree - len(neighbours)
        assert np.all(parts.mask[padding:] == 0.0) and np.all(parts.relative_positions[padding:] == 0.0)
        assert np.all(parts.desired[padding:] == 0.0) and np.all(parts.edge_errors[padding:] == 0.0)
        # info["edge_errors"]: the same slot errors, own frame (PyBullet's link positions carry ~1e-7 m of
        # float rounding, hence the tolerances).
        np.testing.assert_allclose(np.asarray(infos[agent]["edge_errors"][:len(neighbours)]).reshape(len(neighbours), -1),
                                   np.asarray(slot_errors).reshape(len(neighbours), -1), atol=1e-5)
        assert np.all(infos[agent]["edge_errors"][len(neighbours):] == 0.0)  # padded to the largest degree
        assert infos[agent]["edge_mask"].tolist() == [True] * len(neighbours) + [False] * padding_slots
        q, dq = read_state(arm)
        n = arm.n_joints
        np.testing.assert_allclose(parts.q, np.where(arm.model.continuous, (q + np.pi) % (2 * np.pi) - np.pi, q),
                                   atol=1e-6)
        np.testing.assert_allclose(parts.dq, dq, atol=1e-5)
        # info["singularity_margin"]: smallest singular value of PyBullet's translational Jacobian (base
        # frame, first m rows).
        link = _ee_link_index(arm.body, arm.config.ee_link, client)
        jacobian, _ = pybullet.calculateJacobian(arm.body, link, [0.0, 0.0, 0.0], q.tolist(), [0.0] * n, [0.0] * n,
                                                 physicsClientId=client)
        margin = np.linalg.svd(np.asarray(jacobian)[:m], compute_uv=False).min()
        assert infos[agent]["singularity_margin"] == pytest.approx(margin, rel=1e-6, abs=1e-9)
    # state(): end-effector positions (world, first m coordinates), then every q, then every dq.
    state = env.state().astype(np.float64)
    n_agents = len(env.arms)
    np.testing.assert_allclose(state[:n_agents * m], ee[:, :m].ravel(), atol=2e-5)
    joints = [read_state(arm) for arm in env.arms]
    q_all = np.concatenate([np.where(arm.model.continuous, (q + np.pi) % (2 * np.pi) - np.pi, q)
                            for arm, (q, _) in zip(env.arms, joints)])
    np.testing.assert_allclose(state[n_agents * m:n_agents * m + len(q_all)], q_all, atol=1e-6)
    np.testing.assert_allclose(state[n_agents * m + len(q_all):], np.concatenate([dq for _, dq in joints]), atol=1e-5)


@pytest.mark.parametrize("formation", ["planar_square", "planar_square_displacement"])
def test_reward_matches_docstring(make_env, formation):
    settings = {"formation": 0.7, "in_tolerance": 0.4, "position_tolerance": 0.5, "error_floor": 0.2,
                "error_ceiling": 50.0}
    env = make_env(formation, episode_seconds=1.0, reward=settings)
    env.reset(seed=2)
    rng = np.random.default_rng(2)
    for _ in range(3):
        actions = random_actions(env, rng, scale=1.5)
        _, rewards, _, _, infos = env.step(actions)
    ee = _ee_world(env)[:, :2]
    shape = np.asarray(env.scenario.shape)
    z = np.array([ee[t] - ee[h] for t, h in env.scenario.edges])
    z_star = np.array([shape[t] - shape[h] for t, h in env.scenario.edges])
    if env.scenario.formation == "distance":
        per_edge = np.abs(np.sum(z**2, axis=1) - np.sum(z_star**2, axis=1))
        tolerances = 2 * np.linalg.norm(z_star, axis=1) * 0.5  # an edge 0.5 m off its length, to first order
    else:
        per_edge = np.linalg.norm(z - z_star, axis=1)
        tolerances = np.full(len(per_edge), 0.5)
    for i, agent in enumerate(env.agents):
        incident = [k for k, (t, h) in enumerate(env.scenario.edges) if i in (t, h)]
        x = (per_edge[incident] / tolerances[incident]).mean()
        within = bool(np.all(per_edge[incident] <= tolerances[incident]))
        closeness = min(max(math.log10(50.0 / (x + 0.2)) / math.log10(50.0 / 0.2), 0.0), 1.0)
        expected = 0.7 * closeness + 0.4 * within
        assert rewards[agent] == pytest.approx(expected, rel=1e-6)
        assert 0.0 <= rewards[agent] <= 1.1
        expected_rms = math.sqrt(np.mean(per_edge**2))
        assert infos[agent]["formation_error"] == pytest.approx(expected_rms, rel=1e-6)

    team = make_env(formation, episode_seconds=1.0, reward={"team": True})
    team.reset(seed=2)
    _, rewards, *_ = team.step(random_actions(team, np.random.default_rng(3)))
    values = list(rewards.values())
    assert len(set(values)) == 1
    solo = make_env(formation, episode_seconds=1.0)
    solo.reset(seed=2)
    _, solo_rewards, *_ = solo.step(random_actions(solo, np.random.default_rng(3)))
    assert values[0] == pytest.approx(np.mean(list(solo_rewards.values())), rel=1e-12)


# ------------------------------------------------------------------------------------------ determinism
@pytest.mark.parametrize("name", ["planar_square", "spatial_tetrahedron"])
def test_multi_step_determinism_independent_of_history(make_env, name):
    a = make_env(name, episode_seconds=1.0)
    b = make_env(name, episode_seconds=1.0)
    # Different history on A: another seed, random actions.
    a.reset(seed=123)
    junk = np.random.default_rng(99)
    for _ in range(30):
        a.step(random_actions(a, junk))

    obs_a, _ = a.reset(seed=7)
    obs_b, _ = b.reset(seed=7)
    for agent in obs_a:
        assert np.array_equal(obs_a[agent], obs_b[agent])
    stream_a, stream_b = np.random.default_rng(5), np.random.default_rng(5)
    for t in range(60):
        out_a = a.step(random_actions(a, stream_a))
        out_b = b.step(random_actions(b, stream_b))
        for agent in out_a[0]:
            assert np.array_equal(out_a[0][agent], out_b[0][agent]), (t, agent)
        assert out_a[1] == out_b[1], t  # rewards, exact floats
        assert out_a[2] == out_b[2] and out_a[3] == out_b[3]
        assert not any(out_a[2].values())
    assert np.array_equal(a.state(), b.state())


def test_same_seed_same_initial_obs_different_seed_different_q(make_env):
    env = make_env("spatial_tetrahedron")
    first, _ = env.reset(seed=11)
    q_first = [q.copy() for q in (read_state(arm)[0] for arm in env.arms)]
    env.step({a: env.action_space(a).sample() for a in env.agents})
    second, _ = env.reset(seed=11)
    for agent in first:
        assert np.array_equal(first[agent], second[agent])
    env.reset(seed=12)
    q_other = [read_state(arm)[0] for arm in env.arms]
    for q1, q2 in zip(q_first, q_other):
        assert not np.allclose(q1, q2)
    # The noise is uniform within +-initial_q_noise around the nominal q, and really used.
    for q, nominal in zip(q_other, env.scenario.arms):
        offset = q - np.asarray(nominal.initial_q)
        assert np.all(np.abs(offset) <= env.scenario.initial_q_noise + 1e-12)
        assert np.max(np.abs(offset)) > 0.1 * env.scenario.initial_q_noise


@pytest.mark.parametrize("name", ["planar_square", "planar_square_rotated", "spatial_tetrahedron"])
def test_zero_noise_gives_scenario_initial_q(make_env, name):
    env = make_env(name, initial_q_noise=0.0)
    for seed in (0, 1):
        env.reset(seed=seed)
        for arm, config in zip(env.arms, env.scenario.arms):
            q, dq = read_state(arm)
            assert np.array_equal(q, np.asarray(config.initial_q))
            assert np.array_equal(dq, np.zeros_like(dq))


def test_initial_noise_is_clipped_to_joint_limits(make_env):
    data = scenario_dict("spatial_tetrahedron")
    for arm in data["arms"]:
        q = list(arm["initial_q"])
        q[6] = 0.61  # PERA wrist yaw at its upper limit
        arm["initial_q"] = q
    env = make_env(data, initial_q_noise=0.3)
    at_limit = 0
    for seed in range(5):
        env.reset(seed=seed)
        for arm in env.arms:
            q, _ = read_state(arm)
            assert np.all(q >= arm.model.lower) and np.all(q <= arm.model.upper), q
            at_limit += int(q[6] == arm.model.upper[6])
    assert at_limit > 0  # some draws were clipped onto the limit


# ------------------------------------------------------------------------------------------ rendering
@pytest.mark.parametrize("name", ["planar_square", "spatial_tetrahedron"])
def test_render_rgb_array(make_env, name):
    env = make_env(name, render_mode="rgb_array")
    before_reset = env.render()  # allowed: shows the initial configuration
    env.reset(seed=0)
    frame = env.render()
    assert before_reset.shape == frame.shape
    assert isinstance(frame, np.ndarray) and frame.dtype == np.uint8
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.shape[0] > 50 and frame.shape[1] > 50
    colours = np.unique(frame.reshape(-1, 3), axis=0)
    assert len(colours) >= 10, "blank frame"
    red = (frame[..., 0] >= 200) & (frame[..., 1] <= 60) & (frame[..., 2] <= 60)
    assert red.sum() >= 50, "no formation edges drawn"
    env.step({a: np.zeros(env.action_space(a).shape, np.float32) for a in env.agents})
    assert env.render().shape == frame.shape


def test_render_none_and_invalid_mode(make_env):
    env = make_env("planar_square")
    env.reset(seed=0)
    with pytest.warns(UserWarning, match="render_mode"):
        assert env.render() is None
    with pytest.raises(ValueError, match="render_mode"):
        ee_formation_env.parallel_env("planar_square", render_mode="rgb")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the X11 check is Linux-only")
def test_human_mode_without_display_simulates_headless():
    """PyBullet's GUI calls exit() without an X server: the env warns once, simulates without a window,
    and render() returns None (so that headless checkers such as gymnasium's check_env pass).

    Run in a subprocess so that a regression fails this test instead of killing the test session.
    """
    code = ("import warnings\n"
            "import numpy as np\n"
            "import ee_formation_env\n"
            "with warnings.catch_warnings(record=True) as caught:\n"
            "    warnings.simplefilter('always')\n"
            "    envs = [ee_formation_env.parallel_env('planar_square', render_mode='human') for _ in range(2)]\n"
            "env = envs[0]\n"
            "env.reset(seed=0)\n"
            "env.step({a: np.zeros(2) for a in env.agents})\n"
            "print('render:', env.render(), 'gui:', env.world.gui)\n"
            "print('warnings:', sum('DISPLAY' in str(w.message) for w in caught))\n")
    environment = {k: v for k, v in os.environ.items() if k != "DISPLAY"}
    result = subprocess.run([sys.executable, "-c", code], env=environment, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "render: None gui: False" in result.stdout
    assert "warnings: 1" in result.stdout  # once per process, not once per env


# ------------------------------------------------------------------------------------------ local frames
def _rpy_from_matrix(r: np.ndarray) -> list[float]:
    """Inverse of ``rpy_matrix`` (Rz(yaw) Ry(pitch) Rx(roll)) away from pitch = +-pi/2."""
    return [math.atan2(r[2, 1], r[2, 2]), -math.asin(float(np.clip(r[2, 0], -1.0, 1.0))), math.atan2(r[1, 0], r[0, 0])]


def _rot_z(a: float) -> np.ndarray:
    return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _rot_y(a: float) -> np.ndarray:
    return np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])


def _rot_x(a: float) -> np.ndarray:
    return np.array([[1.0, 0.0, 0.0], [0.0, math.cos(a), -math.sin(a)], [0.0, math.sin(a), math.cos(a)]])


def _rotated_scenario(name: str, rotation: np.ndarray, **changes) -> dict:
    data = scenario_dict(name, **changes)
    dim = data["dim"]
    for arm in data["arms"]:
        arm["base_position"] = (rotation @ np.asarray(arm["base_position"], dtype=float)).tolist()
        composed = rotation @ rpy_matrix(arm.get("base_rpy", [0.0, 0.0, 0.0]))
        arm["base_rpy"] = _rpy_from_matrix(composed)
        np.testing.assert_allclose(rpy_matrix(arm["base_rpy"]), composed, atol=1e-12)
        if dim == 2:
            assert abs(arm["base_rpy"][0]) < 1e-12 and abs(arm["base_rpy"][1]) < 1e-12
            arm["base_rpy"][0] = arm["base_rpy"][1] = 0.0
    data["shape"] = (np.asarray(data["shape"]) @ rotation[:dim, :dim].T).tolist()
    return data


@pytest.mark.parametrize("name, rotation, steps, changes", [
    ("planar_square", _rot_z(0.7), 20, {}),
    ("planar_square_displacement", _rot_z(-2.1), 20, {}),
    ("spatial_tetrahedron", _rot_z(0.4) @ _rot_y(0.9) @ _rot_x(-0.6), 8, {"gravity": [0.0, 0.0, 0.0]}),
    ("spatial_tetrahedron_displacement", _rot_z(-1.2) @ _rot_y(-0.5) @ _rot_x(1.1), 8, {"gravity": [0.0, 0.0, 0.0]}),
])
def test_local_frame_invariance(make_env, name, rotation, steps, changes):
    original = make_env(scenario_dict(name, **changes), initial_q_noise=0.0, episode_seconds=1.0)
    rotated = make_env(_rotated_scenario(name, rotation, **changes), initial_q_noise=0.0, episode_seconds=1.0)
    # The rotation really moved things in the world.
    assert not np.allclose(original.arms[1].base_position, rotated.arms[1].base_position)
    obs_a, _ = original.reset(seed=0)
    obs_b, _ = rotated.reset(seed=0)
    assert _max_abs_diff(obs_a, obs_b) < 1e-5
    assert not np.allclose(_ee_world(original), _ee_world(rotated))
    rng = np.random.default_rng(4)
    for _ in range(steps):
        actions = random_actions(original, rng, scale=0.3)
        obs_a, rew_a, *_ = original.step(actions)
        obs_b, rew_b, *_ = rotated.step(actions)
        assert _max_abs_diff(obs_a, obs_b) < 1e-5
        for agent in rew_a:
            assert rew_a[agent] == pytest.approx(rew_b[agent], abs=1e-5)


# ------------------------------------------------------------------------------------------ episodes
@pytest.mark.parametrize("physics_hz, frame_skip, seconds, expected", [
    (1000.0, 10, 0.25, 25),
    (500.0, 4, 0.2, 25),
    (1000.0, 1, 0.013, 13),
])
def test_truncation_after_exact_step_count(make_env, physics_hz, frame_skip, seconds, expected):
    env = make_env("planar_square", physics_hz=physics_hz, frame_skip=frame_skip, episode_seconds=seconds)
    assert env.scenario.max_steps == expected
    with pytest.raises(RuntimeError):
        env.step({a: np.zeros(2, np.float32) for a in env.possible_agents})  # before reset
    env.reset(seed=0)
    zero = {a: np.zeros(2, np.float32) for a in env.possible_agents}
    for t in range(1, expected + 1):
        _, _, terminations, truncations, infos = env.step(zero)
        assert set(truncations) == set(env.possible_agents)
        assert not any(terminations.values())
        assert all(v == (t == expected) for v in truncations.values()), t
        assert infos["arm_0"]["sim_time"] == pytest.approx(t * frame_skip / physics_hz)
    assert env.agents == []
    with pytest.raises(RuntimeError):
        env.step(zero)
    env.reset(seed=0)
    assert env.agents == env.possible_agents


def test_physics_fault_terminates_and_reset_recovers(make_env):
    env = make_env("planar_square", torque_limits=1e5, episode_seconds=1.0)
    observations, _ = env.reset(seed=3)
    ones = {a: np.ones(2, np.float32) for a in env.possible_agents}
    for _ in range(10):
        observations, _, terminations, truncations, infos = env.step(ones)
        if any(terminations.values()):
            break
    assert all(terminations.values()) and not any(truncations.values())
    fault = infos["arm_0"]["physics_fault"]
    assert fault == 2 and "max_joint_velocity" in PHYSICS_FAULTS[fault]
    assert "max_joint_velocity" in env.physics_fault_reason
    assert all(info["physics_fault"] == fault for info in infos.values())
    for agent, obs in observations.items():
        assert obs.dtype == np.float32 and env.observation_space(agent).contains(obs)
    assert env.agents == []
    with pytest.raises(RuntimeError):
        env.step(ones)

    fresh = make_env("planar_square", torque_limits=1e5, episode_seconds=1.0)
    obs_env, _ = env.reset(seed=5)
    obs_fresh, _ = fresh.reset(seed=5)
    assert _max_abs_diff(obs_env, obs_fresh) == 0.0
    small = {a: np.full(2, 1e-4, np.float32) for a in env.possible_agents}
    for _ in range(10):
        out_env, out_fresh = env.step(small), fresh.step(small)
        assert _max_abs_diff(out_env[0], out_fresh[0]) == 0.0
        assert out_env[1] == out_fresh[1]
        assert out_env[4]["arm_0"]["physics_fault"] == 0


def test_non_finite_state_is_a_fault(make_env, monkeypatch):
    env = make_env("planar_square", episode_seconds=1.0)
    env.reset(seed=0)
    arm = env.arms[1]
    real = arm.read_state_lists  # what the env reads joint states through

    def broken():
        q, dq = real()
        return q, [np.nan, dq[1]]

    monkeypatch.setattr(arm, "read_state_lists", broken)
    observations, rewards, terminations, truncations, infos = env.step(_valid(env))
    assert all(terminations.values()) and not any(truncations.values())
    assert infos["arm_0"]["physics_fault"] == 1
    assert env.physics_fault_reason.startswith("arm_1: non-finite joint state")
    for agent, obs in observations.items():
        assert np.all(np.isfinite(obs)) and env.observation_space(agent).contains(obs)
    assert all(math.isfinite(r) for r in rewards.values())
    assert np.all(np.isfinite(env.state()))


# ------------------------------------------------------------------------------------------ actions
def _valid(env):
    return {a: np.full(env.action_space(a).shape, 0.25, np.float32) for a in env.possible_agents}


@pytest.mark.parametrize("mutate, agent_named", [
    (lambda acts: acts.pop("arm_2"), "arm_2"),
    (lambda acts: acts.__setitem__("arm_9", np.zeros(2, np.float32)), "arm_9"),
    (lambda acts: acts.__setitem__("arm_1", np.zeros(3, np.float32)), "arm_1"),
    (lambda acts: acts.__setitem__("arm_1", np.zeros((1, 2), np.float32)), "arm_1"),
    (lambda acts: acts.__setitem__("arm_3", np.array([0.1, np.nan], np.float32)), "arm_3"),
    (lambda acts: acts.__setitem__("arm_0", np.array([np.inf, 0.0])), "arm_0"),
    (lambda acts: acts.__setitem__("arm_2", np.array([-np.inf, 0.0])), "arm_2"),
    (lambda acts: acts.__setitem__("arm_2", "abc"), "arm_2"),
])
def test_bad_actions_raise_and_leave_state_unchanged(make_env, mutate, agent_named):
    env = make_env("planar_square", episode_seconds=1.0)
    reference = make_env("planar_square", episode_seconds=1.0)
    env.reset(seed=4)
    reference.reset(seed=4)
    env.step(_valid(env))
    reference.step(_valid(reference))

    bad = _valid(env)
    bad["arm_0"] = np.array([3.0, -2.0], np.float32)  # out of range but valid: must not be counted
    mutate(bad)
    with pytest.raises(ValueError, match=agent_named):
        env.step(bad)

    out, expected = env.step(_valid(env)), reference.step(_valid(reference))
    assert _max_abs_diff(out[0], expected[0]) == 0.0
    assert out[1] == expected[1]
    for agent in env.possible_agents:
        assert out[4][agent]["clipped_actions"] == expected[4][agent]["clipped_actions"] == 0
        assert out[4][agent]["sim_time"] == expected[4][agent]["sim_time"]


def test_out_of_range_actions_are_clipped_and_counted(make_env):
    clipped = make_env("planar_square", episode_seconds=1.0)
    exact = make_env("planar_square", episode_seconds=1.0)
    obs, infos = clipped.reset(seed=6)
    exact.reset(seed=6)
    assert all(info["clipped_actions"] == 0 and info["torque_saturation"] == 0.0 for info in infos.values())
    wild = {"arm_0": np.array([2.0, -3.0], np.float32), "arm_1": np.array([0.5, 1.5], np.float32),
            "arm_2": np.array([0.2, -0.2], np.float32), "arm_3": np.array([-1.0, 1.0], np.float32)}
    tame = {a: np.clip(v, -1, 1) for a, v in wild.items()}
    out_c, out_e = clipped.step(wild), exact.step(tame)
    assert _max_abs_diff(out_c[0], out_e[0]) == 0.0
    assert out_c[1] == out_e[1]
    info = out_c[4]
    assert [info[a]["clipped_actions"] for a in clipped.agents] == [2, 1, 0, 0]
    assert [info[a]["torque_saturation"] for a in clipped.agents] == [1.0, 0.5, 0.0, 0.0]
    assert [out_e[4][a]["clipped_actions"] for a in exact.agents] == [0, 0, 0, 0]
    if "applied_torque" in info["arm_0"]:  # N m: the clipped action times the 50 N m limits
        np.testing.assert_allclose(info["arm_0"]["applied_torque"], [50.0, -50.0])
        np.testing.assert_allclose(info["arm_1"]["applied_torque"], [25.0, 50.0])
    # The count accumulates over the episode, the saturation is per step, and reset clears both.
    info = clipped.step(wild)[4]
    assert [info[a]["clipped_actions"] for a in clipped.agents] == [4, 2, 0, 0]
    info = clipped.step(tame)[4]
    assert [info[a]["clipped_actions"] for a in clipped.agents] == [4, 2, 0, 0]
    assert [info[a]["torque_saturation"] for a in clipped.agents] == [0.0, 0.0, 0.0, 0.0]
    _, infos = clipped.reset(seed=6)
    assert all(i["clipped_actions"] == 0 for i in infos.values())


# ------------------------------------------------------------------------------------------ contacts
def _drive(env, actions, steps=120):
    """Step with fixed actions; returns (contacts per step, terminated, last info of arm_0)."""
    env.reset(seed=0)
    counts, terminated, info = [], False, None
    for _ in range(steps):
        _, _, terminations, _, infos = env.step(actions)
        assert infos["arm_0"]["contacts"] == infos["arm_1"]["contacts"]  # a contact point involves both
        counts.append(infos["arm_0"]["contacts"])
        info = infos["arm_0"]
        if any(terminations.values()):
            terminated = True
            break
    return counts, terminated, info


def test_contacts_reported(make_env):
    env = make_env(two_planar_arms(), episode_seconds=2.0)
    counts, terminated, _ = _drive(env, CLOSING, steps=100)
    assert counts[0] == 0  # apart at the start
    assert max(counts) > 0
    assert not terminated
    # Control: without torques (gravity is along the joint axes) the arms never touch.
    counts, _, _ = _drive(env, {a: np.zeros(2, np.float32) for a in env.possible_agents}, steps=100)
    assert max(counts) == 0


def test_terminate_on_contact(make_env):
    env = make_env(two_planar_arms(terminate_on_contact=True), episode_seconds=2.0)
    counts, terminated, info = _drive(env, CLOSING)
    assert terminated and counts[-1] > 0 and max(counts[:-1], default=0) == 0  # ends at the first contact
    assert info["physics_fault"] == 0
    assert env.agents == []


def test_no_contacts_without_arm_collisions(make_env):
    env = make_env(two_planar_arms(arm_collisions=False, terminate_on_contact=True), episode_seconds=2.0)
    counts, terminated, _ = _drive(env, CLOSING, steps=100)
    assert max(counts) == 0 and not terminated and len(counts) == 100


def test_reset_after_contact_is_history_free(make_env):
    """A reset in the middle of a collision gives the same episode as a fresh env (contact caches included)."""
    env = make_env(two_planar_arms(initial_q_noise=0.05), episode_seconds=2.0)
    fresh = make_env(two_planar_arms(initial_q_noise=0.05), episode_seconds=2.0)
    env.reset(seed=0)
    for _ in range(200):
        infos = env.step(CLOSING)[4]
        if infos["arm_0"]["contacts"] > 0:
            break
    assert infos["arm_0"]["contacts"] > 0
    obs_a, _ = env.reset(seed=1)
    obs_b, _ = fresh.reset(seed=1)
    assert _max_abs_diff(obs_a, obs_b) == 0.0
    for _ in range(100):
        out_a, out_b = env.step(CLOSING), fresh.step(CLOSING)
        assert _max_abs_diff(out_a[0], out_b[0]) == 0.0
        assert out_a[4]["arm_0"]["contacts"] == out_b[4]["arm_0"]["contacts"]


# ------------------------------------------------------------------------------------------ other URDFs
def _pair(urdf: str, ee_link: str, initial_q: list[float], shape: list[list[float]]) -> dict:
    return {
        "arms": [
            {"urdf": urdf, "ee_link": ee_link, "base_position": [0.0, 0.0, 0.0], "initial_q": initial_q},
            # both face +x, so the arms do not overlap
            {"urdf": urdf, "ee_link": ee_link, "base_position": [1.0, 0.0, 0.0], "initial_q": initial_q},
        ],
        "edges": [[0, 1]],
        "shape": shape,
        "formation": "displacement",
        "dim": 3,
    }


@pytest.mark.parametrize("urdf, ee_link, q0, n_movable", [
    ("kuka_iiwa/model.urdf", "lbr_iiwa_link_7", [0.0, 0.5, 0.0, -1.2, 0.0, 0.8, 0.0], 7),
    ("franka_panda/panda.urdf", "panda_hand", [0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.8], 9),
])
def test_other_urdfs(make_env, urdf, ee_link, q0, n_movable):
    env = make_env(_pair(urdf, ee_link, q0, [[0.5, 0.0, 0.6], [1.5, 0.0, 0.6]]), episode_seconds=0.1)
    for agent in env.possible_agents:
        assert env.action_space(agent).shape == (7,)
        # 1 slot of (mask, z (3), z* (3), error (3)), then q and dq of the 7 chain joints
        assert env.observation_space(agent).shape == (1 + 3 + 3 + 3 + 14,)
    client = env.world.client
    movable = [j for j in range(pybullet.getNumJoints(env.arms[0].body, physicsClientId=client))
               if pybullet.getJointInfo(env.arms[0].body, j, physicsClientId=client)[2] != pybullet.JOINT_FIXED]
    assert len(movable) == n_movable
    assert len(env.arms[0].extra_joint_indices) == n_movable - 7
    observations, _ = env.reset(seed=0)
    _assert_obs_valid(env, observations)
    body, extra = env.arms[0].body, env.arms[0].extra_joint_indices
    fingers_start = [pybullet.getJointState(body, j, physicsClientId=client)[0] for j in extra]
    np.testing.assert_allclose(observations["arm_0"][-14:-7], q0, atol=0.05 + 1e-6)  # initial_q_noise
    rng = np.random.default_rng(0)
    steps = 0
    while env.agents:
        # kuka's URDF gives 300 N m to every joint, light wrist links included: tiny actions keep it sane.
        observations, rewards, terminations, truncations, infos = env.step(random_actions(env, rng, scale=0.002))
        steps += 1
        if env.agents:
            _assert_obs_valid(env, observations)
        assert not any(terminations.values()), infos["arm_0"]["physics_fault"]
    assert steps == env.scenario.max_steps
    assert not np.allclose(read_state(env.arms[0])[0], q0, atol=1e-3)  # gravity and torques moved it
    # The fingers are not agent joints: position motors hold them where they started.
    fingers_end = [pybullet.getJointState(body, j, physicsClientId=client)[0] for j in extra]
    np.testing.assert_allclose(fingers_end, fingers_start, atol=1e-3)


# ------------------------------------------------------------------------------------------ copies and resources
@pytest.mark.parametrize("duplicate", [lambda env: pickle.loads(pickle.dumps(env)), copy.deepcopy])
def test_copies_are_independent(make_env, closer, duplicate):
    env = make_env("planar_square", episode_seconds=1.0)
    env.reset(seed=0)
    env.step(_valid(env))
    twin = closer(duplicate(env))
    assert isinstance(twin, FormationEnv)
    assert twin.world.client >= 0 and twin.world.client != env.world.client
    assert twin.scenario == env.scenario
    assert twin.agents == []  # a copy is a fresh env in a new world: it needs a reset
    with pytest.raises(RuntimeError):
        twin.step(_valid(twin))
    reference = make_env("planar_square", episode_seconds=1.0)
    env.reset(seed=8)
    twin.reset(seed=8)
    reference.reset(seed=8)
    rng = np.random.default_rng(0)
    for _ in range(5):  # only the twin moves
        twin.step(random_actions(twin, rng))
    out_env, out_ref = env.step(_valid(env)), reference.step(_valid(reference))
    assert _max_abs_diff(out_env[0], out_ref[0]) == 0.0
    twin.close()
    assert env.world.connected
    env.step(_valid(env))  # still works after the twin is gone


def test_close_twice_and_context_manager():
    env = ee_formation_env.parallel_env("planar_square", episode_seconds=0.1)
    client = env.world.client
    assert pybullet.isConnected(physicsClientId=client)
    env.close()
    assert not pybullet.isConnected(physicsClientId=client)
    env.close()
    with pytest.raises(RuntimeError):
        env.reset(seed=0)

    with ee_formation_env.parallel_env("planar_square", episode_seconds=0.1) as env2:
        client2 = env2.world.client
        env2.reset(seed=0)
        assert pybullet.isConnected(physicsClientId=client2)
    assert not pybullet.isConnected(physicsClientId=client2)
    assert not env2.world.connected


def test_resets_do_not_reload_urdfs(make_env):
    env = make_env("spatial_tetrahedron")
    client = env.world.client
    count = pybullet.getNumBodies(physicsClientId=client)
    ids = [pybullet.getBodyUniqueId(k, physicsClientId=client) for k in range(count)]
    assert count == len(env.arms)
    assert sorted(ids) == sorted(arm.body for arm in env.arms)
    for seed in range(5):
        env.reset(seed=seed)
        env.step({a: env.action_space(a).sample() for a in env.agents})
    assert pybullet.getNumBodies(physicsClientId=client) == count
    assert [pybullet.getBodyUniqueId(k, physicsClientId=client) for k in range(count)] == ids


def test_smallest_singular_values_match_svd():
    from ee_formation_env.kinematics import smallest_singular_values

    rng = np.random.default_rng(5)
    for shape in [(200, 2, 2), (200, 3, 7), (200, 3, 2), (200, 2, 3)]:
        matrices = rng.normal(size=shape) * rng.uniform(0.01, 3.0, size=(shape[0], 1, 1))
        matrices[:20, 1] = 0.5 * matrices[:20, 0] + 1e-9 * rng.normal(size=(20, shape[2]))  # nearly singular
        expected = np.linalg.svd(matrices, compute_uv=False)
        np.testing.assert_allclose(smallest_singular_values(matrices), expected[:, -1], rtol=0,
                                   atol=1e-14 * expected[:, 0].max())


@pytest.mark.parametrize("name", sorted(ee_formation_env.BUILTIN_SCENARIOS))
def test_infos_are_numeric_and_keep_their_shapes(make_env, name):
    """Multi-agent libraries (TorchRL, RLlib) stack infos: every value a number or a numeric array whose shape
    does not change between reset and steps, and the same for every agent with the same robot."""
    env = make_env(name, episode_seconds=0.2)
    _, infos = env.reset(seed=0)
    shapes = {agent: {key: np.shape(value) for key, value in info.items()} for agent, info in infos.items()}
    rng = np.random.default_rng(0)
    while env.agents:
        *_, infos = env.step(random_actions(env, rng))
        for agent, info in infos.items():
            assert {key: np.shape(value) for key, value in info.items()} == shapes[agent]
            for key, value in info.items():
                assert np.issubdtype(np.asarray(value).dtype, np.number) or np.asarray(value).dtype == bool, key
    degree = env.graph.max_degree
    assert all(shape["edge_errors"][0] == degree and shape["edge_mask"] == (degree,) for shape in shapes.values())
