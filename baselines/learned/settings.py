"""A run's settings, flat: each field of its configuration tree with its flag, and the reading of a written value.

A training run's configuration is a tree of dataclasses: :class:`~ee_formation_env.baselines.learned.config.TrainConfig`
holds the run's own settings (scenario, budget, rollout layout, evaluation, output) and, as its field ``options``,
the :class:`~ee_formation_env.baselines.learned.options.TrainingOptions`. Each setting is declared and checked once,
in the dataclass that owns it. The command line (``--n-envs``), a run's ``config.json`` and a ``--config`` file
name them flat, by field name: a :class:`Setting` is one of them as those see it. This module reads a value
written in a file or as ``--set key=value`` into the setting's type; range checks stay with the owner.
"""

from __future__ import annotations

import argparse
import difflib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import yaml


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
    def has_flag(self) -> bool:
        """Whether it has a flag of its own; False: set by name only (``--set name=value``, ``--config``)."""
        return not self.flag.get("by_name_only", False)

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

    def read(self, value: Any) -> Any:
        """A value written in a settings file (YAML: typed already, or a string as the command line writes it)
        as this setting's: ``null`` only where the field's default is ``None`` (its mode's preset, or unset).
        Raises ``ValueError`` saying what was expected."""
        if isinstance(value, str) and not self.fits(value):
            value = self.parse(value)
        if value is None and self.default is None:
            return None
        if value is None or not self.fits(value):
            null = " or null" if self.default is None else ""
            raise ValueError(f"{self.expected()}{null}, got {value!r}")
        return value

    def parse(self, text: str) -> Any:
        """A value as written on the command line (``--set key=value``), parsed with the flag's type: ``true`` or
        ``false`` for a boolean, ``null`` for ``None``. Raises ``ValueError`` saying what was expected."""
        if text.strip().lower() == "null":
            return None
        if self.boolean:
            words = {"true": True, "false": False}
            if text.strip().lower() not in words:
                raise ValueError(f"{self.expected()}, got {text!r}")
            return words[text.strip().lower()]
        parse = self.flag.get("type")
        if parse is None:
            return text
        try:
            return parse(text)
        except ValueError:
            raise ValueError(f"{self.expected()}, got {text!r}") from None


def _unknown(key: Any, settings: Mapping[str, Setting]) -> str:
    near = difflib.get_close_matches(str(key), list(settings), n=1)
    hint = f" (did you mean {near[0]!r}?)" if near else " (the settings are named as config.json names them)"
    return f"unknown setting {key!r}{hint}"


def read_settings_file(path: str | Path, settings: Mapping[str, Setting]) -> dict[str, Any]:
    """The settings a YAML (or JSON) file holds, flat by name as a run's ``config.json`` writes them, each read
    into its setting's type (:meth:`Setting.read`). A fault is a ``ValueError`` naming ``--config``, the file
    and the key."""
    where = f"--config {path}"
    try:
        data = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as error:
        raise ValueError(f"{where}: cannot read it: {str(error).splitlines()[0]}") from None
    data = {} if data is None else data  # an empty file sets nothing
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected a mapping of setting names to values, got {type(data).__name__}")
    values = {}
    for key, value in data.items():
        if key not in settings:
            raise ValueError(f"{where}: {_unknown(key, settings)}")
        try:
            values[key] = settings[key].read(value)
        except ValueError as error:
            raise ValueError(f"{where}: {key}: {error}") from None
    return values


def parse_assignment(text: str, settings: Mapping[str, Setting]) -> tuple[str, Any]:
    """``key=value`` (a ``--set``) as the setting's name and its value, parsed with the setting's type. A fault
    is a ``ValueError`` naming ``--set`` and the key."""
    key, equals, value = text.partition("=")
    key = key.strip()
    if not equals:
        raise ValueError(f"--set {text}: expected key=value")
    if key not in settings:
        raise ValueError(f"--set {text}: {_unknown(key, settings)}")
    try:
        return key, settings[key].read(settings[key].parse(value))
    except ValueError as error:
        raise ValueError(f"--set {text}: {key}: {error}") from None
