"""studies.benchmarl_runs: a BenchMARL run bounded by wall time or frames, evaluated with the project's metrics, exported."""

from __future__ import annotations

import csv
import json

import importlib.util
import re

import numpy as np
import pytest

from studies import benchmarl_runs

needs_benchmarl = pytest.mark.skipif(importlib.util.find_spec("benchmarl") is None, reason="needs the torchrl extra")


@pytest.mark.parametrize("field, value, error, message", [
    ("lr", 0.0, ValueError, "lr: expected a learning rate > 0"),
    ("lmbda", 1.5, ValueError, "lmbda: expected a value in [0, 1]"),
    ("initial_std", "0.1", TypeError, "initial_std: expected a number"),
    ("initial_std", float("nan"), ValueError, "initial_std: expected a standard deviation > 0"),
    ("epochs", 0, ValueError, "epochs: expected an integer >= 1"),
    ("minibatch_frames", 9_000, ValueError, "minibatch_frames: expected at most frames_per_batch (8000)"),
    ("lr_decay", 1, TypeError, "lr_decay: expected True or False"),
])
def test_bad_run_settings_name_the_field(field, value, error, message):
    with pytest.raises(error, match=re.escape(message)):
        benchmarl_runs.RunSettings(**{field: value})


def test_the_sb3_settings_are_train_pys_torque_preset_where_benchmarl_has_the_knob():
    from ee_formation_env.baselines.learned.config import PRESETS

    torque, sb3 = PRESETS["torque"], benchmarl_runs.SETTINGS["sb3"]
    assert sb3.lr == torque.ppo.learning_rate and sb3.epochs == torque.ppo.n_epochs and sb3.lmbda == 0.95
    assert sb3.initial_std == pytest.approx(2.718281828 ** torque.log_std_init, abs=0.005)
    assert benchmarl_runs.SETTINGS["benchmarl"] == benchmarl_runs.RunSettings()


@needs_benchmarl
def test_a_short_run_stops_on_the_clock_and_writes_its_evaluation(tmp_path, capsys):
    out = tmp_path / "run"
    assert benchmarl_runs.main(["--minutes", "0.2", "--episodes", "1", "--mode", "residual", "--out", str(out)]) == 0
    record = json.loads((out / "evaluation.json").read_text())
    assert record["algorithm"] == "mappo" and record["mode"] == "residual" and record["iterations"] >= 1
    assert record["agent_steps"] == record["frames"] * 4 > 0
    assert record["train_seconds"] < 60  # stopped by the clock, not by its 10^10-frame budget
    evaluation = record["evaluation"]
    assert {"success_rate", "physics_faults", "per_episode"} <= set(evaluation)
    assert len(evaluation["per_episode"]) == 1 and "trajectory" not in evaluation["per_episode"][0]
    rows = list(csv.DictReader((out / "curve.csv").open()))
    assert rows and int(rows[0]["agent_steps"]) == 4 * int(rows[0]["frames"])
    assert (out / "policy" / "actor.pt").is_file() and (out / "policy" / "actor.json").is_file()
    printed = capsys.readouterr().out
    assert "| mappo (residual) |" in printed and "training stopped: wall-clock budget of 12 s reached" in printed


@pytest.fixture
def experiment_arguments(monkeypatch):
    """The keyword arguments the next BenchMARL ``Experiment`` is built with (filled when it is built)."""
    import benchmarl.experiment

    seen = {}
    original = benchmarl.experiment.Experiment.__init__

    def spy(self, *args, **kwargs):
        seen.update(kwargs)
        original(self, *args, **kwargs)

    monkeypatch.setattr(benchmarl.experiment.Experiment, "__init__", spy)
    return seen


@needs_benchmarl
def test_the_settings_reach_benchmarl_and_the_record(tmp_path, experiment_arguments):
    seen = experiment_arguments
    out = tmp_path / "run"
    assert benchmarl_runs.main(["--minutes", "0.05", "--episodes", "1", "--mode", "residual", "--settings", "sb3",
                                "--out", str(out)]) == 0
    record = json.loads((out / "evaluation.json").read_text())
    assert record["settings"] == {**benchmarl_runs.SETTINGS["sb3"].__dict__}
    config, algorithm = seen["config"], seen["algorithm_config"]
    assert (config.lr, config.on_policy_n_minibatch_iters, config.on_policy_minibatch_size) == (3e-4, 10, 400)
    assert (algorithm.lmbda, algorithm.scale_mapping) == (0.95, "biased_softplus_0.14")


@pytest.mark.parametrize("argv, message", [
    (["--settings", "fast"], "--settings: invalid choice"),
    (["--scenario", "nowhere"], "--scenario: unknown"),
    (["--minutes", "0"], "--minutes: expected a duration > 0"),
    (["--episodes", "0"], "--episodes: expected an integer >= 1"),
    (["--frames", "0"], "--frames: expected an integer >= 1"),
    (["--frames", "100", "--minutes", "1"], "not allowed with argument"),
    (["--model", "deepsets"], "--model: deepsets runs with --settings project"),
    (["--model", "gnn"], "--model: invalid choice"),
    (["--task-set", "train_episode_seconds"], "--task-set: expected KEY=VALUE"),
    (["--algorithm-set", "=1"], "--algorithm-set: expected KEY=VALUE"),
])
def test_bad_arguments_are_refused_before_anything_runs(tmp_path, argv, message, capsys):
    with pytest.raises(SystemExit):
        benchmarl_runs.main([*argv, "--out", str(tmp_path / "run")])
    assert message in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


@needs_benchmarl
def test_the_scoreboard_runs_a_benchmarl_method_with_its_test_split(tmp_path, capsys):
    from studies import scoreboard

    argv = ["--quick", "--out", str(tmp_path), "--scenarios", "planar_square", "--methods", "mappo-residual",
            "--seeds", "0", "--episodes", "1"]
    assert scoreboard.main(argv) == 0
    rows = json.loads((tmp_path / "scoreboard.json").read_text())["rows"]
    assert [row["split"] for row in rows] == ["train", "wide", "test", "test", "test", "test"]
    assert all(row["method"] == "mappo-residual" and row["seeds"] == [0] and row["metrics"] for row in rows)
    assert (tmp_path / "runs" / "planar_square" / "mappo-residual" / "seed-0" / "policy" / "actor.pt").is_file()
    capsys.readouterr()
    assert scoreboard.main(argv) == 0  # resumed: every cell from its file
    assert "running" not in capsys.readouterr().out


@needs_benchmarl
def test_a_project_settings_method_runs_on_the_board_and_its_cells_record_the_yaml_files(tmp_path):
    from ee_formation_env.baselines.learned.benchmarl_configs import config_files
    from studies import scoreboard

    argv = ["--quick", "--out", str(tmp_path), "--scenarios", "planar_square", "--methods",
            "mappo-velocity-project", "--seeds", "0", "--episodes", "1", "--no-test-sets"]
    assert scoreboard.main(argv) == 0
    cell = json.loads((tmp_path / "cells" / "planar_square" / "mappo-velocity-project" / "seed-0.json").read_text())
    files = config_files("mappo", "velocity")
    assert list(files) == ["algorithm/mappo.yaml", "experiment/on_policy.yaml", "model/layers/mlp.yaml",
                           "task/ee_formation_training/velocity.yaml"]
    assert json.dumps(files) in json.dumps(cell)


@needs_benchmarl
def test_the_set_method_is_evaluated_at_every_team_size_and_records_its_model_files(tmp_path):
    from ee_formation_env.baselines.learned.benchmarl_configs import config_files
    from studies import scoreboard

    argv = ["--quick", "--out", str(tmp_path), "--scenarios", "planar_random", "--methods", "mappo-residual-set",
            "--seeds", "0", "--episodes", "1"]
    assert scoreboard.main(argv) == 0
    rows = json.loads((tmp_path / "scoreboard.json").read_text())["rows"]
    assert [row["scenario"] for row in rows if row["split"] == "team"] == [f"planar_team_{n}" for n in range(3, 9)]
    actor = json.loads((tmp_path / "runs" / "planar_random" / "mappo-residual-set" / "seed-0" / "policy" /
                        "actor.json").read_text())
    (entry,) = actor["groups"].values()
    assert entry["set_network"]["masked"] and actor["transforms"]["observation_sets"]
    cell = json.loads((tmp_path / "cells" / "planar_random" / "mappo-residual-set" / "seed-0.json").read_text())
    files = config_files("mappo", "residual", "deepsets")
    assert list(files) == ["algorithm/mappo.yaml", "experiment/on_policy.yaml", "model/layers/deepsets.yaml",
                           "model/layers/mlp.yaml", "task/ee_formation_training/residual.yaml"]
    assert json.dumps(files) in json.dumps(cell) and cell["budget"]["model"] == "deepsets"


def _finished_run(folder, settings=None, seed=0, scalar_rows=2):
    scalars = folder / "exp" / "exp" / "scalars"
    scalars.mkdir(parents=True)
    (scalars / "collection_planar_2link_info_formation_error.csv").write_text("".join(
        f"{k},{10.0 / (k + 1)}\n" for k in range(scalar_rows)))
    (scalars / "train_planar_2link_entropy.csv").write_text("0,1.0\n1,0.5\n")
    (scalars / "train_planar_2link_loss_entropy.csv").write_text("0,-9.0\n1,-9.0\n")
    (folder / "curve.csv").write_text("frames,agent_steps,mean_reward_per_step,wall_seconds\n"
                                      "8000,32000,0.1,3.0\n16000,64000,0.2,6.0\n")
    record = {"algorithm": "mappo", "mode": "torque", "seed": seed, "evaluation": {"success_rate": 0.5}}
    if settings is not None:
        record["settings"] = settings
    (folder / "evaluation.json").write_text(json.dumps(record))


def test_plot_draws_finished_runs_without_training(tmp_path, capsys):
    from dataclasses import asdict

    pytest.importorskip("matplotlib")  # the figures extra (the torchrl venv has none)

    _finished_run(tmp_path / "a")
    _finished_run(tmp_path / "b", asdict(benchmarl_runs.SETTINGS["sb3"]))
    assert benchmarl_runs._scalar(tmp_path / "a", "train_*_entropy.csv") == [1.0, 0.5]  # not the loss term
    figure = tmp_path / "curves.png"
    assert benchmarl_runs.main(["--plot", str(tmp_path / "a"), str(tmp_path / "b"), "--figure", str(figure)]) == 0
    assert figure.stat().st_size > 10_000
    _finished_run(tmp_path / "c", seed=1, scalar_rows=1)  # a group's runs of different lengths: cut to the shortest
    banded = tmp_path / "bands.png"
    assert benchmarl_runs.main(["--plot", str(tmp_path / "a"), str(tmp_path / "c"), str(tmp_path / "b"), "--bands",
                                "--figure", str(banded)]) == 0
    assert banded.stat().st_size > 10_000
    with pytest.raises(SystemExit):
        benchmarl_runs.main(["--bands", "--figure", str(banded)])
    assert "--bands: draws finished runs" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        benchmarl_runs.main(["--plot", str(tmp_path / "missing"), "--figure", str(figure)])
    assert "--plot: not a finished run" in capsys.readouterr().err


def test_the_seed_band_is_the_median_and_range_of_the_smoothed_runs_cut_to_the_shortest():
    steps, median, low, high = benchmarl_runs.seed_band([1, 2, 3], [[1.0, 5.0, 9.0], [3.0, 1.0], [2.0, 3.0, 4.0]])
    np.testing.assert_array_equal(steps, [1, 2])
    np.testing.assert_array_equal(median, [2.0, 3.0])
    np.testing.assert_array_equal(low, [1.0, 1.0])
    np.testing.assert_array_equal(high, [3.0, 5.0])
    # 100 values: a running mean over 2 of them, one step fewer
    steps, median, low, high = benchmarl_runs.seed_band(list(range(100)), [list(range(100)), [0.0] * 100])
    np.testing.assert_array_equal(steps, list(range(1, 100)))
    np.testing.assert_allclose(high, np.arange(99) + 0.5)
    np.testing.assert_allclose(median, (np.arange(99) + 0.5) / 2)
    assert benchmarl_runs.seed_band([1], [[1.0], []]) is None


def test_the_wall_clock_callback_decays_the_learning_rate_and_stops(monkeypatch):
    import types

    import torch

    parameter = torch.nn.Parameter(torch.zeros(1))
    optimizer = torch.optim.Adam([parameter], lr=1.0)
    batch = types.SimpleNamespace(get=lambda key: torch.ones(3))
    experiment = types.SimpleNamespace(group_map={"arms": ["a", "b"]}, total_frames=100,
                                       optimizers={"arms": {"loss_objective": optimizer}},
                                       task=types.SimpleNamespace(take_env_reward=lambda: None))
    curve = []
    callback = benchmarl_runs.BudgetCallback(100.0, curve, lr=3e-4)
    callback.experiment = experiment
    now = [1000.0]
    monkeypatch.setattr(benchmarl_runs.time, "time", lambda: now[0])
    callback.on_setup()
    now[0] += 25.0
    callback.on_batch_collected(batch)
    assert optimizer.param_groups[0]["lr"] == pytest.approx(3e-4 * 0.75) and curve == [(100, 1.0, 25.0)]
    now[0] += 80.0
    with pytest.raises(benchmarl_runs.BudgetStop):
        callback.on_batch_collected(batch)
    constant = benchmarl_runs.BudgetCallback(100.0, [])  # no lr: the optimizers are left alone
    constant.experiment = experiment
    constant.on_setup()
    optimizer.param_groups[0]["lr"] = 0.5
    now[0] += 10.0
    constant.on_batch_collected(batch)
    assert optimizer.param_groups[0]["lr"] == 0.5
    # under reward normalization the batch's rewards are not the env's: the curve takes the task's tally
    tallied = benchmarl_runs.BudgetCallback(100.0, [])
    tallied.experiment = types.SimpleNamespace(**{**vars(experiment),
                                                  "task": types.SimpleNamespace(take_env_reward=lambda: 0.7)})
    tallied.on_setup()
    tallied.on_batch_collected(batch)
    assert tallied.curve[0][1] == 0.7


@needs_benchmarl
def test_the_project_settings_are_the_shipped_yaml_files(tmp_path, experiment_arguments):
    from ee_formation_env.baselines.learned import benchmarl_configs

    seen = experiment_arguments
    out = tmp_path / "run"
    assert benchmarl_runs.main(["--minutes", "0.05", "--episodes", "1", "--mode", "torque", "--settings", "project",
                                "--out", str(out)]) == 0
    record = json.loads((out / "evaluation.json").read_text())
    assert record["settings"] == "project"
    assert record["task_config"] == {**benchmarl_configs.task_config("torque")}
    config, algorithm = seen["config"], seen["algorithm_config"]
    shipped = benchmarl_configs.experiment_config("mappo")
    assert (config.lr, config.on_policy_minibatch_size) == (shipped.lr, shipped.on_policy_minibatch_size)
    assert algorithm.normalize_advantage is True and seen["model_config"].num_cells == [128, 128]
    assert seen["task"].transforms().observation_normalization
    # the curve is in the env's reward, not the scaled one: at most 2 per agent step
    with (out / "curve.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert rows and all(0 <= float(row["mean_reward_per_step"]) <= 2 for row in rows)
    assert (out / "policy" / "actor.json").is_file()


@needs_benchmarl
def test_task_overrides_reach_the_task_and_the_record(tmp_path, experiment_arguments):
    out = tmp_path / "run"
    assert benchmarl_runs.main(["--frames", "1024", "--episodes", "1", "--mode", "torque", "--settings", "project",
                                "--task-set", "train_episode_seconds=2.5", "reward_normalization=false",
                                "--algorithm-set", "orthogonal_init=true", "--out", str(out)]) == 0
    record = json.loads((out / "evaluation.json").read_text())
    assert experiment_arguments["algorithm_config"].orthogonal_init is True
    assert record["algorithm_overrides"] == {"orthogonal_init": True}
    assert record["task_config"]["train_episode_seconds"] == 2.5
    assert record["task_config"]["reward_normalization"] is False
    assert not experiment_arguments["task"].transforms().reward_normalization


@needs_benchmarl
@pytest.mark.parametrize("overrides, error, message", [
    ({"train_episode_seconds": -1.0}, ValueError, "train_episode_seconds"),
    ({"mode": "residual"}, ValueError, "task_overrides: 'mode' is the run's mode argument"),
    (["train_episode_seconds"], TypeError, "task_overrides: expected a dict"),
])
def test_bad_task_overrides_are_refused_before_training(tmp_path, overrides, error, message):
    with pytest.raises(error, match=re.escape(message)):
        benchmarl_runs.run("ippo", "planar_square", "torque", None, 0, tmp_path / "run", settings="project",
                           frames=1024, task_overrides=overrides)
    assert not (tmp_path / "run").exists()


@needs_benchmarl
@pytest.mark.parametrize("overrides, error, message", [
    ({"orthogonal_initialization": True}, ValueError, "algorithm_overrides: 'orthogonal_initialization' is not a field"),
    ({"orthogonal_init": "yes"}, TypeError, "orthogonal_init"),
    ([("orthogonal_init", True)], TypeError, "algorithm_overrides: expected a dict"),
])
def test_bad_algorithm_overrides_are_refused_before_training(tmp_path, overrides, error, message):
    with pytest.raises(error, match=re.escape(message)):
        benchmarl_runs.run("mappo", "planar_square", "torque", None, 0, tmp_path / "run", settings="project",
                           frames=1024, algorithm_overrides=overrides)
    assert not (tmp_path / "run").exists()


def test_a_frame_budget_stops_on_frames_and_decays_the_learning_rate_over_them(monkeypatch):
    import types

    import torch

    parameter = torch.nn.Parameter(torch.zeros(1))
    optimizer = torch.optim.Adam([parameter], lr=1.0)
    batch = types.SimpleNamespace(get=lambda key: torch.ones(3))
    experiment = types.SimpleNamespace(group_map={"arms": ["a"]}, total_frames=250,
                                       optimizers={"arms": {"loss_objective": optimizer}},
                                       task=types.SimpleNamespace(take_env_reward=lambda: None))
    callback = benchmarl_runs.BudgetCallback(1.0, [], lr=2e-4, frames=1_000)  # the 1 s is not used
    callback.experiment = experiment
    now = [1000.0]
    monkeypatch.setattr(benchmarl_runs.time, "time", lambda: now[0])
    callback.on_setup()
    now[0] += 50.0  # far past the 1 s: frames decide
    callback.on_batch_collected(batch)
    assert optimizer.param_groups[0]["lr"] == pytest.approx(2e-4 * 0.75)
    experiment.total_frames = 1_000
    with pytest.raises(benchmarl_runs.BudgetStop, match="frame budget of 1,000 frames"):
        callback.on_batch_collected(batch)


def test_a_run_takes_exactly_one_budget(tmp_path):
    for minutes, frames in ((None, None), (1.0, 100)):
        with pytest.raises(ValueError, match="budget: expected minutes or frames"):
            benchmarl_runs.run("mappo", "planar_square", "torque", minutes, 0, tmp_path / "run", frames=frames)
    assert not (tmp_path / "run").exists()


@needs_benchmarl
def test_a_frame_budget_run_of_one_seed_repeats_bit_for_bit(tmp_path):
    records, curves = [], []
    for name in ("a", "b"):
        out = tmp_path / name
        assert benchmarl_runs.main(["--frames", "2048", "--episodes", "1", "--mode", "torque", "--settings",
                                    "project", "--out", str(out)]) == 0
        record = json.loads((out / "evaluation.json").read_text())
        records.append((record["frames"], record["frame_budget"], record["evaluation"]["per_episode"]))
        curves.append([(row["frames"], row["mean_reward_per_step"]) for row in csv.DictReader((out / "curve.csv").open())])
    assert records[0] == records[1] and records[0][:2] == (2048, 2048)
    assert curves[0] == curves[1] and len(curves[0]) == 2  # the second batch reached the budget
    assert (tmp_path / "a" / "policy" / "actor.json").read_bytes() == (tmp_path / "b" / "policy" / "actor.json").read_bytes()


@pytest.mark.parametrize("quick", [False, True])
def test_a_board_method_with_a_frame_budget_trains_on_frames(tmp_path, monkeypatch, quick):
    from studies import scoreboard_methods
    from studies.scoreboard_methods import BenchmarlRun, Board, Method, QUICK_MINUTES, _benchmarl_cell

    calls = []

    def fake_run(algorithm, scenario, mode, minutes, seed, out, episodes, episode_seconds=None, settings=None,
                 frames=None, model="mlp"):
        calls.append((minutes, frames))
        out.mkdir(parents=True)
        (out / "evaluation.json").write_text(json.dumps({
            "agent_steps": 4 * (frames or 64), "train_seconds": 1.0, "minutes": minutes, "frame_budget": frames,
            "evaluation": {"per_episode": []}}))

    monkeypatch.setattr(benchmarl_runs, "run", fake_run)
    method = Method("mappo-framed", benchmarl=BenchmarlRun("mappo", "torque", None, "project", frames=2048))
    board = Board(out=tmp_path, scenarios=("planar_square",), methods=(), seeds=(0,), episodes=1,
                  episode_seconds=None, extra_train_flags=scoreboard_methods.QUICK_FLAGS if quick else ())
    _, budget = _benchmarl_cell(board, "planar_square", method, 0, tmp_path / "run")
    assert calls == [(QUICK_MINUTES, None)] if quick else calls == [(None, 2048)]
    assert budget["frame_budget"] == (None if quick else 2048) and budget["settings"] == "project"
