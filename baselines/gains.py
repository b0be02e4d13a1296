"""Default gains of the reference controllers, and the rule that derives them for any robot.

Built-in scenarios carry gains tuned for their default torque limits and rates (their ``controller_gains``,
dropped by any override of their physics); :data:`PAPER_GAINS` are the paper's (they need torque limits
lifted and 1 ms control steps). For any other scenario :func:`derive_gains` computes gains from the task
(the agent's nominal model, torque limits and control step), no env needed:

1. Damping, per joint: sampled velocity feedback ``dq+ = dq - dt H^-1 K_D dq`` is stable only while the
   spectral radius ``dt rho(H^-1 K_D) < 2`` (``docs/physics.md``: ``dt < 2 lambda_min(H) / K_D`` for a scalar gain).
   Each joint gets ``K_D,j = min(K_D_max, 1 / (dt max_q (H^-1)_jj))`` (its effective inertia over the
   step), then all are scaled down together until ``dt rho(H^-1 K_D) <= 1`` (half the limit) at every
   sampled configuration; ``K_D_max = 20 N m s/rad``. A robot whose light distal joints leave little damping
   at the scenario's control step needs a smaller step (``frame_skip``) or reflected rotor inertia.
2. Formation gain from the torque budget, per joint: ``K_P,j = 0.5 tau_j / (reach * e_ref)``, where
   ``e_ref`` is the agent gradient |e_hat| produced by a 10 % error on each incident edge
   (``2 * 2 d^2 0.1 * d`` per edge for distance formations, ``0.1 d`` for displacement ones), so that such
   an error asks each joint for about half its torque limit ``tau_j``.
3. Internal model: ``K_I = 1 1/s`` when gravity acts on the joints, else 0; adaptation ``alpha`` is the
   inverse of the largest ``|Z|^2`` at that reference error (a unit adaptation rate).
"""

from __future__ import annotations

import functools

import numpy as np

from baselines.controllers import Gains
from baselines.dynamics import nominal_dynamics
from ee_formation_env.kinematics import chain_model
from ee_formation_env.task import FormationTask

# The paper's gains (Sec. VI): 2D alpha = 0.02, K_P = 800, K_D = 180; 3D alpha = 0.01, K_P = 120, K_I = 1, K_D = 20.
PAPER_GAINS: dict[int, Gains] = {
    2: Gains(kp=800.0, kd=180.0, ki=0.0, alpha=0.02),
    3: Gains(kp=120.0, kd=20.0, ki=1.0, alpha=0.01),
}

K_D_MAX = 20.0  # N m s/rad


def default_gains(task: FormationTask, index: int) -> Gains:
    """The scenario's own tuned gains where it carries them (built-ins, unmodified physics), else
    :func:`derive_gains`."""
    tuned = task.scenario.controller_gains
    if tuned is not None:
        return Gains(kp=tuned.kp, kd=tuned.kd, ki=tuned.ki, alpha=tuned.alpha)
    return derive_gains(task, index)


def derive_gains(task: FormationTask, index: int) -> Gains:
    """Gains for arm ``index`` from the task: nominal model, torque limits and control step (module docstring)."""
    chain = task.models[index]
    arm = task.scenario.arms[index]
    dt = task.scenario.control_dt
    kd = stable_damping(arm.urdf, arm.ee_link, dt)

    neighbors = task.graph.neighbors[index]
    lengths = np.linalg.norm(task.formation.desired_vectors[[n.edge for n in neighbors]], axis=1)
    if task.formation.kind == "distance":
        e_ref = float(np.sum(2.0 * (2.0 * lengths**2 * 0.1) * lengths))
    else:
        e_ref = float(np.sum(0.1 * lengths))
    kp = 0.5 * task.torque_limits[index] / (task.reaches[index] * max(e_ref, 1e-9))

    gravity_acts = np.linalg.norm(task.gravity_in_base_frame(index)) > 0 and _gravity_loads_joints(task, index)
    zeta = np.zeros(3)
    zeta[0] = e_ref
    regressor = chain.regressor(task.initial_q[index], zeta)
    alpha = 1.0 / max(float(np.sum(regressor**2)), 1e-9)
    return Gains(kp=kp, kd=kd, ki=1.0 if gravity_acts else 0.0, alpha=alpha)


@functools.lru_cache(maxsize=64)
def stable_damping(urdf: str, ee_link: str, dt: float) -> np.ndarray:
    """Per-joint damping gains (N m s/rad) by rule 1 of the module docstring."""
    chain = chain_model(urdf, ee_link)
    dynamics = nominal_dynamics(urdf, chain.joint_names)
    inverses = [np.linalg.inv(dynamics.mass_matrix(q))
                for q in chain.sample_configurations(200, np.random.default_rng(0))]
    worst_diagonal = np.max([np.diag(inverse) for inverse in inverses], axis=0)
    kd = np.minimum(K_D_MAX, 1.0 / (dt * worst_diagonal))
    radius = max(float(np.max(np.abs(np.linalg.eigvals(dt * inverse * kd)))) for inverse in inverses)
    return kd / max(radius, 1.0)


def _gravity_loads_joints(task: FormationTask, index: int) -> bool:
    chain = task.models[index]
    dynamics = nominal_dynamics(task.scenario.arms[index].urdf, chain.joint_names)
    samples = chain.sample_configurations(16, np.random.default_rng(0))
    gravity = task.gravity_in_base_frame(index)
    return max(float(np.max(np.abs(dynamics.gravity_torque(q, gravity)))) for q in samples) > 1e-6
