"""The env's physics world: one engine (:mod:`ee_formation_env.engines`) per copy of the env.

Rule: the env reaches physics only through the engine seam (:class:`~ee_formation_env.engines.base.Engine`,
built by :func:`make_world`); :class:`PhysicsWorld` names the default engine, PyBullet's, whose frames
(:mod:`ee_formation_env.rendering`) and GUI are its own.
"""

from __future__ import annotations

from ee_formation_env.engines import Engine
from ee_formation_env.engines import make_engine as make_world
from ee_formation_env.engines.pybullet_engine import PyBulletEngine as PhysicsWorld

__all__ = ["Engine", "PhysicsWorld", "make_world"]
