"""The robots: a scenario arm's ``robot: <name>`` names one of :data:`ROBOTS`.

The one registry of robots: those shipped with the package (:data:`ROBOTS`, their URDFs in
``ee_formation_env.assets``) and those of ``pybullet_data`` the package uses (:data:`PYBULLET_DATA_ROBOTS`,
which a scenario gives by ``urdf`` and ``ee_link``), one :class:`RobotSpec` each, and the robot constants
other modules share. The random spatial family (:func:`ee_formation_env.generators.spatial_scenario`) draws
from the robots that have a ``random_base_height`` (:data:`RANDOM_SPATIAL_ROBOTS`). A new robot is one entry
here plus its URDF in ``assets/``; see ``docs/scenarios.md`` for how a scenario names a robot or gives its
own URDF.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pybullet_data

from ee_formation_env.assets import asset_path


@dataclass(frozen=True)
class RobotSpec:
    """A robot: its URDF, end-effector link and default start pose.

    ``start_q`` (rad) is the arm's initial configuration when a scenario arm names the robot and gives no
    ``initial_q``: a pose away from kinematic singularities (the all-zeros pose of an arm stretched straight
    is singular, or close to it). ``random_base_height`` (m) is the height of the robot's base when the random
    spatial family draws it; None: the family does not draw it.
    """

    urdf: Path
    ee_link: str
    start_q: tuple[float, ...]
    random_base_height: float | None = None


# PERA-like arm starts (rad), elbows bent, away from singularities: the end-effectors start 0.25 m in
# front of their bases, low (z = -0.62 m) with the first, high (z = -0.35 m) with the second, so that
# arms alternating between them do not start coplanar (a planar start is invariant under the distance
# gradient of point agents). The built-in spatial_tetrahedron writes them out (tests check they agree);
# the scenario generators alternate them.
SPATIAL_INITIAL_Q = ((-0.45, 0.1, 0.0, 1.15, 0.0, 0.3, 0.0), (-0.85, 0.1, 0.0, 2.0, 0.0, 0.3, 0.0))

ROBOTS: dict[str, RobotSpec] = {
    # Default start: the elbow bent by pi/3 (the paper's initial q2), the tip 2.6 m from the base.
    "planar_2link": RobotSpec(asset_path("planar_2link.urdf"), "ee_link", (0.0, 1.0471975511965976)),
    # Default start: the first of SPATIAL_INITIAL_Q (elbow bent, the tip 0.25 m in front of the base). In the
    # random spatial family it hangs from a base 1 m up.
    "pera_arm": RobotSpec(asset_path("pera_arm.urdf"), "ee_link", SPATIAL_INITIAL_Q[0], random_base_height=1.0),
}

#: Robots of ``pybullet_data`` (not built-in names: a scenario gives their ``urdf`` and ``ee_link``); start
#: poses with the elbow bent. Both stand on the floor in the random spatial family.
PYBULLET_DATA_ROBOTS: dict[str, RobotSpec] = {
    "kuka_iiwa": RobotSpec(Path(pybullet_data.getDataPath()) / "kuka_iiwa" / "model.urdf", "lbr_iiwa_link_7",
                           (0.0, 0.5, 0.0, -1.2, 0.0, 0.8, 0.0), random_base_height=0.0),
    "franka_panda": RobotSpec(Path(pybullet_data.getDataPath()) / "franka_panda" / "panda.urdf", "panda_hand",
                              (0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.8), random_base_height=0.0),
}

#: The robots the random spatial family draws from, in the order its draws index them: every robot with a
#: ``random_base_height``, the ``pybullet_data`` ones first.
RANDOM_SPATIAL_ROBOTS: dict[str, RobotSpec] = {
    name: spec for name, spec in {**PYBULLET_DATA_ROBOTS, **ROBOTS}.items() if spec.random_base_height is not None}
