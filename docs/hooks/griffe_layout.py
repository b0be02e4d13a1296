"""Griffe extension for the docs build: ``baselines/`` is installed as ``ee_formation_env.baselines``.

The repository keeps the package at the top (``pyproject.toml``'s ``package-dir``), so a static loader that
reads ``ee_formation_env/`` does not find it; this extension loads ``baselines/`` and attaches it to the
package under its installed name, so that ``::: ee_formation_env.baselines...`` blocks resolve.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

_MAPPED = {"ee_formation_env": {"baselines": "baselines"}}  # package -> {member name: top-level directory}


class InstalledLayout(griffe.Extension):
    """Attach directories mapped by ``package-dir`` to their installed parent package."""

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs: Any) -> None:
        for member, directory in _MAPPED.get(pkg.name, {}).items():
            if member not in pkg.members:
                pkg.set_member(member, loader.load(directory, find_stubs_package=False))


_ROLE = re.compile(r":(?:py:)?(?:func|class|mod|meth|attr|data|obj|exc|const):`~?([^`]+)`")


class MarkdownDocstrings(griffe.Extension):
    """Show the docstrings' reStructuredText roles (``:func:`name```) and ``::`` literal markers as Markdown
    (inline code, a plain colon), and point to the page of a table that the code fills in at import time;
    the docstrings stay as they are in the code."""

    def on_object(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            text = _ROLE.sub(lambda match: f"`{match.group(1)}`", obj.docstring.value)
            text = text.replace("{observation_table}", "(The observation table, filled in at import time, is on the"
                                " Spaces and reward page.)")
            obj.docstring.value = re.sub(r"::\n", ":\n", text)

    def on_package(self, *, pkg: griffe.Module, **kwargs: Any) -> None:
        self.on_object(obj=pkg)
