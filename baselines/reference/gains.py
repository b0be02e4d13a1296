"""Default gains of the reference controllers, and the rule that derives them for any scenario.

Built-in scenarios carry gains tuned for their default torque limits and rates (their ``controller_gains``,
dropped by any override of their physics); :data:`PAPER_GAINS` are the paper's (they need torque limits
lifted and 1 ms control steps). For any other scenario :func:`derive_gains` computes gains from the task
(nominal models, torque limits, mounting, graph, shape and control step; no env needed) by
:func:`formation_gains`, for the paper's laws with saturated virtual springs
(:mod:`ee_formation_env.baselines.reference.controllers`). K_P is one scalar for the whole team and each
edge's force limit is the same at both its ends, so ``-K_P J^T e_hat`` stays the gradient of one potential;
damping, internal-model and adaptation gains are per arm. The rules, each evaluated at sampled
configurations (seeded) plus the initial one:

1. **Damping**, per joint: ``K_D,j = min(K_D_MAX, 1 / (dt max_q (H^-1)_jj))``, all scaled down together
   until ``beta = dt rho(H^-1 K_D) <= BETA`` (``<= GRAVITY_BETA`` where gravity loads the joints), then
   ``K_D,j <= 0.5 spare_j / JOINT_SPEED`` so that the formation's torque share still moves each joint.
2. **Spring forces** from the torque budget: spare torque = limit minus the largest gravity torque (never
   below ``SPARE_TORQUE_FLOOR`` of the limit); arm i takes ``F_i = TORQUE_SHARE min_j spare_j /
   max_q |J[:, j](q)|``; edge k saturates at ``F_k = min(F_tail, F_head)`` (N).
3. **Formation gain**: ``K_P = KAPPA / (dt^2 lambda_max(S) max_i max_q lambda_max(J_i H_i^-1 J_i^T))``, with
   S = ``4 R^T R`` (distance, R the rigidity matrix) or ``B B^T`` (displacement) at the target shape.
4. **Internal model and adaptation**: ``K_I = min(INTERNAL_MODEL_GAIN, 0.1 / dt)`` where gravity loads the
   joints, else 0; ``Gamma`` bounds the ``Z^T dq`` term's change of a_hat to ``ESTIMATE_CHANGE`` of ``|a|``
   over one reach, ``alpha`` the decay rate ``Gamma alpha |Z|^2`` to ``ADAPTATION_RATE``.
5. **Gradient-rate damping** ``K_R = RATE_STEPS dt`` (``Gains.rate_gain``); :func:`mode_decay` is the
   one-mode model behind rules 1, 3 and 5.
6. **Manoeuvre reference hold**, on a scenario with an active ``manoeuvre`` only, for tuned and derived gains
   alike: ``K_X = HOLD_SHARE K_P lambda_max(S)`` (``Gains.reference_stiffness``, N/m), a share of the
   formation's own stiffness at the target, so that where the hold and the shape disagree the shape wins.

The derivation of each rule, the stability limits and the measurements behind the constants: see
docs/controllers.md ("Gains"); the rule on random scenarios: docs/results.md.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ee_formation_env.baselines.reference.controllers import Gains
from ee_formation_env.baselines.reference.dynamics import NominalDynamics, nominal_dynamics
from ee_formation_env.formation import rigidity_matrix
from ee_formation_env.kinematics import SerialChain
from ee_formation_env.task import FormationTask

# The paper's gains (Sec. VI): 2D alpha = 0.02, K_P = 800, K_D = 180; 3D alpha = 0.01, K_P = 120, K_I = 1, K_D = 20.
PAPER_GAINS: dict[int, Gains] = {
    2: Gains(kp=800.0, kd=180.0, ki=0.0, alpha=0.02),
    3: Gains(kp=120.0, kd=20.0, ki=1.0, alpha=0.01),
}

K_D_MAX = 20.0  # N m s/rad, rule 1
TORQUE_SHARE = 0.5  # rule 2: share of the spare torque the formation force may use (the rest: damping)
SPARE_TORQUE_FLOOR = 0.2  # rule 2: spare torque never counted below this share of the limit
KAPPA = 0.5  # rule 3: bound on dt^2 rho(H^-1 K_q); the limit 2 (2 - dt rho(H^-1 K_D)) is >= 2 under rule 1
INTERNAL_MODEL_GAIN = 5.0  # 1/s, rule 4: K_I where gravity loads the joints (at most 0.1 / dt)
ADAPTATION_RATE = 0.1  # 1/s, rule 4: largest decay rate of a_hat at the saturated gradient
ESTIMATE_CHANGE = 0.1  # rule 4: largest relative change of a_hat by the Z^T dq term over one reach of travel
JOINT_SPEED = 0.5  # rad/s, rule 1: joint speed the formation's torque share reaches against the damping
BETA = 0.1  # rule 1: bound on dt rho(H^-1 K_D)
GRAVITY_BETA = 1.0  # rule 1: the bound where gravity loads the joints (K_I > 0, rule 4)
RATE_STEPS = 1.5  # rule 5: K_R in control steps
HOLD_SHARE = 0.25  # rule 6: K_X as a share of the formation's stiffness K_P lambda_max(S)

_TEAM_GAINS: "weakref.WeakKeyDictionary[FormationTask, list[Gains]]" = weakref.WeakKeyDictionary()


def default_gains(task: FormationTask, index: int) -> Gains:
    """The scenario's own tuned gains where it carries them (built-ins, unmodified physics), else
    :func:`derive_gains`; with an active manoeuvre, the reference hold of rule 6 (:func:`reference_stiffness`)."""
    tuned = task.scenario.controller_gains
    if tuned is not None:
        gains = Gains(kp=tuned.kp, kd=tuned.kd, ki=tuned.ki, alpha=tuned.alpha)
    else:
        gains = derive_gains(task, index)
    manoeuvre = task.scenario.manoeuvre
    if manoeuvre is not None and manoeuvre.active:
        gains = gains.with_updates(reference_stiffness=reference_stiffness(task, gains.kp))
    return gains


def reference_stiffness(task: FormationTask, kp: float) -> float:
    """Rule 6: the manoeuvre's reference hold ``K_X = HOLD_SHARE K_P lambda_max(S)``, N/m, for formation gain
    ``kp`` (the largest, if per joint)."""
    return float(HOLD_SHARE * np.max(kp) * formation_stiffness(task))


def derive_gains(task: FormationTask, index: int) -> Gains:
    """Gains for arm ``index`` of ``task`` by :func:`formation_gains` (module docstring); computed once per task.

    A thin caller: it collects each arm's nominal model, limits and mounting, the arms' edges and the
    formation's stiffness at the target. K_P is common to all arms, each edge's spring force to both its ends.
    """
    if task not in _TEAM_GAINS:
        incident = [[neighbor.edge for neighbor in neighbors] for neighbors in task.graph.neighbors]
        _TEAM_GAINS[task] = formation_gains(arm_inputs(task), task.scenario.control_dt, task.formation.kind, incident,
                                            formation_stiffness(task))
    return _TEAM_GAINS[task][index]


def formation_stiffness(task: FormationTask) -> float:
    """Largest eigenvalue of ``d(e_hat)/dx`` at the target shape: ``4 R^T R`` (R the rigidity matrix) for
    distance formations, ``B B^T`` (the graph Laplacian) for displacement ones; per unit K_P (m^2 or 1)."""
    shape = np.asarray(task.scenario.shape, dtype=np.float64)[:, :task.dim]
    if task.formation.kind == "distance":
        rigidity = rigidity_matrix(task.graph, shape)
        return float(np.max(np.linalg.eigvalsh(4.0 * rigidity.T @ rigidity)))
    incidence = task.graph.incidence
    return float(np.max(np.linalg.eigvalsh(incidence @ incidence.T)))


def arm_inputs(task: FormationTask) -> list["ArmGainInputs"]:
    """What :func:`formation_gains` needs of each arm of ``task``."""
    arms = []
    for i, chain in enumerate(task.models):
        arms.append(ArmGainInputs(
            chain=chain, dynamics=nominal_dynamics(task.scenario.arms[i].urdf, chain.joint_names),
            torque_limits=np.asarray(task.torque_limits[i], dtype=np.float64),
            gravity_in_base=task.gravity_in_base_frame(i), initial_q=np.asarray(task.initial_q[i]),
            dim=task.dim))
    return arms


@dataclass(frozen=True)
class ArmGainInputs:
    """What the gain rule needs to know about one arm (all nominal; SI units)."""

    chain: SerialChain  # nominal kinematics
    dynamics: NominalDynamics  # nominal mass matrix and gravity torque
    torque_limits: np.ndarray  # (n,) N m
    gravity_in_base: np.ndarray  # (3,) m/s^2, world gravity in the arm's base frame
    initial_q: np.ndarray  # (n,) rad
    dim: int  # 2 or 3: the formation's coordinates (rows of the Jacobian that matter)


@dataclass(frozen=True)
class ArmGainLimits:
    """Per-arm results of rules 1-3 (module docstring), before the team-wide minimum is taken."""

    kd: np.ndarray  # (n,) N m s/rad, rule 1
    force_limit: float  # N, rule 2: end-effector force the spare torque can deliver (F_i)
    param_norm: float  # m, |a| of the nominal kinematic parameters
    reach: float  # m, farthest sampled end-effector position from the base, in the formation's axes
    mobility: float  # 1/kg, max_q lambda_max(J H^-1 J^T): the lightest effective end-effector mass, inverted
    gravity_loads_joints: bool
    worst_regressor_norm2: float  # max |Z(q, u)|^2 over sampled q, unit directions u (per unit |zeta|^2)


def arm_gain_limits(arm: ArmGainInputs, control_dt: float, samples: int = 200) -> ArmGainLimits:
    """Rules 1-3 of the module docstring for one arm, from sampled configurations (seeded) plus ``initial_q``."""
    chain, dynamics = arm.chain, arm.dynamics
    configurations = np.vstack([chain.sample_configurations(samples, np.random.default_rng(0)), arm.initial_q])
    gravity = np.array([np.abs(dynamics.gravity_torque(q, arm.gravity_in_base)) for q in configurations])
    gravity_peak = gravity.max(axis=0)  # N m per joint
    gravity_loads_joints = bool(np.max(gravity_peak) > 1e-6)
    kd_step = damping_for_step(chain, dynamics, control_dt, configurations,
                               GRAVITY_BETA if gravity_loads_joints else BETA)
    positions, jacobians = chain.forward_and_jacobian_batch(configurations)
    jacobians = jacobians[:, :arm.dim]  # (k, dim, n): only the formation's coordinates matter

    spare = np.maximum(arm.torque_limits - gravity_peak, SPARE_TORQUE_FLOOR * arm.torque_limits)
    lever = np.linalg.norm(jacobians, axis=1).max(axis=0)  # m: largest |J[:, j]| per joint
    force_limit = float(TORQUE_SHARE * np.min(spare / np.maximum(lever, 1e-9)))
    # Rule 1, second bound: the formation's torque share must drive each joint at JOINT_SPEED against K_D.
    kd = np.minimum(kd_step, TORQUE_SHARE * spare / JOINT_SPEED)

    mobility = max(float(np.max(np.linalg.eigvalsh(j @ np.linalg.solve(dynamics.mass_matrix(q), j.T))))
                   for q, j in zip(configurations, jacobians))  # rule 3

    regressor_norm2 = 0.0
    for q in configurations[:: max(1, len(configurations) // 32)]:
        for direction in np.eye(arm.dim):
            regressor_norm2 = max(regressor_norm2, float(np.sum(chain.regressor(q, direction) ** 2)))
    reach = float(np.max(np.linalg.norm(positions[:, :arm.dim], axis=1)))
    return ArmGainLimits(kd=kd, force_limit=force_limit, param_norm=float(np.linalg.norm(chain.nominal_params)),
                         reach=reach, mobility=mobility,
                         gravity_loads_joints=gravity_loads_joints,
                         worst_regressor_norm2=regressor_norm2)


def formation_gains(arms: Sequence[ArmGainInputs], control_dt: float, formation_kind: str,
                    incident_edges: Sequence[Sequence[int]], formation_stiffness: float) -> list[Gains]:
    """One :class:`Gains` per arm by the rule of the module docstring.

    ``kp`` (a scalar) is the same for every arm (the team-wide minimum of the per-arm limits), and each
    edge's spring force is the smaller of its two ends' limits, so ``-K_P J^T e_hat`` stays the gradient
    of one potential; ``spring_force`` holds, per arm, the forces of its edges in its neighbour-slot order
    (``incident_edges[i]``: arm i's edge indices in that order). ``kd``, ``ki`` and ``alpha`` are per arm.
    ``control_dt`` in s; ``formation_kind`` ``"distance"`` or ``"displacement"``; ``formation_stiffness``:
    the largest eigenvalue of the formation's stiffness ``d(e_hat)/dx`` at the target (:func:`formation_stiffness`).
    """
    if not (formation_stiffness > 0 and np.isfinite(formation_stiffness)):
        raise ValueError(f"formation_stiffness: expected a finite value > 0, got {formation_stiffness!r}")
    if not isinstance(control_dt, (int, float)) or not (control_dt > 0 and np.isfinite(control_dt)):
        raise ValueError(f"control_dt: expected a finite step > 0 s, got {control_dt!r}")
    if formation_kind not in ("distance", "displacement"):
        raise ValueError(f"formation_kind: expected 'distance' or 'displacement', got {formation_kind!r}")
    if not arms or len(incident_edges) != len(arms):
        raise ValueError(f"incident_edges: expected one list of edge indices per arm ({len(arms)}), "
                         f"got {len(incident_edges)}")
    limits = [arm_gain_limits(arm, control_dt) for arm in arms]
    # Rule 3: dt^2 rho(H^-1 K_q) <= KAPPA with K_q = K_P J^T S J over the team (block-diagonal J, H).
    kp = KAPPA / (control_dt**2 * formation_stiffness * max(limit.mobility for limit in limits))
    edge_force: dict[int, float] = {}
    for limit, edges in zip(limits, incident_edges):
        for edge in edges:
            edge_force[edge] = min(edge_force.get(edge, np.inf), limit.force_limit)
    gains = []
    for limit, edges in zip(limits, incident_edges):
        ki = min(INTERNAL_MODEL_GAIN, 0.1 / control_dt) if limit.gravity_loads_joints else 0.0
        # Rule 4: while every spring of the arm pulls at its saturation force, |e_hat| <= sum_k F_k / K_P.
        # Gamma: the Z^T dq term moves a_hat by at most ESTIMATE_CHANGE |a| over one reach of travel;
        # alpha: the rate Gamma alpha |Z|^2 of its decay term stays below ADAPTATION_RATE.
        saturated_gradient = sum(edge_force[edge] for edge in edges) / kp
        gamma = ESTIMATE_CHANGE * limit.param_norm**2 / max(saturated_gradient * limit.reach, 1e-12)
        alpha = ADAPTATION_RATE / max(gamma * limit.worst_regressor_norm2 * saturated_gradient**2, 1e-12)
        gains.append(Gains(kp=kp, kd=limit.kd, ki=ki, alpha=alpha, adaptation_gain=gamma,
                           spring_force=tuple(edge_force[edge] for edge in edges),
                           rate_gain=RATE_STEPS * control_dt))
    return gains


def damping_for_step(chain: SerialChain, dynamics: NominalDynamics, dt: float,
                     configurations: np.ndarray, beta: float = BETA) -> np.ndarray:
    """Rule 1: per-joint K_D (N m s/rad) with ``dt rho(H^-1 K_D) <= beta`` at every given configuration."""
    inverses = [np.linalg.inv(dynamics.mass_matrix(q)) for q in configurations]
    worst_diagonal = np.max([np.diag(inverse) for inverse in inverses], axis=0)
    kd = np.minimum(K_D_MAX, 1.0 / (dt * worst_diagonal))
    radius = max(float(np.max(np.abs(np.linalg.eigvals(dt * inverse * kd)))) for inverse in inverses)
    return kd / max(radius / beta, 1.0)


def mode_decay(kappa: float, beta: float, rate_steps: float = RATE_STEPS, substeps: int = 10) -> float:
    """Spectral radius of one sampled mode (rule 5): ``m ddq = u`` integrated by ``substeps`` semi-implicit
    Euler steps per control step with ``u = -k (q + rate_steps (q - q_prev)) - d dq`` held over the step;
    ``kappa = k dt^2 / m``, ``beta = d dt / m``. Below 1: the mode decays (by this factor per step)."""
    h = 1.0 / substeps  # time in control steps, mass 1
    step = np.array([[1.0, h], [0.0, 1.0]])
    transition, held = np.eye(2), np.zeros((2, 1))
    for _ in range(substeps):
        transition, held = step @ transition, step @ held + np.array([[h * h], [h]])
    closed = np.zeros((3, 3))  # state (q, dq, q_prev)
    closed[:2, :2] = transition - held @ np.array([[kappa * (1.0 + rate_steps), beta]])
    closed[:2, 2] = held[:, 0] * kappa * rate_steps
    closed[2, 0] = 1.0
    return float(np.max(np.abs(np.linalg.eigvals(closed))))
