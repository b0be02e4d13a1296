"""The built-in scenarios' recipes: a recipe is its scoreboard method's settings, the command line's flags win,
another mode or --recipe none takes the flat defaults, and a saved run keeps what it trained with."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from ee_formation_env.baselines.learned.config import TrainConfig
from ee_formation_env.baselines.learned.recipes import FLAT_DEFAULT_METHOD, RECIPES, recipe_budget
from ee_formation_env.builtin import BUILTIN_SCENARIOS, builtin_scenario
from studies.scoreboard import METHODS


def _config(*argv):
    return TrainConfig.from_args([*argv, "--no-progress"])


def _settings(config):
    return {name: value for name, value in dataclasses.asdict(config).items() if name != "recipe"}


@pytest.mark.parametrize("scenario", list(RECIPES))
def test_a_recipe_is_its_scoreboard_methods_flags_on_a_builtin(scenario):
    recipe = RECIPES[scenario]
    assert scenario in BUILTIN_SCENARIOS
    board = _config("--scenario", scenario, "--recipe", "none", *METHODS[recipe.method].train_flags)
    assert _settings(_config("--scenario", scenario)) == _settings(board)
    assert _settings(_config("--scenario", scenario, "--recipe", "none")) != _settings(board)


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
    assert _config("--scenario", str(path)).recipe_used() == "flat defaults (no recipe for this scenario)"
    assert _config().recipe_used() == "residual-ppo-gradient (the board's recipe for planar_square)"
    assert _config("--recipe", "none").recipe_used() == "flat defaults (--recipe none)"
    assert _config("--mode", "torque").recipe_used() == ("flat defaults (--mode torque is not the mode of its "
                                                         "recipe, residual-ppo-gradient)")


def test_a_bad_recipe_is_refused_naming_the_flag(capsys):
    with pytest.raises(SystemExit):
        _config("--recipe", "best")
    assert "--recipe" in capsys.readouterr().err



def _board_leaders_at_the_recipe_budget():
    """Per built-in, the learned method leading its committed board rows among the train.py methods of the
    recipe budget, 3 seeds or more: highest success, then shortest mean settling."""
    board = Path(__file__).resolve().parents[3] / "docs" / "results" / "scoreboard.json"
    rows = [row for row in json.loads(board.read_text())["rows"]
            if row["split"] == "train" and len(row["seeds"]) >= 3
            and row["budget"].get("total_timesteps") == recipe_budget()]
    leaders = {}
    for scenario in BUILTIN_SCENARIOS:
        ranked = sorted((row for row in rows if row["scenario"] == scenario),
                        key=lambda row: (-row["metrics"]["success"]["mean"],
                                         row["metrics"]["settling_time_or_limit"]["mean"]))
        if ranked:
            leaders[scenario] = ranked[0]["method"]
    return leaders


def test_each_recipe_is_the_board_leader_at_the_recipe_budget():
    leaders = _board_leaders_at_the_recipe_budget()
    assert leaders, "no board row at the recipe budget"
    for scenario, leader in leaders.items():
        if leader == FLAT_DEFAULT_METHOD:
            assert scenario not in RECIPES, f"{scenario}: the flat defaults lead, yet it has a recipe"
        else:
            assert scenario in RECIPES and RECIPES[scenario].method == leader, f"{scenario}: the board's leader is {leader}"
    assert set(RECIPES) <= set(leaders)
