"""Kinematic model of a serial robot arm, parsed from its URDF.

This is the project's single source of forward kinematics, translational Jacobians and the
kinematic regressor of the paper (J^T(q, a) zeta = Z(q, zeta) a). It reads the URDF with
``xml.etree`` and does not use PyBullet, so it is the same model for every simulator.

Model. Along the path of joints k = 0 .. m-1 from the URDF root link to the end-effector link,
each joint transform is T_k = Trans(d_k) Rot(rpy_k) Rot(axis_k, q_k) (URDF convention; the rpy
rotation is Rz(yaw) Ry(pitch) Rx(roll), and fixed joints have no axis rotation). The position of
the end-effector link frame in the root link frame is

    p(q, a) = sum_k R_parent(k)(q) d_k,

where R_parent(k) is the orientation of joint k's parent link (the product of every rotation
before joint k). Rotations do not depend on translations, so p and the Jacobian are linear in
the translations d_k. The kinematic parameter vector ``a`` stacks the components of the d_k that
are non-zero in the URDF (|component| > 1e-12), in chain order, x before y before z; the other
components are the constant zero. For a movable joint j with world axis omega_j the regressor is

    Z[j, (k, c)] = zeta . (omega_j x R_parent(k) e_c)   if j comes strictly before k, else 0,

so that J(q, a)^T zeta = Z(q, zeta) a for every a.

Units: lengths in m, angles in rad, torques in N m, velocities in rad/s.

The PyBullet facts this relies on (frames of ``getJointInfo``, ``calculateJacobian``): see docs/physics.md.
"""

from __future__ import annotations

import functools
import math
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ["JointSpec", "SerialChain"]

#: Joint types the model supports on the root -> end-effector path.
SUPPORTED_JOINT_TYPES = ("revolute", "continuous", "fixed")
#: Joint types with one rotational degree of freedom.
MOVABLE_JOINT_TYPES = ("revolute", "continuous")
#: Translation components with a magnitude at or below this are constants (zero), not parameters.
PARAM_ZERO_TOL = 1e-12

_AXIS_NAMES = ("x", "y", "z")


@dataclass(frozen=True, eq=False)
class JointSpec:
    """One URDF joint, as written in the file (arrays are read-only).

    Equality is identity (the fields hold numpy arrays, which have no single truth value).
    """

    name: str
    joint_type: str  # "revolute" | "continuous" | "fixed"
    parent: str
    child: str
    origin_xyz: np.ndarray  # (3,) m, joint frame origin in the parent link frame
    origin_rpy: np.ndarray  # (3,) rad, URDF fixed-axis roll-pitch-yaw
    axis: np.ndarray  # (3,) unit vector in the joint frame; zeros for fixed joints
    lower: float  # rad; -inf for continuous joints
    upper: float  # rad; +inf for continuous joints
    effort: float  # N m; inf if absent
    velocity: float  # rad/s; inf if absent
    damping: float  # N m s/rad; 0 if absent

    @property
    def movable(self) -> bool:
        """True for revolute and continuous joints."""
        return self.joint_type in MOVABLE_JOINT_TYPES


def rpy_to_matrix(rpy: np.ndarray) -> np.ndarray:
    """Rotation matrix of URDF roll-pitch-yaw angles (rad): Rz(yaw) @ Ry(pitch) @ Rx(roll)."""
    roll, pitch, yaw = (float(v) for v in rpy)
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def _skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix S(v), with S(v) @ w = v x w."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _read_only(array: np.ndarray) -> np.ndarray:
    array.setflags(write=False)
    return array


def _parse_vector(text: str | None, default: tuple[float, float, float], field: str) -> np.ndarray:
    if text is None:
        return np.array(default, dtype=float)
    parts = text.split()
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise ValueError(f"{field}: expected 3 numbers, got {text!r}") from None
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ValueError(f"{field}: expected 3 finite numbers, got {text!r}")
    return np.array(values, dtype=float)


def _parse_float(element: ET.Element | None, attribute: str, default: float, field: str) -> float:
    if element is None or element.get(attribute) is None:
        return default
    text = element.get(attribute, "")
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"{field}: expected a number, got {text!r}") from None


def _parse_joint(element: ET.Element) -> JointSpec:
    """Parse one <joint> element (any type; type checks are left to the caller)."""
    name = element.get("name")
    if not name:
        raise ValueError("joint.name: a <joint> element has no name")
    joint_type = element.get("type", "")
    parent_el, child_el = element.find("parent"), element.find("child")
    parent = parent_el.get("link") if parent_el is not None else None
    child = child_el.get("link") if child_el is not None else None
    if not parent or not child:
        raise ValueError(f"joint {name!r}: <parent link> and <child link> are required")

    origin = element.find("origin")
    xyz = _parse_vector(origin.get("xyz") if origin is not None else None, (0, 0, 0),
                        f"joint {name!r} origin.xyz")
    rpy = _parse_vector(origin.get("rpy") if origin is not None else None, (0, 0, 0),
                        f"joint {name!r} origin.rpy")

    limit = element.find("limit")
    effort = _parse_float(limit, "effort", math.inf, f"joint {name!r} limit.effort")
    velocity = _parse_float(limit, "velocity", math.inf, f"joint {name!r} limit.velocity")
    damping = _parse_float(element.find("dynamics"), "damping", 0.0,
                           f"joint {name!r} dynamics.damping")

    if joint_type in MOVABLE_JOINT_TYPES:
        axis_el = element.find("axis")
        axis = _parse_vector(axis_el.get("xyz") if axis_el is not None else None, (1, 0, 0),
                             f"joint {name!r} axis.xyz")
        norm = float(np.linalg.norm(axis))
        if norm < 1e-9:
            raise ValueError(f"joint {name!r} axis.xyz: zero axis")
        axis = axis / norm
    else:
        axis = np.zeros(3)

    if joint_type == "continuous":
        lower, upper = -math.inf, math.inf
    elif joint_type == "revolute":
        if limit is None:
            raise ValueError(f"joint {name!r} limit: a revolute joint needs <limit lower upper>")
        lower = _parse_float(limit, "lower", 0.0, f"joint {name!r} limit.lower")
        upper = _parse_float(limit, "upper", 0.0, f"joint {name!r} limit.upper")
        if not lower <= upper:
            raise ValueError(f"joint {name!r} limit: lower {lower} > upper {upper}")
    else:
        lower = _parse_float(limit, "lower", 0.0, f"joint {name!r} limit.lower")
        upper = _parse_float(limit, "upper", 0.0, f"joint {name!r} limit.upper")

    return JointSpec(
        name=name,
        joint_type=joint_type,
        parent=parent,
        child=child,
        origin_xyz=_read_only(xyz),
        origin_rpy=_read_only(rpy),
        axis=_read_only(axis),
        lower=lower,
        upper=upper,
        effort=effort,
        velocity=velocity,
        damping=damping,
    )


def _chain_from_root(root: ET.Element, ee_link: str) -> tuple[str, list[JointSpec]]:
    """Root link name and the joints on the path root -> ee_link, in order."""
    links = [el.get("name", "") for el in root.findall("link")]
    if ee_link not in links:
        raise ValueError(f"ee_link {ee_link!r} is not a link of the URDF; links: {links}")

    joint_by_child: dict[str, ET.Element] = {}
    for joint_el in root.findall("joint"):
        child_el = joint_el.find("child")
        child = child_el.get("link") if child_el is not None else None
        if child in joint_by_child:
            raise ValueError(f"URDF: link {child!r} is the child of more than one joint")
        if child is not None:
            joint_by_child[child] = joint_el
    roots = [name for name in links if name not in joint_by_child]
    if len(roots) != 1:
        raise ValueError(f"URDF: expected exactly one root link, found {roots}")
    base_link = roots[0]

    path: list[ET.Element] = []
    link = ee_link
    while link in joint_by_child:
        joint_el = joint_by_child[link]
        path.append(joint_el)
        if len(path) > len(joint_by_child):
            raise ValueError(f"URDF: the joints above link {ee_link!r} form a cycle")
        parent_el = joint_el.find("parent")
        link = parent_el.get("link", "") if parent_el is not None else ""
    if link != base_link:
        raise ValueError(f"no path from root link {base_link!r} to ee_link {ee_link!r}")
    path.reverse()

    joints = [_parse_joint(el) for el in path]
    for joint in joints:
        if joint.joint_type not in SUPPORTED_JOINT_TYPES:
            raise ValueError(
                f"joint {joint.name!r} on the path to {ee_link!r} has type {joint.joint_type!r}; "
                f"supported: {SUPPORTED_JOINT_TYPES}"
            )
    for joint_el in path:
        if joint_el.find("mimic") is not None:
            raise ValueError(f"joint {joint_el.get('name')!r}: mimic joints are not supported")
    if not any(joint.movable for joint in joints):
        raise ValueError(f"no path: no movable joint between {base_link!r} and {ee_link!r}")
    return base_link, joints


class SerialChain:
    """Kinematic model of one serial arm from its URDF root link to an end-effector link.

    Every pose-dependent quantity is in the root (base) link frame. ``q`` is a (n,) vector of
    the movable joint angles in rad, base to tip; ``params`` is an optional (p,) kinematic
    parameter vector ``a`` in m replacing :attr:`nominal_params`.

    Internally the chain is split into n + 1 segments: segment 0 is expressed in the root frame,
    segment i + 1 in the child frame F_{i+1} of movable joint i. Fixed-joint rotations are folded
    into constants, so one evaluation does n - 1 small matrix products whatever the fixed joints.
    """

    def __init__(self, urdf_path: Path, robot_name: str, base_link: str, ee_link: str,
                 joints: tuple[JointSpec, ...]) -> None:
        """Build the model from parsed joints (root to ee); use :meth:`from_urdf` to read a file."""
        self.urdf_path = urdf_path
        self.robot_name = robot_name
        self.base_link = base_link
        self.ee_link = ee_link
        self.joints = joints
        movable = [j for j in joints if j.movable]
        self.joint_names: tuple[str, ...] = tuple(j.name for j in movable)
        self.n_joints: int = len(movable)
        self.lower = _read_only(np.array([j.lower for j in movable]))
        self.upper = _read_only(np.array([j.upper for j in movable]))
        self.effort_limits = _read_only(np.array([j.effort for j in movable]))
        self.velocity_limits = _read_only(np.array([j.velocity for j in movable]))
        self.joint_damping = _read_only(np.array([j.damping for j in movable]))
        self.continuous = _read_only(np.array([j.joint_type == "continuous" for j in movable]))

        n = self.n_joints
        if n == 0:
            raise ValueError(f"no path: no movable joint between {base_link!r} and {ee_link!r}")
        # Rotation across movable joint i at angle q: P_i + sin(q) B_i + (1 - cos(q)) C_i
        # (Rodrigues, pre-multiplied by the constant rotations of the fixed joints since the
        # previous movable joint and of joint i's rpy).
        rot_p, rot_b, rot_c = np.empty((n, 3, 3)), np.empty((n, 3, 3)), np.empty((n, 3, 3))
        self._axes = np.array([j.axis for j in movable]).reshape(n, 3, 1)  # in frame F_{i+1}

        names: list[str] = []
        segments: list[int] = []
        directions: list[np.ndarray] = []  # unit vector of each parameter in its segment frame
        values: list[float] = []
        segment = 0
        constant = np.eye(3)  # rotation from the segment frame to the current joint's parent
        for joint in joints:
            for c in range(3):
                value = float(joint.origin_xyz[c])
                if abs(value) > PARAM_ZERO_TOL:
                    names.append(f"{joint.name}.{_AXIS_NAMES[c]}")
                    segments.append(segment)
                    directions.append(constant[:, c].copy())
                    values.append(value)
            rotation = constant @ rpy_to_matrix(joint.origin_rpy)
            if joint.movable:
                skew = _skew(joint.axis)
                rot_p[segment] = rotation
                rot_b[segment] = rotation @ skew
                rot_c[segment] = rotation @ skew @ skew
                segment += 1
                constant = np.eye(3)
            else:
                constant = rotation

        self.param_names: tuple[str, ...] = tuple(names)
        self.nominal_params = _read_only(np.array(values, dtype=float))
        p = len(names)
        self._param_segment = np.array(segments, dtype=np.intp)
        self._param_directions = np.array(directions, dtype=float).reshape(p, 3, 1)
        # Segment translations t (n + 1, 3) = reshape(_param_map @ a).
        self._param_map = np.zeros((n + 1, 3, p))
        for index, (seg, direction) in enumerate(zip(segments, directions)):
            self._param_map[seg, :, index] = direction
        self._param_map = self._param_map.reshape(3 * (n + 1), p)
        self._nominal_translations = (self._param_map @ self.nominal_params).reshape(n + 1, 3, 1)
        # Movable joint j (row) moves parameter i (column) iff parameter i's segment is after j.
        self._regressor_mask = np.arange(n)[:, None] < self._param_segment[None, :]
        # local_i = [1, sin q_i, cos q_i] @ basis_i with basis_i = [P + C, B, -C] (n, 3, 9);
        # the three coefficients are sin(q * [0, 1, 1] + [pi/2, 0, pi/2]) in one ufunc call.
        self._rot_basis = np.stack(
            [rot_p + rot_c, rot_b, -rot_c], axis=1).reshape(n, 3, 9)
        self._trig_scale = np.array([0.0, 1.0, 1.0])
        self._trig_phase = np.array([math.pi / 2, 0.0, math.pi / 2])
        # [lever_0; ...; lever_{n-1}; position] = _lever_sum @ steps, lever_i = sum_{s > i} steps_s.
        self._lever_sum = np.triu(np.ones((n + 1, n + 1)), k=1)
        self._lever_sum[n] = 1.0
        # The last (q bytes, (frames, axes)) evaluated by _pose.
        self._last_pose: tuple[bytes, tuple[np.ndarray, np.ndarray]] = (b"", (np.empty(0), np.empty(0)))

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_urdf(cls, urdf_path: str | os.PathLike, ee_link: str) -> "SerialChain":
        """Parse ``urdf_path`` and model the chain from its root link to ``ee_link``.

        Raises ValueError if the file is missing or not parseable, ``ee_link`` is not a link,
        there is no path, or a joint on the path is not revolute, continuous or fixed.
        """
        path = Path(urdf_path)
        if not path.is_file():
            raise ValueError(f"urdf file not found: {path}")
        try:
            root = ET.parse(path).getroot()
        except ET.ParseError as exc:
            raise ValueError(f"urdf file not parseable: {path}: {exc}") from None
        if root.tag != "robot":
            raise ValueError(f"urdf file not parseable: {path}: root element is <{root.tag}>, "
                             "expected <robot>")
        base_link, joints = _chain_from_root(root, ee_link)
        return cls(path.resolve(), root.get("name", ""), base_link, ee_link, tuple(joints))

    # ------------------------------------------------------------------ helpers
    @property
    def n_params(self) -> int:
        """Length p of the kinematic parameter vector."""
        return len(self.param_names)

    def __repr__(self) -> str:
        return (f"SerialChain({self.robot_name!r}, {self.base_link!r} -> {self.ee_link!r}, "
                f"n_joints={self.n_joints}, n_params={self.n_params})")

    def _translations(self, params: np.ndarray | list[float] | None) -> np.ndarray:
        """Segment translations (n + 1, 3, 1), m, for a parameter vector (None: nominal)."""
        if params is None:
            return self._nominal_translations
        a = np.asarray(params, dtype=float)
        if a.shape != (self.n_params,):
            raise ValueError(f"params: expected shape ({self.n_params},), got {a.shape}")
        return (self._param_map @ a).reshape(self.n_joints + 1, 3, 1)

    def _frames_batch(self, q_batch: np.ndarray) -> np.ndarray:
        """Segment frame orientations (n + 1, k, 3, 3) in the base frame for joint angles q_batch (k, n);
        frames[0] is the identity. The one chain product every kinematic quantity here is built on.

        Segment-major, so that each frames[i] is one contiguous (k, 3, 3) block for the product.
        """
        k, n = q_batch.shape
        trig = np.sin(q_batch[:, :, None] * self._trig_scale + self._trig_phase)  # [1, sin q, cos q], (k, n, 3)
        local = (trig[:, :, None, :] @ self._rot_basis).reshape(k, n, 3, 3)
        frames = np.empty((n + 1, k, 3, 3))
        frames[0] = _IDENTITY
        frames[1] = local[:, 0]
        for i in range(1, n):
            np.matmul(frames[i], local[:, i], out=frames[i + 1])  # distinct buffers: no overlap copy
        return frames

    def _check_batch(self, q_batch: np.ndarray) -> np.ndarray:
        q_batch = np.asarray(q_batch, dtype=float)
        if q_batch.ndim != 2 or q_batch.shape[1] != self.n_joints:
            raise ValueError(f"q_batch: expected shape (k, {self.n_joints}), got {q_batch.shape}")
        return q_batch

    def _pose(self, q: np.ndarray | list[float]) -> tuple[np.ndarray, np.ndarray]:
        """Segment frame orientations (n + 1, 3, 3) in the base frame (frames[0] = identity) and the joint
        axes (n, 3) in the base frame, both read-only.

        The last result is kept: a controller that asks for the regressor and then the Jacobian at the
        same ``q`` (bit for bit) evaluates the chain once.
        """
        q = np.asarray(q, dtype=float)
        if q.shape != (self.n_joints,):
            raise ValueError(f"q: expected shape ({self.n_joints},), got {q.shape}")
        key = q.tobytes()
        last_key, last_pose = self._last_pose
        if key == last_key:
            return last_pose
        frames = self._frames_batch(q[None])[:, 0]
        axes = (frames[1:] @ self._axes).reshape(-1, 3)
        frames.flags.writeable = False
        axes.flags.writeable = False
        self._last_pose = (key, (frames, axes))  # one assignment: readers never see a mixed pair
        return frames, axes

    def _frames(self, q: np.ndarray | list[float]) -> np.ndarray:
        """Segment frame orientations (n + 1, 3, 3) in the base frame; frames[0] = identity."""
        return self._pose(q)[0]

    # ------------------------------------------------------------------ kinematics
    def forward(self, q: np.ndarray | list[float],
                params: np.ndarray | list[float] | None = None) -> np.ndarray:
        """End-effector link frame position (3,) in the base link frame, m."""
        frames = self._frames(q)
        return (frames @ self._translations(params)).reshape(-1, 3).sum(axis=0)

    def jacobian(self, q: np.ndarray | list[float],
                 params: np.ndarray | list[float] | None = None) -> np.ndarray:
        """Translational Jacobian (3, n) of the end-effector position in the base frame, m/rad."""
        return self.forward_and_jacobian(q, params)[1]

    def forward_and_jacobian(self, q: np.ndarray | list[float],
                             params: np.ndarray | list[float] | None = None
                             ) -> tuple[np.ndarray, np.ndarray]:
        """End-effector position (3,), m, and translational Jacobian (3, n), m/rad, one pass."""
        frames, axes = self._pose(q)  # axes: (n, 3) joint axes in the base frame
        steps = (frames @ self._translations(params)).reshape(-1, 3)  # (n + 1, 3), base frame
        levers = self._lever_sum @ steps  # rows: ee position - joint origin, then ee position
        skews = (axes @ _SKEW_BASIS).reshape(-1, 3, 3)  # S(omega_i), omega_i x v = S v
        jac = (skews @ levers[:-1, :, None]).reshape(-1, 3)
        return levers[-1], jac.T

    def forward_and_jacobian_batch(self, q_batch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """End-effector positions (k, 3), m, and Jacobians (k, 3, n), m/rad, at joint angles q_batch (k, n),
        with the URDF's parameters: :meth:`forward_and_jacobian` for k configurations (e.g. k arms) at once."""
        q_batch = self._check_batch(q_batch)
        k, n = q_batch.shape
        frames = self._frames_batch(q_batch)
        steps = (frames @ self._nominal_translations[:, None]).reshape(n + 1, 3 * k)  # base frame
        levers = (self._lever_sum @ steps).reshape(n + 1, k, 3)  # ee - joint origins, then ee position
        axes = (frames[1:] @ self._axes[:, None]).reshape(n, k, 3)  # joint axes in the base frame
        jac = ((axes @ _SKEW_BASIS).reshape(n, k, 3, 3) @ levers[:-1, :, :, None]).reshape(n, k, 3)
        return levers[-1], jac.transpose(1, 2, 0)

    def forward_batch(self, q_batch: np.ndarray,
                      params: np.ndarray | list[float] | None = None) -> np.ndarray:
        """End-effector positions (k, 3), m, for joint angles q_batch (k, n), vectorized over k."""
        q_batch = self._check_batch(q_batch)
        frames = self._frames_batch(q_batch)
        return (frames @ self._translations(params)[:, None]).sum(axis=0)[:, :, 0]

    def regressor(self, q: np.ndarray | list[float], zeta: np.ndarray | list[float]) -> np.ndarray:
        """Kinematic regressor Z(q, zeta) (n, p) with J(q, a)^T zeta = Z(q, zeta) @ a for all a.

        ``zeta`` is a (3,) vector in the base frame, or (2,) for planar formations (z = 0).
        """
        q = np.asarray(q, dtype=float)
        if q.shape != (self.n_joints,):
            raise ValueError(f"q: expected shape ({self.n_joints},), got {q.shape}")
        zeta = np.asarray(zeta, dtype=float)
        if zeta.shape not in ((2,), (3,)):
            raise ValueError(f"zeta: expected shape (3,) or (2,), got {zeta.shape}")
        return self.regressor_batch(q[None], zeta[None])[0]

    def regressor_batch(self, q_batch: np.ndarray, zeta_batch: np.ndarray) -> np.ndarray:
        """Regressors Z(q_k, zeta_k) (k, n, p) of k configurations at once (:meth:`regressor` for k arms):
        ``zeta_batch`` (k, 3) in the base frame, or (k, 2) for planar formations (z = 0)."""
        q_batch = self._check_batch(q_batch)
        k, n = q_batch.shape
        zeta = np.asarray(zeta_batch, dtype=float)
        if zeta.shape == (k, 2):
            zeta = np.concatenate([zeta, np.zeros((k, 1))], axis=1)
        elif zeta.shape != (k, 3):
            raise ValueError(f"zeta_batch: expected shape ({k}, 3) or ({k}, 2), got {zeta.shape}")
        frames = self._frames_batch(q_batch)  # (n + 1, k, 3, 3)
        axes = (frames[1:] @ self._axes[:, None]).reshape(n, k, 1, 3)  # joint axes in the base frame
        # zeta . (omega_j x v) = (zeta x omega_j) . v, and zeta x omega = S(zeta) omega
        skews = (zeta @ _SKEW_BASIS).reshape(k, 3, 3)
        zeta_x_axes = (axes @ skews.transpose(0, 2, 1)).reshape(n, k, 3).transpose(1, 0, 2)  # (k, n, 3)
        columns = (frames[self._param_segment] @ self._param_directions[:, None]).reshape(-1, k, 3)  # (p, k, 3)
        return (zeta_x_axes @ columns.transpose(1, 2, 0)) * self._regressor_mask

    def sample_configurations(self, count: int, rng: np.random.Generator) -> np.ndarray:
        """Joint angles (count, n), rad, uniform within the limits; continuous in [-pi, pi)."""
        low = np.where(self.continuous, -math.pi, self.lower)
        high = np.where(self.continuous, math.pi, self.upper)
        return rng.uniform(low, high, size=(count, self.n_joints))


_IDENTITY = np.eye(3)
# v @ _SKEW_BASIS, reshaped to (3, 3), is the cross-product matrix S(v): S(v) @ w = v x w.
_SKEW_BASIS = np.stack([_skew(e) for e in np.eye(3)]).reshape(3, 9)


@functools.lru_cache(maxsize=32)
def chain_model(urdf: str, ee_link: str) -> SerialChain:
    """The (cached, shared) kinematic model of a URDF up to ``ee_link``."""
    return SerialChain.from_urdf(urdf, ee_link)


def smallest_singular_values(matrices: np.ndarray) -> np.ndarray:
    """Smallest singular value of each matrix of a stack (k, r, c).

    2 x 2 matrices [[a, b], [c, d]] use the closed form sigma_min = |hypot(a + d, b - c) - hypot(a - d, b + c)| / 2
    (the two hypotenuses are sigma_max + sigma_min and sigma_max - sigma_min), accurate to rounding relative to
    sigma_max and much cheaper than a LAPACK call at this size; other shapes use ``np.linalg.svd``.
    """
    if matrices.shape[1:] == (2, 2):
        a, b, c, d = matrices[:, 0, 0], matrices[:, 0, 1], matrices[:, 1, 0], matrices[:, 1, 1]
        return 0.5 * np.abs(np.hypot(a + d, b - c) - np.hypot(a - d, b + c))
    return np.linalg.svd(matrices, compute_uv=False).min(axis=1)


def singularity_margins(jacobians: np.ndarray, dim: int) -> np.ndarray:
    """Singularity margin (m) of each translational Jacobian of a stack (k, 3, n): the smallest singular
    value of its first ``dim`` rows (the formation's axes)."""
    return smallest_singular_values(jacobians[:, :dim])


class ChainBatch:
    """End-effector positions and singularity margins of several arms at once, from one flat joint vector.

    Arms that share one :class:`SerialChain` object are evaluated in one batched call (the cost of a call is
    mostly per call, not per arm, at these sizes).
    """

    def __init__(self, models: Sequence[SerialChain]):
        sizes = [model.n_joints for model in models]
        bounds = np.concatenate([[0], np.cumsum(sizes)]).astype(np.intp)
        groups: dict[int, list[int]] = {}
        for i, model in enumerate(models):
            groups.setdefault(id(model), []).append(i)
        # (model, member arms, their joints in the flat vector, or None when that is the whole vector in order)
        self._groups: list[tuple[SerialChain, np.ndarray, np.ndarray | None]] = []
        for members in groups.values():
            joints = np.concatenate([np.arange(bounds[i], bounds[i + 1]) for i in members])
            in_order = len(members) == len(models) and np.array_equal(joints, np.arange(bounds[-1]))
            self._groups.append((models[members[0]], np.array(members), None if in_order else joints))
        self.n_arms = len(models)

    def positions_and_margins(self, q: np.ndarray, dim: int) -> tuple[np.ndarray, np.ndarray]:
        """Each arm's end-effector position in its base frame (N, 3), m, and singularity margin (N,), m
        (smallest singular value of its Jacobian's first ``dim`` rows), at flat joint angles ``q`` (rad).

        With leading axes (a stack of joint vectors, e.g. ``(K, T)`` for K copies of the arms), the results
        get the same leading axes (``(K, N, 3)``, ``(K, N)``), still in one batched call per model; each
        copy's values are bit for bit those of its own call."""
        lead = q.shape[:-1]
        count = math.prod(lead)
        if len(self._groups) == 1 and self._groups[0][2] is None:  # one model, every arm, in agent order
            model = self._groups[0][0]
            positions, jacobians = model.forward_and_jacobian_batch(q.reshape(count * self.n_arms, -1))
            return (positions.reshape(*lead, self.n_arms, 3),
                    singularity_margins(jacobians, dim).reshape(*lead, self.n_arms))
        flat = q.reshape(count, -1)
        positions, margins = np.empty((count, self.n_arms, 3)), np.empty((count, self.n_arms))
        for model, members, joints in self._groups:
            q_group = flat if joints is None else flat[:, joints]
            group_positions, jacobians = model.forward_and_jacobian_batch(q_group.reshape(count * len(members), -1))
            positions[:, members] = group_positions.reshape(count, len(members), 3)
            margins[:, members] = singularity_margins(jacobians, dim).reshape(count, len(members))
        return positions.reshape(*lead, self.n_arms, 3), margins.reshape(*lead, self.n_arms)
