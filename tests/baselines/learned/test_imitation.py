"""Demonstrations of a reference controller (DAgger's data)."""

from __future__ import annotations

import numpy as np
import pytest

from ee_formation_env import baselines
from ee_formation_env.baselines.reference.team import PolicyTeam
from ee_formation_env.baselines.learned.imitation import demonstrations


def test_labels_are_the_references_clipped_actions_where_the_reference_drives(make_env):
    env = make_env("planar_square", episode_seconds=0.2)
    observations, labels = demonstrations(env, "adaptive_jacobian", 2, np.array([3, 4]))
    assert observations.shape == (2 * 20 * 4, env.observation_space("arm_0").shape[0])
    assert labels.shape == (2 * 20 * 4, 2) and np.all(np.abs(labels) <= 1.0)
    team = PolicyTeam(baselines.make_policies("adaptive_jacobian", env))  # replay the first episode
    replayed, _ = env.reset(seed=3)
    team.reset()
    for step in range(20):
        actions = team(replayed)
        rows = slice(4 * step, 4 * step + 4)
        np.testing.assert_array_equal(observations[rows], np.stack([replayed[a] for a in env.possible_agents]))
        np.testing.assert_array_equal(labels[rows], np.clip(np.stack([actions[a] for a in env.possible_agents]), -1, 1))
        replayed, *_ = env.step(actions)


def test_a_learner_share_of_one_lets_the_learner_drive(make_env):
    env = make_env("planar_square", episode_seconds=0.1)
    still = lambda stacked: np.zeros((len(stacked), 2))  # noqa: E731
    driven, _ = demonstrations(env, "gradient", 1, np.array([0]), learner=still, learner_share=1.0)
    zero = baselines.make_policies("zero", env)
    observations, _ = env.reset(seed=0)
    for step in range(10):
        np.testing.assert_array_equal(driven[4 * step:4 * step + 4],
                                      np.stack([observations[a] for a in env.possible_agents]))
        observations, *_ = env.step({a: zero[a](observations[a]) for a in env.possible_agents})


@pytest.mark.parametrize("kwargs, match", [
    (dict(reference="zero"), "reference"),
    (dict(episodes=0), "episodes"),
    (dict(episodes=3), "episodes"),  # more episodes than seeds
    (dict(learner_share=1.5), "learner_share"),
    (dict(learner_share=0.5), "learner"),
])
def test_bad_arguments_are_refused(make_env, kwargs, match):
    env = make_env("planar_square", episode_seconds=0.1)
    arguments = dict(env=env, reference="gradient", episodes=2, seeds=np.array([0, 1]))
    arguments.update(kwargs)
    with pytest.raises(ValueError, match=match):
        demonstrations(**arguments)


# -- a saved run as the reference: its applied actions (its own mode's rule) are the labels ------------------------
RUN_FAST = ["--n-envs", "1", "--n-workers", "0", "--train-episode-seconds", "0.5", "--eval-episodes", "1",
            "--eval-seconds", "0.2", "--eval-workers", "0", "--no-progress"]


@pytest.fixture(scope="module")
def position_run(tmp_path_factory):
    """A short joint-position run on planar_square (gravity-compensated, log-error features: its preset)."""
    pytest.importorskip("stable_baselines3")
    from ee_formation_env.baselines.cli import train_command

    run_dir = tmp_path_factory.mktemp("reference") / "position"
    assert train_command(["--mode", "position", "--total-timesteps", "512", "--out", str(run_dir), *RUN_FAST]) == 0
    return run_dir


def test_a_saved_runs_applied_actions_are_the_labels(position_run):
    from ee_formation_env.baselines.learned.options import TrainingOptions
    from ee_formation_env.baselines.learned.policy import SavedRun
    from ee_formation_env.baselines.learned.training_env import ParallelTrainingEnv

    run = SavedRun.load(position_run)
    options = TrainingOptions(mode="torque", gravity_compensation=True, obs_features="log-error", hold_penalty=0.0)
    env = ParallelTrainingEnv("planar_square", {"episode_seconds": 0.1}, options)
    try:
        observations, labels = demonstrations(env, run, 1, np.array([7]))
        raw_size = env.observation_layout("arm_0").size
        assert observations.shape == (10 * 4, env.observation_space("arm_0").shape[0])
        assert observations.shape[1] > raw_size  # the copy sees the run's features
        team = PolicyTeam(run.policy_source()(env.batched.env.copy_view(0)))  # replay with the run's own policies
        replayed, _ = env.reset(seed=7)
        team.reset()
        for step in range(10):
            actions = team({agent: replayed[agent][:raw_size] for agent in env.possible_agents})
            wanted = np.clip(np.stack([actions[a] for a in env.possible_agents]), -1, 1)
            rows = slice(4 * step, 4 * step + 4)
            np.testing.assert_array_equal(observations[rows], np.stack([replayed[a] for a in env.possible_agents]))
            np.testing.assert_array_equal(labels[rows], wanted)
            assert np.any(wanted != 0)  # the PD hold's torques, not a zero action
            replayed, *_ = env.step({a: w.astype(np.float32) for a, w in zip(env.possible_agents, wanted)})
    finally:
        env.close()


@pytest.mark.parametrize("argv, match", [
    (["--mode", "torque"], "gravity_compensation"),  # the run acts with gravity compensation
    (["--mode", "torque", "--gravity-compensation", "--obs-features", "none"], "--obs-features log-error"),
    (["--mode", "torque", "--gravity-compensation", "--scenario", "planar_square_rotated"], "same scenario"),
])
def test_a_run_that_cannot_be_copied_is_refused_before_any_folder(position_run, tmp_path, capsys, argv, match):
    from ee_formation_env.baselines.cli import train_command

    out = tmp_path / "copy"
    assert train_command([*argv, "--imitate", str(position_run), "--out", str(out), *RUN_FAST]) != 0
    assert "--imitate" in capsys.readouterr().err and not out.exists()
    with pytest.raises(ValueError, match=match):
        from ee_formation_env.baselines.learned.config import TrainConfig
        from ee_formation_env.baselines.learned.run import train
        train(TrainConfig.from_args([*argv, "--imitate", str(position_run), "--out", str(out), *RUN_FAST]))


@pytest.mark.parametrize("name, match", [("missing", "no such folder"), ("empty", "not a train.py run folder")])
def test_a_reference_that_is_neither_a_law_nor_a_run_is_refused(tmp_path, name, match):
    pytest.importorskip("stable_baselines3")
    from ee_formation_env.baselines.learned.imitation import reference_run

    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=f"--imitate: .*{match}"):
        reference_run(str(tmp_path / name))
    assert reference_run("gradient") is None and reference_run("none") is None
