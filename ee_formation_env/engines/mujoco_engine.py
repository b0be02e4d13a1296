"""The MuJoCo engine (:mod:`ee_formation_env.engines.base`; the ``mujoco`` extra): every arm's URDF compiled
into one model (``MjSpec``), driven by generalized forces.

What is matched to the PyBullet path (``docs/physics.md``, "Engines"):

- each arm is its URDF attached at its base pose (prefix ``arm<i>/``), its root link welded to the world;
  inertias from the URDF, collision shapes only (visuals dropped), mesh paths (``package://`` ones too) from
  the URDF's folder, static bodies kept (not fused) so that a base can move;
- torques are ``qfrc_applied`` on the chain joints, unclipped (the env clips), held for ``steps`` steps of
  ``1 / physics_hz``; no motors, no armature, no joint friction, joint damping the scenario's; URDF joint
  limits enforced; no velocity clamp;
- joints off the chain (a gripper's fingers) are held where they are loaded (0) by equality constraints;
- contacts between arms only: no contact within an arm (every pair of its bodies excluded), none at all
  when ``arm_collisions`` is off; sliding friction 0.5 (PyBullet's default).

What differs: MuJoCo's soft contacts and joint limits against PyBullet's constraint solver, and its Euler
integrator (implicit in the damping) against PyBullet's semi-implicit one; the parity tests bound the effect.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import mujoco
import numpy as np

from ee_formation_env.engines.base import LoadedArm, URDFLoadError
from ee_formation_env.kinematics import rpy_to_matrix

#: PyBullet's default lateral friction coefficient, which the MuJoCo arms' geoms get too.
CONTACT_FRICTION = 0.5


def _quaternion(rpy: Sequence[float]) -> np.ndarray:
    """MuJoCo's (w, x, y, z) quaternion of roll-pitch-yaw angles (rad)."""
    quaternion = np.zeros(4)
    mujoco.mju_mat2Quat(quaternion, rpy_to_matrix(tuple(float(a) for a in rpy)).ravel())
    return quaternion


def _refusal(error: Exception) -> URDFLoadError:
    """MuJoCo's error on one line (its messages add the element on a line of their own)."""
    return URDFLoadError(" ".join(str(error).split()))


def _urdf_spec(urdf: str) -> mujoco.MjSpec:
    """``urdf`` parsed, its mesh paths resolved as PyBullet resolves them: ``package://`` and relative paths
    from the URDF's folder (MuJoCo reads no ``package://``)."""
    try:
        text = Path(urdf).read_text(encoding="utf-8").replace("package://", "")
        spec = mujoco.MjSpec.from_string(text)
    except (OSError, UnicodeDecodeError, ValueError) as error:  # unreadable, or MuJoCo's parse errors
        raise _refusal(error) from None
    spec.meshdir = str(Path(urdf).resolve().parent)
    return spec


@dataclass
class _ArmRecord:
    """What one loaded arm needs once the model is (re)compiled."""

    root: str  # the root body's name in the model
    chain: tuple[str, ...]  # chain joint names, prefixed
    extra: tuple[str, ...]  # other movable joints, prefixed
    damping: np.ndarray
    bodies: tuple[str, ...]


class MuJoCoEngine:
    """One MuJoCo model and data holding every loaded arm (the module docstring's set-up). An arm's ``body``
    is its load index; its joint indices are MuJoCo ``qpos``/``qvel`` addresses (the arms have hinge and
    slide joints only, so the two agree)."""

    name = "mujoco"
    label = "MuJoCo"

    def __init__(self, physics_hz: float, gravity: tuple[float, float, float], render_mode: str | None = None):
        # render_mode: frames are PyBullet's only for now (the env refuses them on MuJoCo before building one)
        self.gui = False
        self.time_step = 1.0 / physics_hz
        self._spec = mujoco.MjSpec()
        self._spec.compiler.fusestatic = False  # keep every arm's static root body, so that its base can move
        self._spec.option.timestep = self.time_step
        self._spec.option.gravity = list(gravity)
        self._arms: list[_ArmRecord] = []
        self._model: mujoco.MjModel | None = None
        self._data: mujoco.MjData | None = None
        self._snapshot: tuple[np.ndarray, ...] | None = None
        self._open = True

    @property
    def connected(self) -> bool:
        return self._open

    # -------------------------------------------------------------------------------------------- loading
    def load_arm(self, urdf: str, position: Sequence[float], rpy: Sequence[float], chain_joints: Sequence[str],
                 joint_damping: np.ndarray, collide_with_other_arms: bool) -> LoadedArm:
        """Attach ``urdf`` at its base pose and recompile (joint states of arms loaded before are lost: load
        every arm, then reset)."""
        child = _urdf_spec(urdf)
        index = len(self._arms)
        prefix = f"arm{index}/"
        root = child.worldbody.first_body()
        attached = self._spec.worldbody.add_frame().attach_body(root, prefix, "")
        attached.pos = [float(v) for v in position]
        attached.quat = _quaternion(rpy)
        bodies = [body for body in self._spec.bodies if body.name.startswith(prefix)]
        for body in bodies:
            for geom in body.geoms:
                geom.contype = geom.conaffinity = 1 if collide_with_other_arms else 0
                geom.friction = [CONTACT_FRICTION, *list(geom.friction)[1:]]
        for a in range(len(bodies)):  # no contact within an arm, as on PyBullet (no self-collision flag)
            for b in range(a + 1, len(bodies)):
                exclude = self._spec.add_exclude()
                exclude.bodyname1, exclude.bodyname2 = bodies[a].name, bodies[b].name
        movable = [joint.name for joint in self._spec.joints if joint.name.startswith(prefix)]
        chain = tuple(prefix + name for name in chain_joints)
        extra = tuple(name for name in movable if name not in chain)
        for name in extra:  # held at 0, where it is loaded
            equality = self._spec.add_equality(type=mujoco.mjtEq.mjEQ_JOINT, objtype=mujoco.mjtObj.mjOBJ_JOINT)
            equality.name1 = name
        self._arms.append(_ArmRecord(attached.name, chain, extra, np.asarray(joint_damping, dtype=np.float64),
                                     tuple(body.name for body in bodies)))
        try:
            self._compile()
        except ValueError as error:  # e.g. a mesh MuJoCo cannot decode; the caller closes this world
            raise _refusal(error) from None
        model = self._model
        return LoadedArm(index, tuple(int(model.joint(name).qposadr[0]) for name in chain),
                         tuple(int(model.joint(name).qposadr[0]) for name in extra),
                         {name[len(prefix):]: 0.0 for name in extra})

    def _compile(self) -> None:
        model = self._spec.compile()
        model.dof_armature[:] = 0.0
        model.dof_frictionloss[:] = 0.0
        model.dof_damping[:] = 0.0
        for arm in self._arms:
            for name, value in zip(arm.chain, arm.damping):
                model.dof_damping[model.joint(name).dofadr[0]] = value
        self._model, self._data = model, mujoco.MjData(model)
        self._roots = np.array([model.body(arm.root).id for arm in self._arms], dtype=np.intp)
        self._dofs = np.array([model.joint(name).dofadr[0] for arm in self._arms for name in arm.chain], dtype=np.intp)
        body_arm = np.full(model.nbody, -1, dtype=np.intp)
        for i, arm in enumerate(self._arms):
            body_arm[[model.body(name).id for name in arm.bodies]] = i
        self._geom_arm = body_arm[model.geom_bodyid]
        self._arm_geoms = [np.flatnonzero(self._geom_arm == i) for i in range(len(self._arms))]
        mujoco.mj_forward(model, self._data)

    # -------------------------------------------------------------------------------------------- state
    def place_base(self, arm: LoadedArm, position: Sequence[float], rpy: Sequence[float]) -> None:
        root = self._roots[arm.body]
        self._model.body_pos[root] = position
        self._model.body_quat[root] = _quaternion(rpy)
        mujoco.mj_forward(self._model, self._data)

    def reset_joints(self, arm: LoadedArm, q: np.ndarray) -> None:
        joints = list(arm.joint_indices)
        self._data.qpos[joints] = q
        self._data.qvel[joints] = 0.0
        mujoco.mj_forward(self._model, self._data)  # positions, contacts and distances of the new state

    def joint_state(self, arm: LoadedArm) -> tuple[tuple[float, ...], tuple[float, ...]]:
        joints = list(arm.joint_indices)
        return tuple(self._data.qpos[joints].tolist()), tuple(self._data.qvel[joints].tolist())

    def step_torques(self, torques: np.ndarray, steps: int) -> None:
        self._data.qfrc_applied[self._dofs] = torques
        mujoco.mj_step(self._model, self._data, nstep=steps)

    def save_snapshot(self) -> None:
        data, model = self._data, self._model
        self._snapshot = (data.qpos.copy(), data.qvel.copy(), data.qacc_warmstart.copy(), model.body_pos.copy(),
                          model.body_quat.copy())

    def restore_snapshot(self) -> None:
        if self._snapshot is None:
            return
        data, model = self._data, self._model
        qpos, qvel, warmstart, body_pos, body_quat = self._snapshot
        mujoco.mj_resetData(model, data)
        data.qpos[:], data.qvel[:], data.qacc_warmstart[:] = qpos, qvel, warmstart
        model.body_pos[:], model.body_quat[:] = body_pos, body_quat
        mujoco.mj_forward(model, data)

    # -------------------------------------------------------------------------------------------- contacts
    def contact_bodies(self) -> list[tuple[int, int]]:
        """(arm a, arm b) of every current contact (MuJoCo makes contacts between arms only: see the module
        docstring)."""
        count = self._data.ncon
        if count == 0:
            return []
        arms = self._geom_arm[self._data.contact.geom[:count]]
        return [(int(a), int(b)) for a, b in arms]

    def closest_distance(self, a: LoadedArm, b: LoadedArm, max_distance: float) -> float | None:
        # mj_geomDistance caps its answer at distmax: ask a little beyond, so that "at most max_distance" is exact
        cap = max_distance + 1.0
        model, data = self._model, self._data
        best = min((mujoco.mj_geomDistance(model, data, int(g1), int(g2), cap, None)
                    for g1 in self._arm_geoms[a.body] for g2 in self._arm_geoms[b.body]), default=cap)
        return best if best <= max_distance else None

    def close(self) -> None:
        self._open = False
        self._model = self._data = None


class MuJoCoModel:
    """The :class:`~ee_formation_env.engines.base.RigidBodyModel` on MuJoCo: the URDF compiled alone, root at
    the origin; gravity torques are ``qfrc_bias`` at rest, the mass matrix ``mj_fullM`` (no armature)."""

    def __init__(self, urdf: str, chain_joints: Sequence[str], held: dict[str, float] | None = None):
        try:
            model = _urdf_spec(urdf).compile()
        except ValueError as error:  # a mesh MuJoCo cannot read
            raise _refusal(error) from None
        model.dof_armature[:] = 0.0
        self._model, self._data = model, mujoco.MjData(model)
        self._chain = np.array([model.joint(name).qposadr[0] for name in chain_joints], dtype=np.intp)
        self._chain_dofs = np.array([model.joint(name).dofadr[0] for name in chain_joints], dtype=np.intp)
        for name, value in (held or {}).items():
            self._data.qpos[model.joint(name).qposadr[0]] = value
        self._dense = np.zeros((model.nv, model.nv))

    def _at(self, q: np.ndarray) -> None:
        self._data.qpos[self._chain] = q
        self._data.qvel[:] = 0.0
        mujoco.mj_forward(self._model, self._data)

    def gravity_torque(self, q: np.ndarray, gravity_in_base: np.ndarray) -> np.ndarray:
        self._model.opt.gravity[:] = gravity_in_base
        self._at(q)
        return self._data.qfrc_bias[self._chain_dofs].copy()

    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        self._at(q)
        if hasattr(self._data, "qM"):  # MuJoCo 3: mj_fullM(m, dst, qM)
            mujoco.mj_fullM(self._model, self._dense, self._data.qM)
        else:  # MuJoCo 4: mj_fullM(m, d, dst)
            mujoco.mj_fullM(self._model, self._data, self._dense)
        return self._dense[np.ix_(self._chain_dofs, self._chain_dofs)].copy()
