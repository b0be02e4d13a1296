"""Optional dependencies: check them up front, so that an entry point fails in one line, before creating anything.

The extras are declared in ``pyproject.toml``: ``train`` (stable-baselines3, matplotlib, TensorBoard, progress
bars), ``distributed`` (Ray RLlib), ``figures`` (matplotlib), ``video`` (imageio).
"""

from __future__ import annotations

import importlib
from typing import Sequence


def missing_modules(modules: Sequence[str]) -> list[str]:
    """The modules of ``modules`` that cannot be imported (importing them is the only reliable check)."""
    missing = []
    for name in modules:
        try:
            importlib.import_module(name)
        except ImportError:
            missing.append(name)
    return missing


def require(modules: Sequence[str], extras: str, purpose: str) -> None:
    """Raise ``SystemExit`` with one line naming the pip extra(s) to install when a module is missing.

    ``extras``: what goes inside the brackets of ``pip install -e ".[...]"``, e.g. ``"train"``.
    """
    missing = missing_modules(modules)
    if missing:
        raise SystemExit(f"{purpose} needs {', '.join(missing)}, not installed: pip install -e \".[{extras}]\"")
