"""Each built-in scenario's training recipe: the learned method that leads the scoreboard on it at the flat
default run's budget (:func:`recipe_budget`).

Rule: ``train.py --scenario S``, with ``S`` the name of a built-in that has a recipe in :data:`RECIPES`, takes
the recipe's value for every setting the command line does not give, unless the command line gives a
``--mode`` other than the recipe's (the recipe is a whole method of one mode) or ``--recipe none``. A
scenario without a recipe, a scenario file and a run built in code (``TrainConfig(...)``) take the flat
defaults; ``--resume`` and ``--eval-only`` take the run's saved settings. A run's ``config.json`` holds the
settings it trained with, recipe included. The recipes, with the board's figures that chose them:
docs/training.md ("Recipes").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

RECIPE_CHOICES = ("board", "none")  # --recipe: the scenario's recipe, or the flat defaults
FLAT_DEFAULT_METHOD = "residual-ppo"  # the scoreboard's name of train.py's flat defaults


@dataclass(frozen=True)
class Recipe:
    """A scoreboard method as ``train.py`` settings: ``method``, the board's name of it; ``settings``, the
    :class:`~ee_formation_env.baselines.learned.config.TrainConfig` fields it sets (``mode`` among them)."""

    method: str
    settings: Mapping[str, Any] = field(default_factory=dict)

    @property
    def mode(self) -> str:
        return self.settings["mode"]


def recipe_budget() -> int:
    """Agent steps of the runs a recipe is chosen among: the flat default run's budget (residual mode's
    preset), so that ``python train.py`` stays a run of minutes; longer methods are reported beside it."""
    from ee_formation_env.baselines.learned.modes import training_mode

    return training_mode("residual").preset.total_timesteps


#: Built-in scenario -> its recipe, where the board's leading learned method at :func:`recipe_budget` is not
#: the flat defaults (``residual-ppo``): the highest success, then the shortest settling time, over 3 seeds.
RECIPES: dict[str, Recipe] = {
    "planar_square": Recipe("residual-ppo-gradient", {"mode": "residual", "reference": "gradient"}),
    "planar_square_displacement": Recipe("residual-ppo-invariant", {"mode": "residual", "obs_features": "invariant"}),
    "spatial_tetrahedron": Recipe("residual-ppo-gradient", {"mode": "residual", "reference": "gradient"}),
}


def recipe_for(scenario: Any) -> Recipe | None:
    """The recipe of ``scenario`` (a built-in's name), or None (no recipe, a file, a scenario object)."""
    return RECIPES.get(scenario) if isinstance(scenario, str) else None


def recipes_table() -> str:
    """Every recipe as a Markdown table (docs/training.md shows it)."""
    lines = ["| scenario | scoreboard method | settings (the flat defaults elsewhere) |", "|---|---|---|"]
    for scenario, recipe in RECIPES.items():
        settings = ", ".join(f"`--{name.replace('_', '-')} {value}`" for name, value in recipe.settings.items())
        lines.append(f"| `{scenario}` | `{recipe.method}` | {settings} |")
    return "\n".join(lines)
