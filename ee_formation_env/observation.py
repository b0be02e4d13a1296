"""Observations: the one definition of their layout, bounds and table, and the env's vectorized builder.

An agent's observation is ``n_slots`` neighbour slots, then its own joint state, then (only with a
scenario ``manoeuvre``, :mod:`ee_formation_env.manoeuvre`) the reference motion in its own base frame:

{observation_table}

``m`` = scenario ``dim``, ``w`` = 1 (distance) or ``m`` (displacement), ``D`` = the graph's largest degree,
``r`` = 1 (``dim`` 2: the turn rate about z) or 3. Without a manoeuvre the reference entries are absent.
Slots follow the order of the agent's edges in the scenario; padding slots are zero with mask 0. Bounds
are finite: |z| by base distances plus reaches, ``q`` by the joint limits, ``dq`` by
``max_joint_velocity`` (faster is a physics fault), the reference by the farthest end-effector from a base
plus |A|, the peak speed and the peak turn rate. Observations are clipped into them.

Spaces, reward and info for users: see docs/spaces.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import gymnasium
import numpy as np

from ee_formation_env.reward import DEFAULT_POSITION_TOLERANCE, edge_length_errors, edge_tolerances
from ee_formation_env.task import FormationTask

# (entry, size, meaning (unit)): the slot entries in order, then the joint entries.
SLOT_ENTRIES = (
    ("mask", "1", "1 if slot s holds a neighbour j, else 0"),
    ("z_ij", "m", "x_i - x_j, end-effector displacement (m)"),
    ("desired", "w", "d*_ij (m), or z*_ij = x*_i - x*_j (m)"),
    ("edge_error", "w", "|z_ij|^2 - d*_ij^2 (m^2), or z_ij - z*_ij (m)"),
)
JOINT_ENTRIES = (
    ("q", "n_i", "joint positions (rad; continuous joints wrapped to [-pi, pi))"),
    ("dq", "n_i", "joint velocities (rad/s)"),
)
# Only with a scenario ``manoeuvre`` (ee_formation_env.manoeuvre): after the joint entries.
REFERENCE_ENTRIES = (
    ("reference_centroid", "m", "c*(t) - b_i, reference centroid relative to the agent's base (m)"),
    ("reference_velocity", "m", "dc*/dt, reference centroid velocity (m/s)"),
    ("reference_angular_velocity", "r", "omega*(t), reference turn rate about the centroid (rad/s)"),
)


def observation_table() -> str:
    """The observation layout as a reStructuredText table (in the env's and this module's docstrings)."""
    rows = [(f"slot s, ``{name}``", size, meaning) for name, size, meaning in SLOT_ENTRIES]
    rows.append(("(slot entries repeat)", "", "for s = 0 .. D-1"))
    rows += [(f"``{name}``", size, meaning) for name, size, meaning in JOINT_ENTRIES]
    rows += [(f"``{name}``", size, f"manoeuvre only: {meaning}") for name, size, meaning in REFERENCE_ENTRIES]
    widths = [max(len(row[c]) for row in rows + [("entries", "size", "meaning (unit)")]) for c in range(3)]
    rule = "  ".join("=" * w for w in widths)
    header = "  ".join(h.ljust(w) for h, w in zip(("entries", "size", "meaning (unit)"), widths)).rstrip()
    body = ["  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip() for row in rows]
    return "\n".join([rule, header, rule, *body, rule])


__doc__ = __doc__.format(observation_table=observation_table())


@dataclass(frozen=True)
class ObservationParts:
    """One observation split into named parts (views into a float64 copy). Split from a stack of k
    observations (k, size), every part has a leading axis of k."""

    mask: np.ndarray  # (n_slots,) 1 for a real neighbour, 0 for padding
    relative_positions: np.ndarray  # (n_slots, dim) z_ij = x_i - x_j, m
    desired: np.ndarray  # (n_slots, w) d*_ij or z*_ij, m
    edge_errors: np.ndarray  # (n_slots, w) |z_ij|^2 - d*_ij^2 (m^2) or z_ij - z*_ij (m)
    q: np.ndarray  # (n_joints,) rad
    dq: np.ndarray  # (n_joints,) rad/s
    # With a manoeuvre only (else None), in the agent's base frame:
    reference_centroid: np.ndarray | None = None  # (dim,) c*(t) - b_i, m
    reference_velocity: np.ndarray | None = None  # (dim,) dc*/dt, m/s
    reference_angular_velocity: np.ndarray | None = None  # (1,) about z (dim 2) or (3,), rad/s


@dataclass(frozen=True)
class ObservationLayout:
    """Sizes of one agent's observation; :meth:`split` parses one (or a stack of them)."""

    n_slots: int
    dim: int
    error_width: int
    n_joints: int
    reference_size: int = 0  # the manoeuvre's entries (2 dim + 1 or 3), 0 without one

    @property
    def slot_size(self) -> int:
        return 1 + self.dim + 2 * self.error_width

    @property
    def size(self) -> int:
        return self.n_slots * self.slot_size + 2 * self.n_joints + self.reference_size

    @property
    def formation_kind(self) -> str:
        """``"distance"`` (one error entry per slot) or ``"displacement"`` (``dim`` entries)."""
        return "distance" if self.error_width == 1 else "displacement"

    def slot_tolerances(self, parts: ObservationParts,
                        position_tolerance: float = DEFAULT_POSITION_TOLERANCE) -> np.ndarray:
        """Each neighbour slot's success tolerance in formation units, ``(n_slots,)`` (or ``(k, n_slots)``):
        the reward's :func:`~ee_formation_env.reward.edge_tolerances` of the desired length the slot carries,
        for an edge accuracy ``position_tolerance`` (m). Padding slots get that of a 1e-9 m edge (their
        errors are 0, so a ratio never divides by zero)."""
        lengths = np.maximum(parts.desired[..., 0], 1e-9)
        return edge_tolerances(self.formation_kind, lengths, position_tolerance)

    def error_ratios(self, observation: np.ndarray, position_tolerance: float = DEFAULT_POSITION_TOLERANCE
                     ) -> tuple[np.ndarray, np.ndarray]:
        """The edge errors in success tolerances as the agent sees them: each slot's ``e_ij / tol_ij``
        ``(n_slots, w)`` (0 for padding; with a leading k axis for a stack), and the mask of real slots."""
        parts = self.split(observation)
        real = parts.mask > 0.5
        ratios = parts.edge_errors / self.slot_tolerances(parts, position_tolerance)[..., None]
        return np.where(real[..., None], ratios, 0.0), real

    def length_errors(self, observation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each neighbour slot's edge length error in metres as the agent sees it
        (:func:`~ee_formation_env.reward.edge_length_errors` of the slot's error and desired length),
        ``(n_slots,)`` (0 for padding; with a leading k axis for a stack), and the mask of real slots."""
        parts = self.split(observation)
        real = parts.mask > 0.5
        errors = parts.edge_errors[..., 0] if self.formation_kind == "distance" else parts.edge_errors
        lengths = edge_length_errors(self.formation_kind, parts.desired[..., 0], errors)
        return np.where(real, lengths, 0.0), real

    def split(self, observation: np.ndarray) -> ObservationParts:
        """Parts of one observation (size,), or of a stack of observations (k, size) with a leading k axis."""
        observation = np.asarray(observation, dtype=np.float64)
        if observation.ndim not in (1, 2) or observation.shape[-1] != self.size:
            raise ValueError(f"observation: expected shape ({self.size},) or (k, {self.size}), got {observation.shape}")
        m, w, n = self.dim, self.error_width, self.n_joints
        lead = observation.shape[:-1]
        joints = self.n_slots * self.slot_size
        slots = observation[..., :joints].reshape(*lead, self.n_slots, self.slot_size)
        reference = {}
        if self.reference_size:
            block = observation[..., joints + 2 * n:]
            reference = {"reference_centroid": block[..., :m], "reference_velocity": block[..., m:2 * m],
                         "reference_angular_velocity": block[..., 2 * m:]}
        return ObservationParts(
            mask=slots[..., 0],
            relative_positions=slots[..., 1:1 + m],
            desired=slots[..., 1 + m:1 + m + w],
            edge_errors=slots[..., 1 + m + w:],
            q=observation[..., joints:joints + n],
            dq=observation[..., joints + n:joints + 2 * n],
            **reference,
        )


class ObservationBuilder:
    """Every agent's layout, space and observation for one task, built in one gather per step.

    Per step, the real neighbour slots of all agents (agent by agent; padding slots are never computed) get
    their z_ij and edge errors in their agent's base frame (:meth:`slots_in_own_frames`); then all agents'
    observations are gathered by one index from one source vector
    ``[0, 1, desired (S w), z (S m), e (S w), q_observed (T), dq (T)]`` (S real slots, T joints) and clipped
    into the spaces' bounds (:meth:`observation_matrix`). With a ``reference``
    (:class:`~ee_formation_env.manoeuvre.ReferenceMotion`), its per-agent blocks (N r') follow at the end of
    the source and each agent's block ends its observation.
    """

    def __init__(self, task: FormationTask, max_joint_velocity: float, bounds: tuple[float, float] | None = None,
                 reference: Any = None, n_slots: int | None = None):
        """``bounds``: (|z| bound, end-effector coordinate bound), m, for spaces that must hold over many
        tasks (a scenario distribution's draws); default: this task's own (module docstring). ``n_slots``: the
        neighbour slots per agent (the scenario's ``neighbour_slots``), at least the graph's largest degree;
        default that degree."""
        formation, graph = task.formation, task.graph
        if n_slots is not None and n_slots < graph.max_degree:
            raise ValueError(f"neighbour_slots: expected at least the graph's largest degree {graph.max_degree}, "
                             f"got {n_slots}")
        m, w = task.dim, formation.error_width
        n_slots = graph.max_degree if n_slots is None else int(n_slots)
        self.kind = formation.kind
        self.reference = reference
        reference_size = 0 if reference is None else reference.size
        self.layouts = [ObservationLayout(n_slots, m, w, model.n_joints, reference_size) for model in task.models]
        self.spaces, self.state_space = _spaces(task, self.layouts, max_joint_velocity, bounds, reference)

        neighbors = graph.neighbors
        degrees = [len(slots) for slots in neighbors]
        slot_bounds = np.concatenate([[0], np.cumsum(degrees)]).astype(np.intp)
        slot_agent = np.array([i for i, slots in enumerate(neighbors) for _ in slots], dtype=np.intp)
        self.slot_edge = np.array([n.edge for slots in neighbors for n in slots], dtype=np.intp)
        self.slot_starts = slot_bounds[:-1]  # for np.add.reduceat over slot vectors
        self.slot_degrees = np.asarray(degrees, dtype=np.float64)
        self.slot_slices = [slice(int(a), int(b)) for a, b in zip(slot_bounds[:-1], slot_bounds[1:])]
        # Every real slot's row in the (N * D) padded slot table; agent i's mask of real slots (read-only).
        self._padded_rows = np.array([i * n_slots + k for i, d in enumerate(degrees) for k in range(d)], dtype=np.intp)
        self.slot_masks = [np.arange(n_slots) < d for d in degrees]
        for mask in self.slot_masks:
            mask.flags.writeable = False
        self._padded_shape = (len(degrees), n_slots) if w == 1 else (len(degrees), n_slots, w)
        self._slot_sign = np.array([[float(n.sign)] for slots in neighbors for n in slots])  # (S, 1)
        self._slot_rotation = task.base_rotations[slot_agent][:, :m, :m]  # row-vector @ R: world -> own base

        # The desired relations in each agent's own frame are constants.
        desired = []
        for i, slots in enumerate(neighbors):
            edges = np.array([n.edge for n in slots], dtype=np.intp)
            if formation.kind == "distance":
                desired.append(formation.desired[edges])
            else:
                signs = np.array([n.sign for n in slots], dtype=np.float64)
                desired.append((signs[:, None] * formation.desired_vectors[edges]) @ task.base_rotations[i][:m, :m])
        self._constants = np.concatenate([[0.0, 1.0], *(d.ravel() for d in desired)])
        # Per real slot: its agent, and its desired relation as its edge error needs it (sensing.py).
        self.slot_agent = slot_agent
        stacked = np.concatenate(desired).astype(np.float64)
        self.slot_desired = stacked**2 if formation.kind == "distance" else stacked  # (S,) m^2 or (S, m) m

        joint_bounds = np.concatenate([[0], np.cumsum([layout.n_joints for layout in self.layouts])])
        n_real, n_total = int(slot_bounds[-1]), int(joint_bounds[-1])
        offset_desired, offset_z = 2, 2 + n_real * w
        offset_e = offset_z + n_real * m
        offset_q = offset_e + n_real * w
        offset_dq = offset_q + n_total
        gather, obs_bounds = [], [0]
        for i, layout in enumerate(self.layouts):
            for k in range(n_slots):
                if k < degrees[i]:
                    r = int(slot_bounds[i]) + k
                    gather += [1, *range(offset_z + r * m, offset_z + (r + 1) * m),
                               *range(offset_desired + r * w, offset_desired + (r + 1) * w),
                               *range(offset_e + r * w, offset_e + (r + 1) * w)]
                else:
                    gather += [0] * layout.slot_size
            gather += [*range(offset_q + joint_bounds[i], offset_q + joint_bounds[i + 1]),
                       *range(offset_dq + joint_bounds[i], offset_dq + joint_bounds[i + 1])]
            if reference_size:
                offset_reference = offset_dq + n_total
                gather += range(offset_reference + i * reference_size, offset_reference + (i + 1) * reference_size)
            obs_bounds.append(len(gather))
        self._gather = np.array(gather, dtype=np.intp)
        self._obs_slices = [slice(a, b) for a, b in zip(obs_bounds[:-1], obs_bounds[1:])]
        self._low = np.concatenate([space.low for space in self.spaces]).astype(np.float64)
        self._high = np.concatenate([space.high for space in self.spaces]).astype(np.float64)
        self._state_low = self.state_space.low
        self._state_high = self.state_space.high

    def slots_in_own_frames(self, z: np.ndarray, edge_errors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every real slot's z_ij (S, m) and edge error ((S,) or (S, m)), each in its agent's base frame,
        from the world-frame edge vectors z_k (E, m) and edge errors. Leading axes (K copies: z (K, E, m))
        carry over."""
        z_slots = self._slot_sign * z[..., self.slot_edge, :]  # z_ij = x_i - x_j, world frame
        if self.kind == "distance":
            return (z_slots[..., None, :] @ self._slot_rotation)[..., 0, :], edge_errors[..., self.slot_edge]
        errors = self._slot_sign * edge_errors[..., self.slot_edge, :]
        rotated = np.stack([z_slots, errors], axis=-2) @ self._slot_rotation
        return rotated[..., 0, :], rotated[..., 1, :]

    def padded_slot_errors(self, slot_errors: np.ndarray) -> np.ndarray:
        """The slots' edge errors padded with zeros to the graph's largest degree: (N, D) for distance,
        (N, D, m) for displacement formations; row i is agent i's (its real slots first). Leading axes of
        ``slot_errors`` ((K, S) or (K, S, m)) carry over."""
        w = len(self._padded_shape) - 2  # 0 (distance) or 1 (displacement): trailing axes per slot
        lead = slot_errors.shape[:slot_errors.ndim - 1 - w]
        padded = np.zeros((*lead, *self._padded_shape))
        n_rows = self._padded_shape[0] * self._padded_shape[1]
        if w:
            padded.reshape(*lead, n_rows, self._padded_shape[2])[..., self._padded_rows, :] = slot_errors
        else:
            padded.reshape(*lead, n_rows)[..., self._padded_rows] = slot_errors
        return padded

    def observation_matrix(self, slot_z: np.ndarray, slot_errors: np.ndarray, q_observed: np.ndarray,
                           dq: np.ndarray, reference: np.ndarray | None = None) -> np.ndarray:
        """Every agent's observation (float32, clipped into its space), concatenated in agent order: (O,), or
        (K, O) from K copies' stacked arrays (slot_z (K, S, m), slot_errors, q_observed and dq (K, T)).
        Agent i's part is ``observation_slices[i]``. ``reference``: the manoeuvre's blocks (N r') or (K, N r')
        (:meth:`~ee_formation_env.manoeuvre.ReferenceMotion.observation_block`), required with one."""
        lead = q_observed.shape[:-1]
        # np.broadcast_to costs more than the rest of a one-copy call: only with a copy axis.
        constants = np.broadcast_to(self._constants, (*lead, len(self._constants))) if lead else self._constants
        parts = [constants, slot_z.reshape(*lead, -1), slot_errors.reshape(*lead, -1), q_observed, dq]
        if (reference is None) != (self.reference is None):
            raise ValueError("reference: expected the manoeuvre's reference blocks exactly when the task has one")
        if reference is not None:
            parts.append(reference.reshape(*lead, -1))
        source = np.concatenate(parts, axis=-1)
        observation = source[..., self._gather]
        np.minimum(np.maximum(observation, self._low, out=observation), self._high, out=observation)  # clip
        return observation.astype(np.float32)

    @property
    def observation_slices(self) -> list[slice]:
        """Each agent's slice of :meth:`observation_matrix`'s last axis."""
        return self._obs_slices

    def state(self, ee_world: np.ndarray, q_observed: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """The global state: all end-effector positions (world, formation axes, m), all q, all dq (leading
        axes, e.g. K copies, carry over: (K, state_dim))."""
        lead = q_observed.shape[:-1]
        state = np.concatenate([ee_world[..., :self.layouts[0].dim].reshape(*lead, -1), q_observed, dq], axis=-1)
        return np.clip(state, self._state_low, self._state_high).astype(np.float32)


def _spaces(task: FormationTask, layouts: list[ObservationLayout], max_joint_velocity: float,
            bounds: tuple[float, float] | None = None, reference: Any = None
            ) -> tuple[list[gymnasium.spaces.Box], gymnasium.spaces.Box]:
    """Each agent's observation space and the state space, with finite bounds (module docstring)."""
    formation, m = task.formation, task.dim
    bases = task.base_positions
    # One bound on |z_ij| for every agent (the largest base distance plus reaches over all edges), so
    # that identical arms get identical spaces and can share one policy.
    if bounds is not None:
        z_bound = bounds[0]
    else:
        z_bound = max(float(np.max(np.abs(formation.desired))), max(
            float(np.linalg.norm(bases[tail] - bases[head])) + task.reaches[tail] + task.reaches[head]
            for tail, head in task.graph.edges))
    if formation.kind == "distance":
        desired_low, desired_high, error_bound = 0.0, z_bound, z_bound**2
    else:
        desired_low, desired_high, error_bound = -z_bound, z_bound, 2 * z_bound
    w = formation.error_width
    slot_low = np.concatenate([[0.0], np.full(m, -z_bound), np.full(w, desired_low), np.full(w, -error_bound)])
    slot_high = np.concatenate([[1.0], np.full(m, z_bound), np.full(w, desired_high), np.full(w, error_bound)])
    spaces, q_lows, q_highs, speeds = [], [], [], []
    for layout, model in zip(layouts, task.models):
        q_lows.append(np.where(model.continuous, -math.pi, model.lower))
        q_highs.append(np.where(model.continuous, math.pi, model.upper))
        speeds.append(np.full(model.n_joints, max_joint_velocity))
        extra = () if reference is None else (reference.bound,)  # one bound for every agent (module docstring)
        low = np.concatenate([np.tile(slot_low, layout.n_slots), q_lows[-1], -speeds[-1],
                              *(-b for b in extra)]).astype(np.float32)
        high = np.concatenate([np.tile(slot_high, layout.n_slots), q_highs[-1], speeds[-1], *extra]).astype(np.float32)
        spaces.append(gymnasium.spaces.Box(low, high, dtype=np.float32))

    ee_bound = max(float(np.max(np.abs(bases[:, :m]))) + max(task.reaches), 1.0) if bounds is None else bounds[1]
    n_ee = task.n_agents * m
    state_low = np.concatenate([np.full(n_ee, -ee_bound), *q_lows, *(-v for v in speeds)]).astype(np.float32)
    state_high = np.concatenate([np.full(n_ee, ee_bound), *q_highs, *speeds]).astype(np.float32)
    return spaces, gymnasium.spaces.Box(state_low, state_high, dtype=np.float32)
