"""The built-in scenarios' recipes: a recipe is its scoreboard method's settings, the command line's flags win,
another mode or --recipe none takes the flat defaults, and a saved run keeps what it trained with."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from ee_formation_env.baselines.learned.config import TrainConfig
from ee_formation_env.baselines.learned.recipes import RECIPES, load_recipes, recipe_budget
from ee_formation_env.builtin import BUILTIN_SCENARIOS, builtin_scenario


def _config(*argv):
    return TrainConfig.from_args([*argv, "--no-progress"])


def _settings(config):
    return {name: value for name, value in dataclasses.asdict(config).items() if name != "recipe"}


def test_a_preset_applies_its_settings_on_its_builtin_only():
    for scenario, recipe in RECIPES.items():
        assert scenario in BUILTIN_SCENARIOS
        flags = [word for name, value in recipe.settings.items() for word in (f"--{name.replace('_', '-')}", str(value))]
        given = _config("--scenario", scenario, "--recipe", "none", *flags)
        assert _settings(_config("--scenario", scenario)) == _settings(given)
        assert _settings(_config("--scenario", scenario, "--recipe", "none")) != _settings(given)


@pytest.mark.parametrize("text, message", [
    ("planar_squares: {mode: residual}\n", "'planar_squares' is not a built-in scenario"),
    ("planar_square: {reference: gradient}\n", "planar_square: expected a mapping of settings naming its mode"),
    ("- planar_square\n", "expected a mapping of built-in scenario names"),
])
def test_a_bad_presets_file_is_refused_naming_the_file_and_entry(tmp_path, text, message):
    path = tmp_path / "presets.yaml"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        load_recipes(path)


def test_flags_given_win_over_the_recipe_and_another_mode_takes_no_recipe():
    assert _config().options.reference == "gradient"  # planar_square's recipe: the default run
    assert _config("--reference", "adaptive_jacobian").options.reference == "adaptive_jacobian"
    assert _config("--reference", "gradient", "--recipe", "none").options.reference == "gradient"
    assert _config("--recipe", "none").options.reference == "adaptive_jacobian"
    torque = _config("--mode", "torque")
    assert (torque.options.mode, torque.options.reference) == ("torque", "adaptive_jacobian")
    displacement = _config("--scenario", "planar_square_displacement", "--total-timesteps", "10")
    assert (displacement.options.obs_features, displacement.total_timesteps) == ("invariant", 10)
    assert _config("--scenario", "planar_random").options.reference == "adaptive_jacobian"  # no recipe: the flat defaults


def test_a_scenario_file_takes_no_recipe(tmp_path):
    import yaml

    path = tmp_path / "planar_square.yaml"
    path.write_text(yaml.safe_dump(builtin_scenario("planar_square")))
    assert _config("--scenario", str(path)).options.reference == "adaptive_jacobian"


def test_the_settings_a_run_trains_with_are_said_in_words(tmp_path):
    import yaml

    path = tmp_path / "mine.yaml"
    path.write_text(yaml.safe_dump(builtin_scenario("planar_square")))
    assert _config("--scenario", str(path)).recipe_used() == "flat defaults (no preset for this scenario)"
    assert _config().recipe_used() == "planar_square's preset (--mode residual --reference gradient)"
    assert _config("--recipe", "none").recipe_used() == "flat defaults (--recipe none)"
    assert _config("--mode", "torque").recipe_used() == ("flat defaults (--mode torque is not the mode of its "
                                                         "preset, --mode residual --reference gradient)")


def test_a_bad_recipe_is_refused_naming_the_flag(capsys):
    with pytest.raises(SystemExit):
        _config("--recipe", "best")
    assert "--recipe" in capsys.readouterr().err
