"""Scenario distributions: ranges instead of values, sampled at every ``reset(seed=...)``.

Scenario key ``distribution`` (default: none, a fixed scenario). The scenario's team stays fixed (which robot
sits in which slot, so the spaces, the agents and the robots' URDFs never change and a reset reloads
nothing); what each reset draws, from the env's generator (so the reset seed fixes it):

============================ ================= ==================================================================
key                          default           meaning
============================ ================= ==================================================================
``ring_radius``              null              m, ``[low, high]`` or a number: the bases on a circle of this
                                               radius about the world origin, evenly spaced and facing its
                                               centre (base heights kept from ``arms``); null keeps the
                                               scenario's base positions and yaws
``ring_offset``              0                 rad, range of the rotation of the whole ring about z
``base_yaw``                 0                 rad, range of each base's yaw added to facing the centre (or to
                                               its scenario yaw when ``ring_radius`` is null)
``initial_q``                ``"scenario"``    ``"scenario"`` (the arms' ``initial_q``) or ``"random"`` (uniform
                                               within the joint limits less a 10 % margin); reset noise
                                               (``initial_q_noise``) is added on top either way
``shape``                    ``"scenario"``    ``"scenario"`` (the scenario's shape, scaled, stretched and
                                               turned below, moved to the layout's centre), ``"regular"`` (a
                                               regular polygon in 2D, a regular polygon or tetrahedron in 3D,
                                               circumradius ``shape_scale``) or ``"reachable"`` (each vertex
                                               the end-effector of a random configuration of its own arm inside
                                               the shared region)
``shape_scale``              1                 range: a factor (``"scenario"``) or a circumradius in m
                                               (``"regular"``)
``shape_aspect``             1                 range of the x stretch (x times a, y divided by a)
``shape_rotation``           0                 rad, range of the shape's turn about z
``region_radius``            1.0               m, ``"reachable"``: horizontal distance of a vertex from the
                                               layout's centre
``region_height``            null              m, ``[low, high]`` world z of the vertices (3D ``"reachable"``)
                                               or of the centre of a ``"regular"`` 3D shape; null: the
                                               scenario shape's mean height
``graph``                    ``"scenario"``    ``"scenario"`` (its ``edges``), ``"trilateration"`` (minimally
                                               rigid: the first dim + 1 vertices fully joined, every later one
                                               to the dim before it) or ``"complete"``; fixed for the
                                               distribution (the neighbour slots are part of the spaces)
``singularity_margin``       0.05              m, smallest Jacobian singular value allowed at the initial
                                               configurations (and at a ``"reachable"`` vertex's)
``vertex_spacing``           0.1               m, smallest distance between two target vertices
``reach_margin``             0                 m, each drawn vertex at least this much inside its own arm's
                                               reach (its distance from the base at most the reach less
                                               this): targets that need a stretched arm are redrawn
``max_tries``                200               draws before a distribution is declared infeasible
============================ ================= ==================================================================

Each draw is validated as a fixed scenario is (reachable, rigid at its shape, no singular start), plus the
margins above and no contact between the arms at the start; a draw that fails is redrawn, at most
``max_tries`` times, then ``ValueError`` names the distribution and the last reason. The env draws one sample
at construction (generator seeded 0), so an infeasible distribution is refused before any episode; that first
draw also stops after :data:`FIRST_DRAW_DEADLINE_SECONDS` of rejected draws (a draw the reach check refuses
outright costs microseconds, one that needs the full placement search a fraction of a second), so that
``max_tries: 10000`` on an infeasible distribution is refused in bounded time. Later draws (at reset) have no
deadline: their outcome depends only on the seed. The
sampling itself lives in :mod:`ee_formation_env.generators` (the one home of scenario generation).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, Mapping

from ee_formation_env.inputs import check_known_keys, excerpt, is_real_number

INITIAL_Q_MODES = ("scenario", "random")
SHAPE_MODES = ("scenario", "regular", "reachable")
GRAPH_MODES = ("scenario", "trilateration", "complete")
MAX_TRIES = 10_000
#: Wall-clock bound (s) on the env's first draw of a distribution, the one that decides it is feasible.
FIRST_DRAW_DEADLINE_SECONDS = 10.0

Range = tuple[float, float]


@dataclass(frozen=True)
class DistributionConfig:
    """The ranges of a scenario distribution (module docstring); ranges are (low, high)."""

    ring_radius: Range | None = None  # m
    ring_offset: Range = (0.0, 0.0)  # rad
    base_yaw: Range = (0.0, 0.0)  # rad
    initial_q: str = "scenario"
    shape: str = "scenario"
    shape_scale: Range = (1.0, 1.0)  # factor or m
    shape_aspect: Range = (1.0, 1.0)
    shape_rotation: Range = (0.0, 0.0)  # rad
    region_radius: float = 1.0  # m
    region_height: Range | None = None  # m
    graph: str = "scenario"
    singularity_margin: float = 0.05  # m
    vertex_spacing: float = 0.1  # m
    reach_margin: float = 0.0  # m
    max_tries: int = 200
    active: bool = False  # True once given in a scenario

    def to_dict(self) -> dict[str, Any] | None:
        """Plain data :func:`parse_distribution` accepts back (None for no distribution)."""
        if not self.active:
            return None
        data = {}
        for name in DISTRIBUTION_KEYS:
            value = getattr(self, name)
            data[name] = list(value) if isinstance(value, tuple) else value
        return data


DISTRIBUTION_KEYS = tuple(f.name for f in fields(DistributionConfig) if f.name != "active")


def parse_distribution(value: Any, dim: int) -> DistributionConfig:
    """``distribution`` from scenario data; ``ValueError`` naming the field on bad input."""
    if isinstance(value, DistributionConfig):
        return value
    if value is None:
        return DistributionConfig()
    if not isinstance(value, Mapping):
        raise ValueError(f"distribution: expected a dict with keys among {list(DISTRIBUTION_KEYS)}, got "
                         f"{excerpt(value)}")
    check_known_keys("distribution", value, list(DISTRIBUTION_KEYS))
    defaults = DistributionConfig()
    parsed: dict[str, Any] = {"active": True}
    radius = value.get("ring_radius")
    parsed["ring_radius"] = None if radius is None else _range("ring_radius", radius, minimum=0.0, positive=True)
    for name in ("ring_offset", "base_yaw", "shape_rotation"):
        parsed[name] = _range(name, value.get(name, getattr(defaults, name)))
    parsed["shape_scale"] = _range("shape_scale", value.get("shape_scale", 1.0), minimum=0.0, positive=True)
    parsed["shape_aspect"] = _range("shape_aspect", value.get("shape_aspect", 1.0), minimum=0.0, positive=True)
    height = value.get("region_height")
    parsed["region_height"] = None if height is None else _range("region_height", height)
    for name, choices in (("initial_q", INITIAL_Q_MODES), ("shape", SHAPE_MODES), ("graph", GRAPH_MODES)):
        choice = value.get(name, getattr(defaults, name))
        if choice not in choices:
            raise ValueError(f"distribution.{name}: expected one of {list(choices)}, got {excerpt(choice)}")
        parsed[name] = choice
    for name in ("region_radius", "singularity_margin", "vertex_spacing", "reach_margin"):
        parsed[name] = _number(name, value.get(name, getattr(defaults, name)), positive=name == "region_radius")
    tries = value.get("max_tries", defaults.max_tries)
    if isinstance(tries, bool) or not isinstance(tries, int) or not 1 <= tries <= MAX_TRIES:
        raise ValueError(f"distribution.max_tries: expected an integer in [1, {MAX_TRIES}], got {excerpt(tries)}")
    parsed["max_tries"] = tries
    return DistributionConfig(**parsed)


def _number(name: str, value: Any, positive: bool = False) -> float:
    if not is_real_number(value) or not math.isfinite(value) or value < 0 or (positive and value == 0):
        raise ValueError(f"distribution.{name}: expected a finite number {'> 0' if positive else '>= 0'}, got "
                         f"{excerpt(value)}")
    return float(value)


def _range(name: str, value: Any, minimum: float | None = None, positive: bool = False) -> Range:
    """A (low, high) range from a number or a two-number list."""
    if is_real_number(value):
        low = high = value
    elif isinstance(value, (list, tuple)) and len(value) == 2 and all(is_real_number(v) for v in value):
        low, high = value
    else:
        raise ValueError(f"distribution.{name}: expected a number or [low, high], got {excerpt(value)}")
    if not (math.isfinite(low) and math.isfinite(high)) or low > high:
        raise ValueError(f"distribution.{name}: expected finite numbers with low <= high, got {excerpt(value)}")
    if minimum is not None and (low < minimum or (positive and low <= minimum)):
        raise ValueError(f"distribution.{name}: expected values > {minimum:g}, got {excerpt(value)}")
    return float(low), float(high)
