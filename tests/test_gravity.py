"""The gravity-compensated torque convention (ee_formation_env/gravity.py): zero action holds every arm at rest."""

import numpy as np
import pytest

import ee_formation_env
from ee_formation_env import baselines
from tests.conftest import scenario_dict


def _drift_under_zero_actions(env, steps: int = 30) -> float:
    """Largest joint motion (rad) over ``steps`` env steps of zero actions from a seeded reset."""
    env.reset(seed=3)
    start = np.concatenate(env.joint_positions())
    zeros = {agent: np.zeros(env.action_space(agent).shape, np.float32) for agent in env.agents}
    for _ in range(steps):
        env.step(zeros)
    return float(np.abs(np.concatenate(env.joint_positions()) - start).max())


def test_zero_action_holds_the_arms_still_only_with_gravity_compensation(make_env):
    assert _drift_under_zero_actions(make_env("spatial_tetrahedron", initial_q_noise=0.0)) > 0.1
    assert _drift_under_zero_actions(make_env("spatial_tetrahedron", initial_q_noise=0.0,
                                              gravity_compensation=True)) < 1e-9


def test_gravity_compensation_holds_tilted_bases_and_grippers(make_env):
    """g is taken in each arm's base frame (PyBullet's inverse dynamics ignores a fixed base's orientation), and
    a Panda's finger joints, off the chain, sit where they are held."""
    data = {
        "arms": [{"robot": "pera_arm", "base_position": [0, 0, 0.6], "base_rpy": [0.5, -0.3, 0.2]},
                 {"urdf": "franka_panda/panda.urdf", "ee_link": "panda_hand", "base_position": [1.5, 0, 0],
                  "base_rpy": [0.0, 0.4, 0.0], "initial_q": [0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.8]}],
        "edges": [[0, 1]], "shape": [[0, 0, 0], [1.0, 0, 0]], "dim": 3, "arm_collisions": False,
        "initial_q_noise": 0.0, "gravity_compensation": True,
    }
    env = make_env(data)
    assert _drift_under_zero_actions(env) < 1e-6
    assert _drift_under_zero_actions(make_env({**data, "gravity_compensation": False})) > 1e-2


def test_gravity_compensated_torque_stays_within_the_limits(make_env):
    env = make_env("spatial_tetrahedron", gravity_compensation=True)
    env.reset(seed=0)
    gravity = env.batch.gravity_torques()[0]
    limits = np.concatenate(env.task.torque_limits)
    full = {agent: np.ones(env.action_space(agent).shape, np.float32) for agent in env.agents}
    infos = env.step(full)[4]
    applied = np.concatenate([infos[agent]["applied_torque"] for agent in env.agents])
    np.testing.assert_array_equal(applied, np.clip(limits + gravity, -limits, limits))
    assert np.any(gravity > 0) and np.all(applied <= limits)


def test_batched_copies_match_the_parallel_env_under_gravity_compensation(closer):
    venv = closer(ee_formation_env.vector_env("spatial_tetrahedron", num_envs=2, gravity_compensation=True))
    single = closer(ee_formation_env.parallel_env("spatial_tetrahedron", gravity_compensation=True))
    venv.reset(seed=5)
    single.reset(seed=6)  # copy 1 of seed 5
    rng = np.random.default_rng(0)
    for _ in range(5):
        actions = {agent: rng.uniform(-1, 1, (2, 7)).astype(np.float32) for agent in venv.possible_agents}
        batched = venv.step(actions)
        one = single.step({agent: action[1] for agent, action in actions.items()})
        for agent in venv.possible_agents:
            np.testing.assert_array_equal(batched[0][agent][1], one[0][agent])


def test_reference_laws_refuse_gravity_compensation(make_env):
    env = make_env("spatial_tetrahedron", gravity_compensation=True)
    with pytest.raises(ValueError, match="gravity_compensation: false"):
        baselines.make_policies("gradient", env)
    assert set(baselines.make_policies("zero", env)) == set(env.possible_agents)  # not a law: allowed


def test_gravity_compensation_must_be_a_boolean():
    with pytest.raises(ValueError, match="gravity_compensation: expected true or false"):
        ee_formation_env.load_scenario(scenario_dict("spatial_tetrahedron", gravity_compensation="yes"))
