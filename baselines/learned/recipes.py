"""Each built-in scenario's training preset (the ``--recipe`` of ``train.py``): a default, read from
``scenario_presets.yaml`` beside this module.

Rule: ``train.py --scenario S``, with ``S`` the name of a built-in that has a preset in :data:`RECIPES`, takes
the preset's value for every setting the command line does not give, unless the command line gives a
``--mode`` other than the preset's (a preset is a whole method of one mode) or ``--recipe none``. A scenario
without a preset, a scenario file and a run built in code (``TrainConfig(...)``) take the flat defaults;
``--resume`` and ``--eval-only`` take the run's saved settings. A run's ``config.json`` holds the settings it
trained with, preset included. The presets, with the figures that chose them: docs/training.md ("Recipes").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import yaml

RECIPE_CHOICES = ("board", "none")  # --recipe: the scenario's preset, or the flat defaults
#: The presets' file: ``scenario name: {setting: value}``.
PRESETS_FILE = Path(__file__).with_name("scenario_presets.yaml")


@dataclass(frozen=True)
class Recipe:
    """A built-in scenario's preset: ``settings``, the
    :class:`~ee_formation_env.baselines.learned.config.TrainConfig` settings it sets by name (``mode`` among
    them)."""

    settings: Mapping[str, Any] = field(default_factory=dict)

    @property
    def mode(self) -> str:
        return self.settings["mode"]

    def describe(self) -> str:
        """The settings in words, as flags: ``--mode residual --reference gradient``."""
        return " ".join(f"--{name.replace('_', '-')} {value}" for name, value in self.settings.items())


def recipe_budget() -> int:
    """Agent steps of the runs a preset is chosen among: the flat default run's budget (residual mode's
    preset), so that ``python train.py`` stays a run of minutes; longer methods are reported beside it."""
    from ee_formation_env.baselines.learned.modes import training_mode

    return training_mode("residual").preset.total_timesteps


def load_recipes(path: Path = PRESETS_FILE) -> dict[str, Recipe]:
    """The presets of ``path``, checked: each name a built-in scenario, each preset a mapping of settings that
    names its ``mode`` (``ValueError`` naming the file and the entry). The settings' names and values are checked
    by :class:`~ee_formation_env.baselines.learned.config.TrainConfig` when a preset is applied."""
    from ee_formation_env.builtin import BUILTIN_SCENARIOS

    data = yaml.safe_load(Path(path).read_text(encoding="utf-8")) or {}
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping of built-in scenario names to settings")
    recipes = {}
    for name, settings in data.items():
        if name not in BUILTIN_SCENARIOS:
            raise ValueError(f"{path}: {name!r} is not a built-in scenario")
        if not isinstance(settings, dict) or not isinstance(settings.get("mode"), str):
            raise ValueError(f"{path}: {name}: expected a mapping of settings naming its mode")
        recipes[name] = Recipe(dict(settings))
    return recipes


#: Built-in scenario -> its preset (:func:`load_recipes`).
RECIPES: dict[str, Recipe] = load_recipes()


def recipe_for(scenario: Any) -> Recipe | None:
    """The preset of ``scenario`` (a built-in's name), or None (no preset, a file, a scenario object)."""
    return RECIPES.get(scenario) if isinstance(scenario, str) else None


def recipes_table() -> str:
    """Every preset as a Markdown table (docs/training.md shows it)."""
    lines = ["| scenario | settings (the flat defaults elsewhere) |", "|---|---|"]
    for scenario, recipe in RECIPES.items():
        settings = ", ".join(f"`--{name.replace('_', '-')} {value}`" for name, value in recipe.settings.items())
        lines.append(f"| `{scenario}` | {settings} |")
    return "\n".join(lines)
