"""A run's configuration: one tree of dataclasses, each setting declared once; the flags and config.json name
the same flat settings."""

from __future__ import annotations

import dataclasses
import json
import re
import typing

import pytest

from ee_formation_env.baselines.learned.config import TrainConfig
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


def test_every_flag_of_train_py_is_the_field_of_exactly_one_dataclass_and_each_field_has_its_flag():
    owners = _declared(_configuration_tree())
    usage = TrainConfig.parser().format_usage()
    flags = set(re.findall(r"\[(--[a-z][a-z0-9-]*)", usage))
    fields = {flag[2:].replace("-", "_") for flag in flags}
    assert {name: owners.get(name) for name in fields if len(owners.get(name, [])) != 1} == {}
    assert "--no-residual-gate" in usage  # a boolean option's negative spelling is its own field's
    # every setting of TrainConfig and of its nested options is a flag (PPOSettings are the mode's, no flags)
    settings = {name for name, (owner, *_) in owners.items() if owner in ("TrainConfig", "TrainingOptions")}
    assert settings == fields == {setting.name for setting in TrainConfig.settings()}
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
