"""Reading a scenario file: YAML (the YAML 1.2 core schema) or JSON, bounded, with no key given twice.

Rules (the bounds are in :mod:`ee_formation_env.inputs` and ``docs/scenarios.md``, "Limits"):

- a file is at most :data:`~ee_formation_env.inputs.MAX_SCENARIO_FILE_BYTES` bytes, refused before it is parsed;
- YAML is read with the YAML 1.2 core schema, not PyYAML's YAML 1.1 one (:class:`BoundedSafeLoader`): ``010``
  is the integer 10 (not octal 8), ``1e3`` the float 1000.0, ``1:30``, ``yes``/``no``/``on``/``off`` and dates
  are strings, which the field that expects a number or a boolean then refuses, naming itself;
- a key given twice in one mapping (YAML) or object (JSON) is refused, naming the key (and, for YAML, both
  lines), instead of the last one silently winning;
- a YAML document expands to at most :data:`~ee_formation_env.inputs.MAX_SCENARIO_NODES` nodes, aliases
  expanded, counted before anything is constructed;
- lists and dicts nested more than :data:`~ee_formation_env.inputs.MAX_NESTING_DEPTH` deep, and an integer of more
  than :data:`~ee_formation_env.inputs.MAX_INTEGER_DIGITS` digits (Python's own bound on reading one), are refused
  naming the file and the key (:func:`~ee_formation_env.inputs.field_path`), for YAML with the line: YAML while
  it is composed, before the parser's recursion could run out of stack; JSON after it is parsed, or, when the
  parser's recursion ran out first, by a scan of the text;
- a file that does not parse is a ``ValueError`` whose message is the parser's own, several readable lines
  (the problem, the line and column, the line with a caret).
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import yaml

from ee_formation_env.inputs import (MAX_INTEGER_DIGITS, MAX_NESTING_DEPTH, MAX_SCENARIO_FILE_BYTES, MAX_SCENARIO_NODES,
                                     excerpt, field_path)

# The YAML 1.2 core schema's implicit types (https://yaml.org/spec/1.2.2/#1032-tag-resolution), replacing
# PyYAML's YAML 1.1 ones (octal 010, sexagesimal 1:30, booleans yes/no/on/off, timestamps, and 1e3 a string).
_YAML12_BOOL = re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$")
_YAML12_INT = re.compile(r"^(?:[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+)$")
_YAML12_FLOAT = re.compile(r"^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?"
                           r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$")
_INT_TAG = "tag:yaml.org,2002:int"
_YAML11_TAGS = {"tag:yaml.org,2002:bool", "tag:yaml.org,2002:int", "tag:yaml.org,2002:float",
                "tag:yaml.org,2002:timestamp"}


class FileRefusal(ValueError):
    """A refusal of a part of a scenario file, its message starting with the key; :func:`read_scenario_file`
    puts the file's name before it."""


class BoundedSafeLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` reading the YAML 1.2 core schema, refusing a key given twice in one mapping, and
    refusing a document expanding to more than :data:`MAX_SCENARIO_NODES` nodes or nesting deeper than
    :data:`MAX_NESTING_DEPTH`.

    Plain scalars resolve as YAML 1.2 does: ``true``/``false`` booleans, decimal (``010`` is 10), ``0o`` octal
    and ``0x`` hexadecimal integers, floats with or without a dot (``1e3``), ``.inf``/``.nan``; everything
    else (``1:30``, ``yes``, ``2001-12-14``) is a string. The node count is made on the composed node graph,
    before construction: each node's expanded size is computed once (memoized by identity), so counting is
    linear in the file's size even when the expansion is exponential.
    """

    max_nodes = MAX_SCENARIO_NODES

    def __init__(self, stream: Any):
        super().__init__(stream)
        self._path: list[Any] = []  # the keys and indexes of the node being composed, from the document down

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node:
        """Compose one node, refusing it, with its key and line, when it lies deeper than
        :data:`MAX_NESTING_DEPTH` (before recursing further) or is an integer of more than
        :data:`MAX_INTEGER_DIGITS` digits."""
        key = index.value if isinstance(index, yaml.ScalarNode) else "(a key)" if index is None else index
        self._path.append(key)
        try:
            if len(self._path) > MAX_NESTING_DEPTH + 1:  # the document's root is at depth 0
                line = self.peek_event().start_mark.line + 1
                raise FileRefusal(f"{field_path(self._path[1:])}: lists and dicts nest more than {MAX_NESTING_DEPTH} "
                                  f"levels deep (line {line}; the scenario format needs 4)")
            node = super().compose_node(parent, index)
            if node.tag == _INT_TAG and len(node.value.lstrip("+-")) > MAX_INTEGER_DIGITS:
                raise FileRefusal(f"{field_path(self._path[1:])}: expected an integer of at most {MAX_INTEGER_DIGITS} "
                                  f"digits, got one of {len(node.value.lstrip('+-'))} (line {node.start_mark.line + 1})")
            return node
        finally:
            self._path.pop()

    def compose_document(self) -> yaml.Node:
        node = super().compose_document()
        count = expanded_node_count(node, self.max_nodes)
        if count > self.max_nodes:
            raise ValueError(f"scenario: the YAML document expands to more than {self.max_nodes} nodes "
                             "(aliases expanded); a scenario needs far fewer")
        return node

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        if isinstance(node, yaml.MappingNode):
            lines: dict[Any, int] = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue  # a '<<' merge's keys may be overridden by the mapping's own: that is its purpose
                key = self.construct_object(key_node, deep=True)
                line = key_node.start_mark.line + 1
                try:
                    first = lines.get(key)
                except TypeError:
                    continue  # an unhashable key: the base constructor reports it
                if first is not None:
                    raise yaml.constructor.ConstructorError(
                        None, None, f"key {excerpt(key)} is given twice (lines {first} and {line}); give each "
                        "key once", key_node.start_mark)
                lines[key] = line
        return super().construct_mapping(node, deep=deep)

    def construct_yaml_int(self, node: yaml.ScalarNode) -> int:
        text = self.construct_scalar(node)
        if text.startswith(("0o", "0x")):
            return int(text[2:], 8 if text[1] == "o" else 16)
        return int(text, 10)

    def construct_yaml_float(self, node: yaml.ScalarNode) -> float:
        text = self.construct_scalar(node).lower()
        if text.endswith((".inf", ".nan")):
            return float(text.replace(".", ""))
        return float(text)


BoundedSafeLoader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag not in _YAML11_TAGS]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()}
BoundedSafeLoader.add_implicit_resolver("tag:yaml.org,2002:bool", _YAML12_BOOL, list("tTfF"))
BoundedSafeLoader.add_implicit_resolver("tag:yaml.org,2002:int", _YAML12_INT, list("-+0123456789"))
BoundedSafeLoader.add_implicit_resolver("tag:yaml.org,2002:float", _YAML12_FLOAT, list("-+0123456789."))
BoundedSafeLoader.add_constructor("tag:yaml.org,2002:int", BoundedSafeLoader.construct_yaml_int)
BoundedSafeLoader.add_constructor("tag:yaml.org,2002:float", BoundedSafeLoader.construct_yaml_float)


def expanded_node_count(root: yaml.Node, limit: int) -> int:
    """Nodes of ``root`` with aliases expanded (stops counting once past ``limit``)."""
    sizes: dict[int, int] = {}
    on_path: set[int] = set()
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, children_done = stack.pop()
        key = id(node)
        if key in sizes and not children_done:
            continue
        children = _children(node)
        if not children_done:
            if key in on_path:
                raise ValueError("scenario: the YAML document contains a recursive alias")
            on_path.add(key)
            stack.append((node, True))
            stack.extend((child, False) for child in children if id(child) not in sizes)
            continue
        on_path.discard(key)
        sizes[key] = min(1 + sum(sizes[id(child)] for child in children), limit + 1)
    return sizes[id(root)]


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    if isinstance(node, yaml.MappingNode):
        return [item for pair in node.value for item in pair]
    return []


class _LongInteger:
    """A JSON integer of more than :data:`MAX_INTEGER_DIGITS` digits, kept unconverted so that the key it is
    the value of can be named."""

    def __init__(self, text: str):
        self.digits = len(text.lstrip("-"))


def _json_int(text: str) -> int | _LongInteger:
    return int(text) if len(text.lstrip("-")) <= MAX_INTEGER_DIGITS else _LongInteger(text)


def _refuse_long_integers(data: Any) -> None:
    """Refuse the first :class:`_LongInteger` in parsed JSON, naming its key (walked without recursion)."""
    stack: list[tuple[Any, tuple[Any, ...]]] = [(data, ())]
    while stack:
        item, path = stack.pop()
        if isinstance(item, _LongInteger):
            raise FileRefusal(f"{field_path(path) or 'the document'}: expected an integer of at most "
                              f"{MAX_INTEGER_DIGITS} digits, got one of {item.digits}")
        children = item.items() if isinstance(item, dict) else enumerate(item) if isinstance(item, list) else ()
        stack.extend((child, (*path, key)) for key, child in reversed(list(children)))


def _json_deep_path(text: str, limit: int) -> list[Any] | None:
    """The keys and indexes leading to the first list or dict of a JSON text nested deeper than ``limit``, by a
    scan with its own stack (for a text too deep for the parser's recursion); None if the scan finds none."""
    path: list[Any] = []  # per open list its current index, per open dict its current key (None before it)
    i, n = 0, len(text)
    while i < n:
        char = text[i]
        if char == '"':
            end = i + 1
            while end < n and text[end] != '"':
                end += 2 if text[end] == "\\" else 1
            if path and path[-1] is None:  # a dict's key
                path[-1] = text[i + 1:end]
            i = end + 1
            continue
        if char in "[{":
            if len(path) >= limit:
                return path
            path.append(0 if char == "[" else None)
        elif char in "]}" and path:
            path.pop()
        elif char == "," and path:
            path[-1] = path[-1] + 1 if isinstance(path[-1], int) else None
        i += 1
    return None


def _no_duplicate_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """A JSON object from its key-value pairs; ``ValueError`` for a key given twice."""
    data: dict[str, Any] = {}
    for key, value in pairs:
        if key in data:
            raise ValueError(f"key {excerpt(key)} is given twice in one object; give each key once")
        data[key] = value
    return data


def read_scenario_file(path: Path) -> Any:
    """The plain data of a YAML/JSON scenario file, within :data:`MAX_SCENARIO_FILE_BYTES` and (YAML) the
    alias-expansion bound of :class:`BoundedSafeLoader`."""
    size = path.stat().st_size
    if size > MAX_SCENARIO_FILE_BYTES:
        raise ValueError(f"scenario: {excerpt(str(path))} is {size} bytes; a scenario file is at most "
                         f"{MAX_SCENARIO_FILE_BYTES} bytes")
    with open(path, "rb") as handle:
        raw = handle.read(MAX_SCENARIO_FILE_BYTES + 1)
    if len(raw) > MAX_SCENARIO_FILE_BYTES:  # grew since stat
        raise ValueError(f"scenario: {excerpt(str(path))} is over {MAX_SCENARIO_FILE_BYTES} bytes")
    kind = "JSON" if path.suffix == ".json" else "YAML"
    try:
        text = raw.decode("utf-8")
        if path.suffix == ".json":
            data = json.loads(text, object_pairs_hook=_no_duplicate_keys, parse_int=_json_int)
            _refuse_long_integers(data)
            return data
        return yaml.load(text, Loader=BoundedSafeLoader)  # noqa: S506 (a SafeLoader subclass)
    except RecursionError:  # JSON's parser only: the YAML loader refuses the depth before it recurses
        deep = _json_deep_path(text, MAX_NESTING_DEPTH)
        field = f"{field_path(deep)}: " if deep else ""
        raise ValueError(f"scenario: {excerpt(str(path))}: {field}lists and dicts nest more than {MAX_NESTING_DEPTH} "
                         "levels deep (the scenario format needs 4)") from None
    except FileRefusal as refusal:
        raise ValueError(f"scenario: {excerpt(str(path))}: {refusal}") from None
    except (UnicodeDecodeError, json.JSONDecodeError, yaml.YAMLError) as error:
        # YAML's message is several lines (what, where, the line with a caret): shown as it is, at most 12 lines.
        detail = "\n".join(line[:300] for line in
                           str(error).replace('"<unicode string>"', f'"{path}"').splitlines()[:12])
        raise ValueError(f"scenario: {excerpt(str(path))} is not valid {kind}:\n{detail}") from None
    except ValueError as error:
        if kind != "JSON":
            raise  # the YAML loader's own refusals (size, aliases) name the scenario already
        raise ValueError(f"scenario: {excerpt(str(path))} is not valid {kind}: {error}") from None
