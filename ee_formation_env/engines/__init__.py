"""Physics engines behind one seam (:mod:`ee_formation_env.engines.base`): PyBullet (the default) and MuJoCo
(the ``mujoco`` extra). A scenario's ``engine`` key picks one; nothing falls back from one to the other."""

from __future__ import annotations

from typing import Sequence

from ee_formation_env.engines.base import ENGINES, Engine, LoadedArm, RigidBodyModel, URDFLoadError

__all__ = ["ENGINES", "Engine", "LoadedArm", "RigidBodyModel", "URDFLoadError", "check_engine", "make_engine", "rigid_body_model",
           "require_engine"]

MUJOCO_EXTRA = 'pip install "ee-formation-env[mujoco]"'


def require_engine(name: str) -> None:
    """Refuse an engine that cannot run here: an unknown name is a ``ValueError`` naming the key, MuJoCo
    without its package an ``ImportError`` naming the extra (checked before any world starts)."""
    if name not in ENGINES:
        raise ValueError(f"engine: expected one of {list(ENGINES)}, got {name!r}")
    if name == "mujoco":
        try:
            import mujoco  # noqa: F401
        except ImportError:
            raise ImportError(f"engine: 'mujoco' needs the mujoco package: {MUJOCO_EXTRA}") from None


def make_engine(name: str, physics_hz: float, gravity: tuple[float, float, float],
                render_mode: str | None = None) -> Engine:
    """A fresh world of engine ``name`` stepping at ``physics_hz`` under ``gravity`` (m/s^2)."""
    require_engine(name)
    if name == "mujoco":
        from ee_formation_env.engines.mujoco_engine import MuJoCoEngine

        return MuJoCoEngine(physics_hz, gravity, render_mode)
    from ee_formation_env.engines.pybullet_engine import PyBulletEngine

    return PyBulletEngine(physics_hz, gravity, render_mode)


def rigid_body_model(name: str, urdf: str, chain_joints: Sequence[str],
                     held: dict[str, float] | None = None) -> RigidBodyModel:
    """Engine ``name``'s rigid-body dynamics of ``urdf``'s chain joints (fixed base at the origin; other
    movable joints at ``held``, by name, default 0)."""
    require_engine(name)
    if name == "mujoco":
        from ee_formation_env.engines.mujoco_engine import MuJoCoModel

        return MuJoCoModel(urdf, tuple(chain_joints), held)
    from ee_formation_env.engines.pybullet_engine import PyBulletModel

    return PyBulletModel(urdf, tuple(chain_joints), held)


def check_engine(engine: str, num_envs: int, render_mode: str | None) -> None:
    """Refuse what the scenario's engine cannot do yet, before any world starts: MuJoCo runs one copy (the
    parallel env) without frames; its package missing is an ``ImportError`` naming the extra."""
    if engine != "pybullet" and num_envs != 1:
        raise ValueError(f"num_envs: the batched env runs on PyBullet only for now; engine {engine!r} takes "
                         f"num_envs=1 (the parallel env), got {num_envs}")
    if engine != "pybullet" and render_mode is not None:
        raise ValueError(f"render_mode: frames are PyBullet's only for now; engine {engine!r} takes render_mode=None, "
                         f"got {render_mode!r}")
    require_engine(engine)
