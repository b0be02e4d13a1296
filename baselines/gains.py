"""Default gains of the reference controllers, and the rule that derives them for any robot.

Built-in scenarios have tuned defaults that respect the scenario's torque limits (:data:`SCENARIO_GAINS`);
:data:`PAPER_GAINS` are the paper's (they need torque limits lifted and 1 ms control steps). For any
other scenario :func:`derive_gains` computes gains from the agent's nominal model and control step:

1. Damping: explicit (sampled) velocity feedback is stable only for ``dt < 2 lambda_min(H) / K_D``
   (FACTS.md), so ``K_D = min(K_D_max, lambda_min(H) / dt)``: half that bound, capped at
   ``K_D_max = 20 N m s/rad``. ``lambda_min(H)`` is the smallest eigenvalue of the nominal mass matrix
   over sampled configurations within the joint limits.
2. Formation gain from the torque budget: ``K_P = 0.5 tau_min / (reach * e_ref)``, where ``e_ref`` is the
   agent gradient |e_hat| produced by a 10 % error on each incident edge (``2 * 2 d^2 0.1 * d`` per edge
   for distance formations, ``0.1 d`` for displacement ones), so that such an error asks for half the
   weakest joint's torque.
3. Internal model: ``K_I = 1 1/s`` when gravity acts on the joints, else 0; adaptation ``alpha`` is the
   inverse of the largest ``|Z|^2`` at that reference error (a unit adaptation rate).
"""

from __future__ import annotations

import functools

import numpy as np

from baselines.controllers import Gains
from baselines.dynamics import nominal_dynamics
from ee_formation_env.env import FormationEnv
from ee_formation_env.validation import chain_model

# Tuned for the built-in scenarios under their default torque limits (see README, "Reference policies").
SCENARIO_GAINS: dict[str, Gains] = {
    "planar_square": Gains(kp=5.0, kd=20.0, ki=0.0, alpha=0.02),
    "planar_square_rotated": Gains(kp=5.0, kd=20.0, ki=0.0, alpha=0.02),
    "planar_square_displacement": Gains(kp=60.0, kd=20.0, ki=0.0, alpha=0.5),
    "spatial_tetrahedron": Gains(kp=120.0, kd=2.0, ki=1.0, alpha=0.01),
    "spatial_tetrahedron_displacement": Gains(kp=20.0, kd=2.0, ki=1.0, alpha=1.0),
}

# The paper's gains (Sec. VI): 2D alpha = 0.02, K_P = 800, K_D = 180; 3D alpha = 0.01, K_P = 120, K_I = 1, K_D = 20.
PAPER_GAINS: dict[int, Gains] = {
    2: Gains(kp=800.0, kd=180.0, ki=0.0, alpha=0.02),
    3: Gains(kp=120.0, kd=20.0, ki=1.0, alpha=0.01),
}

K_D_MAX = 20.0  # N m s/rad


def default_gains(env: FormationEnv, agent: str) -> Gains:
    """Tuned gains for a built-in scenario (by name), else :func:`derive_gains`."""
    if env.scenario.name in SCENARIO_GAINS:
        return SCENARIO_GAINS[env.scenario.name]
    return derive_gains(env, agent)


def derive_gains(env: FormationEnv, agent: str) -> Gains:
    """Gains from the agent's nominal model, torque limits and control step (rule in the module docstring)."""
    i = env.possible_agents.index(agent)
    chain = env.nominal_models[i]
    dt = env.scenario.control_dt
    lambda_min = _smallest_inertia(env.scenario.arms[i].urdf, env.scenario.arms[i].ee_link)
    kd = min(K_D_MAX, lambda_min / dt)

    neighbors = env.graph.neighbors[i]
    lengths = np.linalg.norm(env.formation.desired_vectors[[n.edge for n in neighbors]], axis=1)
    if env.formation.kind == "distance":
        e_ref = float(np.sum(2.0 * (2.0 * lengths**2 * 0.1) * lengths))
    else:
        e_ref = float(np.sum(0.1 * lengths))
    reach = float(np.max(np.linalg.norm(chain.forward_batch(chain.sample_configurations(
        256, np.random.default_rng(0))), axis=1)))
    kp = 0.5 * float(np.min(env.torque_limits[i])) / (reach * max(e_ref, 1e-9))

    gravity_acts = np.linalg.norm(env.gravity_in_base_frame(agent)) > 0 and _gravity_loads_joints(env, i)
    q0 = env.nominal_initial_q(agent)
    zeta = np.zeros(3)
    zeta[0] = e_ref
    regressor = chain.regressor(q0, zeta)
    alpha = 1.0 / max(float(np.sum(regressor**2)), 1e-9)
    return Gains(kp=kp, kd=kd, ki=1.0 if gravity_acts else 0.0, alpha=alpha)


@functools.lru_cache(maxsize=32)
def _smallest_inertia(urdf: str, ee_link: str) -> float:
    """Smallest eigenvalue of the nominal mass matrix over 200 sampled configurations (kg m^2)."""
    chain = chain_model(urdf, ee_link)
    dynamics = nominal_dynamics(urdf, chain.joint_names)
    samples = chain.sample_configurations(200, np.random.default_rng(0))
    return float(min(np.linalg.eigvalsh(dynamics.mass_matrix(q))[0] for q in samples))


def _gravity_loads_joints(env: FormationEnv, index: int) -> bool:
    chain = env.nominal_models[index]
    dynamics = nominal_dynamics(env.scenario.arms[index].urdf, chain.joint_names)
    samples = chain.sample_configurations(16, np.random.default_rng(0))
    gravity = env.gravity_in_base_frame(env.possible_agents[index])
    return max(float(np.max(np.abs(dynamics.gravity_torque(q, gravity)))) for q in samples) > 1e-6
