"""Imperfect sensing: each knob changes exactly what the agents observe of z_ij, never the physics, the reward
or the infos; batched copies sense as single envs do; bad knobs name their field."""

from __future__ import annotations

import numpy as np
import pytest

from ee_formation_env import load_scenario
from ee_formation_env.sensing import SensingConfig

STEPS = 12


def _drive(open_loop, scenario, sensing, seed=3, steps=STEPS):
    """Observations, rewards and infos of ``steps`` open-loop steps (the same torques whatever is sensed)."""
    return open_loop(scenario, steps=steps, seed=seed, sensing=sensing)


@pytest.mark.parametrize("scenario", ["planar_square", "planar_square_displacement", "spatial_tetrahedron"])
def test_no_sensing_knob_changes_the_physics_reward_or_infos(open_loop, scenario):
    sensing = {"noise": 0.01, "delay": 2, "bias": 0.05, "yaw": 0.2, "seed": 4}
    _, exact = _drive(open_loop, scenario, None)
    _, sensed = _drive(open_loop, scenario, sensing)
    for (obs_a, rewards_a, infos_a), (obs_b, rewards_b, infos_b) in zip(exact, sensed):
        assert rewards_a == rewards_b
        for agent in infos_a:
            assert infos_a[agent]["formation_error"] == infos_b[agent]["formation_error"]
            assert np.array_equal(infos_a[agent]["edge_errors"], infos_b[agent]["edge_errors"])
    changed = [not np.array_equal(exact[-1][0][a], sensed[-1][0][a]) for a in exact[-1][0]]
    assert all(changed)


def test_zero_knobs_are_exact(open_loop):
    _, exact = _drive(open_loop, "planar_square", None)
    _, zero = _drive(open_loop, "planar_square", {"noise": 0, "delay": 0, "bias": 0, "yaw": 0})
    assert not load_scenario("planar_square", sensing={"noise": 0}).sensing.active
    for (obs_a, *_), (obs_b, *_) in zip(exact, zero):
        assert all(obs_a[a].tobytes() == obs_b[a].tobytes() for a in obs_a)


def _z_and_errors(env, observations):
    """Per agent: its real slots' z (k, m) and edge errors, from its observation."""
    out = {}
    for agent, observation in observations.items():
        layout = env.observation_layout(agent)
        parts = layout.split(np.asarray(observation, dtype=np.float64)[None])
        real = parts.mask[0] > 0.5
        out[agent] = (parts.relative_positions[0][real], parts.edge_errors[0][real], parts.desired[0][real])
    return out


@pytest.mark.parametrize("scenario", ["planar_square", "planar_square_displacement"])
def test_delay_yaw_and_bias_transform_the_true_displacements(open_loop, scenario):
    exact_env, exact = _drive(open_loop, scenario, None)
    yaws = [0.1, -0.2, 0.3, 0.05]
    biases = [[0.01, 0.0], [0.0, -0.02], [0.03, 0.01], [-0.01, -0.01]]
    env, sensed = _drive(open_loop, scenario, {"delay": 3, "yaw": yaws, "bias": biases})
    for t in range(STEPS + 1):
        true = _z_and_errors(exact_env, exact[max(t - 3, 0)][0])  # the start is held through the delay
        seen = _z_and_errors(env, sensed[t][0])
        for i, agent in enumerate(env.possible_agents):
            c, s = np.cos(yaws[i]), np.sin(yaws[i])
            expected = true[agent][0] @ np.array([[c, s], [-s, c]]) + biases[i]
            np.testing.assert_allclose(seen[agent][0], expected, atol=2e-6)
            z, errors, desired = seen[agent]
            if env.scenario.formation == "distance":  # errors follow the measured z: |z|^2 - d^2
                np.testing.assert_allclose(errors[:, 0], np.sum(z * z, axis=1) - desired[:, 0] ** 2, atol=2e-5)
            else:
                np.testing.assert_allclose(errors, z - desired, atol=2e-6)


def test_noise_has_its_standard_deviation_and_follows_the_reset_seed(open_loop):
    _, exact = _drive(open_loop, "planar_square", None, steps=40)
    env, noisy = _drive(open_loop, "planar_square", {"noise": 0.02}, steps=40)
    _, again = _drive(open_loop, "planar_square", {"noise": 0.02}, steps=40)
    _, other = _drive(open_loop, "planar_square", {"noise": 0.02}, seed=4, steps=40)
    differences = np.concatenate([
        (_z_and_errors(env, b[0])[a][0] - _z_and_errors(env, e[0])[a][0]).ravel()
        for e, b in zip(exact, noisy) for a in env.possible_agents])
    assert abs(differences.mean()) < 0.003 and differences.std() == pytest.approx(0.02, rel=0.1)
    assert all(noisy[-1][0][a].tobytes() == again[-1][0][a].tobytes() for a in env.possible_agents)
    assert any(noisy[1][0][a].tobytes() != other[1][0][a].tobytes() for a in env.possible_agents)


def test_batched_copies_sense_as_single_envs_through_autoresets(lockstep):
    sensing = {"noise": 0.01, "delay": 2, "bias": 0.02, "yaw": 0.1}
    assert lockstep("planar_square", {"episode_seconds": 0.1, "sensing": sensing}) >= 4  # 10-step episodes


def test_a_scalar_bias_has_its_length_in_a_seeded_direction():
    config = load_scenario("spatial_tetrahedron", sensing={"bias": 0.03, "seed": 2}).sensing
    biases = config.agent_biases(4, 3)
    np.testing.assert_allclose(np.linalg.norm(biases, axis=1), 0.03)
    assert not np.allclose(biases, SensingConfig(bias=0.03, seed=3).agent_biases(4, 3))
    round_trip = load_scenario(load_scenario("spatial_tetrahedron", sensing={"bias": 0.03, "seed": 2}).to_dict())
    assert round_trip.sensing == config


@pytest.mark.parametrize("sensing, message", [
    ({"noise": -0.1}, "sensing.noise: expected a standard deviation >= 0"),
    ({"noise": True}, "sensing.noise"),
    ({"delay": 1.5}, "sensing.delay: expected an integer in [0, 1000]"),
    ({"delay": 5000}, "sensing.delay: expected an integer in [0, 1000]"),
    ({"yaw": [0.1, 0.2]}, "sensing.yaw: expected 4 numbers (rad), one per agent"),
    ({"bias": [[0.1, 0.0]] * 3}, "sensing.bias: expected 4 vectors of 2 numbers (m), one per agent"),
    ({"bias": -0.01}, "sensing.bias: expected a length >= 0"),
    ({"lag": 2}, "sensing: unknown key(s)"),
    ("noisy", "sensing: expected a dict"),
])
def test_bad_sensing_knobs_name_their_field(sensing, message):
    with pytest.raises(ValueError, match=None) as raised:
        load_scenario("planar_square", sensing=sensing)
    assert message in str(raised.value)
