"""The built-in scenarios: one YAML file each, ``ee_formation_env/builtin/<name>.yaml``, shipped as package data.

Rule: a built-in scenario is a file in the documented scenario format (``docs/scenarios.md``) and nothing
else; adding ``builtin/<name>.yaml`` adds the scenario everywhere: :data:`BUILTIN_SCENARIOS` lists the files,
and from it come the PettingZoo and Gymnasium ids (:mod:`ee_formation_env.registration`), the BenchMARL task
enum (:mod:`ee_formation_env.integrations.benchmarl`) and the docs. Each file's comments say where its numbers
come from (the paper's set-ups, and where and why they deviate).
"""

from __future__ import annotations

import copy
import functools
from importlib import resources
from typing import Any

import yaml

from ee_formation_env.inputs import excerpt
from ee_formation_env.scenario_file import BoundedSafeLoader

_FILES = resources.files("ee_formation_env") / "builtin"

BUILTIN_SCENARIOS: tuple[str, ...] = tuple(sorted(
    entry.name[:-len(".yaml")] for entry in _FILES.iterdir() if entry.name.endswith(".yaml")))
"""The built-in scenario names, sorted: the stems of the ``builtin/*.yaml`` files."""


def builtin_scenario(name: str) -> dict[str, Any]:
    """A fresh plain-data copy of built-in scenario ``name`` (its YAML file, parsed)."""
    if name not in BUILTIN_SCENARIOS:
        raise ValueError(f"scenario: unknown built-in scenario {excerpt(name)}; available: {sorted(BUILTIN_SCENARIOS)}")
    return copy.deepcopy(_parsed(name))


@functools.lru_cache(maxsize=None)
def _parsed(name: str) -> dict[str, Any]:
    return yaml.load((_FILES / f"{name}.yaml").read_text(encoding="utf-8"), Loader=BoundedSafeLoader)  # noqa: S506 (a SafeLoader subclass: the one YAML rule of scenario files)
