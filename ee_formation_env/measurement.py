"""What the env reads off its worlds and derives from it, for K copies at once: one :class:`Measurement`.

Every function here takes K copies' stacked arrays ((K, T) joints, (K, E) edges) and returns results with the
same leading axis; the parallel env is the K = 1 case (:mod:`ee_formation_env.env`).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ee_formation_env.observation import ObservationBuilder
from ee_formation_env.reward import agent_error_ratios, rewards_from_ratios
from ee_formation_env.engines.pybullet_engine import PYBULLET_MAX_JOINT_VELOCITY

# ``info["physics_fault"]`` codes (0: none). The last fault's full reason (arm, speed) is ``env.physics_fault_reason``.
PHYSICS_FAULTS: dict[int, str] = {0: "none", 1: "non-finite joint state", 2: "joint speed above max_joint_velocity"}


@dataclass(frozen=True, slots=True)
class Measurement:
    """What the env measured at the last reset or step of K copies (world frame unless said otherwise)."""

    q: np.ndarray  # (K, T) every arm's joint positions, flat, rad (unwrapped)
    dq: np.ndarray  # (K, T) rad/s
    q_observed: np.ndarray  # (K, T) q with continuous joints wrapped to [-pi, pi), rad
    ee_world: np.ndarray  # (K, N, 3) end-effector positions, m
    edge_errors: np.ndarray  # (K, E) m^2 (distance) or (K, E, dim) m (displacement)
    edge_squares: np.ndarray  # (K, E) |e_k|^2
    slot_z: np.ndarray  # (K, S, dim) every real neighbour slot's z_ij in its agent's base frame, m
    slot_errors: np.ndarray  # (K, S) or (K, S, dim) the slots' edge errors in their agents' base frames
    singularity_margins: np.ndarray  # (K, N) m
    fault: np.ndarray  # (K,) PHYSICS_FAULTS codes, 0 if none
    fault_reason: np.ndarray  # (K,) object: "" or why the copy's episode must end

    def with_rows(self, rows: np.ndarray, part: "Measurement") -> "Measurement":
        """This measurement with the copies ``rows`` replaced by ``part``'s (fresh arrays; this one is unchanged)."""
        values = {}
        for name in Measurement.__slots__:
            array = np.array(getattr(self, name), dtype=object if name == "fault_reason" else None)
            array[rows] = getattr(part, name)
            values[name] = array
        return Measurement(**values)

    @staticmethod
    def stacked(parts: list["Measurement"]) -> "Measurement":
        """One measurement of the copies of ``parts`` (each of one copy, K = 1), in order."""
        return Measurement(**{name: np.concatenate([getattr(part, name) for part in parts])
                              for name in Measurement.__slots__})


def physics_faults(q: np.ndarray, dq: np.ndarray, joint_slices: list[slice], limit: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Each copy's fault (K,) codes and (K,) reasons: a non-finite state, or a joint speed over ``limit`` =
    ``max_joint_velocity`` (rad/s), the first faulty arm's; ``q`` and ``dq`` (K, T) get their non-finite values
    replaced by finite ones in place."""
    count = q.shape[0]
    # One test for both faults: NaN fails the comparison, and a non-finite q makes its sum non-finite.
    if np.abs(dq).max() <= limit and math.isfinite(q.sum()):
        return _no_faults(count)
    faults = np.zeros(count, dtype=np.int64)
    reasons = np.full(count, "", dtype=object)
    healthy = (np.abs(dq).max(axis=1) <= limit) & np.isfinite(q.sum(axis=1))
    for r in np.flatnonzero(~healthy):
        faults[r], reasons[r] = _first_fault(q[r], dq[r], joint_slices, limit)
        q[r], dq[r] = np.nan_to_num(q[r]), np.nan_to_num(dq[r])
    return faults, reasons


@functools.lru_cache(maxsize=8)
def _no_faults(count: int) -> tuple[np.ndarray, np.ndarray]:
    """(count,) fault codes 0 and reasons "", read-only: shared by every healthy step (the hot path)."""
    faults, reasons = np.zeros(count, dtype=np.int64), np.full(count, "", dtype=object)
    faults.flags.writeable = reasons.flags.writeable = False
    return faults, reasons


def _first_fault(q: np.ndarray, dq: np.ndarray, joint_slices: list[slice], limit: float) -> tuple[int, str]:
    for i, joints in enumerate(joint_slices):
        if not (np.all(np.isfinite(q[joints])) and np.all(np.isfinite(dq[joints]))):
            return 1, f"arm_{i}: non-finite joint state"
        if np.max(np.abs(dq[joints])) > limit:
            speed = float(np.max(np.abs(dq[joints])))
            # At PyBullet's own clamp the true speed is unknown, only that it is at least that.
            shown = f"at least {speed:.0f}" if speed >= 0.999 * PYBULLET_MAX_JOINT_VELOCITY else f"{speed:.1f}"
            return 2, f"arm_{i}: joint speed {shown} rad/s exceeds max_joint_velocity {limit} rad/s"
    raise AssertionError("a copy flagged faulty has no fault")


def measure(task: Any, observer: ObservationBuilder, kinematics: Any, wrap: Any, q: np.ndarray, dq: np.ndarray,
            fault: np.ndarray, reason: np.ndarray, one_copy: bool = False) -> Measurement:
    """Everything derived from K copies' finite joint states ``q``, ``dq`` (K, T) of one ``task``.
    ``wrap``: None, True or a mask of the joints observed wrapped to [-pi, pi). ``one_copy``: ``q`` and ``dq``
    are one copy's (T,) (the arithmetic without the copy axis, which numpy runs faster), and the results get
    the K = 1 axis."""
    ee_base, margins = kinematics.positions_and_margins(q, task.dim)
    ee_world = (task.base_rotations @ ee_base[..., None])[..., 0] + task.base_positions
    if wrap is None:
        q_observed = q
    else:
        wrapped = (q + math.pi) % (2 * math.pi) - math.pi
        q_observed = wrapped if wrap is True else np.where(wrap, wrapped, q)
    z = task.graph.edge_vectors(ee_world[..., :task.dim])
    edge_errors = task.formation.edge_errors(z)
    errors = edge_errors.reshape(*q.shape[:-1], task.graph.n_edges, -1)
    slot_z, slot_errors = observer.slots_in_own_frames(z, edge_errors)
    edge_squares = np.add.reduce(errors * errors, axis=-1)
    if one_copy:
        return Measurement(q=q[None], dq=dq[None], q_observed=q_observed[None], ee_world=ee_world[None],
                           edge_errors=edge_errors[None], edge_squares=edge_squares[None], slot_z=slot_z[None],
                           slot_errors=slot_errors[None], singularity_margins=margins[None], fault=fault,
                           fault_reason=reason)
    return Measurement(q=q, dq=dq, q_observed=q_observed, ee_world=ee_world, edge_errors=edge_errors,
                       edge_squares=edge_squares, slot_z=slot_z,
                       slot_errors=slot_errors, singularity_margins=margins, fault=fault, fault_reason=reason)


def reward_array(edge_squares: np.ndarray, tolerances: np.ndarray, observer: ObservationBuilder,
                 config: Any, tracking_ratios: np.ndarray | None = None) -> np.ndarray:
    """Every agent's reward (K, N) from K copies' squared edge errors (K, E) (and the tracking term's ratios
    (K, N), or None: :func:`~ee_formation_env.reward.rewards_from_ratios`)."""
    ratios, within = agent_error_ratios(np.sqrt(edge_squares), tolerances, observer.slot_edge,
                                        observer.slot_starts, observer.slot_degrees)
    return rewards_from_ratios(ratios, within, config, tracking_ratios)
