"""The env's infos in their three forms: stacked arrays of K copies (the array API's, made by the batched env),
agent -> dict of (K, ...) arrays (the batched dict API's) and agent -> dict of one copy's values (the parallel
env's). The keys and their meaning: ``docs/spaces.md``."""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

# Info keys with one value per agent (K, N, ...) in the array API; the others are per copy (K,).
PER_AGENT_INFO = ("edge_errors", "edge_mask", "singularity_margin", "torque_saturation", "clipped_actions",
                  "contacts")
PER_COPY_INFO = ("formation_error", "physics_fault", "physics_fault_reason", "sim_time")


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


def one_copy_info_dicts(infos: dict[str, np.ndarray], agents: Sequence[str], joint_slices: Sequence[slice]
                        ) -> dict[str, dict[str, Any]]:
    """agent -> its info dict, from the stacked infos of one copy (K = 1): numbers as Python numbers, arrays
    as views of arrays made for this step only, one disjoint slice per agent."""
    # One numpy call per entry (``item``, ``tolist`` of the whole (1, N) array): this runs every step.
    formation_error, sim_time = infos["formation_error"].item(), infos["sim_time"].item()
    fault = infos["physics_fault"].item()
    (margins,), (saturation,) = infos["singularity_margin"].tolist(), infos["torque_saturation"].tolist()
    (clipped_so_far,), (contacts,) = infos["clipped_actions"].tolist(), infos["contacts"].tolist()
    (errors,), (masks,), (torques,) = infos["edge_errors"], infos["edge_mask"], infos["applied_torque"]
    result = {}
    for i, (agent, joints) in enumerate(zip(agents, joint_slices)):
        result[agent] = {
            "formation_error": formation_error,
            "edge_errors": errors[i],
            "edge_mask": masks[i],
            "singularity_margin": margins[i],
            "torque_saturation": saturation[i],
            "applied_torque": torques[joints],
            "clipped_actions": clipped_so_far[i],
            "contacts": contacts[i],
            "physics_fault": fault,
            "sim_time": sim_time,
        }
    return result
