"""A run's configuration: one tree of dataclasses, each setting declared once; the flags, config.json, --config
and --set all name the same flat settings."""

from __future__ import annotations

import dataclasses
import json
import re
import typing

import pytest
import yaml

from ee_formation_env.baselines.cli import train_command
from ee_formation_env.baselines.learned.config import PRESETS, TrainConfig
from ee_formation_env.baselines.learned.modes import PPOSettings
from ee_formation_env.baselines.learned.options import TrainingOptions


def _tree(cls: type) -> list[type]:
    """``cls`` and every dataclass a field of it holds (by its type), depth first."""
    hints = typing.get_type_hints(cls)
    nested = [hints[spec.name] for spec in dataclasses.fields(cls) if dataclasses.is_dataclass(hints[spec.name])]
    return [cls, *(inner for kind in nested for inner in _tree(kind))]


def _configuration_tree() -> list[type]:
    """The dataclasses of a training run's configuration: TrainConfig, what it nests, and the PPO settings it
    hands the backends (``TrainConfig.ppo``)."""
    return [*_tree(TrainConfig), typing.get_type_hints(TrainConfig.ppo.fget)["return"]]


def _declared(tree: list[type]) -> dict[str, list[str]]:
    """Field name -> the dataclasses of ``tree`` that declare it (a field nesting a dataclass left out)."""
    owners: dict[str, list[str]] = {}
    for cls in tree:
        hints = typing.get_type_hints(cls)
        for spec in dataclasses.fields(cls):
            if not dataclasses.is_dataclass(hints[spec.name]):
                owners.setdefault(spec.name, []).append(cls.__name__)
    return owners


def test_no_field_is_declared_in_two_dataclasses_of_a_runs_configuration():
    tree = _configuration_tree()
    assert {TrainConfig, TrainingOptions, PPOSettings} <= set(tree)
    twice = {name: owners for name, owners in _declared(tree).items() if len(owners) > 1}
    assert not twice, f"declared in more than one dataclass of the configuration: {twice}"

    @dataclasses.dataclass
    class Mirror:  # what the walk exists to catch: a field mirrored in the outer class
        mode: str = "residual"
        options: TrainingOptions = dataclasses.field(default_factory=TrainingOptions)

    assert _declared(_tree(Mirror))["mode"] == ["Mirror", "TrainingOptions"]


def test_every_flag_of_train_py_is_the_field_of_exactly_one_dataclass_and_each_field_has_its_flag_or_is_set_by_name():
    owners = _declared(_configuration_tree())
    usage = TrainConfig.parser().format_usage()
    flags = set(re.findall(r"\[(--[a-z][a-z0-9-]*)", usage)) - {f"--{name}" for name in TrainConfig.SOURCE_FLAGS}
    fields = {flag[2:].replace("-", "_") for flag in flags}
    assert {name: owners.get(name) for name in fields if len(owners.get(name, [])) != 1} == {}
    assert "--no-residual-gate" in usage  # a boolean option's negative spelling is its own field's
    # every setting of TrainConfig and of its nested options is a flag (PPOSettings are the mode's, no flags)
    settings = {name for name, (owner, *_) in owners.items() if owner in ("TrainConfig", "TrainingOptions")}
    by_name = {setting.name for setting in TrainConfig.settings() if not setting.has_flag}
    assert by_name == {"precision_bonus", "precision_band"}  # newer settings: --set name=value, no flag
    assert settings == fields | by_name == {setting.name for setting in TrainConfig.settings()}
    assert len(fields) == 50  # the flags the board's methods and saved runs use, none lost


def test_the_training_options_live_once_nested_and_the_flat_names_reach_them():
    config = TrainConfig.from_args(["--mode", "torque", "--residual-scale", "0.2", "--seed", "3"])
    assert isinstance(config.options, TrainingOptions) and config.options.residual_scale == 0.2
    assert not hasattr(config, "residual_scale")  # no mirror
    saved = config.to_dict()
    assert "options" not in saved and saved["residual_scale"] == 0.2 and saved["seed"] == 3
    assert list(saved) == [s.name for s in TrainConfig.settings() if s.name not in TrainConfig.UNSAVED_FIELDS]
    assert TrainConfig.from_dict(saved) == config
    assert TrainConfig.from_saved(json.loads(json.dumps(saved))) == config
    with pytest.raises(ValueError, match="unknown setting"):
        config.with_settings({"residual_scael": 0.1})
    with pytest.raises(ValueError, match=r"--residual-scale: expected a value in \(0, 1\]"):
        config.with_settings({"residual_scale": 3})


@pytest.mark.parametrize("argv", [[], ["--mode", "torque"], ["--mode", "torque", "--imitate", "gradient"],
                                  ["--scenario", "planar_square_displacement", "--total-timesteps", "10k"],
                                  ["--mode", "position", "--no-gravity-compensation", "--n-workers", "0"],
                                  ["--recipe", "none", "--reward-error-ceiling", "1e4", "--eval-seconds", "2"]])
@pytest.mark.parametrize("writer", [yaml.safe_dump, json.dumps])
def test_a_config_file_written_by_to_dict_resolves_to_the_config_the_flags_made(tmp_path, argv, writer):
    config = TrainConfig.from_args(argv)
    path = tmp_path / "config.yaml"
    path.write_text(writer(config.to_dict()))
    assert TrainConfig.from_args(["--config", str(path)]) == config


def test_flags_win_over_set_which_wins_over_the_file_which_wins_over_the_recipe_and_the_preset(tmp_path):
    path = tmp_path / "settings.yaml"
    path.write_text("n_envs: 4\nn_steps: 16\ngamma: 0.9\nreference: approx_jacobian\ntotal_timesteps: 20k\n")
    config = TrainConfig.from_args(["--config", str(path), "--set", "n_steps=8", "--set", "gamma=0.95",
                                    "--gamma", "0.5", "--set", "residual_gate=false", "--set", "gamma=0.97"])
    assert (config.n_envs, config.n_steps, config.gamma, config.total_timesteps) == (4, 8, 0.5, 20_000)
    assert config.options.residual_gate is False
    assert config.options.reference == "approx_jacobian"  # planar_square's recipe (gradient) sets only the rest
    assert config.log_std_init == PRESETS["residual"].log_std_init  # neither given: the mode's preset
    assert TrainConfig.from_args(["--set", "reference=approx_jacobian"]).options.reference == "approx_jacobian"
    assert TrainConfig.from_args(["--config", str(path), "--set", "gamma=null"]).gamma == PRESETS["residual"].gamma
    path.write_text("mode: torque\n")  # another mode: no recipe, its preset
    torque = TrainConfig.from_args(["--config", str(path)])
    assert (torque.options.mode, torque.n_envs, torque.options.reference) == (
        "torque", PRESETS["torque"].n_envs, "adaptive_jacobian")


@pytest.mark.parametrize("text, argv, message", [
    ("n_envz: 4\n", [], "--config {path}: unknown setting 'n_envz' (did you mean 'n_envs'?)"),
    ("n_envs: 4.5\n", [], "--config {path}: n_envs: expected an integer or null, got 4.5"),
    ("residual_gate: 3\n", [], "--config {path}: residual_gate: expected true or false, got 3"),
    ("obs_features: squared\n", [], "--config {path}: obs_features: expected one of none, log-error, invariant"),
    ("seed: null\n", [], "--config {path}: seed: expected an integer, got None"),
    ("residual_scale: 5\n", [], r"--config {path}: --residual-scale: expected a value in (0, 1], got 5"),
    ("n_envs: 0\n", [], "--config {path}: --n-envs, --n-steps and --eval-episodes must be >= 1"),
    ("- n_envs\n", [], "--config {path}: expected a mapping of setting names to values, got list"),
    ("n_envs: [\n", [], "--config {path}: cannot read it"),
    ("n_envs: 0\n", ["--n-envs", "2"], None),  # the flag wins: the file's value is never used
    ("", ["--set", "n_envs"], "--set n_envs: expected key=value"),
    ("", ["--set", "n_envs=x"], "--set n_envs=x: n_envs: expected an integer, got 'x'"),
    ("", ["--set", "residual_gate=yes"], "--set residual_gate=yes: residual_gate: expected true or false"),
    ("", ["--set", "gamma=nan"], "--set gamma=nan: gamma: expected a finite number or null, got nan"),
    ("", ["--set", "residual_scale=2"], "--set residual_scale=2: --residual-scale: expected a value in (0, 1]"),
    ("", ["--set", "foo=1"], "--set foo=1: unknown setting 'foo'"),
])
def test_a_bad_config_file_or_set_is_one_line_naming_it_and_the_key_before_any_training(tmp_path, capsys, text,
                                                                                        argv, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    out = tmp_path / "run"
    if message is None:
        assert TrainConfig.from_args(["--config", str(path), *argv]).n_envs == 2
        return
    with pytest.raises(SystemExit) as exited:
        train_command(["--config", str(path), *argv, "--out", str(out)])
    assert exited.value.code == 2 and not out.exists()
    (line,) = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
    assert line.startswith("train.py: error: ") and message.format(path=path) in line, line
