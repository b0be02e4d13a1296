"""Team-size families: one scenario distribution per team size N, for policies that must serve any N.

Rule: ``team_scenario(family, n_agents)`` is the plain scenario data (with a ``distribution`` key) of family
``family`` at team size ``n_agents``; the team size is fixed per scenario (per env), every reset draws the
layout, the shape and the start as any distribution does (docs/scenarios.md, "Team-size families"):

- ``planar_team`` (N = 3..8): ``planar_2link`` arms (2 DOF), distance formation, ``dim = 2``. At N = 4 it is
  ``planar_random``'s distribution on the complete graph. The bases sit on a ring whose radius grows with N so
  that neighbouring bases stay as far apart as in ``planar_random`` (radius ``4 m x sin(pi / 4) / sin(pi / N)``,
  chord about 5.7 m), and never below planar_random's 4 m (on a smaller ring three arms crowd the centre);
  drawn within 0.5 m of it. The shape is a regular N-gon of circumradius ``R - (2.0 .. 2.8) m`` (R the mid
  radius), so every target vertex lies about 1.5-3.3 m from its own base before the stretch and turn (a draw
  beyond the reach less ``reach_margin``, 0.3 m, is redrawn), stretched and turned by at most
  planar_random's amounts, scaled down as the polygon grows (a turn moves a vertex by ``circumradius x
  angle``). Graph: the ring and its second-neighbour chords (:func:`ring_chord_edges`), globally rigid, so that
  a law has no flipped realization to settle in.
- ``spatial_team`` (N = 3..6): PERA-like 7-DOF arms, distance formation, ``dim = 3``, gravity on. At N = 4 it is
  ``spatial_random``'s distribution; the ring's radius range and the shared region above its centre grow by
  ``sin(pi / 4) / sin(pi / N)``. Graph: the complete graph.

Each draw is validated like every distribution draw (reach, rigidity, singularities, the margins, no start
contact). The fixed test draws of a family at N are its draws at the reset seeds
:data:`~ee_formation_env.scenario_sets.TEST_SEEDS` (:func:`team_test_draws`).
"""

from __future__ import annotations

import math
from typing import Any

from ee_formation_env.builtin import builtin_scenario
from ee_formation_env.inputs import excerpt

#: family -> (smallest, largest) team size it is defined for.
TEAM_FAMILIES: dict[str, tuple[int, int]] = {"planar_team": (3, 8), "spatial_team": (3, 6)}
#: family -> the 4-arm built-in distribution whose ranges it grows from.
TEAM_FAMILY_SOURCES = {"planar_team": "planar_random", "spatial_team": "spatial_random"}

_PLANAR_RING_RADIUS_AT_4 = 4.0  # m, mid ring radius of planar_random
_PLANAR_RING_HALF_WIDTH = 0.5  # m: the ring radius is drawn within this of its mid value
_PLANAR_VERTEX_INSET = (2.0, 2.8)  # m: circumradius = ring radius less this (planar_random: 4.0 - 1.6 +- 0.4)
_PLANAR_SHAPE_AT_4 = 1.6  # m, planar_random's mid circumradius: the turn and stretch are scaled to it
_SPATIAL_RING_AT_4 = (0.3, 0.42)  # m, spatial_random's ring radius range
_SPATIAL_REGION_AT_4 = 0.2  # m, spatial_random's region radius


def ring_growth(n_agents: int) -> float:
    """The factor by which a ring of 4 bases grows to keep its neighbour spacing with ``n_agents`` bases:
    ``sin(pi / 4) / sin(pi / N)`` (1 at N = 4)."""
    return math.sin(math.pi / 4) / math.sin(math.pi / n_agents)


def check_team_size(family: Any, n_agents: Any) -> None:
    """``ValueError`` naming ``family`` or ``n_agents`` unless the family is known and defined at that size."""
    if family not in TEAM_FAMILIES:
        raise ValueError(f"family: expected one of {list(TEAM_FAMILIES)}, got {excerpt(family)}")
    low, high = TEAM_FAMILIES[family]
    if isinstance(n_agents, bool) or not isinstance(n_agents, int) or not low <= n_agents <= high:
        raise ValueError(f"n_agents: {family} is defined for {low} to {high} arms, got {excerpt(n_agents)}")


def _arms(template: dict[str, Any], n_agents: int, radius: float) -> list[dict[str, Any]]:
    """``n_agents`` copies of the template's arms (cycled) on a ring of ``radius`` m, facing its centre (the
    nominal instance; the draws replace the bases and the starts)."""
    arms = []
    for i in range(n_agents):
        arm = dict(template["arms"][i % len(template["arms"])])
        angle = 2 * math.pi * i / n_agents
        arm["base_position"] = [radius * math.cos(angle), radius * math.sin(angle), arm["base_position"][2]]
        arm["base_rpy"] = [0.0, 0.0, angle + math.pi]
        arms.append(arm)
    return arms


def ring_chord_edges(n_agents: int) -> list[list[int]]:
    """The ring and its second-neighbour chords (the circulant graph C_N(1, 2)): every vertex joined to the two
    next to it on each side; the complete graph for N <= 5 (without repeats). For N >= 5 it is 3-connected and
    stays rigid with any one edge removed, so generically globally rigid in the plane: the shape is unique up to
    a congruence, with no flipped realization for a law to settle in."""
    edges = {tuple(sorted((i, (i + step) % n_agents))) for i in range(n_agents) for step in (1, 2)}
    return sorted([list(edge) for edge in edges if edge[0] != edge[1]])


def _planar(n_agents: int) -> dict[str, Any]:
    template = builtin_scenario("planar_random")
    radius = _PLANAR_RING_RADIUS_AT_4 * max(1.0, ring_growth(n_agents))
    circumradius = (radius - _PLANAR_VERTEX_INSET[1], radius - _PLANAR_VERTEX_INSET[0])
    shrink = min(1.0, _PLANAR_SHAPE_AT_4 / (radius - sum(_PLANAR_VERTEX_INSET) / 2))
    source = template["distribution"]
    stretch = 1.0 + (source["shape_aspect"][1] - 1.0) * shrink
    turn = source["shape_rotation"][1] * shrink
    angles = [2 * math.pi * i / n_agents for i in range(n_agents)]
    mid = sum(circumradius) / 2
    distribution = dict(source)
    distribution.update({
        "ring_radius": [radius - _PLANAR_RING_HALF_WIDTH, radius + _PLANAR_RING_HALF_WIDTH],
        "shape_scale": list(circumradius), "shape_aspect": [1.0 / stretch, stretch],
        "shape_rotation": [-turn, turn], "graph": "scenario"})
    return {"name": f"planar_team_{n_agents}", "arms": _arms(template, n_agents, radius),
            "edges": ring_chord_edges(n_agents),
            "shape": [[mid * math.cos(a), mid * math.sin(a)] for a in angles],
            "formation": "distance", "dim": 2, "episode_seconds": template["episode_seconds"],
            "distribution": distribution}


def _spatial(n_agents: int) -> dict[str, Any]:
    template = builtin_scenario("spatial_random")
    growth = ring_growth(n_agents)
    low, high = _SPATIAL_RING_AT_4
    radius = (low + high) / 2 * growth
    distribution = dict(template["distribution"])
    distribution.update({"ring_radius": [low * growth, high * growth],
                         "region_radius": _SPATIAL_REGION_AT_4 * growth, "graph": "complete"})
    height = sum(distribution["region_height"]) / 2
    angles = [2 * math.pi * i / n_agents for i in range(n_agents)]
    scale = _SPATIAL_REGION_AT_4 * growth
    data = {key: value for key, value in template.items() if key not in ("arms", "edges", "shape", "distribution")}
    data.update({"name": f"spatial_team_{n_agents}", "arms": _arms(template, n_agents, radius),
                 "edges": [[i, j] for i in range(n_agents) for j in range(i + 1, n_agents)],
                 "shape": [[scale * math.cos(a), scale * math.sin(a), height + 0.1 * (-1) ** i]
                           for i, a in enumerate(angles)],
                 "distribution": distribution})
    return data


def team_scenario(family: str, n_agents: int) -> dict[str, Any]:
    """The scenario data of ``family`` (:data:`TEAM_FAMILIES`) with ``n_agents`` arms (module docstring): a
    distribution, named ``<family>_<n_agents>``. ``ValueError`` naming the field for an unknown family or a
    team size outside the family's range."""
    check_team_size(family, n_agents)
    return _planar(n_agents) if family == "planar_team" else _spatial(n_agents)


def team_test_draws(family: str, n_agents: int, seeds: Any = None) -> dict[int, Any]:
    """The fixed test draws of ``family`` at ``n_agents`` arms: seed -> the fixed scenario an env reset with that
    seed runs (:func:`~ee_formation_env.scenario_sets.held_out_draws`; default seeds: its ``TEST_SEEDS``)."""
    from ee_formation_env.scenario_sets import TEST_SEEDS, held_out_draws

    return held_out_draws(team_scenario(family, n_agents), TEST_SEEDS if seeds is None else seeds)
