"""The deprecated alias modules: each warns with its removal date and forwards every name to its new home."""

from __future__ import annotations

import importlib
import sys
import warnings

import pytest

ALIASES = {"ee_formation_env.sb3": ("ee_formation_env.integrations.sb3", "SharedPolicyVecEnv"),
           "ee_formation_env.centralized": ("ee_formation_env.integrations.centralized", "CentralizedFormationEnv")}


@pytest.mark.parametrize("old", sorted(ALIASES))
def test_an_alias_warns_with_its_removal_date_and_forwards(old):
    new, name = ALIASES[old]
    sys.modules.pop(old, None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        module = importlib.import_module(old)
    messages = [str(w.message) for w in caught if issubclass(w.category, DeprecationWarning)]
    assert any(f"import {new} instead" in m and "2027-06-01" in m and "0.3" in m for m in messages), messages
    assert getattr(module, name) is getattr(importlib.import_module(new), name)
    assert "2027-06-01" in module.__doc__
