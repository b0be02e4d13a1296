"""The physics-engine seam: what the env asks of a physics engine, whichever simulates the arms.

An engine holds one world of fixed-base arms loaded from URDFs, torque-controlled, and answers for them:

================================ ==========================================================================
call                             meaning
================================ ==========================================================================
``load_arm(urdf, ...)``          load a fixed-base arm at a base pose; chain joints torque-driven with the
                                 given viscous damping, joints off the chain held where they are, contacts
                                 with other arms on or off (never within an arm); returns a :class:`LoadedArm`
``place_base(arm, pos, rpy)``    move an arm's fixed base (m, rad) as if loaded there
``reset_joints(arm, q)``         chain joints at ``q`` (rad), at rest
``joint_state(arm)``             chain joint positions (rad) and velocities (rad/s), as Python tuples
``step_torques(torques, steps)`` hold the flat torques (N m; every arm's chain joints in load order) for
                                 ``steps`` physics steps of ``time_step`` s
``save_snapshot()`` /            remember / return to the whole world (joint states, base poses, solver
``restore_snapshot()``           caches), so that a reset does not depend on what ran before
``contact_bodies()``             ``(body a, body b)`` of every current contact point between arms
``closest_distance(a, b, d)``    the signed distance (m, negative: penetration) between two arms if it is at
                                 most ``d``, else None
``close()`` / ``connected``      release the world (idempotent) / whether it is still held
================================ ==========================================================================

and, for the nominal model of the reference laws and the env's gravity compensation, a
:class:`RigidBodyModel` of one URDF (fixed base at the origin): gravity torques and mass matrix. Frames
(``render``, ``link_positions`` and the GUI calls) are PyBullet's only for now.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, Sequence

import numpy as np

#: The engines a scenario's ``engine`` key names; the first is the default.
ENGINES = ("pybullet", "mujoco")


class URDFLoadError(RuntimeError):
    """The engine refused a URDF (a mesh it cannot find or parse, a malformed file); the message is its own."""


@dataclass(frozen=True)
class LoadedArm:
    """One loaded arm: ``body``, the engine's handle of it (what :meth:`Engine.contact_bodies` names);
    ``joint_indices`` / ``extra_joint_indices``, the engine's indices of its chain joints (in chain order) and
    of its other movable joints; ``held_positions``, where those other joints are held, by joint name."""

    body: int
    joint_indices: tuple[int, ...]
    extra_joint_indices: tuple[int, ...] = ()
    held_positions: dict[str, float] = field(default_factory=dict)


class Engine(Protocol):
    """One world of arms (the table of the module docstring)."""

    name: str  # the scenario's ``engine`` value
    label: str  # the engine's name in messages
    time_step: float  # s, one physics step
    gui: bool  # a window is open (PyBullet's ``render_mode="human"``)

    @property
    def connected(self) -> bool: ...

    def load_arm(self, urdf: str, position: Sequence[float], rpy: Sequence[float], chain_joints: Sequence[str],
                 joint_damping: np.ndarray, collide_with_other_arms: bool) -> LoadedArm: ...

    def place_base(self, arm: LoadedArm, position: Sequence[float], rpy: Sequence[float]) -> None: ...

    def reset_joints(self, arm: LoadedArm, q: np.ndarray) -> None: ...

    def joint_state(self, arm: LoadedArm) -> tuple[tuple[float, ...], tuple[float, ...]]: ...

    def step_torques(self, torques: np.ndarray, steps: int) -> None: ...

    def save_snapshot(self) -> None: ...

    def restore_snapshot(self) -> None: ...

    def contact_bodies(self) -> list[tuple[int, int]]: ...

    def closest_distance(self, a: LoadedArm, b: LoadedArm, max_distance: float) -> float | None: ...

    def close(self) -> None: ...


class RigidBodyModel(Protocol):
    """Rigid-body dynamics of one URDF's chain joints, fixed base at the origin; joints off the chain sit at
    their held positions."""

    def gravity_torque(self, q: np.ndarray, gravity_in_base: np.ndarray) -> np.ndarray:
        """g(q) (N m): the torques that hold the arm still against ``gravity_in_base`` (m/s^2, base frame)."""
        ...

    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        """H(q) (kg m^2) of the chain joints."""
        ...
