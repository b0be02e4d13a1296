"""A run's settings, flat: each field of its configuration tree with its flag, and the reading of a written value.

A training run's configuration is a tree of dataclasses: :class:`~ee_formation_env.baselines.learned.config.TrainConfig`
holds the run's own settings (scenario, budget, rollout layout, evaluation, output) and, as its field ``options``,
the :class:`~ee_formation_env.baselines.learned.options.TrainingOptions`. Each setting is declared and checked once,
in the dataclass that owns it. The command line (``--n-envs``) and a run's ``config.json`` name them flat, by
field name: a :class:`Setting` is one of them as those see it, with its type; range checks stay with the owner.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from typing import Any, Mapping


def agent_steps(text: str) -> int:
    """A budget as written on the command line: an integer, or an integer-valued ``1e5``, ``600k``, ``5M``
    (``argparse``'s ``ValueError`` for anything else, which names the flag)."""
    cleaned = str(text).strip().replace("_", "")
    if cleaned.isdigit():  # exactly, not through a float (9007199254740993 stays itself)
        return int(cleaned)
    scale = {"k": 1_000, "m": 1_000_000}.get(cleaned[-1:].lower(), 1)
    number = float(cleaned[:-1] if scale != 1 else cleaned)
    value = number * scale
    if not math.isfinite(value) or value != int(value):
        raise ValueError(f"not a whole number of agent steps: {text!r}")
    return int(value)


agent_steps.__name__ = "agent steps"  # argparse names the type in its message


def flag_of(name: str) -> str:
    """The command-line flag of the setting ``name``: ``--n-envs`` for ``n_envs``."""
    return "--" + name.replace("_", "-")


@dataclass(frozen=True)
class Setting:
    """One setting of a run: a field of the dataclass ``owner`` (the one that declares and checks it), and its
    flag's argparse keywords (``help``, and ``type``, ``choices``, ``action`` or ``metavar`` where it has them)."""

    name: str
    owner: type
    default: Any
    flag: Mapping[str, Any]

    @property
    def boolean(self) -> bool:
        return self.flag.get("action") in ("store_true", argparse.BooleanOptionalAction)

    @property
    def kind(self) -> Any:
        """The type of its value: the flag's ``type`` (an integer for a budget read by :func:`agent_steps`)."""
        kind = self.flag.get("type")
        return int if kind is agent_steps else kind

    @property
    def choices(self) -> Any:
        # the mode is any registered one (modes.py), checked by its owner
        return None if self.name == "mode" else self.flag.get("choices")

    def fits(self, value: Any) -> bool:
        """Whether ``value`` (not ``None``) has this setting's type: a bool for a boolean flag, an integer, a
        finite number, one of its choices, a string (a scenario may also be an object)."""
        if self.name == "scenario":
            return isinstance(value, (str, dict))
        if self.boolean:
            return isinstance(value, bool)
        if self.kind is int:
            return isinstance(value, int) and not isinstance(value, bool)
        if self.kind is float:
            return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        if self.choices is not None:
            return value in self.choices
        return isinstance(value, str)

    def expected(self) -> str:
        """What :meth:`fits` accepts, in words."""
        if self.boolean:
            return "expected true or false"
        if self.kind in (int, float):
            return "expected " + ("an integer" if self.kind is int else "a finite number")
        if self.choices is not None:
            return "expected one of " + ", ".join(map(str, self.choices))
        return "expected " + ("a scenario name, file or object" if self.name == "scenario" else "a string")
