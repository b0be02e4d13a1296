"""The team env: one env whose team size is drawn at every reset, PettingZoo semantics, padded arrays with an agent
mask, the same episode as the family's env at that size, refusals naming the field."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from gymnasium.vector import AutoresetMode
from pettingzoo.test import parallel_api_test

import ee_formation_env
from ee_formation_env.env import FormationEnv
from ee_formation_env.team_env import TeamVectorEnv, largest_degree
from ee_formation_env.team_families import ring_chord_edges, team_scenario


@pytest.fixture(autouse=True)
def _quiet_rigidity_warnings():
    with warnings.catch_warnings():  # the ring-and-chords graphs are rigid but not minimally so (a UserWarning)
        warnings.simplefilter("ignore", UserWarning)
        yield


@pytest.mark.parametrize("family, cycles", [("planar_team", 200), ("spatial_team", 40)])
def test_the_team_env_passes_pettingzoo_parallel_api_test(family, cycles):
    env = ee_formation_env.team_parallel_env(family, max_cycles=30)
    parallel_api_test(env, num_cycles=cycles)
    env.close()


def test_possible_agents_cover_the_largest_team_and_agents_are_this_episodes():
    env = ee_formation_env.team_parallel_env("planar_team")
    assert env.possible_agents == [f"arm_{i}" for i in range(8)]
    assert env.agents == []
    sizes = set()
    for seed in range(40):
        observations, infos = env.reset(seed=seed)
        assert env.agents == env.possible_agents[:env.team_size] == list(observations) == list(infos)
        assert all(info["team_size"] == env.team_size for info in infos.values())
        assert all(env.observation_space(agent).contains(obs) for agent, obs in observations.items())
        sizes.add(env.team_size)
    assert sizes == set(range(3, 9))  # every size is drawn
    env.close()


def test_a_seed_fixes_the_team_size_and_the_episode_which_is_the_families_env_at_that_size():
    env = ee_formation_env.team_parallel_env("planar_team", team_sizes=[3, 5, 8])
    rng = np.random.default_rng(0)
    actions = rng.uniform(-0.3, 0.3, (20, 8, 2)).astype(np.float32)

    def episode() -> tuple[int, list[dict]]:
        observations, _ = env.reset(seed=123)
        trace = [observations]
        for step in range(20):
            observations, rewards, *_ = env.step({a: actions[step, i] for i, a in enumerate(env.agents)})
            trace.append({**observations, **{f"r_{a}": np.float64(r) for a, r in rewards.items()}})
        return env.team_size, trace

    size, first = episode()
    env.reset(seed=7)  # anything in between
    env.step({a: np.ones(2, np.float32) for a in env.agents})
    again_size, again = episode()
    assert size == again_size
    for a, b in zip(first, again):
        assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    # The same episode through the family's env at that size, reset with the drawn seed.
    episode_seed = int(env.team.episode_seeds[0])
    env.close()
    slots = max(largest_degree(ring_chord_edges(n), n) for n in (3, 5, 8))
    with FormationEnv(team_scenario("planar_team", size), neighbour_slots=slots) as single:
        observations, _ = single.reset(seed=episode_seed)
        assert all(np.array_equal(observations[a], first[0][a]) for a in observations)
        for step in range(20):
            observations, rewards, *_ = single.step({a: actions[step, i] for i, a in enumerate(single.agents)})
            assert all(np.array_equal(observations[a], first[step + 1][a]) for a in observations)
            assert all(rewards[a] == first[step + 1][f"r_{a}"] for a in rewards)


def test_the_array_api_pads_absent_agents_and_masks_them():
    env = ee_formation_env.team_vector_env("planar_team", num_envs=3, team_sizes=[3, 6], max_cycles=5)
    result = env.reset_arrays(seed=[1, 2, 3])
    N, O, n = env.max_agents, env.observation_size, env.n_joints_per_arm
    assert (N, O, n) == (6, 24, 2) and result.observations.shape == (3, N * O)
    for k, size in enumerate(env.team_size):
        assert result.infos["agent_mask"][k].tolist() == [i < size for i in range(N)]
        assert not result.observations[k, size * O:].any()
    actions = np.full((3, N, n), 0.5)
    actions[:, 3:] = 1e3  # absent agents' entries are ignored, present ones' clipped as always
    step = env.step_arrays(actions)
    for k, size in enumerate(step.infos["team_size"]):
        assert not step.rewards[k, size:].any()
        torque = step.infos["applied_torque"][k]
        assert not torque[size * n:].any() and torque[:size * n].any()
        assert not step.infos["edge_mask"][k, size:].any()
        assert step.infos["clipped_actions"][k].tolist() == [0] * min(size, 3) + [2] * (size - 3) + [0] * (N - size)
    assert env.state().shape == (3, env.state_space.shape[0]) == (3, N * (3 + 2 * n))
    env.close()


def test_same_step_autoreset_draws_the_next_team_size_and_keeps_the_final_observation():
    env = ee_formation_env.team_vector_env("planar_team", num_envs=2, max_cycles=3)
    env.reset_arrays(seed=0)
    zero = np.zeros((2, env.max_agents, 2))
    sizes_seen = set()
    for _ in range(3 * 6):
        before = env.team_size.copy()
        step = env.step_arrays(zero)
        done = step.terminations | step.truncations
        assert step.infos["team_size"].tolist() == before.tolist()  # the step reports the agents that acted
        for k in np.flatnonzero(done):
            size = env.team_size[k]  # the next episode's, already in the observation row
            sizes_seen.add(int(size))
            assert not step.observations[k, size * env.observation_size:].any()
            assert not np.array_equal(step.infos["final_observation"][k], step.observations[k])
    assert len(sizes_seen) > 2
    env.close()


def test_without_autoreset_an_ended_copy_is_refused_until_reset():
    env = TeamVectorEnv("planar_team", num_envs=2, autoreset_mode=AutoresetMode.DISABLED, episode_seconds=0.02)
    env.reset_arrays(seed=0)
    zero = np.zeros((2, env.max_agents * 2))
    env.step_arrays(zero)
    step = env.step_arrays(zero)
    assert step.truncations.all()
    with pytest.raises(RuntimeError, match="reset"):
        env.step_arrays(zero)
    env.reset_arrays(options={"reset_mask": np.array([True, True])})
    env.step_arrays(zero)
    env.close()


def test_a_reference_law_runs_on_the_current_team():
    from ee_formation_env.baselines import make_policies

    env = ee_formation_env.team_parallel_env("planar_team", team_sizes=[3, 7])
    for seed in (0, 1):
        observations, infos = env.reset(seed=seed)
        policies = make_policies("gradient", env.current)
        start = infos["arm_0"]["formation_error"]
        for _ in range(150):
            actions = {a: policies[a](observations[a]) for a in env.agents}
            observations, _, _, _, infos = env.step(actions)
        assert infos["arm_0"]["formation_error"] < 0.1 * start
    env.close()


def test_the_scenario_key_neighbour_slots_pads_and_changes_no_episode():
    def run(**overrides):
        with FormationEnv("planar_square", **overrides) as env:
            observations, _ = env.reset(seed=4)
            steps = [env.step({a: np.full(2, 0.2, np.float32) for a in env.agents}) for _ in range(5)]
        return env.observation_layout("arm_0"), observations, steps

    plain_layout, plain, plain_steps = run()
    layout, padded, padded_steps = run(neighbour_slots=5)
    assert (plain_layout.n_slots, layout.n_slots) == (3, 5)
    for agent in plain:
        parts, plain_parts = layout.split(padded[agent]), plain_layout.split(plain[agent])
        assert parts.mask.tolist() == plain_parts.mask.tolist() + [0, 0] and not parts.relative_positions[3:].any()
        np.testing.assert_array_equal(parts.relative_positions[:3], plain_parts.relative_positions)
        np.testing.assert_array_equal(padded[agent][-4:], plain[agent][-4:])  # own q, dq
    for (_, rewards, *_, infos), (_, padded_rewards, *_, padded_infos) in zip(plain_steps, padded_steps):
        assert rewards == padded_rewards
        assert infos["arm_0"]["formation_error"] == padded_infos["arm_0"]["formation_error"]


@pytest.mark.parametrize("kwargs, field", [
    ({"family": "planar"}, "family"),
    ({"team_sizes": [2, 4]}, "team_sizes"),
    ({"team_sizes": []}, "team_sizes"),
    ({"team_sizes": "34"}, "team_sizes"),
    ({"team_sizes": [4.0]}, "team_sizes"),
    ({"num_envs": 0}, "num_envs"),
    ({"num_envs": 200}, "num_envs"),  # 200 copies x 6 sizes > 1024 clients
    ({"render_mode": "human"}, "render_mode"),
    ({"neighbour_slots": 6}, "neighbour_slots"),
    ({"frame_skp": 5}, "scenario"),
    ({"frame_skip": 0}, "frame_skip"),
])
def test_bad_arguments_are_refused_naming_the_field(kwargs, field):
    arguments = {"family": "planar_team", **kwargs}
    with pytest.raises(ValueError, match=rf"^{field}"):
        TeamVectorEnv(**arguments)


def test_bad_actions_are_refused_naming_the_field_before_any_copy_moves():
    env = ee_formation_env.team_parallel_env("planar_team", team_sizes=[3])
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"^actions: missing agents \[\], unknown agents \['arm_7'\]"):
        env.step({**{a: np.zeros(2, np.float32) for a in env.agents}, "arm_7": np.zeros(2, np.float32)})
    with pytest.raises(ValueError, match=r"^actions\['arm_1'\]"):
        env.step({a: np.full(2, np.nan if a == "arm_1" else 0.0, np.float32) for a in env.agents})
    assert env.current.batch.step_count(0) == 0
    vector = env.team
    with pytest.raises(ValueError, match=r"^actions: expected shape"):
        vector.step_arrays(np.zeros((1, 5)))
    with pytest.raises(ValueError, match=r"^actions: expected finite values"):
        vector.step_arrays(np.full((1, 3, 2), np.inf))
    env.close()


def test_non_finite_actions_name_the_agent_and_an_absent_agent_s_padded_slot_is_ignored():
    vector = ee_formation_env.team_vector_env("planar_team", num_envs=1, team_sizes=[3, 4])
    seed = next(s for s in range(100) if vector.reset_arrays(seed=s) and vector.team_size[0] == 3)
    actions = np.zeros((1, 4, 2))
    actions[0, 1] = np.nan  # a live agent
    with pytest.raises(ValueError, match=r"^actions: expected finite values, got non-finite values in copies \[0\] "
                                         r"\(copy 0, agent 'arm_1': \[nan, nan\]\)"):
        vector.step_arrays(actions)
    padded = np.zeros((1, 4, 2))
    padded[0, 3] = np.nan  # arm_3 is absent from a team of 3: its slot is ignored, as documented
    stepped = vector.step_arrays(padded)
    vector.reset_arrays(seed=seed)
    assert np.array_equal(stepped.observations, vector.step_arrays(np.zeros((1, 4, 2))).observations)
    vector.close()


@pytest.mark.parametrize("build", [
    lambda: ee_formation_env.team_parallel_env("spatial_team"),
    lambda: ee_formation_env.team_vector_env("planar_team", num_envs=2, team_sizes=[3, 4, 5]),
])
def test_the_families_rigidity_warning_is_warned_once_per_build_at_the_user_s_line(build):
    from ee_formation_env.validation import RigidityWarning

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        env = build()
        for seed in range(6):  # later copies build their sizes' envs at their first resets: no warning again
            getattr(env, "reset_arrays", getattr(env, "reset", None))(seed=seed)
    rigidity = [w for w in caught if issubclass(w.category, RigidityWarning)]
    assert len(rigidity) == 1, [str(w.message) for w in rigidity]
    assert rigidity[0].filename == __file__, rigidity[0].filename
    assert "graphs at team sizes [" in str(rigidity[0].message) and "not minimally rigid" in str(rigidity[0].message)
    env.close()
