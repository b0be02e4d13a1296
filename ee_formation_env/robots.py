"""The built-in robots: a scenario arm's ``robot: <name>`` names one of :data:`ROBOTS`.

The one registry of robots shipped with the package (their URDFs are in ``ee_formation_env.assets``), and
the robot constants other modules share. A new robot is one entry here plus its URDF in ``assets/``; see
``docs/scenarios.md`` for how a scenario names a robot or gives its own URDF.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ee_formation_env.assets import asset_path


@dataclass(frozen=True)
class RobotSpec:
    """A built-in robot: its URDF and end-effector link."""

    urdf: Path
    ee_link: str


ROBOTS: dict[str, RobotSpec] = {
    "planar_2link": RobotSpec(asset_path("planar_2link.urdf"), "ee_link"),
    "pera_arm": RobotSpec(asset_path("pera_arm.urdf"), "ee_link"),
}

# PERA-like arm starts (rad), elbows bent, away from singularities: the end-effectors start 0.25 m in
# front of their bases, low (z = -0.62 m) with the first, high (z = -0.35 m) with the second, so that
# arms alternating between them do not start coplanar (a planar start is invariant under the distance
# gradient of point agents). The built-in spatial_tetrahedron writes them out (tests check they agree);
# the scenario generators alternate them.
SPATIAL_INITIAL_Q = ((-0.45, 0.1, 0.0, 1.15, 0.0, 0.3, 0.0), (-0.85, 0.1, 0.0, 2.0, 0.0, 0.3, 0.0))
