"""Bounds on what the env accepts, and the helpers that enforce them before any physics starts.

Rule: bad input is a ``ValueError`` (or ``TypeError``) whose message starts with the field's name, raised
before a PyBullet client connects (or after closing it), that never echoes more than a short excerpt of
the input. The bounds are documented in ``docs/scenarios.md`` ("Limits"):

- a scenario file is at most :data:`MAX_SCENARIO_FILE_BYTES` bytes (checked before it is parsed);
- a YAML scenario expands to at most :data:`MAX_SCENARIO_NODES` nodes, counted on the composed document
  before anything is constructed (each use of an alias counts its anchor's nodes again), so that a few
  hundred bytes of nested aliases ("billion laughs") are refused without being expanded;
- scenario data (a file's or a dict's) nests lists and dicts at most :data:`MAX_NESTING_DEPTH` deep (the
  refusal names the key where it does);
- an integer in a scenario file has at most :data:`MAX_INTEGER_DIGITS` digits (refused naming the key);
- a scenario has at most :data:`MAX_ARMS` arms (checked before any arm is parsed);
- a key given twice in one YAML or JSON mapping is refused (naming the key, and for YAML its lines);
- YAML files are read with the YAML 1.2 core schema (:mod:`ee_formation_env.scenario_file`): ``010`` is 10,
  ``1e3`` is 1000.0, ``1:30`` and ``yes`` are strings (then refused by the field that expects a number or a
  boolean);
- ``episode_seconds`` <= :data:`MAX_EPISODE_SECONDS`, ``physics_hz`` <= :data:`MAX_PHYSICS_HZ` and
  ``frame_skip`` <= :data:`MAX_FRAME_SKIP`, so that every derived count (``max_steps``) is a finite int;
- ``neighbour_slots`` <= :data:`MAX_NEIGHBOUR_SLOTS`;
- a batched env has at most :data:`MAX_NUM_ENVS` copies, and no more than the machine's physical memory holds
  at :data:`COPY_BYTES_ESTIMATE` bytes each (checked before the first PyBullet client connects);
- a seed is ``None`` or an integer >= 0 (Python or numpy); booleans are not numbers anywhere.
"""

from __future__ import annotations

import difflib
import os
import reprlib
import sys
import warnings
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

#: Largest scenario file (YAML or JSON) read, bytes. A scenario of :data:`MAX_ARMS` arms with every key and
#: comments is under 64 kB; at this size the YAML parser takes about a second before any bound below applies.
MAX_SCENARIO_FILE_BYTES = 256_000
#: Largest number of YAML nodes (scalars, sequences, mappings, keys included) a scenario file may expand
#: to, aliases expanded. The built-in scenarios have fewer than 300.
MAX_SCENARIO_NODES = 100_000
#: Deepest nesting of lists and dicts in scenario data; the format needs 4 (arms, a list of dicts of lists).
MAX_NESTING_DEPTH = 32
#: Most arms in a scenario. Building a task checks every pair of arms (start contacts, reach), so the cost
#: grows with the square of the count (500 arms take seconds, 2,000 tens of seconds); 64 arms, far more than a
#: formation study needs, build in a fraction of a second.
MAX_ARMS = 64
#: Most neighbour slots per agent (``neighbour_slots``): an agent of the largest scenario has at most
#: ``MAX_ARMS - 1`` neighbours, so more slots would only ever be empty (each slot is one row of every agent's
#: observation, allocated per copy).
MAX_NEIGHBOUR_SLOTS = MAX_ARMS - 1
#: Most digits of an integer in a scenario file: Python's own bound on converting a decimal string to an int
#: (``sys.get_int_max_str_digits``' default). No scenario number needs more than a few.
MAX_INTEGER_DIGITS = 4300
#: Most copies of a batched env: PyBullet holds at most 1024 clients per process (its MAX_PHYSICS_CLIENTS).
MAX_NUM_ENVS = 1024
#: Resident memory of one copy (one PyBullet client with a scenario's arms), bytes, for the estimate below.
COPY_BYTES_ESTIMATE = 30_000_000
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


_PACKAGE_DIR = os.path.dirname(os.path.abspath(__file__)) + os.sep


def user_stacklevel() -> int:
    """The ``stacklevel`` that attributes a warning, warned by the function calling this, to the first caller
    outside this package: the user's line that built the env or scenario, however deep inside the package the
    warning is raised."""
    level, frame = 1, sys._getframe(1)
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(_PACKAGE_DIR):
        level, frame = level + 1, frame.f_back
    return level


def check_seed(seed: Any) -> int | None:
    """``seed`` as a Python int (or None); ``TypeError`` / ``ValueError`` starting with ``seed:`` otherwise."""
    if seed is None:
        return None
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)):
        raise TypeError(f"seed: expected None or an integer >= 0, got {type(seed).__name__} {excerpt(seed)}")
    if seed < 0:
        raise ValueError(f"seed: expected None or an integer >= 0, got {int(seed)}")
    return int(seed)


def check_num_envs(num_envs: Any) -> int:
    """``num_envs`` as an int within :data:`MAX_NUM_ENVS` and the memory estimate; ``ValueError`` naming it."""
    if isinstance(num_envs, (bool, np.bool_)) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
        raise ValueError(f"num_envs: expected an integer >= 1 (copies of the scenario), got {excerpt(num_envs)}")
    if num_envs > MAX_NUM_ENVS:
        raise ValueError(f"num_envs: expected at most {MAX_NUM_ENVS} copies (PyBullet's clients per process), got "
                         f"{int(num_envs)}; run more processes instead")
    memory = _physical_memory_bytes()
    if memory is not None and num_envs * COPY_BYTES_ESTIMATE > memory:
        raise ValueError(f"num_envs: {int(num_envs)} copies need about {num_envs * COPY_BYTES_ESTIMATE / 1e9:.1f} GB "
                         f"({COPY_BYTES_ESTIMATE / 1e6:.0f} MB each); this machine has {memory / 1e9:.1f} GB")
    return int(num_envs)


def _physical_memory_bytes() -> int | None:
    """The machine's physical memory (bytes), or None where the platform does not say."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, OSError, ValueError):
        return None


def check_known_keys(where: str, keys: Iterable[Any], allowed: Iterable[str]) -> None:
    """Refuse keys of ``where`` outside ``allowed``: ``ValueError`` starting with ``where``, listing the allowed
    keys and, for a key close to an allowed one, the likely intended key ("did you mean")."""
    allowed = list(allowed)
    unknown = sorted(str(key) for key in keys if key not in allowed)
    if not unknown:
        return
    hints = [f"{close[0]!r} for {key!r}" for key in unknown[:12]
             for close in [difflib.get_close_matches(key, allowed, n=1, cutoff=0.6)] if close]
    hint = f" (did you mean {', '.join(hints)}?)" if hints else ""
    raise ValueError(f"{where}: unknown key(s) {excerpt(unknown)}{hint}; allowed: {allowed}")


def field_path(components: Sequence[Any]) -> str:
    """The scenario field that ``components`` (its keys and list indexes from the top) lead to, as an error
    names it: ``shape``, ``arms[0].initial_q``: up to the last key (a run of list indexes below it is the
    field's value), at most 4 components."""
    keys = [k for k, part in enumerate(components) if not isinstance(part, int)]
    shown = list(components[:min(keys[-1] + 1, 4)] if keys else components[:1])
    text = "".join(f"[{part}]" if isinstance(part, int) else f".{part}" for part in shown).lstrip(".")
    return text + ("..." if len(shown) < (keys[-1] + 1 if keys else 1) else "")


def check_nesting(where: str, value: Any, limit: int = MAX_NESTING_DEPTH) -> None:
    """Refuse data whose lists/tuples/dicts nest more than ``limit`` deep (checked without recursion):
    ``ValueError`` starting with ``where``, then the field it happens in (:func:`field_path`)."""
    stack: list[tuple[Any, int, tuple[Any, ...]]] = [(value, 0, ())]
    while stack:
        item, depth, path = stack.pop()
        if isinstance(item, Mapping):
            children = [(child, (*path, key if isinstance(key, (int, str)) else excerpt(key, 40)))
                        for key, child in item.items()]
        elif isinstance(item, (list, tuple)):
            children = [(child, (*path, k)) for k, child in enumerate(item)]
        else:
            continue
        if depth + 1 > limit:
            field = f"{field_path(path)}: " if path else ""
            raise ValueError(f"{where}: {field}lists and dicts nest more than {limit} levels deep (the scenario "
                             "format needs 4)")
        stack.extend((child, depth + 1, child_path) for child, child_path in children)


def numeric_array(value: Any) -> np.ndarray:
    """``value`` as a numpy array without copying where it can: numpy arrays, lists, and any array type with
    ``__array__`` (a torch tensor that requires grad is detached first, and a tensor on an accelerator copied to
    the CPU: detected by their ``detach`` and ``cpu`` methods, so that torch is not imported here). Raises
    ``TypeError``/``ValueError`` (also for a conversion that fails with another error) for the caller to name."""
    if callable(getattr(value, "detach", None)) and callable(getattr(value, "cpu", None)):
        try:
            value = value.detach().cpu()
        except Exception as error:  # noqa: BLE001 (any array library's failure is the caller's one-line refusal)
            raise ValueError(str(error)) from None
    try:
        return np.asarray(value)
    except (TypeError, ValueError):
        raise
    except Exception as error:  # noqa: BLE001 (e.g. a RuntimeError of an array library's __array__)
        raise ValueError(str(error)) from None


def numeric_action(agent: str, action: Any, shape: tuple[int, ...]) -> np.ndarray:
    """``agent``'s action as a float64 array of ``shape`` (of any array type :func:`numeric_array` converts);
    ``ValueError`` naming the agent if it is not a numeric (bool, int or float; not string, object or complex)
    array of that shape."""
    try:
        raw = numeric_array(action)
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


#: The keys ``reset(options=...)`` accepts.
RESET_OPTIONS = ("reset_mask",)


def reset_rows(options: Any, copies: int, first_reset: bool) -> np.ndarray:
    """The copies a ``reset`` resets (the batched env's, and the parallel env's, its one-copy view): all, or
    ``options["reset_mask"]``'s (a (copies,) bool array; the first reset must reset every copy). ``options`` is
    None or a dict (else ``TypeError`` naming it); a key outside :data:`RESET_OPTIONS` is ignored with a
    ``UserWarning`` naming it and the accepted keys, not refused: PettingZoo's API conformance test resets with
    ``options={"options": 1}`` and requires it to be accepted."""
    if options is None:
        return np.arange(copies)
    if not isinstance(options, Mapping):
        raise TypeError(f"options: expected None or a dict with keys among {list(RESET_OPTIONS)}, got "
                        f"{type(options).__name__} {excerpt(options)}")
    try:
        check_known_keys("options", options, RESET_OPTIONS)
    except ValueError as unknown:
        warnings.warn(f"{unknown} (ignored)", UserWarning, stacklevel=4)
    if "reset_mask" not in options:
        return np.arange(copies)
    mask = options["reset_mask"]
    array = np.asarray(mask)
    if array.dtype != bool or array.shape != (copies,):
        raise ValueError(f"options['reset_mask']: expected a bool array of shape ({copies},), got "
                         f"{array.dtype} {array.shape} {excerpt(mask)}")
    if first_reset and not array.all():
        raise RuntimeError("options['reset_mask']: the first reset must reset every copy (call reset() "
                           "without a mask first)")
    return np.flatnonzero(array)


def check_steppable(connected: bool, needs_reset: bool, ended: np.ndarray) -> None:
    """Refuse a batched step of a closed env, of one never reset, or of copies whose episode has ended (``ended``,
    (copies,) bool, without autoreset): ``RuntimeError`` saying which and how to reset."""
    if not connected:
        raise RuntimeError("step: the environment is closed")
    if needs_reset:
        raise RuntimeError("step: call reset() first (the env has never been reset)")
    if ended.any():
        raise RuntimeError(f"step: call reset() first (the episode has ended in copies "
                           f"{np.flatnonzero(ended).tolist()}: reset them, e.g. with options={{'reset_mask': mask}})")
