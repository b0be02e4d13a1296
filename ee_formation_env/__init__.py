"""ee-formation-env: distributed formation control of manipulator end-effectors as a PettingZoo env.

Quick use::

    import ee_formation_env
    env = ee_formation_env.parallel_env("planar_square")          # or pettingzoo.make("parallel", "ee_formation/planar_square-v0")
    observations, infos = env.reset(seed=0)
    batched = ee_formation_env.vector_env("planar_square", num_envs=16)  # 16 copies, one step call

Registered ids: PettingZoo ``ee_formation/<scenario>-v0`` for every built-in scenario; Gymnasium
(centralized, one joint observation and action) ``EEFormation/PlanarSquare-v0`` and
``EEFormation/SpatialTetrahedron-v0`` (plus the other built-ins in CamelCase). The built-ins are the YAML
files in ``ee_formation_env/builtin/`` (:data:`BUILTIN_SCENARIOS`); the scenario format is documented in
``docs/scenarios.md``.
"""

from __future__ import annotations

from typing import Any

from ee_formation_env.pybullet_banner import import_pybullet_quietly

import_pybullet_quietly()  # the process's first import of PyBullet, without its build-time banner on stdout

from ee_formation_env.env import FormationEnv  # noqa: E402 (after the quiet import)
from ee_formation_env.builtin import BUILTIN_SCENARIOS  # noqa: E402
from ee_formation_env.robots import ROBOTS  # noqa: E402
from ee_formation_env.scenario import Scenario, load_scenario  # noqa: E402

__all__ = ["FormationEnv", "Scenario", "load_scenario", "validate_scenario", "parallel_env", "vector_env", "env",
           "raw_env", "team_parallel_env", "team_vector_env", "BUILTIN_SCENARIOS", "ROBOTS", "__version__"]
__version__ = "0.1.0"


def _with_max_cycles(scenario: Any, max_cycles: int | None, overrides: dict[str, Any]) -> dict[str, Any]:
    """``overrides`` plus the ``episode_seconds`` that truncates the episode after ``max_cycles`` env steps."""
    if max_cycles is None:
        return overrides
    if isinstance(max_cycles, bool) or not isinstance(max_cycles, int) or max_cycles < 1:
        raise ValueError(f"max_cycles: expected an integer >= 1 (env steps per episode), got {max_cycles!r}")
    if "episode_seconds" in overrides:
        raise ValueError("max_cycles: give either max_cycles (env steps) or episode_seconds (s), not both")
    control_dt = load_scenario(scenario, **overrides).control_dt
    return {**overrides, "episode_seconds": max_cycles * control_dt}


def parallel_env(scenario: Any = "planar_square", render_mode: str | None = None, max_cycles: int | None = None,
                 **overrides: Any) -> FormationEnv:
    """Build the parallel env from a built-in name, a YAML/JSON path or a dict, plus key overrides.

    ``max_cycles`` (PettingZoo's name): truncate episodes after this many env steps, i.e. set
    ``episode_seconds = max_cycles * control_dt``.
    """
    return FormationEnv(scenario, render_mode=render_mode, **_with_max_cycles(scenario, max_cycles, overrides))


def validate_scenario(scenario: Any = "planar_square", **overrides: Any) -> Scenario:
    """Run every check :func:`parallel_env` runs on ``scenario`` plus ``overrides`` and return the parsed scenario;
    ``ValueError``/``TypeError`` naming the field on the first failure (``ee-formation validate SCENARIO``).

    The checks: the format (:func:`load_scenario`), the geometry (:mod:`ee_formation_env.validation`, run by
    :func:`ee_formation_env.task.build_task`), the arms' start contacts, and for a distribution its first draw
    (:func:`ee_formation_env.generators.first_draw`). Contacts are a PyBullet collision query, so one headless
    client loads the arms; no physics step runs, and the client is closed before returning.
    """
    from ee_formation_env.generators import first_draw
    from ee_formation_env.robot import build_world
    from ee_formation_env.task import build_task

    parsed = load_scenario(scenario, **overrides)
    world, arm_set = build_world(build_task(parsed))
    try:
        if parsed.distribution.active:
            first_draw(parsed, arm_set)
    finally:
        world.close()
    return parsed


def vector_env(scenario: Any = "planar_square", num_envs: int = 1, max_cycles: int | None = None,
               **overrides: Any):
    """The batched env: ``num_envs`` copies of the scenario stepped by one call, observations agent ->
    ``(num_envs, obs_dim)`` (:class:`ee_formation_env.vector.VectorFormationEnv`; its module docstring
    documents conventions, spaces, autoreset and layout). ``max_cycles`` and ``overrides`` as in
    :func:`parallel_env`."""
    from ee_formation_env.vector import VectorFormationEnv

    return VectorFormationEnv(scenario, num_envs=num_envs, **_with_max_cycles(scenario, max_cycles, overrides))


def team_parallel_env(family: str = "planar_team", team_sizes: Any = None, render_mode: str | None = None,
                      max_cycles: int | None = None, **overrides: Any):
    """The parallel env of a team-size family whose team size is drawn at every reset (``planar_team``: 3-8
    arms, ``spatial_team``: 3-6): ``possible_agents`` the largest team's, ``agents`` this episode's
    (:class:`ee_formation_env.team_env.TeamParallelEnv`). ``max_cycles`` and ``overrides`` as in
    :func:`parallel_env`, applied to every team size."""
    from ee_formation_env.team_env import TeamParallelEnv, check_team_sizes
    from ee_formation_env.team_families import team_scenario

    sizes = check_team_sizes(family, team_sizes)
    return TeamParallelEnv(family, team_sizes=sizes, render_mode=render_mode,
                           **_with_max_cycles(team_scenario(family, sizes[0]), max_cycles, overrides))


def team_vector_env(family: str = "planar_team", num_envs: int = 1, team_sizes: Any = None,
                    max_cycles: int | None = None, **overrides: Any):
    """K copies of a team-size family, each drawing its team size at every reset, padded to the largest team
    with an agent mask (:class:`ee_formation_env.team_env.TeamVectorEnv`); arguments as
    :func:`team_parallel_env`'s."""
    from ee_formation_env.team_env import TeamVectorEnv, check_team_sizes
    from ee_formation_env.team_families import team_scenario

    sizes = check_team_sizes(family, team_sizes)
    return TeamVectorEnv(family, num_envs=num_envs, team_sizes=sizes,
                         **_with_max_cycles(team_scenario(family, sizes[0]), max_cycles, overrides))


def raw_env(scenario: Any = "planar_square", render_mode: str | None = None, max_cycles: int | None = None,
            **overrides: Any):
    """The AEC form of the env (PettingZoo's ``parallel_to_aec`` conversion, order-enforced as it does), whose
    ``step`` checks each agent's action when it is given (:class:`ee_formation_env.aec.FormationAECEnv`)."""
    from pettingzoo.utils.wrappers import OrderEnforcingWrapper

    from ee_formation_env.aec import FormationAECEnv

    return OrderEnforcingWrapper(FormationAECEnv(parallel_env(scenario, render_mode=render_mode,
                                                              max_cycles=max_cycles, **overrides)))


def env(scenario: Any = "planar_square", render_mode: str | None = None, max_cycles: int | None = None,
        **overrides: Any):
    """The AEC env wrapped with PettingZoo's order-enforcing wrapper (the classic ``env()`` entry)."""
    from pettingzoo.utils import wrappers

    return wrappers.OrderEnforcingWrapper(raw_env(scenario, render_mode=render_mode, max_cycles=max_cycles,
                                                  **overrides))


from ee_formation_env import registration as _registration  # noqa: E402  (registers the ids)

_registration.register_all()
