"""The env's infos in their three forms, made here from the env's values: stacked arrays of K copies (the array
API's), agent -> dict of (K, ...) arrays (the batched dict API's) and agent -> dict of one copy's values (the
parallel env's). The keys and their meaning: ``docs/spaces.md``."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from ee_formation_env.formation import formation_errors_from_squares

if TYPE_CHECKING:
    from ee_formation_env.measurement import Measurement

# Info keys with one value per agent (K, N, ...) in the array API; the others are per copy (K,).
PER_AGENT_INFO = ("edge_errors", "edge_mask", "singularity_margin", "torque_saturation", "clipped_actions",
                  "contacts")
PER_COPY_INFO = ("formation_error", "physics_fault", "physics_fault_reason", "sim_time")


def stacked_infos(measured: Measurement, edge_errors: np.ndarray, edge_masks: np.ndarray, saturations: np.ndarray,
                  torques: np.ndarray, clipped_so_far: np.ndarray, contacts: np.ndarray, sim_times: np.ndarray
                  ) -> dict[str, np.ndarray]:
    """The infos of every (copy, agent) as stacked arrays (the array API's form), none shared with the env: from
    the measurement, the padded slot errors (K, N, D[, m]), the edge masks (K, N, D), the fractions of joints
    clipped (K, N), the torques (K, T) N m, the clipped counts so far (K, N), the contacts (K, N), the times (K,) s."""
    return {
        "formation_error": formation_errors_from_squares(measured.edge_squares),
        "edge_errors": edge_errors,
        "edge_mask": edge_masks.copy(),  # fresh each call (the masks themselves are read-only)
        "singularity_margin": measured.singularity_margins,
        "torque_saturation": saturations,
        "applied_torque": torques,
        "clipped_actions": clipped_so_far.copy(),  # the next step reads it
        "contacts": contacts,
        "physics_fault": measured.fault.copy(),
        "physics_fault_reason": np.array(measured.fault_reason, dtype=object),
        "sim_time": sim_times,
    }


def copies_info_dicts(infos: dict[str, np.ndarray], agents: Sequence[str], joint_slices: Sequence[slice],
                      observation_slices: Sequence[slice]) -> dict[str, dict[str, np.ndarray]]:
    """agent -> dict of (K, ...) arrays, from the stacked infos (agent i's joints and observation part:
    ``joint_slices[i]``, ``observation_slices[i]``)."""
    per_agent = {key: infos[key].swapaxes(0, 1) for key in PER_AGENT_INFO}  # agent-major views
    result = {}
    for i, (agent, joints, part) in enumerate(zip(agents, joint_slices, observation_slices)):
        info = {key: values[i] for key, values in per_agent.items()}
        info["applied_torque"] = infos["applied_torque"][:, joints]
        if "final_observation" in infos:
            info["final_observation"] = infos["final_observation"][:, part]
        for key in PER_COPY_INFO:
            info[key] = infos[key].copy() if i else infos[key]
        result[agent] = info
    return result


def one_copy_info_dicts(agents: Sequence[str], joint_slices: Sequence[slice], formation_error: float,
                        sim_time: float, physics_fault: int, edge_errors: np.ndarray, edge_masks: np.ndarray,
                        margins: list[float], saturations: list[float], torques: np.ndarray,
                        clipped_so_far: list[int], contacts: list[int]) -> dict[str, dict[str, Any]]:
    """agent -> its info dict of one copy (the parallel env's form), from that copy's values: the per-copy ones
    as Python numbers; per agent, row i of ``edge_errors`` and ``edge_masks`` (views of arrays made for this
    step only), entry i of the lists, and ``torques[joint_slices[i]]`` (T,), N m."""
    return {agent: {"formation_error": formation_error, "edge_errors": errors, "edge_mask": mask,
                    "singularity_margin": margin, "torque_saturation": saturation, "applied_torque": torques[joints],
                    "clipped_actions": clipped, "contacts": touching, "physics_fault": physics_fault,
                    "sim_time": sim_time}
            for agent, joints, errors, mask, margin, saturation, clipped, touching
            in zip(agents, joint_slices, edge_errors, edge_masks, margins, saturations, clipped_so_far, contacts)}
