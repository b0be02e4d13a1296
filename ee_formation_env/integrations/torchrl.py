"""TorchRL and BenchMARL support (the ``torchrl`` extra): the env as a TorchRL ``PettingZooWrapper``.

    from ee_formation_env.integrations.torchrl import make_torchrl_env
    env = make_torchrl_env("planar_square")          # groups: {"planar_2link": ["arm_0", ..., "arm_3"]}
    rollout = env.rollout(100)                       # rollout["planar_2link", "observation"]: (100, 4, 19)

**Groups.** TorchRL stacks the tensors of the agents of one group, so a group's agents need identical
observation and action spaces. :func:`group_map` puts agents with identical spaces in one group, named
after their robot (``planar_2link``, or a URDF's robot name such as ``lbr_iiwa`` and ``panda``): one group for the built-in scenarios, one per
robot kind for mixed teams (e.g. an ``lbr_iiwa`` group of KUKA arms and a ``panda`` group of Franka
arms: both have 7 joints, but different joint limits and so different observation bounds). Pass
``group_map=MarlGroupMapType.ONE_GROUP_PER_AGENT`` for one group per arm (no stacking at all).
TorchRL's default, grouping by the name before the last ``_`` (every agent is ``arm_<i>``), puts mixed
robots in one group and fails to stack their actions.

Every info entry is numeric and fixed-shape per agent, so TorchRL builds specs from it.
"""

from __future__ import annotations

from typing import Any
from xml.etree import ElementTree

from torchrl.envs.libs.pettingzoo import PettingZooWrapper
from torchrl.envs.utils import MarlGroupMapType

import ee_formation_env
from ee_formation_env.env import FormationEnv


def robot_name(env: FormationEnv, index: int) -> str:
    """The robot of arm ``index``: its built-in name, else the ``<robot name=...>`` of its URDF."""
    arm = env.scenario.arms[index]
    if arm.robot:
        return arm.robot
    return ElementTree.parse(arm.urdf).getroot().get("name") or f"robot_{index}"


def group_map(env: FormationEnv) -> dict[str, list[str]]:
    """Agents with identical observation and action spaces share a group, named after their robot
    (with a numeric suffix if one robot has arms with different spaces)."""
    groups: dict[str, list[str]] = {}
    signatures: dict[str, tuple[Any, Any]] = {}
    for i, agent in enumerate(env.possible_agents):
        signature = (env.observation_space(agent), env.action_space(agent))
        base = robot_name(env, i)
        name, suffix = base, 1
        while name in signatures and signatures[name] != signature:
            suffix += 1
            name = f"{base}_{suffix}"
        signatures[name] = signature
        groups.setdefault(name, []).append(agent)
    return groups


def make_torchrl_env(scenario: Any = "planar_square", group_map_type: MarlGroupMapType | dict | None = None,
                     return_state: bool = True, seed: int | None = None, device: Any = "cpu",
                     **overrides: Any) -> PettingZooWrapper:
    """The formation env (built-in name, file or dict ``scenario``, with scenario ``overrides``) as a TorchRL
    env. ``group_map_type``: None for :func:`group_map`, a ``MarlGroupMapType`` or an explicit dict.
    ``return_state``: include ``env.state()`` as ``"state"`` (for centralized critics, e.g. MAPPO)."""
    env = ee_formation_env.parallel_env(scenario, **overrides)
    groups = group_map(env) if group_map_type is None else group_map_type
    return PettingZooWrapper(env, group_map=groups, return_state=return_state, use_mask=False,
                             categorical_actions=False, seed=seed, device=device)
