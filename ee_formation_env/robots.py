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
    """A built-in robot: its URDF, end-effector link and default start pose.

    ``start_q`` (rad) is the arm's initial configuration when a scenario arm names the robot and gives no
    ``initial_q``: a pose away from kinematic singularities (the all-zeros pose of an arm stretched straight
    is singular, or close to it).
    """

    urdf: Path
    ee_link: str
    start_q: tuple[float, ...]


# PERA-like arm starts (rad), elbows bent, away from singularities: the end-effectors start 0.25 m in
# front of their bases, low (z = -0.62 m) with the first, high (z = -0.35 m) with the second, so that
# arms alternating between them do not start coplanar (a planar start is invariant under the distance
# gradient of point agents). The built-in spatial_tetrahedron writes them out (tests check they agree);
# the scenario generators alternate them.
SPATIAL_INITIAL_Q = ((-0.45, 0.1, 0.0, 1.15, 0.0, 0.3, 0.0), (-0.85, 0.1, 0.0, 2.0, 0.0, 0.3, 0.0))

ROBOTS: dict[str, RobotSpec] = {
    # Default start: the elbow bent by pi/3 (the paper's initial q2), the tip 2.6 m from the base.
    "planar_2link": RobotSpec(asset_path("planar_2link.urdf"), "ee_link", (0.0, 1.0471975511965976)),
    # Default start: the first of SPATIAL_INITIAL_Q (elbow bent, the tip 0.25 m in front of the base).
    "pera_arm": RobotSpec(asset_path("pera_arm.urdf"), "ee_link", SPATIAL_INITIAL_Q[0]),
}
