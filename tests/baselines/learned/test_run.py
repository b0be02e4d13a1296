"""Training runs (``train.py`` / ``ee-formation train``): smoke runs of both backends, the saved artefacts, and
reproducible re-evaluation."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("stable_baselines3")

import numpy as np  # noqa: E402

from ee_formation_env import baselines  # noqa: E402
from ee_formation_env.baselines.cli import train_command  # noqa: E402
from ee_formation_env.baselines.learned.checkpoint import load_policy  # noqa: E402
from ee_formation_env.baselines.learned.config import PRESETS, TrainConfig  # noqa: E402
from ee_formation_env.baselines.learned.training_env import EVAL_SEED_OFFSET  # noqa: E402
from ee_formation_env.baselines.learned.imitation import actor_mean, fit_actor  # noqa: E402
from ee_formation_env.baselines.learned.sb3_backend import build_sb3_model, collected_steps  # noqa: E402
from ee_formation_env.baselines.learned.imitation import demonstrations  # noqa: E402
from ee_formation_env.baselines.learned.options import TrainingOptions  # noqa: E402
from ee_formation_env.baselines.learned.training_env import ParallelTrainingEnv  # noqa: E402

EVAL_FAST = ["--eval-episodes", "2", "--eval-seconds", "0.3", "--no-progress", "--eval-workers", "0"]
FAST = ["--n-envs", "1", "--n-workers", "0", "--train-episode-seconds", "0.5", "--imitation-rounds", "1",
        "--imitation-episodes", "2", *EVAL_FAST]
METRIC_FIELDS = {"success_rate", "final_formation_error", "settling_time", "control_energy", "peak_torque",
                 "saturation_fraction", "min_singularity_margin", "contact_steps", "centroid_drift"}


def _comparison(run_dir):
    return json.loads((run_dir / "comparison.json").read_text())


@pytest.mark.parametrize("mode,algo", [("torque", "ppo"), ("residual", "ppo"), ("torque", "sac")])
def test_sb3_smoke_run_writes_every_artefact(tmp_path, mode, algo):
    run_dir = tmp_path / "run"
    assert train_command(["--total-timesteps", "300", "--mode", mode, "--algo", algo, "--out", str(run_dir), *FAST]) == 0
    for name in ("config.json", "model.zip", "model/policy.pt", "model/policy.json", "model/obs_normalizer.json",
                 "model/state.json", "learning_curve.csv", "comparison.json", "comparison.md", "comparison.png"):
        assert (run_dir / name).is_file(), name
    assert any((run_dir / "tensorboard").iterdir())
    config = json.loads((run_dir / "config.json").read_text())
    assert config["mode"] == mode and config["algo"] == algo and config["scenario_data"]["arms"]
    assert config["obs_features"] == PRESETS[mode].obs_features  # what the evaluation applies again
    comparison = _comparison(run_dir)
    assert {"learned", *baselines.POLICIES} <= set(comparison["results"])  # and each law's tuned row where it has one
    for summary in comparison["results"].values():
        assert METRIC_FIELDS <= set(summary)
        assert summary["episodes"] == 2
    assert comparison["seeds"] == [EVAL_SEED_OFFSET, EVAL_SEED_OFFSET + 1]
    # planar_square: no joint carries gravity, so law II's rows are law I's, and the table says why
    assert comparison["notes"] and comparison["notes"][0] in (run_dir / "comparison.md").read_text()


def test_saved_model_reloads_and_reproduces_its_evaluation(tmp_path):
    run_dir = tmp_path / "run"
    train_command(["--total-timesteps", "300", "--out", str(run_dir), *FAST, "--eval-workers", "1"])  # in a worker
    first = _comparison(run_dir)["results"]["learned"]
    assert train_command(["--eval-only", str(run_dir), *EVAL_FAST]) == 0
    (evaluation,) = (run_dir / "evaluations").iterdir()  # beside the run's own results, which stay
    again = json.loads((evaluation / "comparison.json").read_text())["results"]["learned"]
    assert again["per_episode"] == first["per_episode"]
    assert _comparison(run_dir)["results"]["learned"] == first


def test_bad_arguments_fail_before_training(tmp_path, capsys):
    for bad in (["--total-timesteps", "0"], ["--residual-scale", "2"], ["--obs-features", "squared"],
                ["--log-std-init", "nan"], ["--hold-penalty", "1.5"], ["--max-train-seconds", "0"],
                ["--in-process-envs", "32"], ["--n-workers", "0", "--in-process-envs", "4"],
                ["--eval-seconds", "-1"], ["--contact-penalty", "-1"]):
        with pytest.raises(SystemExit):
            train_command([*bad, "--out", str(tmp_path / "x")])
    # The library raises; the command prints one line naming the field and exits with 2.
    capsys.readouterr()
    assert train_command(["--scenario", "no_such_scenario", "--out", str(tmp_path / "x")]) == 2
    assert capsys.readouterr().err.startswith("error: scenario:")
    assert train_command(["--eval-only", str(tmp_path / "missing")]) == 2
    assert capsys.readouterr().err.startswith(f"error: --eval-only: {tmp_path / 'missing'} is not a train.py run "
                                              "folder (no config.json in it)")
    with pytest.raises(ValueError, match="scenario"):
        train_command(["--scenario", "no_such_scenario", "--out", str(tmp_path / "x"), "--debug"])
    assert not (tmp_path / "x").exists()


def test_gsde_explores_through_the_features_and_its_saved_policy_acts_as_the_model(tmp_path):
    from stable_baselines3 import PPO

    args = TrainConfig.from_args(["--mode", "torque", "--sde-sample-freq", "4", "--n-envs", "1", "--n-workers", "0",
                                  "--no-progress"])
    model = build_sb3_model(args, None)
    try:
        assert model.use_sde and model.sde_sample_freq == 4
        assert tuple(model.policy.log_std.shape) == (128, model.action_space.shape[0])  # latent x action
        observation = model.get_env().reset()
        first, _ = model.predict(observation, deterministic=False)
        again, _ = model.predict(observation, deterministic=False)
        np.testing.assert_array_equal(first, again)  # the noise is a function of the state while its matrix holds
        model.policy.reset_noise()
        assert not np.array_equal(model.predict(observation, deterministic=False)[0], first)
    finally:
        model.get_env().close()
    white = build_sb3_model(TrainConfig.from_args(["--mode", "torque", "--n-envs", "1", "--n-workers", "0"]), None)
    try:  # the default draws white noise at each step
        assert not white.use_sde
        observation = white.get_env().reset()
        assert not np.array_equal(white.predict(observation)[0], white.predict(observation)[0])
    finally:
        white.get_env().close()

    run_dir = tmp_path / "run"
    assert train_command(["--total-timesteps", "300", "--mode", "torque", "--sde-sample-freq", "4",
                          "--out", str(run_dir), *FAST]) == 0
    assert json.loads((run_dir / "config.json").read_text())["sde_sample_freq"] == 4
    policy = load_policy(run_dir / "model")
    assert policy.use_sde
    trained = PPO.load(run_dir / "model.zip", device="cpu")
    observation = np.random.default_rng(0).normal(size=(3, *policy.observation_space.shape)).astype(np.float32)
    np.testing.assert_allclose(policy.predict(observation, deterministic=True)[0],
                               trained.policy.predict(observation, deterministic=True)[0], rtol=0, atol=1e-6)


@pytest.mark.parametrize("argv", [["--sde-sample-freq", "-2"], ["--sde-sample-freq", "4", "--algo", "sac"],
                                  ["--sde-sample-freq", "4", "--backend", "rllib"],
                                  ["--sde-sample-freq", "4", "--mode", "torque", "--imitate", "gradient"]])
def test_gsde_options_are_validated(argv, capsys):
    with pytest.raises(SystemExit):
        TrainConfig.from_args(argv)
    assert "--sde-sample-freq" in capsys.readouterr().err


def test_max_train_seconds_stops_training_early(tmp_path):
    run_dir = tmp_path / "run"
    assert train_command(["--total-timesteps", "10000000", "--max-train-seconds", "2", "--mode", "torque",
                       "--out", str(run_dir), *FAST]) == 0
    timing = json.loads((run_dir / "timing.json").read_text())
    assert timing["agent_steps"] < 10_000_000 and timing["train_seconds"] < 30
    assert (run_dir / "model.zip").is_file() and (run_dir / "comparison.json").is_file()


def test_mode_defaults_and_explicit_values():
    torque = TrainConfig.from_args(["--mode", "torque"])
    assert (torque.options.obs_features, torque.gamma, torque.log_std_init, torque.options.hold_penalty) == (
        PRESETS["torque"].obs_features, PRESETS["torque"].gamma, PRESETS["torque"].log_std_init,
        PRESETS["torque"].hold_penalty)
    residual = TrainConfig.from_args(["--obs-features", "log-error", "--gamma", "0.9", "--log-std-init", "-2",
                                 "--hold-penalty", "0.25"])
    assert (residual.options.obs_features, residual.gamma, residual.log_std_init, residual.options.hold_penalty) == (
        "log-error", 0.9, -2.0, 0.25)
    # The learner steps its share of the envs only beside worker processes.
    assert residual.in_process_envs == PRESETS["residual"].in_process_envs > 0 and torque.in_process_envs == 0
    assert TrainConfig.from_args(["--n-workers", "0"]).in_process_envs == 0


def test_rllib_smoke_run(tmp_path):
    pytest.importorskip("ray.rllib")
    run_dir = tmp_path / "rllib"
    assert train_command(["--backend", "rllib", "--total-timesteps", "2000", "--out", str(run_dir),
                       "--n-workers", "0", "--eval-episodes", "1", "--eval-seconds", "0.3",
                       "--train-episode-seconds", "0.5", "--no-progress"]) == 0
    comparison = _comparison(run_dir)
    assert "learned" in comparison["results"]
    assert (run_dir / "model" / "rllib_module.pt").is_file()


def test_progress_total_is_what_sb3_collects():
    from types import SimpleNamespace

    # PPO collects whole rollouts of n_steps x num_envs agent steps; SAC whole vec-env steps.
    assert collected_steps(3000, SimpleNamespace(n_steps=256), 4) == 3072
    assert collected_steps(2048, SimpleNamespace(n_steps=256), 4) == 2048
    assert collected_steps(3001, SimpleNamespace(), 4) == 3004


def test_a_resumed_runs_progress_bar_starts_at_the_agent_steps_done():
    from types import SimpleNamespace

    from ee_formation_env.baselines.learned.sb3_backend import _progress_callback

    bar = _progress_callback(512, done=1024)
    bar.model = SimpleNamespace(get_env=lambda: SimpleNamespace(num_envs=4))  # what init_callback sets
    bar._on_training_start()
    try:
        assert (bar.bar.n, bar.bar.total) == (1024, 1536)
        bar._on_step()
        assert bar.bar.n == 1028
    finally:
        bar._on_training_end()


def test_a_run_says_its_settings_reference_gains_and_tensorboard_folder_at_its_start(tmp_path, capsys):
    import yaml

    from ee_formation_env.builtin import builtin_scenario

    scenario = builtin_scenario("planar_square")
    scenario["name"] = "my_square"
    path = tmp_path / "my_square.yaml"
    path.write_text(yaml.safe_dump(scenario))
    run_dir = tmp_path / "run"
    assert train_command(["--scenario", str(path), "--out", str(run_dir), "--mode", "torque",
                          "--total-timesteps", "200", *FAST]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert ("recipe: flat defaults (no preset for this scenario); reference laws: default gains (no tuned file "
            "for this scenario)") in lines
    logs = run_dir / "tensorboard"
    assert f"TensorBoard logs: {logs} (watch with `tensorboard --logdir {logs}`)" in lines and logs.is_dir()


def test_torque_mode_starts_as_a_copy_of_its_reference(tmp_path):
    """--imitate: DAgger rounds, the actor fitted to the reference's actions."""
    run_dir = tmp_path / "run"
    args = ["--mode", "torque", "--imitate", "gradient", "--total-timesteps", "0", "--out", str(run_dir), *FAST,
            "--imitation-rounds", "2"]
    assert train_command(args) == 0
    imitation = json.loads((run_dir / "imitation.json").read_text())
    assert imitation["reference"] == "gradient" and [r["round"] for r in imitation["rounds"]] == [0, 1]
    assert imitation["rounds"][1]["samples"] == 2 * imitation["rounds"][0]["samples"] == 2 * 2 * 50 * 4
    config = json.loads((run_dir / "config.json").read_text())
    assert config["imitate"] == "gradient" and config["total_timesteps"] == 0
    assert _comparison(run_dir)["results"]["learned"]["episodes"] == 2


def test_the_fitted_actor_follows_the_reference_actions():
    args = TrainConfig.from_args(["--mode", "torque", "--imitate", "gradient", "--n-envs", "1", "--n-workers", "0",
                             "--no-progress"])
    model = build_sb3_model(args, None)
    try:
        env = ParallelTrainingEnv("planar_square", {"episode_seconds": 0.5},
                                  TrainingOptions(mode="torque", obs_features="none", hold_penalty=0.0))
        observations, labels = demonstrations(env, "gradient", 3, np.arange(3))
        env.close()
        venv = model.get_env()
        before = np.mean((actor_mean(model, venv, observations) - labels) ** 2)
        fit_actor(model, venv, observations, labels, epochs=200, seed=0)  # 200 Adam steps on 600 samples
        after = np.mean((actor_mean(model, venv, observations) - labels) ** 2)
        assert after < 0.1 * before
    finally:
        model.get_env().close()


@pytest.mark.parametrize("argv, match", [
    (["--imitate", "gradient"], "--imitate"),  # residual mode
    (["--mode", "torque", "--algo", "sac", "--imitate", "gradient"], "--imitate"),
    (["--mode", "torque", "--imitation-rounds", "0"], "--imitation-rounds"),
    (["--total-timesteps", "0"], "--total-timesteps"),  # only an imitated policy may skip PPO
    (["--mode", "torque", "--imitate", "gradient", "--obs-features", "log-error"], "--obs-features"),
])
def test_imitation_options_are_validated(argv, match, capsys):
    with pytest.raises(SystemExit):
        TrainConfig.from_args(argv)
    assert match in capsys.readouterr().err


# SHA-256 (first 16 hex digits) of the policy's parameters after 3 PPO updates at seed 3 on planar_square, all envs
# in this process: with the flat defaults (--recipe none) as training computed them before the training code was
# reorganized, and with planar_square's recipe (residual on gradient; a torque run takes no residual recipe). Any
# change of the training env, the PPO settings or the model changes them.
# With torch's kernels pinned as tests/conftest.py pins them (MKL's vendor-independent branch). That pin gives one
# set of bits on the machines it was measured on (an Intel Xeon with AVX-512 among them) and another on an AMD EPYC
# with AVX-512, from the tree before this file's change as from this one (docs/physics.md, "The same bits on another
# machine"): a machine passes with the digests of one kernel family; any change of the training code changes them all.
PINNED_TRAINING_DIGESTS = {
    "MKL compatible branch, Intel Xeon AVX-512": {
        ("residual", "none"): "601df0ac22a86863", ("torque", "none"): "5ca4e9e2475de1d8",
        ("residual", "board"): "2bd4cdf70601cd4f", ("torque", "board"): "5ca4e9e2475de1d8"},
    "MKL compatible branch, AMD EPYC AVX-512": {
        ("residual", "none"): "f1dd1817ea2149b8", ("torque", "none"): "356d49e55795232b",
        ("residual", "board"): "4dca90f7dbc8a3d9", ("torque", "board"): "356d49e55795232b"},
}


@pytest.mark.parametrize("mode, recipe", [("residual", "none"), ("torque", "none"), ("residual", "board"),
                                          ("torque", "board")])
def test_three_ppo_updates_give_the_pinned_parameters(mode, recipe):
    import hashlib

    args = TrainConfig.from_args(["--mode", mode, "--recipe", recipe, "--seed", "3", "--n-workers", "0",
                                  "--no-progress"])
    model = build_sb3_model(args, None)
    try:
        model.learn(total_timesteps=3 * model.n_steps * model.get_env().num_envs)
        digest = hashlib.sha256()
        for name, value in model.policy.state_dict().items():
            digest.update(name.encode())
            digest.update(value.detach().cpu().numpy().tobytes())
        assert model.num_timesteps == 3 * 4096
        families = {digests[mode, recipe]: family for family, digests in PINNED_TRAINING_DIGESTS.items()}
        assert digest.hexdigest()[:16] in families, f"no kernel family gives {digest.hexdigest()[:16]}: {families}"
    finally:
        model.get_env().close()


def _undrivable_scenario(tmp_path):
    """planar_square with 1e5 N m torque limits, and learned actions allowed all of it (``UNDRIVABLE``'s
    --action-acceleration): any sizeable action ends the episode in a joint-speed fault."""
    import yaml

    from ee_formation_env.builtin import builtin_scenario

    scenario = builtin_scenario("planar_square")
    scenario["torque_limits"] = 1e5
    path = tmp_path / "undrivable.yaml"
    path.write_text(yaml.safe_dump(scenario), encoding="utf-8")
    return path


UNDRIVABLE = ["--mode", "torque", "--n-envs", "4", "--n-workers", "0", "--train-episode-seconds", "0.05",
              "--log-std-init", "0", "--action-acceleration", "1e9", "--fault-guard-start", "0", *EVAL_FAST]


def test_training_stops_naming_the_fault_when_most_episodes_fault(tmp_path, capsys):
    run_dir = tmp_path / "run"
    assert train_command(["--scenario", str(_undrivable_scenario(tmp_path)), "--total-timesteps", "1000000",
                          "--out", str(run_dir), *UNDRIVABLE]) == 2
    message = capsys.readouterr().err
    assert message.startswith("error: training: ")
    assert "of the last 100 training episodes ended in a physics fault" in message
    assert "joint speed" in message and "--action-acceleration" in message
    assert (run_dir / "model" / "state.json").is_file()  # the model so far is kept
    assert not (run_dir / "comparison.json").exists()  # no comparison table from faulted training
    timing = json.loads((run_dir / "timing.json").read_text())  # ends at the stop, not "running" at 0 steps
    segment = timing["segments"][-1]
    assert not segment["running"] and segment["interrupted"] == timing["interrupted"] == "physics faults"
    assert 0 < timing["agent_steps"] == segment["agent_steps"] < 1000000 and timing["train_seconds"] > 0
    assert segment["faulted_training_episodes"] > 90 and (run_dir / "learning_curve.csv").is_file()


def test_the_fault_guard_judges_from_its_share_of_the_budget_on(tmp_path, capsys):
    """A run learning from scratch may fault in every episode early on and recover: the guard waits for
    --fault-guard-start of the budget, then stops a run that still faults."""
    run_dir = tmp_path / "run"
    argv = ["--scenario", str(_undrivable_scenario(tmp_path)), "--total-timesteps", "40000", "--out", str(run_dir),
            *UNDRIVABLE, "--fault-guard-start", "0.5"]  # the later flag wins
    assert train_command(argv) == 2
    assert "of the last 100 training episodes ended in a physics fault" in capsys.readouterr().err
    timing = json.loads((run_dir / "timing.json").read_text())
    assert 20000 <= timing["agent_steps"] < 40000 and timing["interrupted"] == "physics faults"


def test_faults_below_the_threshold_are_reported_not_hidden(tmp_path, capsys):
    run_dir = tmp_path / "run"
    assert train_command(["--scenario", str(_undrivable_scenario(tmp_path)), "--total-timesteps", "600",
                          "--max-fault-fraction", "1", "--out", str(run_dir), *UNDRIVABLE]) == 0
    segment = json.loads((run_dir / "timing.json").read_text())["segments"][-1]
    assert segment["faulted_training_episodes"] > 0
    assert segment["faulted_training_episodes"] <= segment["training_episodes"]
    assert any("joint speed" in reason for reason in segment["fault_reasons"])
    assert "training episodes ended in a physics fault" in capsys.readouterr().out
    table = (run_dir / "comparison.md").read_text()
    assert "| faults (episodes) |" in table.splitlines()[2]  # the comparison counts faulted episodes too


def test_fault_tally_counts_one_kind_of_fault_once():
    from ee_formation_env.baselines.learned.sb3_backend import FaultTally

    tally = FaultTally()
    for reason in ("", "arm_1: joint speed 120.5 rad/s exceeds max_joint_velocity 100 rad/s",
                   "arm_1: joint speed 131.0 rad/s exceeds max_joint_velocity 100 rad/s", "arm_0: non-finite joint state"):
        tally.add(reason)
    summary = tally.as_dict()
    assert summary["training_episodes"] == 4 and summary["faulted_training_episodes"] == 3
    assert summary["fault_reasons"] == {"arm_1: joint speed 131.0 rad/s exceeds max_joint_velocity 100 rad/s": 2,
                                        "arm_0: non-finite joint state": 1}
