"""The paper's three distributed formation controllers, each acting on one agent's observation only.

Every controller sees: its own observation (neighbour displacements, desired relations and edge errors
in its base frame, its joint states), its own *nominal* robot model (kinematic chain from the URDF,
nominal dynamics), its own gravity direction (its mounting) and its torque limits. It returns the env's
normalized action ``tau / torque_limits`` (not clipped, so the env reports the saturation it causes).

With ``e_hat_i = 2 sum_j e_ij z_ij`` (distance) or ``sum_j (z_ij - z*_ij)`` (displacement), in the
agent's base frame (paper Sec. V):

- ``gradient`` (Theorem 3.1, law-I): ``u = -K_P J^T(q, a) e_hat - K_D dq + G(q)``.
- ``approx_jacobian`` (Proposition 4.1, law-II): ``u = -K_P J^T(q, a_hat) e_hat - K_D dq + K_I eta`` with
  the fixed estimate ``a_hat`` and the internal model ``d(eta)/dt = -K_I eta + u``.
- ``adaptive_jacobian`` (Theorem 4.2, law-III): law-II plus
  ``d(a_hat)/dt = -Gamma Z^T(q, e_hat) [alpha Z(q, e_hat) a_hat - dq]``, projected onto a parameter box;
  the printed law has ``Gamma = 1`` (``Gains.adaptation_gain``, the default). A scalar Gamma > 0 only
  rescales the estimate's term ``|a_tilde|^2 / Gamma`` of the Lyapunov function, as usual in adaptive
  control. Why it is there: along any descent of the formation potential ``e_hat^T dx < 0``, and the
  ``Z^T dq`` term moves a_hat by ``a_hat^T Z^T dq = e_hat^T J(q, a_hat) dq``, so the estimate shrinks in
  proportion to the potential released (m^3 of e_hat times metres travelled): with Gamma = 1 a far
  start drives it to the lower bound of its box within a second whatever alpha is.

Saturated springs (``Gains.spring_force`` = F finite; ``inf``, the default, is the paper's law): every
edge is a virtual spring whose force saturates. Distance formations replace the potential
``V = 1/2 sum_k e_k^2`` (whose gradient is the paper's e_hat) by ``V_F = sum_k rho_k(e_k)`` with the
Huber function ``rho_k(e) = e^2 / 2`` for ``|e| <= c_k``, ``c_k |e| - c_k^2 / 2`` beyond, of level
``c_k = F / (2 K_P d_k)``, so ``e_hat_i = 2 sum_j clip(e_ij, -c_ij, c_ij) z_ij``; displacement formations
scale each ``e_k`` to length at most ``F / K_P``. Every law then uses this e_hat (law-III also in its
regressor ``Z(q, e_hat)``). Why this form:

- ``-K_P J^T e_hat`` is still the gradient field of one potential (``K_P V_F`` in joint space), with one
  scalar K_P, as Theorems 3.1 and 4.2 assume; ``V_F`` has the same minimizers as ``V`` and coincides
  with it where every ``|e_k| <= c_k``, so near the target the laws are the printed ones.
- Far from the target each edge pulls with at most ``F |z_k| / d_k`` (F at the desired length) instead of
  a force growing with the cube of the error, so a gain that is fast near the target no longer asks
  far away for torques the actuators cannot give (which, clipped, also removes the damping).
- Both ends of an edge know ``d_k`` (their observation), K_P and F, so they use the same ``c_k``:
  the law stays distributed.

Gradient-rate damping (``Gains.rate_gain`` = K_R > 0; 0, the default, is the paper's law): the spring
term acts on ``e_hat + K_R d(e_hat)/dt``, the derivative taken as the backward difference of the agent's
own e_hat over one control step (its observation at two steps: no neighbour velocity is needed), so
``u = -K_P J^T (e_hat + K_R d(e_hat)/dt) - K_D dq + ...``; law-III adapts with e_hat itself. Why:

- ``-K_P J^T e_hat`` is unchanged (the gradient of one potential, one scalar K_P); the added term is,
  in continuous time, the damping ``-K_R K_P J^T S(x) J dq`` (S the Hessian of the formation potential
  in x), proportional to the formation's stiffness, positive semi-definite near the target.
- The control is held over each step, so a spring acts on a state half a step old on average: a
  negative damping ``K dt / 2`` per mode of stiffness K. Joint damping K_D must outweigh it on the
  stiffest mode, and then over-damps the softest ones (their rate is about K / K_D): on an ill-conditioned
  formation (stiffness eigenvalues 1e4 apart) they take minutes. The rate term damps each mode in
  proportion to its own stiffness, which cancels the lag (K_R > dt / 2), so K_D can be ten times lower
  (:mod:`baselines.gains`).

Internal states are integrated once per env step (the control step ``dt``): ``eta`` by explicit Euler,
``a_hat`` by a linearly implicit Euler step, ``(I + dt Gamma alpha Z^T Z) a_hat+ = a_hat + dt Gamma Z^T dq``, because
``alpha Z^T Z`` is stiff (rates of ~2000 1/s on the paper's planar arms, unstable for explicit Euler at
any control step above 1 ms) while the implicit step has the same fixed points and is stable for all dt.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from ee_formation_env.formation import agent_gradient
from ee_formation_env.kinematics import SerialChain
from ee_formation_env.observation import ObservationLayout, ObservationParts
from baselines.dynamics import NominalDynamics


@dataclass(frozen=True)
class Gains:
    """Controller gains.

    ``kp``: formation gain (N m per m^3 of e_hat for distance formations, per m for displacement), a scalar
    (a per-joint array is accepted only without saturation, and then ``-K_P J^T e_hat`` is no gradient
    field); ``kd``: joint damping, N m s/rad, scalar or per joint; ``ki``: internal-model gain, 1/s, scalar or
    per joint; ``alpha``: adaptation gain of law-III (1 / (m^4 s) for distance formations);
    ``adaptation_gain``: Gamma of law-III (module docstring; 1, the default, is the printed law);
    ``spring_force``: saturation force (N) of each edge's virtual spring at its desired length
    (module docstring, "Saturated springs"), one number for every edge or one per neighbour slot (the
    agent's edges in scenario order); ``inf`` (default) is the paper's unsaturated law;
    ``rate_gain``: K_R, s, of the gradient-rate damping (module docstring, "Gradient-rate damping"); 0, the
    default, is the paper's law.
    """

    kp: Any = 5.0
    kd: Any = 20.0
    ki: Any = 0.0
    alpha: float = 0.02
    spring_force: Any = math.inf
    adaptation_gain: float = 1.0
    rate_gain: float = 0.0

    def with_updates(self, **changes: Any) -> "Gains":
        allowed = sorted(field.name for field in fields(self))
        unknown = set(changes) - set(allowed)
        if unknown:
            raise ValueError(f"gains: unknown key(s) {sorted(unknown)}; allowed: {allowed}")
        return replace(self, **changes)

    def validated(self, n_joints: int) -> "Gains":
        """Check shapes and signs; ``ValueError`` naming the gain otherwise."""
        for name in ("kp", "kd", "ki"):
            value = np.asarray(getattr(self, name), dtype=np.float64)
            if value.shape not in ((), (n_joints,)):
                raise ValueError(f"gains.{name}: expected a scalar or {n_joints} per-joint values, got shape {value.shape}")
            if not np.all(np.isfinite(value)) or np.any(value < 0):
                raise ValueError(f"gains.{name}: expected finite values >= 0, got {getattr(self, name)!r}")
        if not np.isfinite(self.alpha) or self.alpha < 0:
            raise ValueError(f"gains.alpha: expected a finite value >= 0, got {self.alpha!r}")
        if isinstance(self.adaptation_gain, bool) or not isinstance(self.adaptation_gain, (int, float)) \
                or not (self.adaptation_gain > 0 and math.isfinite(self.adaptation_gain)):
            raise ValueError(f"gains.adaptation_gain: expected a finite value > 0, got {self.adaptation_gain!r}")
        if isinstance(self.rate_gain, bool) or not isinstance(self.rate_gain, (int, float)) \
                or not (self.rate_gain >= 0 and math.isfinite(self.rate_gain)):
            raise ValueError(f"gains.rate_gain: expected a finite value >= 0 s, got {self.rate_gain!r}")
        try:
            forces = np.asarray(self.spring_force, dtype=np.float64)
        except (TypeError, ValueError):
            forces = np.array(np.nan)
        if isinstance(self.spring_force, bool) or forces.ndim > 1 or forces.size == 0 or np.any(np.isnan(forces)) \
                or np.any(forces <= 0):
            raise ValueError("gains.spring_force: expected forces > 0 N (inf: no saturation), one number or one "
                             f"per neighbour slot, got {self.spring_force!r}")
        if np.any(np.isfinite(forces)) and np.ndim(self.kp) != 0:
            raise ValueError("gains.kp: a saturated spring (finite spring_force) needs a scalar formation gain, "
                             f"got {self.kp!r}")
        return self


@dataclass(frozen=True)
class AgentModel:
    """What one agent knows about itself: nominal kinematics and dynamics, mounting, limits, control step."""

    layout: ObservationLayout
    formation_kind: str
    chain: SerialChain  # nominal kinematic model
    dynamics: NominalDynamics  # nominal dynamic model
    gravity_in_base: np.ndarray  # m/s^2
    torque_limits: np.ndarray  # N m
    control_dt: float  # s


class FormationController:
    """Common part of the three laws: the agent gradient and the action scaling."""

    name = "formation_controller"

    def __init__(self, agent: AgentModel, gains: Gains, a_hat0: np.ndarray | None = None):
        self.agent = agent
        self.gains = gains.validated(agent.chain.n_joints)
        self.a_hat0 = np.array(agent.chain.nominal_params if a_hat0 is None else a_hat0, dtype=np.float64)
        if self.a_hat0.shape != agent.chain.nominal_params.shape:
            raise ValueError(
                f"a_hat0: expected {len(agent.chain.nominal_params)} values {list(agent.chain.param_names)}, "
                f"got {self.a_hat0.shape}"
            )
        self._kp = np.asarray(gains.kp, dtype=np.float64)
        self._kd = np.asarray(gains.kd, dtype=np.float64)
        self._ki = np.asarray(gains.ki, dtype=np.float64)
        forces = np.asarray(gains.spring_force, dtype=np.float64)
        n_slots = agent.layout.n_slots
        if forces.ndim == 1 and len(forces) > n_slots:
            raise ValueError(f"gains.spring_force: expected at most {n_slots} per-slot forces, got {len(forces)}")
        self._spring_force = np.full(n_slots, np.inf)  # N per neighbour slot; padding slots never matter
        if forces.ndim == 0:
            self._spring_force[:] = float(forces)
        else:
            self._spring_force[:len(forces)] = forces
        self.reset()

    def reset(self) -> None:
        """Clear internal state (start of an episode)."""
        self._previous_e_hat: np.ndarray | None = None

    # ---- Gradient-rate damping (module docstring): the only state it needs is the previous e_hat.
    def spring_gradient(self, e_hat: np.ndarray) -> np.ndarray:
        """``e_hat + K_R (e_hat - e_hat_prev) / dt``: the gradient the spring term ``-K_P J^T (.)`` acts on.

        The first call after a reset has no previous value and returns ``e_hat``; ``K_R = 0`` always does.
        """
        previous, self._previous_e_hat = self._previous_e_hat, e_hat
        if self.gains.rate_gain == 0.0 or previous is None:
            return e_hat
        return e_hat + (self.gains.rate_gain / self.agent.control_dt) * (e_hat - previous)
    # ---- end of gradient-rate damping

    def gradient(self, parts: ObservationParts) -> np.ndarray:
        """e_hat_i in the base frame, padded to 3 components (edge errors saturated if ``spring_force`` is finite)."""
        mask = parts.mask[:, None]
        errors = self.saturated_errors(parts.edge_errors * mask, parts.desired * mask)
        e_hat = agent_gradient(self.agent.formation_kind, parts.relative_positions * mask,
                               errors[:, 0] if self.agent.formation_kind == "distance" else errors)
        padded = np.zeros(3)
        padded[:len(e_hat)] = e_hat
        return padded

    def saturated_errors(self, edge_errors: np.ndarray, desired: np.ndarray) -> np.ndarray:
        """Edge errors clipped at each spring's saturation level (module docstring); unchanged if unsaturated.

        Distance: ``clip(e_k, -c_k, c_k)`` with ``c_k = F / (2 K_P d_k)``; displacement: ``e_k`` scaled to
        length at most ``F / K_P``. Padding slots (``d_k = 0``) carry zero errors and stay zero.
        """
        force = self._spring_force[:, None]  # (slots, 1), N
        if not np.any(np.isfinite(force)) or float(self._kp) == 0.0:
            return edge_errors
        if self.agent.formation_kind == "distance":
            lengths = np.abs(desired)
            level = np.where(lengths > 0, force / (2.0 * float(self._kp) * np.maximum(lengths, 1e-12)), 0.0)
            return np.clip(edge_errors, -level, level)
        norms = np.linalg.norm(edge_errors, axis=1, keepdims=True)
        level = force / float(self._kp)
        return edge_errors * np.minimum(1.0, level / np.maximum(norms, 1e-300))

    def torque(self, parts: ObservationParts) -> np.ndarray:
        raise NotImplementedError

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        parts = self.agent.layout.split(observation)
        return (self.torque(parts) / self.agent.torque_limits).astype(np.float32)


class GradientController(FormationController):
    """Theorem 3.1 (law-I): exact nominal Jacobian and gravity compensation, no internal state."""

    name = "gradient"

    def torque(self, parts: ObservationParts) -> np.ndarray:
        jacobian = self.agent.chain.jacobian(parts.q, self.a_hat0)
        gravity = self.agent.dynamics.gravity_torque(parts.q, self.agent.gravity_in_base)
        return -self._kp * (jacobian.T @ self.spring_gradient(self.gradient(parts))) - self._kd * parts.dq + gravity


class ApproxJacobianController(FormationController):
    """Proposition 4.1 (law-II): fixed estimate a_hat, internal model eta against unknown gravity.

    ``anti_windup=True`` feeds the internal model the torque the actuators can apply,
    ``d(eta)/dt = -K_I eta + clip(u, -tau_max, tau_max)``, instead of the commanded ``u``: under torque
    limits the printed model integrates torque that is never applied, and ``K_I eta`` then holds the
    commanded torque beyond the limits long after the error has gone (integrator windup). With the
    clipped input ``|K_I eta|`` stays within the limits. Without saturation both are the printed law.
    """

    name = "approx_jacobian"

    def __init__(self, agent: AgentModel, gains: Gains, a_hat0: np.ndarray | None = None, anti_windup: bool = False):
        if not isinstance(anti_windup, bool):
            raise TypeError(f"anti_windup: expected a bool, got {type(anti_windup).__name__}")
        self.anti_windup = anti_windup
        super().__init__(agent, gains, a_hat0)

    def reset(self) -> None:
        super().reset()
        self.eta = np.zeros(self.agent.chain.n_joints)
        self.a_hat = self.a_hat0.copy()

    def torque(self, parts: ObservationParts) -> np.ndarray:
        e_hat = self.gradient(parts)
        self._adapt(parts, e_hat)
        jacobian = self.agent.chain.jacobian(parts.q, self.a_hat)
        u = -self._kp * (jacobian.T @ self.spring_gradient(e_hat)) - self._kd * parts.dq + self._ki * self.eta
        limits = self.agent.torque_limits
        applied = np.clip(u, -limits, limits) if self.anti_windup else u
        self.eta = self.eta + self.agent.control_dt * (-self._ki * self.eta + applied)
        return u

    def _adapt(self, parts: ObservationParts, e_hat: np.ndarray) -> None:
        """Law-II keeps a_hat fixed."""


DEFAULT_BOUNDS_SCALE = (0.5, 2.0)  # default parameter_bounds: these multiples of the nominal parameters


def parameter_box(nominal: np.ndarray, parameter_bounds: Any, names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) arrays (m) from ``parameter_bounds``; ``ValueError`` naming the field on bad input.

    ``None``: ``[0.5, 2] x`` the nominal parameters (per component, keeping each one's sign). Otherwise a
    pair ``(lower, upper)``, each a number or one value per kinematic parameter ``names``.
    """
    if parameter_bounds is None:
        ends = np.stack([DEFAULT_BOUNDS_SCALE[0] * nominal, DEFAULT_BOUNDS_SCALE[1] * nominal])
        return ends.min(axis=0), ends.max(axis=0)
    if not isinstance(parameter_bounds, (tuple, list)) or len(parameter_bounds) != 2:
        raise ValueError(f"parameter_bounds: expected a pair (lower, upper), got {parameter_bounds!r}")
    ends = []
    for label, value in zip(("lower", "upper"), parameter_bounds):
        try:
            array = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"parameter_bounds.{label}: expected numbers, got {value!r}") from None
        if array.shape not in ((), nominal.shape):
            raise ValueError(f"parameter_bounds.{label}: expected a number or {len(nominal)} values "
                             f"{list(names)}, got shape {array.shape}")
        if not np.all(np.isfinite(array)):
            raise ValueError(f"parameter_bounds.{label}: expected finite values, got {value!r}")
        ends.append(np.broadcast_to(array, nominal.shape).copy())
    lower, upper = ends
    if np.any(lower > upper):
        k = int(np.flatnonzero(lower > upper)[0])
        raise ValueError(f"parameter_bounds: lower {lower[k]:g} > upper {upper[k]:g} for parameter {names[k]}")
    return lower, upper


class AdaptiveJacobianController(ApproxJacobianController):
    """Theorem 4.2 (law-III): law-II with the adaptive kinematic estimate.

    ``projection=True`` (default) clips a_hat after each update onto the known parameter set
    ``parameter_bounds`` = (lower, upper), m, one value per kinematic parameter (or a number for all);
    default ``[0.5, 2] x`` the nominal URDF parameters. The paper assumes the true parameters lie in a
    known compact set; without the projection the printed law has a spurious equilibrium at ``a_hat = 0``
    that captures it far from the target (``docs/physics.md``, "The printed adaptive law stalls far from
    the target"). ``projection=False`` is the printed law.
    ``a_hat0`` must lie in the box. :attr:`boundary_fraction` is the fraction of control steps (since the
    last reset) after which some component of a_hat sat on the boundary of the box.
    """

    name = "adaptive_jacobian"

    def __init__(self, agent: AgentModel, gains: Gains, a_hat0: np.ndarray | None = None,
                 projection: bool = True, parameter_bounds: Any = None, anti_windup: bool = False):
        super().__init__(agent, gains, a_hat0, anti_windup=anti_windup)
        self.projection = bool(projection)
        names = agent.chain.param_names
        self.param_low, self.param_high = parameter_box(np.asarray(agent.chain.nominal_params), parameter_bounds, names)
        outside = (self.a_hat0 < self.param_low) | (self.a_hat0 > self.param_high)
        if self.projection and outside.any():
            k = int(np.flatnonzero(outside)[0])
            raise ValueError(f"a_hat0: {names[k]} = {self.a_hat0[k]:g} lies outside parameter_bounds "
                             f"[{self.param_low[k]:g}, {self.param_high[k]:g}]")
        self._identity = np.eye(len(self.a_hat0))

    def reset(self) -> None:
        super().reset()
        self.adaptation_steps = 0
        self.boundary_steps = 0

    @property
    def boundary_fraction(self) -> float:
        """Fraction of adaptation steps that ended with a_hat on the box boundary (0 before any step)."""
        return self.boundary_steps / self.adaptation_steps if self.adaptation_steps else 0.0

    def _adapt(self, parts: ObservationParts, e_hat: np.ndarray) -> None:
        regressor = self.agent.chain.regressor(parts.q, e_hat)  # (n, p): J^T e_hat = Z a
        dt, alpha, gamma = self.agent.control_dt, self.gains.alpha, self.gains.adaptation_gain
        system = self._identity + dt * gamma * alpha * (regressor.T @ regressor)
        self.a_hat = np.linalg.solve(system, self.a_hat + dt * gamma * (regressor.T @ parts.dq))
        self.adaptation_steps += 1
        if self.projection:
            np.clip(self.a_hat, self.param_low, self.param_high, out=self.a_hat)
            self.boundary_steps += int(np.any((self.a_hat == self.param_low) | (self.a_hat == self.param_high)))


class ZeroPolicy:
    """Zero torque: the arms fall or drift (a lower reference)."""

    name = "zero"

    def __init__(self, n_joints: int):
        self.n_joints = n_joints

    def reset(self) -> None:
        pass

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        return np.zeros(self.n_joints, dtype=np.float32)


class RandomPolicy:
    """Uniform random normalized torques from a seeded generator (re-seeded by ``reset``)."""

    name = "random"

    def __init__(self, n_joints: int, seed: int = 0):
        self.n_joints, self.seed = n_joints, seed
        self.reset()

    def reset(self) -> None:
        self.rng = np.random.default_rng(self.seed)

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        return self.rng.uniform(-1.0, 1.0, self.n_joints).astype(np.float32)
