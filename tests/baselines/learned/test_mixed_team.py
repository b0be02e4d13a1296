"""Mixed teams: one shared policy over arms of different robots, through padded spaces and a robot-kind one-hot
(team.py), in training and evaluation; a uniform team exactly as before."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from conftest import mixed_team
from ee_formation_env.baselines.learned.action_scale import rescaling
from ee_formation_env.baselines.learned.features import FeatureRows
from ee_formation_env.baselines.learned.options import TrainingOptions
from ee_formation_env.baselines.learned.shaping import hold_penalty_factors
from ee_formation_env.baselines.learned.team import TeamPadding, agent_rules, refuse_mixed_team, robot_kind
from ee_formation_env.baselines.learned.training_env import BatchedTrainingEnv, ParallelTrainingEnv

SCENARIOS = Path(__file__).parents[3] / "studies" / "scenarios"
KUKA_TEAM, KUKA_PANDA_TEAM = str(SCENARIOS / "kuka_team.yaml"), str(SCENARIOS / "kuka_panda_team.yaml")
KUKA = "kuka_iiwa/model.urdf:lbr_iiwa_link_7"
PANDA = "franka_panda/panda.urdf:panda_hand"
PLANAR = "planar_2link:ee_link"
MODES = {"residual": TrainingOptions(mode="residual", obs_features="none", residual_gate=True, correction_penalty=0.5),
         "torque": TrainingOptions(mode="torque", obs_features="none"),
         "velocity": TrainingOptions(mode="velocity", obs_features="none")}


def _raw_parts(env, observations):
    """Agent i's own raw observation rows (K, size_i), read from the padded observations (obs_features none)."""
    width, N = env.padding.width, len(env.possible_agents)
    rows = observations.reshape(-1, N, width)
    return [rows[:, i, :env.env.observation_space(agent).shape[0]] for i, agent in enumerate(env.possible_agents)]


@pytest.mark.parametrize("features", ["none", "log-error"])
def test_a_mixed_team_gets_padded_observations_with_its_robot_kind(closer, features):
    import ee_formation_env

    env = closer(BatchedTrainingEnv(mixed_team(), options=TrainingOptions(mode="torque", obs_features=features),
                                    num_envs=2))
    plain = closer(ee_formation_env.vector_env(mixed_team(), num_envs=2))  # the same copies, unpadded
    assert env.padding.kinds == (KUKA, PLANAR)  # sorted by name: the one-hot's order
    kinds = [env.padding.kinds.index(robot_kind(arm)) for arm in plain.scenario.arms]
    assert kinds == [1, 0]  # arm_0 is the planar arm
    featured = [FeatureRows([plain.observation_layout(agent)], [features]) for agent in env.possible_agents]
    raw = plain.reset_arrays(seed=3).observations
    own = [featured[i](raw[:, part]) for i, part in enumerate(plain.observation_slices)]  # (2, size_i) each
    P = max(part.shape[1] for part in own)
    for agent in env.possible_agents:
        assert env.observation_space(agent).shape == (P + 2,)
        assert env.action_space(agent).shape == (7,)  # the KUKA's joints; the planar arm uses the first 2
    rows = env.reset_arrays(seed=3).observations.reshape(2, 2, P + 2)
    for i in range(2):
        size = own[i].shape[1]
        assert np.array_equal(rows[:, i, :size], own[i])  # its own featured observation
        assert np.all(rows[:, i, size:P] == 0)  # zero padding
        assert rows[:, i, P:].tolist() == [[1.0 if k == kinds[i] else 0.0 for k in range(2)]] * 2


def test_a_uniform_team_is_unchanged(closer):
    env = closer(BatchedTrainingEnv(KUKA_TEAM, options=TrainingOptions(mode="residual"), num_envs=2))
    assert env.padding is None
    for agent in env.possible_agents:
        assert env.observation_space(agent) == env.env.observation_space(agent)  # no padding, no one-hot
        assert env.action_space(agent) == env.env.action_space(agent)


def _episode_digest(scenario, options, steps=15):
    digest = hashlib.sha256()
    with BatchedTrainingEnv(scenario, {"episode_seconds": 0.2}, options, num_envs=2) as env:
        for agent in env.possible_agents:
            for space in (env.observation_space(agent), env.action_space(agent)):
                digest.update(repr((space.shape, space.low.tolist(), space.high.tolist())).encode())
        result = env.reset_arrays(seed=7)
        digest.update(result.observations.tobytes())
        n = env.action_space(env.possible_agents[0]).shape[0]
        rng = np.random.default_rng(1)
        for _ in range(steps):
            result = env.step_arrays(rng.uniform(-1, 1, (2 * len(env.possible_agents), n)))
            for part in (result.observations, result.rewards, result.terminations, result.infos["final_observation"]):
                digest.update(np.ascontiguousarray(part).tobytes())
    return digest.hexdigest()[:16]


# Spaces, observations, rewards and final observations of 15 steps (autoresets included) of uniform teams, as the
# training env computed them before mixed teams trained (bit-level: the float kernels conftest.py fixes).
PINNED_EPISODE_DIGESTS = {
    "residual-kuka": (KUKA_TEAM, TrainingOptions(mode="residual", hold_penalty=0.5, obs_features="log-error",
                                                 residual_gate=True, correction_penalty=0.5), "647198978c00b775"),
    "torque-kuka": (KUKA_TEAM, TrainingOptions(mode="torque"), "03db661cac3410ac"),
    "velocity-planar": ("planar_square", TrainingOptions(mode="velocity"), "d2f4b147e0e7f089"),
    "residual-planar": ("planar_square", TrainingOptions(mode="residual"), "6ccc14aa8f747dde"),
}


@pytest.mark.parametrize("case", sorted(PINNED_EPISODE_DIGESTS))
def test_a_uniform_team_s_episodes_are_bit_identical_to_before(case):
    scenario, options, digest = PINNED_EPISODE_DIGESTS[case]
    assert _episode_digest(scenario, options) == digest


@pytest.mark.parametrize("mode", sorted(MODES))
def test_each_mode_s_rule_applies_each_agent_s_own_joints(closer, mode):
    options = MODES[mode]
    env = closer(BatchedTrainingEnv(mixed_team(), options=options, num_envs=2))
    result = env.reset_arrays(seed=5)
    raw = _raw_parts(env, result.observations)
    learned = np.random.default_rng(0).uniform(-1, 1, (4, 7))
    applied, factors = env.action_rows(env._raw, learned)
    resolved = env.options
    scales = rescaling(env.task, resolved.action_acceleration)
    N, joints = 2, env.joint_slices
    for copy in range(2):
        rules = agent_rules(resolved.training_mode, resolved, env.env.copy_view(copy), scales)  # fresh, as reset
        for i, agent in enumerate(env.possible_agents):
            n = joints[i].stop - joints[i].start
            own, factor = rules[agent](raw[i][copy:copy + 1], learned[copy * N + i:copy * N + i + 1, :n])
            assert np.array_equal(applied[copy, joints[i]], own[0])
            if factor is None:
                assert factors is None
            else:
                assert factors[copy * N + i] == factor[0]
    # The entries past an agent's joints are ignored: garbage there steps the team exactly as zeros do.
    steps = []
    for fill in (0.0, 0.9):
        twin = closer(BatchedTrainingEnv(mixed_team(), options=options, num_envs=2))
        twin.reset_arrays(seed=5)
        padded = learned.copy()
        padded[0::2, 2:] = fill  # arm_0 (the planar arm) has 2 joints
        steps.append(twin.step_arrays(padded))
    assert np.array_equal(steps[0].observations, steps[1].observations)
    assert np.array_equal(steps[0].rewards, steps[1].rewards)


def test_the_hold_penalty_reads_each_agent_s_own_observation(closer):
    scenario = {**mixed_team(), "episode_seconds": 5.0}
    plain, shaped = (closer(BatchedTrainingEnv(scenario, options=TrainingOptions(mode="torque", obs_features="none",
                                                                                hold_penalty=penalty), num_envs=2))
                     for penalty in (0.0, 1.0))
    plain.reset_arrays(seed=2)
    shaped.reset_arrays(seed=2)
    actions = np.random.default_rng(4).uniform(-0.05, 0.05, (4, 7))
    for _ in range(3):
        a, b = plain.step_arrays(actions), shaped.step_arrays(actions)
    raw = _raw_parts(shaped, b.infos["final_observation"])
    for i, agent in enumerate(shaped.possible_agents):
        factors = hold_penalty_factors(shaped.env.observation_layout(agent), raw[i])
        assert np.array_equal(b.rewards[:, i], a.rewards[:, i] - factors)


def test_a_mixed_team_s_bad_actions_are_refused_before_anything_moves(closer):
    env = closer(BatchedTrainingEnv(mixed_team(), options=MODES["residual"], num_envs=2))
    env.reset_arrays(seed=0)
    positions = env.env.joint_positions().copy()
    for bad, match in [(np.zeros((4, 2)), r"actions: expected shape \(4, 7\) or \(2, 2, 7\)"),
                       (np.full((4, 7), np.nan), "actions: expected finite values"),
                       (np.array([["a"] * 7] * 4), "actions: expected a numeric array")]:
        with pytest.raises(ValueError, match=match):
            env.step_arrays(bad)
    assert np.array_equal(env.env.joint_positions(), positions)


def test_the_single_copy_view_serves_a_mixed_team(closer):
    env = closer(ParallelTrainingEnv(KUKA_PANDA_TEAM, {"episode_seconds": 0.1}, MODES["residual"]))
    observations, _ = env.reset(seed=1)
    assert {obs.shape for obs in observations.values()} == {(28,)}  # 26 entries and two kinds
    observations, *_ = env.step({agent: np.zeros(7, np.float32) for agent in env.possible_agents})
    assert observations["arm_2"][-2:].tolist() == [1.0, 0.0] and observations["arm_0"][-2:].tolist() == [0.0, 1.0]


def test_robot_kinds_and_the_saved_padding():
    from ee_formation_env import load_scenario

    arms = load_scenario(KUKA_PANDA_TEAM).arms
    assert [robot_kind(arm) for arm in arms] == [KUKA, KUKA, PANDA]
    assert robot_kind(load_scenario("spatial_tetrahedron").arms[0]) == "pera_arm:ee_link"
    padding = TeamPadding((PANDA, KUKA), ((26, 7), (26, 7)))
    assert TeamPadding.from_saved({"team_padding": padding.to_dict()}) == padding
    assert TeamPadding.from_saved({}) is None
    bad = {**padding.to_dict(), "action_size": 9}
    with pytest.raises(ValueError, match="team_padding: malformed"):
        TeamPadding.from_saved({"team_padding": bad})


def test_backends_that_cannot_train_a_mixed_team_refuse_it(closer):
    env = BatchedTrainingEnv(mixed_team(), options=MODES["torque"], num_envs=1)
    with pytest.raises(ValueError, match="scenario: the BenchMARL task cannot train a mixed team yet"):
        refuse_mixed_team(env, "the BenchMARL task")
    assert not env.env.connected  # closed
    uniform = closer(BatchedTrainingEnv("planar_square", options=MODES["torque"], num_envs=1))
    refuse_mixed_team(uniform, "the BenchMARL task")  # a uniform team passes


# --- training and evaluation through train.py --------------------------------------------------------------------
pytest.importorskip("stable_baselines3")

from ee_formation_env.baselines.cli import train_command  # noqa: E402

EVAL_FAST = ["--eval-episodes", "2", "--eval-seconds", "0.3", "--no-progress", "--eval-workers", "0"]
FAST = ["--n-envs", "1", "--n-workers", "0", "--train-episode-seconds", "0.5", *EVAL_FAST]


@pytest.fixture(scope="module")
def mixed_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("mixed") / "run"
    assert train_command(["--scenario", KUKA_PANDA_TEAM, "--total-timesteps", "300", "--out", str(run_dir),
                          *FAST]) == 0
    return run_dir


def test_a_mixed_team_trains_and_its_comparison_evaluates_the_learned_policy(mixed_run):
    config = json.loads((mixed_run / "config.json").read_text())
    assert config["team_padding"] == {"kinds": [PANDA, KUKA], "observation_size": 26, "action_size": 7,
                                      "kind_sizes": {PANDA: {"observation": 26, "joints": 7},
                                                     KUKA: {"observation": 26, "joints": 7}}}
    policy = json.loads((mixed_run / "model" / "policy.json").read_text())
    assert policy["observation_shape"] == [28]
    comparison = json.loads((mixed_run / "comparison.json").read_text())
    assert comparison["results"]["learned"]["episodes"] == 2


def test_a_mixed_team_s_run_acts_for_a_team_of_its_kinds(mixed_run):
    import ee_formation_env
    from ee_formation_env.baselines.learned.policy import SavedRun

    source = SavedRun.load(mixed_run).policy_source()
    with ee_formation_env.parallel_env(KUKA_TEAM) as env:  # three KUKAs: a kind the run trained on
        observations, _ = env.reset(seed=0)
        policies = source(env)
        actions = {agent: policies[agent](observations[agent]) for agent in env.possible_agents}
    assert {np.shape(action) for action in actions.values()} == {(7,)}


def test_a_stack_of_a_mixed_team_s_policies_acts_as_each_alone(mixed_run):
    import ee_formation_env
    from ee_formation_env.baselines.learned.policy import ComposedPolicy, SavedRun

    source = SavedRun.load(mixed_run).policy_source()
    with ee_formation_env.parallel_env(KUKA_PANDA_TEAM) as env:  # the batched evaluation stacks all three arms
        observations, _ = env.reset(seed=4)
        alone, stacked = source(env), source(env)
        expected = np.stack([alone[agent](observations[agent]) for agent in env.possible_agents])
        together = ComposedPolicy.stacked([stacked[agent] for agent in env.possible_agents])(
            np.stack([observations[agent] for agent in env.possible_agents]))
    assert np.array_equal(together, expected)


def test_evaluating_a_mixed_team_s_run_on_an_unknown_robot_kind_is_refused_naming_the_agent(mixed_run, capsys):
    from ee_formation_env.baselines.evaluate import main

    with pytest.raises(SystemExit) as exit_info:  # refused before any episode (the policies are built first)
        main(["--policy", str(mixed_run), "--scenario", "spatial_tetrahedron", "--episodes", "1", "--quiet"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].endswith("error: policy: arm_0 of scenario spatial_tetrahedron is robot kind pera_arm:ee_link, "
                            "which the run's policy never trained on (its kinds: "
                            f"{PANDA}, {KUKA}): it cannot act for this team")


@pytest.mark.parametrize("argv, match", [
    (["--backend", "rllib"], "error: --backend: rllib cannot train a mixed team yet"),
    (["--mode", "torque", "--imitate", "gradient"], "error: --imitate: the imitation cannot start a mixed team's"),
])
def test_what_a_mixed_team_cannot_train_with_is_refused_before_any_run_folder(tmp_path, capsys, argv, match):
    out = tmp_path / "run"
    assert train_command(["--scenario", KUKA_PANDA_TEAM, "--out", str(out), *argv, *FAST]) == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(match), lines
    assert not out.exists()
