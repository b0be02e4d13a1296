"""Registration of the built-in scenarios in PettingZoo's and Gymnasium's registries.

Every name in :data:`ee_formation_env.builtin.BUILTIN_SCENARIOS` (one YAML file each, see ``docs/scenarios.md``)
gets both ids; nothing here lists scenarios by hand.
"""

from __future__ import annotations

import gymnasium
import pettingzoo

from ee_formation_env.builtin import BUILTIN_SCENARIOS
from ee_formation_env.scenario import load_scenario

PETTINGZOO_NAMESPACE = "ee_formation"
GYMNASIUM_NAMESPACE = "EEFormation"


def gymnasium_id(scenario: str) -> str:
    """``planar_square`` -> ``EEFormation/PlanarSquare-v0``."""
    return f"{GYMNASIUM_NAMESPACE}/{''.join(part.capitalize() for part in scenario.split('_'))}-v0"


def pettingzoo_id(scenario: str) -> str:
    """``planar_square`` -> ``ee_formation/planar_square-v0``."""
    return f"{PETTINGZOO_NAMESPACE}/{scenario}-v0"


def register_all() -> None:
    """Register every built-in scenario (idempotent)."""
    for name in BUILTIN_SCENARIOS:
        if pettingzoo_id(name) not in pettingzoo.parallel_registry:
            pettingzoo.register("parallel", pettingzoo_id(name), entry_point="ee_formation_env:parallel_env",
                                kwargs={"scenario": name})
        if gymnasium_id(name) not in gymnasium.registry:
            # max_episode_steps: the built-in episode length in env steps (the env truncates there too);
            # gymnasium.make(..., episode_seconds=T) with a longer T also needs max_episode_steps.
            # vector_entry_point: gymnasium.make_vec(id, num_envs=K, vectorization_mode="vector_entry_point")
            # gives K copies over the batched env (ee_formation_env.vector) in one VectorEnv.
            gymnasium.register(gymnasium_id(name), entry_point="ee_formation_env.integrations.centralized:CentralizedFormationEnv",
                               vector_entry_point="ee_formation_env.integrations.centralized:CentralizedFormationVectorEnv",
                               kwargs={"scenario": name}, max_episode_steps=load_scenario(name).max_steps)
