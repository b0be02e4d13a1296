"""The one check of the env's actions: per-agent dicts (one copy's ``(n_i,)`` or K copies' ``(K, n_i)``), flat
arrays of the array API, and one agent's action; each refused before any copy moves, with an error naming the
field (``actions['arm_0']: ...``, ``actions: ...``)."""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np

from ee_formation_env.inputs import excerpt, numeric_action, numeric_array


class ActionCheck:
    """The actions of the agents ``agents`` whose joints are ``joint_slices`` of one flat (T,) vector."""

    def __init__(self, agents: Sequence[str], joint_slices: Sequence[slice]):
        self.agents = list(agents)
        self.shapes = {agent: (joints.stop - joints.start,) for agent, joints in zip(agents, joint_slices)}
        self.joint_slices = list(joint_slices)
        self.joint_starts = np.array([joints.start for joints in joint_slices], dtype=np.intp)
        self.n_joints = joint_slices[-1].stop
        sizes = set(self.shapes.values())
        self.uniform_joints = sizes.pop()[0] if len(sizes) == 1 else None  # n when every arm has n joints

    def agent_dict(self, actions: Any, copies: int | None) -> np.ndarray:
        """Every agent's action from a dict agent -> array, as one fresh float64 (K, T) array: of one copy
        ((n_i,) each, ``copies`` None, K = 1) or of ``copies`` copies ((copies, n_i) each). The errors name the
        first bad agent in agent order."""
        if not isinstance(actions, Mapping):
            raise TypeError(f"actions: expected a dict agent -> array, got {type(actions).__name__}")
        if actions.keys() != self.shapes.keys():
            missing = [a for a in self.agents if a not in actions]
            unknown = [a for a in actions if a not in self.shapes]
            raise ValueError(f"actions: missing agents {missing}, unknown agents {unknown}; expected keys {self.agents}")
        lead = () if copies is None else (copies,)
        parts = [actions[agent] for agent in self.agents]
        normalized = None
        # The common case in one call: numpy arrays of the right shapes; anything else (lists, tensors) gets the
        # detailed check, which converts them one by one and names the agent of a failure.
        if all(isinstance(part, np.ndarray) and part.shape == (*lead, *self.shapes[agent])
               for agent, part in zip(self.agents, parts)):
            try:
                normalized = np.concatenate(parts, axis=-1, dtype=np.float64)
            except (TypeError, ValueError):
                normalized = None
        # A finite sum means finite entries (an overflow to inf only sends finite values to the detailed check).
        if normalized is None or not math.isfinite(normalized.sum()):
            # The first bad agent's error (bad type, shape or values), in agent order.
            normalized = np.concatenate([self._checked(agent, part, lead) for agent, part in zip(self.agents, parts)],
                                        axis=-1)
        return normalized.reshape(-1, self.n_joints)

    def agent_action(self, agent: str, action: Any) -> None:
        """Check one agent's action as a one-copy dict's entry is checked; changes nothing."""
        if agent not in self.shapes:
            raise ValueError(f"actions: unknown agent {excerpt(agent)}; expected one of {self.agents}")
        self._checked(agent, action, ())

    def flat_array(self, actions: Any, copies: int, live: np.ndarray | None = None) -> np.ndarray:
        """A fresh float64 (K, T) copy of the array API's actions: (K, T), or, when every arm has n joints,
        (K * N, n) or (K, N, n); a ``ValueError`` starting ``actions:`` otherwise, and for non-finite values,
        naming their copies and the first such copy's first such agent. ``live`` (K, N) bool: the agents whose
        entries count (a team env's absent agents': ignored whatever they hold, zeroed); None: every agent's."""
        K, T, n, N = copies, self.n_joints, self.uniform_joints, len(self.agents)
        shapes = [(K, T)] + ([(K * N, n), (K, N, n)] if n else [])
        flat = numeric_action_array(actions, shapes, (K, T), check_finite=False)  # always a copy: clipped in place
        if live is not None:
            flat[~np.repeat(live, np.diff([*self.joint_starts, T]), axis=1)] = 0.0
        finite = np.isfinite(flat)
        if not finite.all():
            bad = np.flatnonzero(~finite.all(axis=1))
            k = bad[0]
            agent, joints = next((a, j) for a, j in zip(self.agents, self.joint_slices) if not finite[k, j].all())
            raise ValueError(f"actions: expected finite values, got non-finite values in copies {bad.tolist()} "
                             f"(copy {k}, agent {agent!r}: {flat[k, joints].tolist()})")
        return flat

    def clip(self, normalized: np.ndarray) -> np.ndarray:
        """Clip checked (K, T) actions to [-1, 1] in place; the entries clipped per (copy, agent) (K, N)."""
        outside = np.abs(normalized) > 1.0
        if not np.count_nonzero(outside):  # the common case, in two cheap calls
            return np.zeros((len(normalized), len(self.agents)), dtype=np.int64)
        clipped = np.add.reduceat(outside, self.joint_starts, axis=1, dtype=np.int64)
        np.minimum(np.maximum(normalized, -1.0, out=normalized), 1.0, out=normalized)  # np.clip, without its overhead
        return clipped

    def _checked(self, agent: str, action: Any, lead: tuple[int, ...]) -> np.ndarray:
        """``agent``'s action as a float64 array of shape ``lead + (n_i,)``, or its error."""
        shape = (*lead, *self.shapes[agent])
        array = numeric_action(agent, action, shape)
        finite = np.isfinite(array)
        if finite.all():
            return array
        if not lead:
            raise ValueError(f"actions[{agent!r}]: expected finite values of shape {shape}, got {array.tolist()}")
        bad = ~finite.all(axis=1)
        raise ValueError(f"actions[{agent!r}]: expected finite values of shape {shape}, got non-finite values in "
                         f"copies {np.flatnonzero(bad).tolist()}: {array[bad].tolist()[:3]}")


def numeric_action_array(actions: Any, shapes: Sequence[tuple[int, ...]], flat_shape: tuple[int, int],
                         rows_per_copy: int = 1, check_finite: bool = True) -> np.ndarray:
    """A fresh float64 array of ``flat_shape`` from ``actions``, an array (of any type
    :func:`~ee_formation_env.inputs.numeric_array` converts) of one of ``shapes``; a ``ValueError`` starting
    ``actions:`` for anything else or (``check_finite``) for non-finite values, naming their copies
    (row // rows_per_copy of the flat array)."""
    try:
        raw = numeric_array(actions)
        if raw.dtype.kind not in "biuf":
            raise ValueError
    except (TypeError, ValueError):
        raise ValueError(f"actions: expected a numeric array of shape {' or '.join(map(str, shapes))}, got "
                         f"{type(actions).__name__} {excerpt(actions)}") from None
    if raw.shape not in shapes:
        raise ValueError(f"actions: expected shape {' or '.join(map(str, shapes))}, got {raw.shape}")
    flat = raw.reshape(flat_shape).astype(np.float64)
    if check_finite and not np.isfinite(flat).all():
        bad = sorted({int(row) // rows_per_copy for row in np.flatnonzero(~np.isfinite(flat).all(axis=1))})
        raise ValueError(f"actions: expected finite values, got non-finite values in copies {bad}")
    return flat
