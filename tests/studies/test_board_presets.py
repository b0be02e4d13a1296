"""The lab's view of the library's training presets (baselines/learned/scenario_presets.yaml): each preset is a
board method, run as such, and the board's standings at the presets' budget are checked against them."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from ee_formation_env.baselines.learned.config import TrainConfig
from ee_formation_env.baselines.learned.recipes import RECIPES, recipe_budget
from ee_formation_env.builtin import BUILTIN_SCENARIOS
from studies.scoreboard import METHODS

FLAT_DEFAULT_METHOD = "residual-ppo"  # the board's name of train.py's flat defaults


def _settings(*argv):
    config = TrainConfig.from_args([*argv, "--no-progress"])
    return {name: value for name, value in dataclasses.asdict(config).items() if name != "recipe"}


def preset_methods() -> dict[str, str]:
    """Built-in -> the board method whose flags train exactly what ``train.py --scenario NAME`` trains."""
    found = {}
    for scenario in RECIPES:
        preset = _settings("--scenario", scenario)
        found[scenario] = [name for name, method in METHODS.items()
                           if method.learned and method.benchmarl is None and method.teacher is None
                           and _settings("--scenario", scenario, "--recipe", "none", *method.train_flags) == preset]
    return found


def test_each_preset_is_a_board_method():
    for scenario, methods in preset_methods().items():
        assert methods, f"{scenario}: no board method trains what its preset trains"


def _board_leaders_at_the_preset_budget():
    """Per built-in, the learned method leading its committed board rows among the train.py methods of the
    presets' budget, 3 seeds or more: highest success, then shortest mean settling (1 cm)."""
    board = Path(__file__).resolve().parents[2] / "docs" / "results" / "scoreboard.json"
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


def test_each_preset_is_the_board_leader_at_the_preset_budget():
    leaders, methods = _board_leaders_at_the_preset_budget(), preset_methods()
    assert leaders, "no board row at the presets' budget"
    for scenario, leader in leaders.items():
        if leader == FLAT_DEFAULT_METHOD:
            assert scenario not in RECIPES, f"{scenario}: the flat defaults lead, yet it has a preset"
        else:
            assert scenario in RECIPES and leader in methods[scenario], f"{scenario}: the board's leader is {leader}"
    assert set(RECIPES) <= set(leaders)
