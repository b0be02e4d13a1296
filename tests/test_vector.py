"""The batched env (``ee_formation_env.vector_env``): copy k reproduces ``parallel_env`` reset with seed s + k,
bit for bit (one PyBullet client per copy, the single env's arithmetic with a leading copy axis), through
autoresets, contacts, a physics fault in one copy and partial resets; spaces; the array API; bad input."""

from __future__ import annotations

from typing import Any, Callable

import gymnasium
import numpy as np
import pytest

import ee_formation_env
from conftest import CLOSING, two_planar_arms


@pytest.fixture
def make_pair(closer) -> Callable[..., tuple[Any, list[Any]]]:
    """``make_pair(scenario, K, **overrides)``: the batched env and K single envs of the same scenario."""

    def factory(scenario: Any, count: int, **overrides: Any):
        batched = closer(ee_formation_env.vector_env(scenario, num_envs=count, **overrides))
        singles = [closer(ee_formation_env.parallel_env(scenario, **overrides)) for _ in range(count)]
        return batched, singles

    return factory


def assert_copy_matches(batched_out: tuple, k: int, single_out: tuple, agents: list[str]) -> None:
    """Copy k of a batched step equals a single env's step, bit for bit (observations, rewards, ends, infos)."""
    observations, rewards, terminations, truncations, infos = batched_out
    s_obs, s_rewards, s_terms, s_truncs, s_infos = single_out
    ended = bool(terminations[agents[0]][k] or truncations[agents[0]][k])
    for agent in agents:
        # SAME_STEP autoreset: an ended copy's final observation is in the infos.
        final = infos[agent]["final_observation"][k]
        assert np.array_equal(final, s_obs[agent]), agent
        if not ended:
            assert np.array_equal(observations[agent][k], s_obs[agent]), agent
        assert rewards[agent][k] == s_rewards[agent]
        assert terminations[agent][k] == s_terms[agent] and truncations[agent][k] == s_truncs[agent]
        assert set(s_infos[agent]) <= set(infos[agent])
        for key, value in s_infos[agent].items():
            assert np.array_equal(infos[agent][key][k], value), (agent, key)
            assert np.asarray(infos[agent][key]).shape[0] == len(rewards[agent])


def run_and_compare(batched: Any, singles: list[Any], seed: int, actions_at: Callable[[int], dict], steps: int
                    ) -> dict[str, Any]:
    """Step the batched env and the K singles (reset with seed + k, then without a seed whenever an episode
    ends) under the same actions, checking every copy at every step; what happened, for the callers' checks."""
    agents = batched.possible_agents
    observations, infos = batched.reset(seed=seed)
    for k, single in enumerate(singles):
        s_obs, s_infos = single.reset(seed=seed + k)
        for agent in agents:
            assert np.array_equal(observations[agent][k], s_obs[agent])
            for key, value in s_infos[agent].items():
                assert np.array_equal(infos[agent][key][k], value), key
        assert np.array_equal(batched.state()[k], single.state())
    seen = {"ends": np.zeros(len(singles), dtype=int), "faults": [], "contacts": 0}
    for t in range(steps):
        actions = actions_at(t)
        out = batched.step(actions)
        for k, single in enumerate(singles):
            single_out = single.step({agent: actions[agent][k] for agent in agents})
            assert_copy_matches(out, k, single_out, agents)
            if out[2][agents[0]][k]:
                seen["faults"].append((t, k, out[4][agents[0]]["physics_fault"][k],
                                       out[4][agents[0]]["physics_fault_reason"][k]))
                assert out[4][agents[0]]["physics_fault_reason"][k] == single.physics_fault_reason
            seen["contacts"] += int(single_out[4][agents[0]]["contacts"])
            if not single.agents:  # the autoreset: the next episode from the copy's own generator
                seen["ends"][k] += 1
                s_obs, _ = single.reset()
                for agent in agents:
                    assert np.array_equal(out[0][agent][k], s_obs[agent]), agent
            assert np.array_equal(batched.state()[k], single.state())
    return seen


def random_batched_actions(batched: Any, seed: int, scale: float = 1.2) -> Callable[[int], dict]:
    rng = np.random.default_rng(seed)
    shapes = {agent: batched.batched_action_space(agent).shape for agent in batched.possible_agents}
    stream = [{agent: rng.uniform(-scale, scale, shape).astype(np.float32) for agent, shape in shapes.items()}
              for _ in range(200)]
    return lambda t: stream[t]


# ------------------------------------------------------------------------------------------ equivalence
@pytest.mark.parametrize("scenario, count", [("planar_square", 3), ("spatial_tetrahedron", 2)])
def test_copies_are_the_single_env_bit_for_bit_through_autoresets(make_pair, scenario, count):
    """110 steps of random actions (some outside [-1, 1]: clipping is counted), episodes of 40 steps: every
    copy truncates twice and autoresets from its own generator, as the single env's unseeded reset does."""
    batched, singles = make_pair(scenario, count, max_cycles=40)
    seen = run_and_compare(batched, singles, seed=7, actions_at=random_batched_actions(batched, 0), steps=110)
    assert seen["ends"].tolist() == [2] * count and not seen["faults"]


MIXED_TEAM = {  # two 7-DOF arms and a 2-DOF one: kinematics evaluated per model group, with the copy axis
    "arms": [{"robot": "pera_arm", "base_position": [0.0, 0.0, 0.0]},
             {"robot": "pera_arm", "base_position": [1.2, 0.0, 0.0], "base_rpy": [0.0, 0.0, 3.14159]},
             {"robot": "planar_2link", "base_position": [0.6, 1.2, 0.0], "base_rpy": [1.5708, 0.0, 0.0]}],
    "edges": [[0, 1], [1, 2], [0, 2]], "shape": [[0.0, 0.0, 0.5], [0.6, 0.0, 0.5], [0.3, 0.4, 0.5]], "dim": 3,
}


@pytest.mark.parametrize("scenario, overrides", [
    (MIXED_TEAM, {}),
    ("planar_square", {"model_mismatch": {"length": 0.1, "mass": 0.1}, "reward": {"team": True}}),
    ("planar_square_rotated", {"frame_skip": 1}),
    ("spatial_tetrahedron_displacement", {}),
], ids=["mixed_team", "model_mismatch_team_reward", "rotated_frame_skip_1", "spatial_displacement"])
def test_copies_are_the_single_env_for_other_teams_and_options(make_pair, scenario, overrides):
    batched, singles = make_pair(scenario, 2, max_cycles=30, **overrides)
    seen = run_and_compare(batched, singles, seed=1, actions_at=random_batched_actions(batched, 4), steps=40)
    assert seen["ends"].tolist() == [1, 1]


def test_contacts_between_arms_match(make_pair):
    """Two planar arms driven into each other: the contact points of every copy are the single env's."""
    batched, singles = make_pair(two_planar_arms(initial_q_noise=0.05), 2, episode_seconds=2.0)
    closing = {agent: np.tile(action, (2, 1)) for agent, action in CLOSING.items()}
    seen = run_and_compare(batched, singles, seed=0, actions_at=lambda t: closing, steps=100)
    assert seen["contacts"] > 0


def test_a_physics_fault_ends_one_copy_and_leaves_the_others_alone(make_pair):
    """Torque limits raised; copy 1 alone is driven at full torque until its joints run away: it terminates
    with the fault (code and reason), autoresets, and copies 0 and 2 go on bit for bit as single envs."""
    batched, singles = make_pair("planar_square", 3, torque_limits=1e5, episode_seconds=5.0)
    rng = np.random.default_rng(1)
    small = [{agent: rng.uniform(-1e-4, 1e-4, (3, 2)).astype(np.float32) for agent in batched.possible_agents}
             for _ in range(110)]

    def actions_at(t: int) -> dict:
        actions = {agent: value.copy() for agent, value in small[t].items()}
        for value in actions.values():
            value[1] = 1.0
        return actions

    seen = run_and_compare(batched, singles, seed=3, actions_at=actions_at, steps=110)
    assert seen["faults"] and {k for _, k, _, _ in seen["faults"]} == {1}
    _, _, code, reason = seen["faults"][0]
    assert code == 2 and reason.startswith("arm_") and "max_joint_velocity" in reason
    assert seen["ends"][0] == seen["ends"][2] == 0


def test_partial_reset_resets_only_the_masked_copies(make_pair):
    batched, singles = make_pair("planar_square", 3)
    actions = random_batched_actions(batched, 2)
    batched.reset(seed=20)
    for k, single in enumerate(singles):
        single.reset(seed=20 + k)
    for t in range(5):
        batched.step(actions(t))
        for k, single in enumerate(singles):
            single.step({agent: value[k] for agent, value in actions(t).items()})
    observations, infos = batched.reset(seed=50, options={"reset_mask": np.array([False, True, False])})
    s_obs, _ = singles[1].reset(seed=51)  # copy k of a seeded reset gets seed + k
    for agent in batched.possible_agents:
        assert np.array_equal(observations[agent][1], s_obs[agent])
        assert infos[agent]["sim_time"].tolist() == pytest.approx([5 * batched.scenario.control_dt, 0.0,
                                                                   5 * batched.scenario.control_dt])
    for t in range(5, 15):  # the copies left alone keep their episodes; copy 1 runs its new one
        out = batched.step(actions(t))
        for k, single in enumerate(singles):
            assert_copy_matches(out, k, single.step({agent: value[k] for agent, value in actions(t).items()}),
                                batched.possible_agents)


def test_an_all_false_reset_mask_resets_nothing(make_pair):
    """(The batched TorchRL env asks for it when every copy to reset was already autoreset.)"""
    batched, singles = make_pair("planar_square", 2)
    actions = random_batched_actions(batched, 3)
    batched.reset(seed=9)
    stepped = batched.step_arrays(np.concatenate([actions(0)[a] for a in batched.possible_agents], axis=1))
    again = batched.reset_arrays(seed=1, options={"reset_mask": np.zeros(2, dtype=bool)})
    assert np.array_equal(again.observations, stepped.observations)
    assert again.infos["sim_time"].tolist() == pytest.approx([batched.scenario.control_dt] * 2)


def test_unseeded_reset_continues_every_copy_generator(make_pair):
    batched, singles = make_pair("planar_square", 2)
    batched.reset(seed=4)
    observations, _ = batched.reset()
    for k, single in enumerate(singles):
        single.reset(seed=4 + k)
        s_obs, _ = single.reset()
        assert all(np.array_equal(observations[a][k], s_obs[a]) for a in batched.possible_agents)


def test_a_sequence_of_seeds_seeds_each_copy(make_pair):
    """Gymnasium's vector convention: seed[k] for copy k, None for its own generator."""
    batched, singles = make_pair("planar_square", 3)
    batched.reset(seed=0)  # copy 1's generator: seeded 1
    observations, _ = batched.reset(seed=[7, None, np.int64(2)])
    singles[1].reset(seed=1)
    expected = [singles[0].reset(seed=7)[0], singles[1].reset()[0], singles[2].reset(seed=2)[0]]
    for k, s_obs in enumerate(expected):
        assert all(np.array_equal(observations[a][k], s_obs[a]) for a in batched.possible_agents), k


@pytest.mark.parametrize("seed, message", [([1, 2], "seed: expected None, an integer or a sequence of 3 seeds"),
                                           ([1, -2, 3], "seed[1]: expected None or an integer >= 0, got -2"),
                                           ([1, 2, "3"], "seed[2]: expected None or an integer >= 0, got str")])
def test_bad_seed_sequences_name_the_copy(closer, seed, message):
    batched = closer(ee_formation_env.vector_env("planar_square", num_envs=3))
    with pytest.raises((TypeError, ValueError), match=message.replace("[", r"\[").replace("]", r"\]")):
        batched.reset(seed=seed)
    assert not any(batched.is_running(k) for k in range(3))  # nothing was reset


# ------------------------------------------------------------------------------------------ spaces and arrays
def test_spaces_shapes_and_dtypes(closer):
    count = 4
    batched = closer(ee_formation_env.vector_env("spatial_tetrahedron", num_envs=count))
    single = closer(ee_formation_env.parallel_env("spatial_tetrahedron"))
    assert batched.possible_agents == batched.agents == single.possible_agents
    assert batched.metadata["autoreset_mode"].name == "SAME_STEP"
    observations, infos = batched.reset(seed=0)
    for agent in batched.possible_agents:
        space, batched_space = batched.observation_space(agent), batched.batched_observation_space(agent)
        assert space == single.observation_space(agent) and batched.action_space(agent) == single.action_space(agent)
        assert batched_space.shape == (count, *space.shape)
        assert batched.batched_action_space(agent).shape == (count, *single.action_space(agent).shape)
        assert observations[agent].dtype == np.float32 and batched_space.contains(observations[agent])
        for key, value in infos[agent].items():
            assert np.asarray(value).shape[0] == count, key
    assert batched.state().shape == (count, *single.state_space.shape) == batched.batched_state_space.shape
    assert batched.state_space == single.state_space
    _, rewards, terminations, truncations, _ = batched.step(
        {agent: np.zeros((count, 7), np.float32) for agent in batched.possible_agents})
    assert all(r.shape == (count,) and r.dtype == np.float64 for r in rewards.values())
    assert all(t.shape == (count,) and t.dtype == bool for t in [*terminations.values(), *truncations.values()])


def test_array_api_is_the_dict_api(closer):
    """``step_arrays`` from one (K * N, n) array gives the dict API's values as stacked arrays."""
    count = 3
    a = closer(ee_formation_env.vector_env("planar_square", num_envs=count))
    b = closer(ee_formation_env.vector_env("planar_square", num_envs=count))
    assert np.array_equal(a.reset_arrays(seed=1).observations,
                          np.concatenate([b.reset(seed=1)[0][agent] for agent in b.possible_agents], axis=1))
    actions = random_batched_actions(a, 3)
    n_agents = len(a.possible_agents)
    for t in range(30):
        flat = np.stack([actions(t)[agent] for agent in a.possible_agents], axis=1).reshape(count * n_agents, 2)
        result = a.step_arrays(flat)
        observations, rewards, terminations, _, infos = b.step(actions(t))
        for i, agent in enumerate(a.possible_agents):
            assert np.array_equal(result.observations[:, a.observation_slices[i]], observations[agent])
            assert np.array_equal(result.rewards[:, i], rewards[agent])
            assert np.array_equal(result.infos["edge_errors"][:, i], infos[agent]["edge_errors"])
            assert np.array_equal(result.infos["applied_torque"][:, a.joint_slices[i]], infos[agent]["applied_torque"])
        assert np.array_equal(result.terminations, terminations["arm_0"])
        assert np.array_equal(result.infos["formation_error"], infos["arm_0"]["formation_error"])


# ------------------------------------------------------------------------------------------ one copy
def test_the_per_copy_api_reads_row_k_of_the_batched_values(closer):
    batched = closer(ee_formation_env.vector_env("planar_square", num_envs=2,
                                                 autoreset_mode=gymnasium.vector.AutoresetMode.DISABLED))
    assert not batched.is_running(0) and batched.renderer is None  # never reset; no render_mode
    batched.reset(seed=[4, 5])
    actions = {agent: np.full((2, 2), 3.0, np.float32) for agent in batched.possible_agents}  # clipped: counted
    infos = batched.step(actions)[-1]
    assert batched.world(0).client != batched.world(1).client
    assert batched.arm_set(1).world is batched.world(1) and batched.arm_set(0).world is batched.world(0)
    np.testing.assert_array_equal(batched.formation_errors(), infos["arm_0"]["formation_error"])
    for k in range(2):
        assert batched.is_running(k) and batched.step_count(k) == 1 and batched.fault_reason(k) == ""
        copy = batched.copy_infos(k)
        assert list(copy) == batched.possible_agents
        for agent, info in copy.items():
            assert set(info) == set(infos[agent]) - {"physics_fault_reason"}, agent
            for key, value in info.items():
                np.testing.assert_array_equal(value, infos[agent][key][k], err_msg=f"{agent} {key}")
        assert copy["arm_1"]["clipped_actions"] == 2 and copy["arm_1"]["sim_time"] > 0
    batched.reset(options={"reset_mask": np.array([False, True])})
    assert (batched.step_count(0), batched.step_count(1)) == (1, 0)
    copy = batched.copy_infos(1)
    copy["arm_0"]["edge_mask"][:] = False  # a fresh array: the env's masks are untouched
    assert batched.copy_infos(1)["arm_0"]["edge_mask"].any()
    batched.close()
    assert not batched.is_running(0) and not batched.is_running(1)


# ------------------------------------------------------------------------------------------ bad input
def test_bad_actions_raise_the_single_env_errors_before_any_copy_moves(closer):
    count = 3
    batched = closer(ee_formation_env.vector_env("planar_square", num_envs=count))
    with pytest.raises(RuntimeError, match="reset"):
        batched.step({agent: np.zeros((count, 2)) for agent in batched.possible_agents})
    batched.reset(seed=0)
    state = batched.state()
    good = {agent: np.zeros((count, 2), np.float32) for agent in batched.possible_agents}
    cases = [
        ({k: v for k, v in good.items() if k != "arm_3"}, r"^actions: missing agents \['arm_3'\]"),
        ({**good, "arm_0": np.zeros(2)}, r"^actions\['arm_0'\]: expected shape \(3, 2\), got \(2,\)"),
        ({**good, "arm_1": np.zeros((count, 3))}, r"^actions\['arm_1'\]: expected shape \(3, 2\)"),
        ({**good, "arm_2": np.array([["a", "b"]] * count)}, r"^actions\['arm_2'\]: expected a numeric array"),
        ({**good, "arm_0": np.array([[0.0, 0.0], [0.0, np.nan], [0.0, 0.0]])},
         r"^actions\['arm_0'\]: expected finite values of shape \(3, 2\), got non-finite values in copies \[1\]"),
    ]
    for actions, message in cases:
        with pytest.raises(ValueError, match=message):
            batched.step(actions)
    with pytest.raises(TypeError, match="^actions: expected a dict"):
        batched.step(np.zeros((count, 8)))
    with pytest.raises(ValueError, match=r"^actions: expected shape \(3, 8\) or \(12, 2\) or \(3, 4, 2\)"):
        batched.step_arrays(np.zeros((count, 7)))
    with pytest.raises(ValueError, match=r"^actions: expected finite values"):
        batched.step_arrays(np.full((count, 8), np.inf))
    assert np.array_equal(batched.state(), state)  # nothing moved
    with pytest.raises(ValueError, match=r"^options\['reset_mask'\]: expected a bool array of shape \(3,\)"):
        batched.reset(options={"reset_mask": [1, 0, 1]})
    with pytest.raises(ValueError, match="^seed"):
        batched.reset(seed=-1)
    assert np.array_equal(batched.state(), state)
    with pytest.raises(ValueError, match="^num_envs"):
        ee_formation_env.vector_env("planar_square", num_envs=0)
    batched.close()
    batched.close()
    with pytest.raises(RuntimeError, match="closed"):
        batched.reset()


# ------------------------------------------------------------------------------------------ Gymnasium make_vec
def test_gymnasium_make_vec_is_k_centralized_envs(closer):
    """``make_vec(id, K, "vector_entry_point")``: copy k is ``gymnasium.make(id)`` reset with seed + k, through
    TimeLimit truncations and SAME_STEP autoresets."""
    import gymnasium

    count, limit = 3, 25
    vector = closer(gymnasium.make_vec("EEFormation/PlanarSquare-v0", num_envs=count,
                                       vectorization_mode="vector_entry_point", max_episode_steps=limit))
    singles = [closer(gymnasium.make("EEFormation/PlanarSquare-v0", max_episode_steps=limit)) for _ in range(count)]
    assert vector.metadata["autoreset_mode"] == gymnasium.vector.AutoresetMode.SAME_STEP
    assert vector.single_observation_space == singles[0].observation_space
    assert vector.single_action_space == singles[0].action_space
    assert vector.observation_space.shape == (count, *singles[0].observation_space.shape)
    observations, infos = vector.reset(seed=11)
    for k, single in enumerate(singles):
        s_obs, s_info = single.reset(seed=11 + k)
        assert np.array_equal(observations[k], s_obs) and infos["formation_error"][k] == s_info["formation_error"]
    rng = np.random.default_rng(0)
    ends = 0
    for _ in range(60):
        actions = rng.uniform(-1, 1, vector.action_space.shape).astype(np.float32)
        observations, rewards, terminations, truncations, infos = vector.step(actions)
        for k, single in enumerate(singles):
            s_obs, s_reward, s_term, s_trunc, s_info = single.step(actions[k])
            assert rewards[k] == s_reward and terminations[k] == s_term and truncations[k] == s_trunc
            if s_term or s_trunc:
                ends += 1
                assert infos["_final_obs"][k] and np.array_equal(infos["final_obs"][k], s_obs)
                assert infos["final_info"]["formation_error"][k] == s_info["formation_error"]
                s_obs, s_info = single.reset()
            assert np.array_equal(observations[k], s_obs) and infos["formation_error"][k] == s_info["formation_error"]
    assert ends == 2 * count


# ------------------------------------------------------------------------------------------ the one implementation
def test_the_parallel_env_is_the_batched_env_at_one_copy_without_autoreset(closer):
    env = closer(ee_formation_env.parallel_env("planar_square", episode_seconds=0.05))
    assert isinstance(env.batch, ee_formation_env.vector.VectorFormationEnv)
    assert env.batch.num_envs == 1 and env.batch.metadata["autoreset_mode"].name == "DISABLED"
    observations, _ = env.reset(seed=4)
    zeros = {agent: np.zeros(2, np.float32) for agent in env.agents}
    while env.agents:
        observations, *_ = env.step(zeros)
    # no autoreset: the ended copy keeps its final state, and the view says the episode is over
    assert np.array_equal(env.batch.joint_positions()[0], np.concatenate(env.joint_positions()))
    with pytest.raises(RuntimeError, match=r"^step: call reset\(\) first \(the episode has ended"):
        env.step(zeros)
    env.close()
    assert env.agents == []
    with pytest.raises(RuntimeError, match=r"^step: the environment is closed"):
        env.step(zeros)


def test_without_autoreset_an_ended_copy_is_refused_until_its_masked_reset(closer):
    disabled = gymnasium.vector.AutoresetMode.DISABLED
    batched = closer(ee_formation_env.vector_env("planar_square", num_envs=2, autoreset_mode=disabled,
                                                 episode_seconds=0.05))
    batched.reset(seed=0)
    zeros = np.zeros((2, 8))
    result = batched.step_arrays(zeros)
    while not result.truncations.all():
        result = batched.step_arrays(zeros)
    assert "final_observation" not in result.infos  # nothing was replaced: the returned row is the final one
    with pytest.raises(RuntimeError, match=r"episode has ended in copies \[0, 1\]"):
        batched.step_arrays(zeros)
    batched.reset(seed=7, options={"reset_mask": np.array([False, True])})
    with pytest.raises(RuntimeError, match=r"episode has ended in copies \[0\]"):
        batched.step_arrays(zeros)
    batched.reset(options={"reset_mask": np.array([True, False])})
    batched.step_arrays(zeros)  # both running again


def test_the_batched_env_renders_one_copy_and_refuses_rendering_several(closer):
    single = closer(ee_formation_env.vector_env("planar_square", num_envs=1, render_mode="rgb_array",
                                                render_width=64, render_height=48))
    single.reset(seed=0)
    frame = single.render()
    assert frame.shape == (48, 64, 3) and frame.dtype == np.uint8
    with pytest.raises(ValueError, match=r"^render_mode: the batched env renders only with num_envs=1"):
        ee_formation_env.vector_env("planar_square", num_envs=2, render_mode="rgb_array")
    with pytest.raises(ValueError, match=r"^autoreset_mode: "):
        ee_formation_env.vector_env("planar_square", num_envs=2, autoreset_mode="next")
    for name in ("num_envs", "autoreset_mode"):
        with pytest.raises(ValueError, match=rf"^{name}: not an argument of the parallel env"):
            ee_formation_env.parallel_env("planar_square", **{name: 2})


def test_reset_options_that_are_not_a_dict_are_refused_and_unknown_keys_named_in_a_warning_in_both_envs(closer):
    """Unknown keys warn rather than raise: PettingZoo's API test resets with options={"options": 1}."""
    batched = closer(ee_formation_env.vector_env("planar_square", num_envs=2))
    single = closer(ee_formation_env.parallel_env("planar_square"))
    for env in (batched, single):
        env.reset(seed=3)
        state = env.state().copy()
        with pytest.raises(TypeError, match=r"^options: expected None or a dict with keys among \['reset_mask'\], "
                                            r"got list"):
            env.reset(seed=4, options=["reset_mask"])
        assert np.array_equal(env.state(), state)  # nothing was reset
        with pytest.warns(UserWarning, match=r"^options: unknown key\(s\) \['reset_maks'\] \(did you mean "
                                             r"'reset_mask' for 'reset_maks'\?\); allowed: \['reset_mask'\] \(ignored\)"):
            env.reset(seed=4, options={"reset_maks": np.ones(2, dtype=bool)})


def test_more_copies_than_pybullet_or_memory_holds_are_refused_naming_num_envs_before_any_client(monkeypatch):
    import pybullet

    import ee_formation_env.inputs as inputs

    def no_connect(*args, **kwargs):
        raise AssertionError("a PyBullet client was asked for")

    monkeypatch.setattr(pybullet, "connect", no_connect)
    with pytest.raises(ValueError, match=r"^num_envs: expected at most 1024 copies \(PyBullet's clients per process\), "
                                         r"got 10000000"):
        ee_formation_env.vector_env("planar_square", num_envs=10**7)
    monkeypatch.setattr(inputs, "_physical_memory_bytes", lambda: 2_000_000_000)  # a 2 GB machine
    with pytest.raises(ValueError, match=r"^num_envs: 100 copies need about 3\.0 GB \(30 MB each\); this machine has "
                                         r"2\.0 GB"):
        ee_formation_env.vector_env("planar_square", num_envs=100)
