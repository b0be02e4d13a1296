"""The set policy network: permutation invariance, padding, any team size, save/load, refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

import ee_formation_env  # noqa: E402
from ee_formation_env.baselines.learned.checkpoint import load_policy  # noqa: E402
from ee_formation_env.baselines.learned.config import TrainConfig  # noqa: E402
from ee_formation_env.baselines.learned.options import TrainingOptions  # noqa: E402
from ee_formation_env.baselines.learned.policy import ObservationNormalizer, learned_policies  # noqa: E402
from ee_formation_env.baselines.learned.set_network import (SlotLayout, check_serves, expanded_statistics,  # noqa: E402
                                                            numpy_set_actor, pooled_running_statistics,
                                                            pooled_statistics, sb3_policy_kwargs, set_description,
                                                            slot_layout, team_signature)
from ee_formation_env.team_families import team_scenario  # noqa: E402

LAYOUT = SlotLayout(n_slots=4, slot_size=5, own_size=4)


def _policy(layout: SlotLayout = LAYOUT, seed: int = 0):
    import gymnasium
    import torch
    from stable_baselines3.common.policies import ActorCriticPolicy

    torch.manual_seed(seed)
    plain = {"net_arch": [16, 16], "log_std_init": -1.0,
             "set_network": {"layout": layout.to_dict(), "team": {}}}
    space = gymnasium.spaces.Box(-np.inf, np.inf, (layout.size,), dtype=np.float32)
    actions = gymnasium.spaces.Box(-1.0, 1.0, (2,), dtype=np.float32)
    policy = ActorCriticPolicy(space, actions, lambda _: 0.0, **sb3_policy_kwargs(plain))
    policy.set_training_mode(False)
    return policy


def _observations(rng: np.random.Generator, layout: SlotLayout, real: int, k: int = 3) -> np.ndarray:
    observations = rng.normal(size=(k, layout.size))
    slots = observations[:, :layout.n_slots * layout.slot_size].reshape(k, layout.n_slots, layout.slot_size)
    slots[:, :, 0] = 0.0
    slots[:, :real, 0] = 1.0
    slots[:, real:, 1:] = 0.0  # padding slots are zero (observation.py)
    return observations


def _torch_action(policy, observations: np.ndarray) -> np.ndarray:
    import torch

    with torch.no_grad():
        return policy.get_distribution(torch.as_tensor(observations, dtype=torch.float32)).distribution.mean.numpy()


def test_shuffling_the_real_slots_leaves_the_action_unchanged():
    policy = _policy()
    rng = np.random.default_rng(0)
    observations = _observations(rng, LAYOUT, real=3)
    block = LAYOUT.n_slots * LAYOUT.slot_size
    shuffled = observations.copy()
    slots = shuffled[:, :block].reshape(-1, LAYOUT.n_slots, LAYOUT.slot_size)
    slots[:, :3] = slots[:, [2, 0, 1]]
    assert not np.allclose(shuffled, observations)
    np.testing.assert_allclose(_torch_action(policy, shuffled), _torch_action(policy, observations), atol=1e-6)
    actor = numpy_set_actor(policy, LAYOUT)
    np.testing.assert_allclose(actor(shuffled), actor(observations), atol=1e-12)
    # and the numpy actor is the torch network
    np.testing.assert_allclose(actor(observations), _torch_action(policy, observations), atol=1e-5)


def test_padding_slots_have_no_effect():
    policy = _policy()
    rng = np.random.default_rng(1)
    observations = _observations(rng, LAYOUT, real=2)
    noisy = observations.copy()
    slots = noisy[:, :LAYOUT.n_slots * LAYOUT.slot_size].reshape(-1, LAYOUT.n_slots, LAYOUT.slot_size)
    slots[:, 2:, 1:] = rng.normal(size=slots[:, 2:, 1:].shape) * 100  # garbage behind mask 0
    np.testing.assert_allclose(_torch_action(policy, noisy), _torch_action(policy, observations), atol=1e-6)
    # a team with fewer slots (D = 2) and the same real slots acts the same: the slot count is no weight
    small = SlotLayout(2, LAYOUT.slot_size, LAYOUT.own_size)
    trimmed = np.concatenate([observations[:, :2 * LAYOUT.slot_size],
                              observations[:, LAYOUT.n_slots * LAYOUT.slot_size:]], axis=1)
    np.testing.assert_allclose(numpy_set_actor(policy, small)(trimmed), numpy_set_actor(policy, LAYOUT)(observations),
                               atol=1e-12)


def test_a_stack_of_rows_acts_as_each_row_alone():
    actor = numpy_set_actor(_policy(), LAYOUT)
    observations = _observations(np.random.default_rng(2), LAYOUT, real=3, k=5)
    stacked = actor(observations)
    for row, expected in zip(observations, stacked):
        assert np.array_equal(actor(row), expected)


def test_pooled_statistics_share_one_slot_statistic_and_skip_padding():
    statistics = pooled_running_statistics(LAYOUT)
    observations = _observations(np.random.default_rng(3), LAYOUT, real=2, k=200)
    statistics.update(observations)
    slots, own = LAYOUT.split(observations)
    real = slots[:, :2].reshape(-1, LAYOUT.slot_size)
    mean, var = statistics.mean, statistics.var
    np.testing.assert_allclose(mean[1:LAYOUT.slot_size], real[:, 1:].mean(axis=0), atol=1e-3)
    np.testing.assert_allclose(mean[LAYOUT.slot_size + 1:2 * LAYOUT.slot_size], real[:, 1:].mean(axis=0), atol=1e-3)
    assert mean[0] == 0.0 and var[0] == 1.0  # the mask passes unchanged
    np.testing.assert_allclose(mean[-LAYOUT.own_size:], own.mean(axis=0), atol=1e-3)
    # set back from whole-observation vectors (a resumed run's vecnormalize.json): the same statistics
    again = pooled_running_statistics(LAYOUT)
    again.mean, again.var, again.count = mean, var, statistics.count
    np.testing.assert_array_equal(again.mean, mean)
    np.testing.assert_array_equal(again.var, var)
    # expanded to another slot count, every slot gets the same statistics
    bigger = SlotLayout(6, LAYOUT.slot_size, LAYOUT.own_size)
    big_mean, _ = expanded_statistics(bigger, *pooled_statistics(LAYOUT, mean, var))
    np.testing.assert_array_equal(big_mean[5 * LAYOUT.slot_size:6 * LAYOUT.slot_size], mean[:LAYOUT.slot_size])


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A set network trained for a few updates on planar_random (4 arms), residual mode on gradient."""
    from ee_formation_env.baselines.learned.run import train

    out = tmp_path_factory.mktemp("set_run") / "run"
    train(TrainConfig.from_args(["--scenario", "planar_random", "--policy-network", "set", "--reference", "gradient",
                                 "--total-timesteps", "1024", "--n-envs", "2", "--n-steps", "64", "--n-workers", "0",
                                 "--eval-episodes", "1", "--eval-seconds", "0.2", "--eval-workers", "0",
                                 "--no-progress", "--out", str(out)]))
    return out


@pytest.mark.parametrize("n_agents", [3, 8])
def test_the_same_weights_act_for_three_and_eight_arms(tiny_run, n_agents):
    config = json.loads((tiny_run / "config.json").read_text())
    with ee_formation_env.parallel_env(team_scenario("planar_team", n_agents), episode_seconds=0.2) as env:
        observations, _ = env.reset(seed=10_000)
        policies = learned_policies(tiny_run, env, config)
        assert len(policies) == n_agents
        for agent in env.possible_agents:
            action = policies[agent](observations[agent])
            assert action.shape == env.action_space(agent).shape and np.isfinite(action).all()


def test_the_set_policy_acts_in_the_team_env_at_every_drawn_size(tiny_run):
    import warnings

    config = json.loads((tiny_run / "config.json").read_text())
    with warnings.catch_warnings():  # the ring-and-chords graphs are rigid but not minimally so
        warnings.simplefilter("ignore", UserWarning)
        env = ee_formation_env.team_parallel_env("planar_team", episode_seconds=0.2)
        sizes = set()
        for seed in range(8):
            observations, _ = env.reset(seed=seed)
            policies = learned_policies(tiny_run, env.current, config)  # the episode's team, 4 slots each
            assert sorted(policies) == sorted(env.agents)
            while env.agents:
                actions = {agent: policies[agent](observations[agent]) for agent in env.agents}
                observations, *_ = env.step(actions)
            sizes.add(env.team_size)
        env.close()
    assert len(sizes) >= 3


def test_save_and_load_round_trip_reproduces_the_training_inputs_and_weights(tiny_run):
    import torch

    model_dir = tiny_run / "model"
    saved = json.loads((model_dir / "policy.json").read_text())["policy_kwargs"]["set_network"]
    trained = SlotLayout(**saved["layout"])
    assert trained == SlotLayout(3, 5, 4)  # planar_random: largest degree 3, distance slots, 2 joints
    vecnormalize = json.loads((model_dir / "vecnormalize.json").read_text())
    normalizer = ObservationNormalizer.from_checkpoint(model_dir)
    np.testing.assert_array_equal(normalizer.mean, vecnormalize["obs_mean"])  # what training normalized with
    weights = torch.load(model_dir / "policy.pt", weights_only=True)
    for n_slots in (2, 3, 4):
        policy = load_policy(model_dir, n_slots=n_slots)
        assert policy.observation_space.shape == (n_slots * 5 + 4,)
        for name, tensor in policy.state_dict().items():
            assert torch.equal(tensor, weights[name]), name


def test_a_team_it_cannot_serve_is_refused_naming_the_field(tiny_run):
    config = json.loads((tiny_run / "config.json").read_text())
    with ee_formation_env.parallel_env(team_scenario("spatial_team", 4), episode_seconds=0.2) as env:
        with pytest.raises(ValueError, match="policy: robot: .*pera_arm"):
            learned_policies(tiny_run, env, config)
    trained = set_description("planar_random", "none")["team"]
    with ee_formation_env.parallel_env("planar_square_displacement", episode_seconds=0.2) as env:
        with pytest.raises(ValueError, match="policy: formation: .*'displacement'"):
            check_serves(trained, env)
    with ee_formation_env.parallel_env("planar_square", episode_seconds=0.2) as env:
        check_serves(trained, env)  # the same robot and formation kind: served
        with pytest.raises(ValueError, match="policy: n_joints"):
            check_serves({**trained, "n_joints": 7}, env)
        with pytest.raises(ValueError, match="policy: manoeuvre"):
            check_serves({**trained, "manoeuvre": True}, env)


def test_bad_options_are_refused_naming_the_field(capsys):
    with pytest.raises(ValueError, match="policy_network: expected one of"):
        TrainingOptions(policy_network="transformer")
    with pytest.raises(ValueError, match="policy_network: 'set' .*obs_features"):
        TrainingOptions(policy_network="set", mode="torque")  # the torque preset's log-error features
    TrainingOptions(policy_network="set", mode="torque", obs_features="none")  # torque mode with the set network
    with pytest.raises(ValueError, match="obs_features: .*'invariant'"):
        slot_layout(ee_formation_env.observation.ObservationLayout(3, 2, 1, 2), "invariant")
    for argv in (["--policy-network", "set", "--backend", "rllib"], ["--policy-network", "set", "--algo", "sac"]):
        with pytest.raises(SystemExit):
            TrainConfig.from_args(argv)
        assert "--policy-network: set trains with --backend sb3 and --algo ppo" in capsys.readouterr().err


def test_a_mixed_team_is_refused_naming_policy_network():
    with ee_formation_env.parallel_env("planar_square", episode_seconds=0.2) as env:
        assert team_signature(env)["robot"] == "planar_2link.urdf:ee_link"
    mixed = {"arms": [{"robot": "planar_2link", "base_position": [0, 0, 0]},
                      {"robot": "planar_2link", "base_position": [6, 0, 0]},
                      {"robot": "planar_2link", "base_position": [3, 5, 0]}],
             "edges": [[0, 1], [1, 2], [0, 2]], "shape": [[1.5, 1.0], [4.5, 1.0], [3.0, 3.5]],
             "formation": "distance", "dim": 2}

    class Team:  # a team whose third agent reports another robot
        def __init__(self, env):
            self.env, self.possible_agents, self.scenario = env, env.possible_agents, env.scenario

        def observation_layout(self, agent):
            layout = self.env.observation_layout(agent)
            return layout if agent != self.possible_agents[-1] else type(layout)(layout.n_slots, layout.dim,
                                                                                 layout.error_width, 3)

    with ee_formation_env.parallel_env(mixed, episode_seconds=0.2) as env:
        with pytest.raises(ValueError, match="policy_network: 'set' shares one network"):
            team_signature(Team(env))


def test_torque_mode_trains_a_set_network_that_acts_for_another_team_size(tmp_path):
    from ee_formation_env.baselines.learned.run import train

    out = tmp_path / "torque"
    train(TrainConfig.from_args(["--scenario", "planar_random", "--mode", "torque", "--obs-features", "none",
                                 "--policy-network", "set", "--total-timesteps", "512", "--n-envs", "1",
                                 "--n-steps", "64", "--n-workers", "0", "--eval-episodes", "1", "--eval-seconds",
                                 "0.2", "--eval-workers", "0", "--no-progress", "--out", str(out)]))
    config = json.loads((out / "config.json").read_text())
    assert (config["mode"], config["policy_network"]) == ("torque", "set")
    with ee_formation_env.parallel_env(team_scenario("planar_team", 6), episode_seconds=0.2) as env:
        observations, _ = env.reset(seed=10_000)
        policies = learned_policies(out, env, config)
        actions = [policies[agent](observations[agent]) for agent in env.possible_agents]
        assert all(np.isfinite(action).all() and np.abs(action).max() <= 1.0 for action in actions)
