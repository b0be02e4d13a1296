"""Old import paths kept for one release: each forwards every name to the module's new home, with a warning."""

from __future__ import annotations

import importlib
import warnings
from typing import Any, Callable


def forward(old: str, new: str) -> Callable[[str], Any]:
    """A module ``__getattr__`` for the deprecated module ``old``, whose contents now live in ``new``."""
    warnings.warn(f"{old} is deprecated: import {new} instead (the old path is kept until 2027-06-01 and removed in version 0.3)",
                  DeprecationWarning, stacklevel=3)
    target = importlib.import_module(new)

    def __getattr__(name: str) -> Any:
        return getattr(target, name)

    return __getattr__
