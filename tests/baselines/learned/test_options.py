"""The training options: one class, its defaults the ones every backend builds with, its table in the docs."""

from __future__ import annotations

import pickle
import re
from pathlib import Path

import pytest

from ee_formation_env.baselines.learned.config import TrainConfig
from ee_formation_env.baselines.learned.options import SAVED_RUN_DEFAULTS, TrainingOptions
from ee_formation_env.baselines.learned.training_env import batched_env_factory, env_factory

DOCS = Path(__file__).parents[3] / "docs"


def test_train_py_flags_default_to_the_options():
    defaults = vars(TrainConfig.parser().parse_args([]))
    by_name = {setting.name for setting in TrainConfig.settings() if not setting.has_flag}
    for name in TrainingOptions.fields():
        expected = getattr(TrainingOptions(), name) if name in by_name else defaults[name]  # --set only: no flag
        assert expected == getattr(TrainingOptions(), name) == getattr(TrainConfig().options, name), name
    assert (TrainingOptions().mode, TrainingOptions().residual_scale, TrainingOptions().residual_gate) == (
        "residual", 0.3, True)  # the settings the committed results were produced with


@pytest.mark.parametrize("argv", [[], ["--mode", "torque", "--residual-scale", "0.2", "--no-residual-gate"]])
def test_both_env_factories_carry_the_runs_options_and_pickle(argv):
    config = TrainConfig.from_args(["--no-progress", *argv])
    for factory in (batched_env_factory(config), env_factory(config)):
        again = pickle.loads(pickle.dumps(factory))  # into worker processes
        assert again.args[2] == config.options
        assert again.args[2].residual_scale == config.options.residual_scale


@pytest.mark.parametrize("argv, message", [
    (["--residual-scale", "0"], r"--residual-scale: expected a value in \(0, 1\]"),
    (["--reference", "zero"], "--reference"),
    (["--mode", "torques"], "--mode: expected one of"),
    (["--contact-penalty", "nan"], "--contact-penalty"),
])
def test_bad_flags_name_the_flag(argv, message, capsys):
    with pytest.raises(SystemExit):
        TrainConfig.from_args(argv)
    assert re.search(message, capsys.readouterr().err)


def test_saved_runs_read_back_with_the_options_they_had():
    old = {"mode": "residual", "reference": "gradient", "residual_scale": 0.1, "algo": "ppo"}  # before the gate
    options = TrainingOptions.from_saved(old)
    assert (options.reference, options.residual_scale) == ("gradient", 0.1)
    for name, value in SAVED_RUN_DEFAULTS.items():
        assert getattr(options, name) == value, name
    saved = TrainConfig.from_args(["--mode", "torque"]).to_dict()
    assert TrainingOptions.from_saved(saved) == TrainConfig.from_dict(saved).options


def test_the_training_options_are_one_run_of_the_flags_table_as_the_training_page_says():
    """docs/training.md points BenchMARL's task options at the flags table "from --mode to --train-initial-q-noise"."""
    from ee_formation_env.baselines.learned.config import TrainConfig

    names = [setting.name for setting in TrainConfig.settings()]
    start = names.index(TrainingOptions.fields()[0])
    assert tuple(names[start:start + len(TrainingOptions.fields())]) == TrainingOptions.fields()
    assert (TrainingOptions.fields()[0], TrainingOptions.fields()[-1]) == ("mode", "train_initial_q_noise")
    assert "from `--mode` to `--train-initial-q-noise`" in (DOCS / "training.md").read_text(encoding="utf-8")


@pytest.mark.parametrize("written, steps", [("400000", 400_000), ("1e5", 100_000), ("600k", 600_000), ("5M", 5_000_000),
                                            ("4_000", 4_000), ("1.5e6", 1_500_000), ("1.5k", 1_500),
                                            ("9007199254740993", 9_007_199_254_740_993)])
def test_budgets_are_read_as_the_docs_write_them(written, steps):
    from ee_formation_env.baselines.learned.config import TrainConfig

    assert TrainConfig.from_args(["--total-timesteps", written]).total_timesteps == steps


@pytest.mark.parametrize("written", ["1.5", "1e-3", "5x", "inf"])
def test_a_budget_that_is_not_a_whole_number_of_steps_is_refused_naming_the_flag(written, capsys):
    from ee_formation_env.baselines.learned.config import TrainConfig

    with pytest.raises(SystemExit):
        TrainConfig.from_args(["--total-timesteps", written])
    assert "argument --total-timesteps: invalid agent steps value" in capsys.readouterr().err
