"""Checks for assets/pera_arm.urdf; run as ``python assets/check_pera.py``.

Loads the arm in PyBullet DIRECT with ``useFixedBase=True`` and ``URDF_USE_INERTIA_FROM_FILE``
(without that flag PyBullet recomputes inertias from the collision shapes) and reports:

* that every inertia tensor in the file is physically valid (positive principal moments that
  satisfy the triangle inequality; the massless ``ee_link`` all zero) and that PyBullet kept it;
* that every joint axis is unit length;
* min / median lambda_min(H(q)) over random q within the joint limits, and the largest step
  size that explicit damping with K_D = 20 N m s/rad tolerates, dt < 2 lambda_min / K_D;
* max over q of |G_j(q)| / effort_j (gravity (0, 0, -9.81)), over random q and over the
  3^7 grid {lower, 0 (clipped into the range), upper}, which holds the worst case
  (arm stretched horizontally);
* the reach, max |p_ee(q)| from the base origin;
* the end-effector position at q = 0 (straight below the base, up to the description's two
  0.01 m forward offsets at the elbow and wrist);
* a 2 s damped run at 1 ms (tau = G(q) - K_D dq) that must come to rest.

Exits with status 1 if any check fails.
"""

from __future__ import annotations

import itertools
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pybullet as p

URDF = Path(__file__).resolve().parent / "pera_arm.urdf"
EE_LINK = "ee_link"
N_SAMPLES = 4000
K_D = 20.0
DT = 1e-3
LAMBDA_MIN_REQUIRED = 0.015
SEED = 0


def inertia_checks(root: ET.Element) -> list[tuple[str, float, float, float, bool]]:
    """(link, mass, smallest principal moment, triangle margin, ok) for every link."""
    rows = []
    for link in root.findall("link"):
        inertial = link.find("inertial")
        if inertial is None:
            rows.append((link.get("name"), float("nan"), float("nan"), float("nan"), False))
            continue
        m = float(inertial.find("mass").get("value"))
        a = {k: float(v) for k, v in inertial.find("inertia").attrib.items()}
        tensor = np.array(
            [
                [a["ixx"], a["ixy"], a["ixz"]],
                [a["ixy"], a["iyy"], a["iyz"]],
                [a["ixz"], a["iyz"], a["izz"]],
            ]
        )
        ev = np.linalg.eigvalsh(tensor)
        margin = ev[0] + ev[1] - ev[2]  # triangle inequality: the largest <= the sum of the others
        if m == 0.0:
            ok = bool(np.all(tensor == 0.0))
        else:
            ok = m > 0.0 and ev[0] > 0.0 and margin > 0.0
        rows.append((link.get("name"), m, ev[0], margin, ok))
    return rows


def main() -> int:
    root = ET.parse(URDF).getroot()
    failures: list[str] = []

    # --- inertia tensors and axes, from the file ---
    inertia_rows = inertia_checks(root)
    for name, _, _, _, ok in inertia_rows:
        if not ok:
            failures.append(f"invalid inertia tensor: {name}")
    for joint in root.findall("joint"):
        axis = joint.find("axis")
        if axis is not None:
            norm = np.linalg.norm([float(x) for x in axis.get("xyz").split()])
            if abs(norm - 1.0) > 1e-12:
                failures.append(f"axis of {joint.get('name')} has length {norm}")

    # --- PyBullet ---
    client = p.connect(p.DIRECT)
    p.setGravity(0, 0, -9.81, physicsClientId=client)
    body = p.loadURDF(
        str(URDF), useFixedBase=True, flags=p.URDF_USE_INERTIA_FROM_FILE, physicsClientId=client
    )
    n_joints = p.getNumJoints(body, physicsClientId=client)
    infos = [p.getJointInfo(body, j, physicsClientId=client) for j in range(n_joints)]
    joints = [i[0] for i in infos if i[2] == p.JOINT_REVOLUTE]
    ee = next(i[0] for i in infos if i[12].decode() == EE_LINK)
    lo = np.array([infos[j][8] for j in joints])
    hi = np.array([infos[j][9] for j in joints])
    effort = np.array([infos[j][10] for j in joints])
    n = len(joints)
    if n != 7:
        failures.append(f"expected 7 revolute joints, found {n}")

    # PyBullet zeroes tensors it finds invalid ("Bad inertia tensor properties"): compare.
    file_moments = {name: mmin for name, _, mmin, _, _ in inertia_rows}
    for j in range(n_joints):
        name = infos[j][12].decode()
        local = p.getDynamicsInfo(body, j, physicsClientId=client)[2]
        if file_moments.get(name, 0.0) > 0.0 and min(local) <= 0.0:
            failures.append(f"PyBullet zeroed the inertia of {name}")

    def mass_matrix(q: np.ndarray) -> np.ndarray:
        return np.array(p.calculateMassMatrix(body, [float(x) for x in q], physicsClientId=client))

    def gravity(q: np.ndarray) -> np.ndarray:
        zeros = [0.0] * n
        return np.array(
            p.calculateInverseDynamics(
                body, [float(x) for x in q], zeros, zeros, physicsClientId=client
            )
        )

    def ee_position(q: np.ndarray) -> np.ndarray:
        for j, x in zip(joints, q):
            p.resetJointState(body, j, float(x), 0.0, physicsClientId=client)
        return np.array(
            p.getLinkState(body, ee, computeForwardKinematics=True, physicsClientId=client)[4]
        )

    rng = np.random.default_rng(SEED)
    samples = rng.uniform(lo, hi, size=(N_SAMPLES, n))
    lam = np.array([np.linalg.eigvalsh(mass_matrix(q))[0] for q in samples])
    levels = [(a, float(np.clip(0.0, a, b)), b) for a, b in zip(lo, hi)]
    grid = np.array(list(itertools.product(*levels)))
    g_ratio = np.array([np.abs(gravity(q)) / effort for q in np.vstack([samples, grid])])
    reach = max(np.linalg.norm(ee_position(q)) for q in samples)
    stretched = np.linalg.norm(ee_position(np.zeros(n)))
    p_zero = ee_position(np.zeros(n))

    # --- damped run: tau = G(q) - K_D dq at 1 ms from a mid-range pose ---
    p.setTimeStep(DT, physicsClientId=client)
    p.setJointMotorControlArray(
        body, joints, p.VELOCITY_CONTROL, forces=[0.0] * n, physicsClientId=client
    )
    for j in range(-1, n_joints):
        p.changeDynamics(body, j, linearDamping=0.0, angularDamping=0.0, jointDamping=0.0,
                         physicsClientId=client)
    q0 = 0.5 * (lo + hi)
    dq0 = rng.uniform(-1.0, 1.0, size=n)
    for j, x, v in zip(joints, q0, dq0):
        p.resetJointState(body, j, float(x), float(v), physicsClientId=client)
    peak = 0.0
    for _ in range(int(2.0 / DT)):
        states = p.getJointStates(body, joints, physicsClientId=client)
        q = np.array([s[0] for s in states])
        dq = np.array([s[1] for s in states])
        peak = max(peak, float(np.abs(dq).max()))
        tau = gravity(q) - K_D * dq
        p.setJointMotorControlArray(
            body, joints, p.TORQUE_CONTROL, forces=tau.tolist(), physicsClientId=client
        )
        p.stepSimulation(physicsClientId=client)
    final = p.getJointStates(body, joints, physicsClientId=client)
    dq_end = float(np.abs([s[1] for s in final]).max())
    p.disconnect(physicsClientId=client)

    # --- verdicts ---
    lam_min = float(lam.min())
    dt_max = 2.0 * lam_min / K_D
    g_max = g_ratio.max(axis=0)
    horizontal = float(np.hypot(p_zero[0], p_zero[1]))
    if lam_min < LAMBDA_MIN_REQUIRED:
        failures.append(f"lambda_min(H) = {lam_min:.4f} < {LAMBDA_MIN_REQUIRED}")
    if g_max.max() >= 1.0:
        failures.append(f"gravity torque exceeds effort: max ratio {g_max.max():.3f}")
    if not (p_zero[2] < 0.0 and horizontal <= 0.02 + 1e-9 and abs(p_zero[1]) < 1e-12):
        failures.append(f"ee at q = 0 is not below the base: {p_zero}")
    if dq_end > 1e-3 or peak > 10.0:
        failures.append(f"damped run did not settle: peak |dq| {peak:.3f}, final {dq_end:.2e}")

    print(f"pera_arm.urdf checks ({N_SAMPLES} random q, seed {SEED}; URDF_USE_INERTIA_FROM_FILE)")
    print(f"{'link':<10} {'mass kg':>8} {'min moment':>11} {'triangle margin':>16}  valid")
    for name, m, mmin, margin, ok in inertia_rows:
        print(f"{name:<10} {m:8.3f} {mmin:11.3e} {margin:16.3e}  {'yes' if ok else 'NO'}")
    rows = [
        ("lambda_min(H): min / median [kg m^2]", f"{lam_min:.4f} / {np.median(lam):.4f}"),
        (
            f"dt limit 2 lambda_min / K_D (K_D = {K_D:g})",
            f"{dt_max * 1e3:.2f} ms (need > {DT * 1e3:g} ms)",
        ),
        ("max_q |G_j| / effort_j, joints 1..7", " ".join(f"{x:.3f}" for x in g_max)),
        ("max_q |G_j| / effort_j, all joints", f"{g_max.max():.3f} (must be < 1)"),
        ("reach max |p_ee| over samples [m]", f"{reach:.4f} (stretched arm {stretched:.4f})"),
        ("p_ee at q = 0 [m]", " ".join(f"{x:+.4f}" for x in p_zero)),
        ("  horizontal offset at q = 0 [m]", f"{horizontal:.4f} (two 0.01 m offsets)"),
        ("damped run 2 s @ 1 ms: peak / final |dq|", f"{peak:.3f} / {dq_end:.1e} rad/s"),
    ]
    width = max(len(r[0]) for r in rows)
    for label, value in rows:
        print(f"{label:<{width}}  {value}")
    if failures:
        print("FAILED:\n  " + "\n  ".join(failures))
        return 1
    print("all checks passed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
