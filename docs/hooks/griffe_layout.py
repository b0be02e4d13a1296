"""Griffe extensions for the docs build: ``baselines/`` is installed as ``ee_formation_env.baselines``; field
defaults written through a private helper are shown as their values.

The repository keeps the package at the top (``pyproject.toml``'s ``package-dir``), so a static loader that
reads ``ee_formation_env/`` does not find it; this extension loads ``baselines/`` and attaches it to the
package under its installed name, so that ``::: ee_formation_env.baselines...`` blocks resolve.
"""

from __future__ import annotations

import ast
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


#: Private helpers that declare a dataclass field, and the index of their positional argument that is the default
#: (a ``default_factory=`` keyword, when given, wins: the default is shown as ``factory()``).
_FIELD_HELPERS = {"_key": 0, "_option": 0}


class PublicDefaults(griffe.Extension):
    """Show a field declared through a private helper (``formation: str = _key("distance", "meaning")``) with its
    default (``formation: str = 'distance'``), so signatures and attribute lines never show a private call."""

    def on_attribute_instance(self, *, attr: griffe.Attribute, **kwargs: Any) -> None:
        if attr.value is None:
            return
        try:
            call = ast.parse(str(attr.value), mode="eval").body
        except SyntaxError:
            return
        if not (isinstance(call, ast.Call) and isinstance(call.func, ast.Name) and call.func.id in _FIELD_HELPERS):
            return
        factory = next((keyword.value for keyword in call.keywords if keyword.arg == "default_factory"), None)
        index = _FIELD_HELPERS[call.func.id]
        if factory is not None and not (isinstance(factory, ast.Constant) and factory.value is None):
            attr.value = f"{ast.unparse(factory)}()"
        elif len(call.args) > index:
            attr.value = ast.unparse(call.args[index])
