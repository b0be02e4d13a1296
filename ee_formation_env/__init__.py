"""ee-formation-env: distributed formation control of manipulator end-effectors as a PettingZoo env.

Quick use::

    import ee_formation_env
    env = ee_formation_env.parallel_env("planar_square")          # or pettingzoo.make("parallel", "ee_formation/planar_square-v0")
    observations, infos = env.reset(seed=0)

Registered ids: PettingZoo ``ee_formation/<scenario>-v0`` for every built-in scenario; Gymnasium
(centralized, one joint observation and action) ``EEFormation/PlanarSquare-v0`` and
``EEFormation/SpatialTetrahedron-v0`` (plus the other built-ins in CamelCase).
"""

from __future__ import annotations

from typing import Any

from ee_formation_env.env import FormationEnv
from ee_formation_env.scenario import BUILTIN_SCENARIOS, ROBOTS, Scenario, load_scenario

__all__ = ["FormationEnv", "Scenario", "load_scenario", "parallel_env", "env", "raw_env",
           "BUILTIN_SCENARIOS", "ROBOTS", "__version__"]
__version__ = "0.1.0"


def parallel_env(scenario: Any = "planar_square", render_mode: str | None = None, **overrides: Any) -> FormationEnv:
    """Build the parallel env from a built-in name, a YAML/JSON path or a dict, plus key overrides."""
    return FormationEnv(scenario, render_mode=render_mode, **overrides)


def raw_env(scenario: Any = "planar_square", render_mode: str | None = None, **overrides: Any):
    """The AEC form of the env (PettingZoo's ``parallel_to_aec`` conversion)."""
    from pettingzoo.utils.conversions import parallel_to_aec

    return parallel_to_aec(parallel_env(scenario, render_mode=render_mode, **overrides))


def env(scenario: Any = "planar_square", render_mode: str | None = None, **overrides: Any):
    """The AEC env wrapped with PettingZoo's order-enforcing wrapper (the classic ``env()`` entry)."""
    from pettingzoo.utils import wrappers

    return wrappers.OrderEnforcingWrapper(raw_env(scenario, render_mode=render_mode, **overrides))


from ee_formation_env import registration as _registration  # noqa: E402  (registers the ids)

_registration.register_all()
