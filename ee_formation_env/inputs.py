"""Bounds on what the env accepts, and the helpers that enforce them before any physics starts.

Rule: bad input is a ``ValueError`` (or ``TypeError``) whose message starts with the field's name, raised
before a PyBullet client connects (or after closing it), that never echoes more than a short excerpt of
the input. The bounds are documented in ``docs/scenarios.md`` ("Limits"):

- a scenario file is at most :data:`MAX_SCENARIO_FILE_BYTES` bytes;
- a YAML scenario expands to at most :data:`MAX_SCENARIO_NODES` nodes, counted on the composed document
  before anything is constructed (each use of an alias counts its anchor's nodes again), so that a few
  hundred bytes of nested aliases ("billion laughs") are refused without being expanded;
- ``episode_seconds`` <= :data:`MAX_EPISODE_SECONDS`, ``physics_hz`` <= :data:`MAX_PHYSICS_HZ` and
  ``frame_skip`` <= :data:`MAX_FRAME_SKIP`, so that every derived count (``max_steps``) is a finite int;
- a seed is ``None`` or an integer >= 0 (Python or numpy); booleans are not numbers anywhere.
"""

from __future__ import annotations

import reprlib
from typing import Any, Mapping

import numpy as np
import yaml

#: Largest scenario file (YAML or JSON) read, bytes.
MAX_SCENARIO_FILE_BYTES = 1_000_000
#: Largest number of YAML nodes (scalars, sequences, mappings, keys included) a scenario file may expand
#: to, aliases expanded. The built-in scenarios have fewer than 300.
MAX_SCENARIO_NODES = 100_000
#: Longest episode, simulated seconds (11.6 days).
MAX_EPISODE_SECONDS = 1.0e6
#: Fastest physics rate, Hz.
MAX_PHYSICS_HZ = 1.0e6
#: Most physics steps per env step.
MAX_FRAME_SKIP = 1_000_000
#: Longest excerpt of an input value shown in an error message, characters.
MAX_EXCERPT_CHARS = 200

_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxlist, _REPR.maxtuple, _REPR.maxdict = 4, 12, 12, 12
_REPR.maxstring, _REPR.maxother, _REPR.maxlong = 80, 80, 40


def excerpt(value: Any, limit: int = MAX_EXCERPT_CHARS) -> str:
    """``repr(value)`` cut to at most ``limit`` characters, computed in bounded time and memory."""
    text = _REPR.repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def is_real_number(value: Any) -> bool:
    """Whether ``value`` is an int or float (Python or numpy), not a bool."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def check_seed(seed: Any) -> int | None:
    """``seed`` as a Python int (or None); ``TypeError`` / ``ValueError`` starting with ``seed:`` otherwise."""
    if seed is None:
        return None
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)):
        raise TypeError(f"seed: expected None or an integer >= 0, got {type(seed).__name__} {excerpt(seed)}")
    if seed < 0:
        raise ValueError(f"seed: expected None or an integer >= 0, got {int(seed)}")
    return int(seed)


class BoundedSafeLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses a document expanding to more than :data:`MAX_SCENARIO_NODES` nodes.

    The count is made on the composed node graph, before construction: each node's expanded size is
    computed once (memoized by identity), so counting is linear in the file's size even when the expansion
    is exponential.
    """

    max_nodes = MAX_SCENARIO_NODES

    def compose_document(self) -> yaml.Node:
        node = super().compose_document()
        count = expanded_node_count(node, self.max_nodes)
        if count > self.max_nodes:
            raise ValueError(f"scenario: the YAML document expands to more than {self.max_nodes} nodes "
                             "(aliases expanded); a scenario needs far fewer")
        return node


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


def numeric_action(agent: str, action: Any, shape: tuple[int, ...]) -> np.ndarray:
    """``agent``'s action as a float64 array of ``shape``; ``ValueError`` naming the agent if it is not a numeric
    (bool, int or float; not string, object or complex) array of that shape."""
    try:
        raw = np.asarray(action)
        if raw.dtype.kind not in "biuf":
            raise ValueError
        array = raw.astype(np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"actions[{agent!r}]: expected a numeric array of shape {shape}, got "
                         f"{type(action).__name__} {excerpt(action)}") from None
    if array.shape != shape:
        raise ValueError(f"actions[{agent!r}]: expected shape {shape}, got {array.shape}")
    return array


def copy_seeds(seed: Any, copies: int) -> list[int | None]:
    """Each of ``copies`` copies' seed from a batched ``reset``'s ``seed``: None, an integer s (copy k: s + k) or
    one seed per copy (Gymnasium's vector convention)."""
    if isinstance(seed, (list, tuple, np.ndarray)):
        if len(seed) != copies:
            raise ValueError(f"seed: expected None, an integer or a sequence of {copies} seeds (one per copy), "
                             f"got {len(seed)} seeds")
        seeds = []
        for k, value in enumerate(seed):
            try:
                seeds.append(check_seed(value))
            except (TypeError, ValueError) as error:
                raise type(error)(f"seed[{k}]{str(error)[len('seed'):]}") from None
        return seeds
    first = check_seed(seed)
    return [None if first is None else first + k for k in range(copies)]


def reset_rows(options: Any, copies: int, first_reset: bool) -> np.ndarray:
    """The copies a batched ``reset`` resets: all, or ``options["reset_mask"]``'s (a (copies,) bool array; the
    first reset must reset every copy)."""
    if options is None or "reset_mask" not in options:
        return np.arange(copies)
    if not isinstance(options, Mapping):
        raise TypeError(f"options: expected a dict, got {type(options).__name__}")
    mask = options["reset_mask"]
    array = np.asarray(mask)
    if array.dtype != bool or array.shape != (copies,):
        raise ValueError(f"options['reset_mask']: expected a bool array of shape ({copies},), got "
                         f"{array.dtype} {array.shape} {excerpt(mask)}")
    if first_reset and not array.all():
        raise RuntimeError("options['reset_mask']: the first reset must reset every copy (call reset() "
                           "without a mask first)")
    return np.flatnonzero(array)
