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
  ``d(a_hat)/dt = -Z^T(q, e_hat) [alpha Z(q, e_hat) a_hat - dq]``, projected onto a parameter box.

Internal states are integrated once per env step (the control step ``dt``): ``eta`` by explicit Euler,
``a_hat`` by a linearly implicit Euler step, ``(I + dt alpha Z^T Z) a_hat+ = a_hat + dt Z^T dq``, because
``alpha Z^T Z`` is stiff (rates of ~2000 1/s on the paper's planar arms, unstable for explicit Euler at
any control step above 1 ms) while the implicit step has the same fixed points and is stable for all dt.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ee_formation_env.formation import agent_gradient
from ee_formation_env.kinematics import SerialChain
from ee_formation_env.observation import ObservationLayout, ObservationParts
from baselines.dynamics import NominalDynamics


@dataclass(frozen=True)
class Gains:
    """Controller gains; each a scalar or a per-joint array.

    ``kp``: formation gain (N m per m^3 of e_hat for distance formations, per m for displacement);
    ``kd``: joint damping, N m s/rad; ``ki``: internal-model gain, 1/s; ``alpha``: adaptation gain of
    law-III (1 / (m^4 s) for distance formations).
    """

    kp: Any = 5.0
    kd: Any = 20.0
    ki: Any = 0.0
    alpha: float = 0.02

    def with_updates(self, **changes: Any) -> "Gains":
        unknown = set(changes) - {"kp", "kd", "ki", "alpha"}
        if unknown:
            raise ValueError(f"gains: unknown key(s) {sorted(unknown)}; allowed: ['alpha', 'kd', 'ki', 'kp']")
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
        self.reset()

    def reset(self) -> None:
        """Clear internal state (start of an episode)."""

    def gradient(self, parts: ObservationParts) -> np.ndarray:
        """e_hat_i in the base frame, padded to 3 components."""
        mask = parts.mask[:, None]
        errors = parts.edge_errors * mask
        e_hat = agent_gradient(self.agent.formation_kind, parts.relative_positions * mask,
                               errors[:, 0] if self.agent.formation_kind == "distance" else errors)
        padded = np.zeros(3)
        padded[:len(e_hat)] = e_hat
        return padded

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
        return -self._kp * (jacobian.T @ self.gradient(parts)) - self._kd * parts.dq + gravity


class ApproxJacobianController(FormationController):
    """Proposition 4.1 (law-II): fixed estimate a_hat, internal model eta against unknown gravity."""

    name = "approx_jacobian"

    def reset(self) -> None:
        self.eta = np.zeros(self.agent.chain.n_joints)
        self.a_hat = self.a_hat0.copy()

    def torque(self, parts: ObservationParts) -> np.ndarray:
        e_hat = self.gradient(parts)
        self._adapt(parts, e_hat)
        jacobian = self.agent.chain.jacobian(parts.q, self.a_hat)
        u = -self._kp * (jacobian.T @ e_hat) - self._kd * parts.dq + self._ki * self.eta
        self.eta = self.eta + self.agent.control_dt * (-self._ki * self.eta + u)
        return u

    def _adapt(self, parts: ObservationParts, e_hat: np.ndarray) -> None:
        """Law-II keeps a_hat fixed."""


class AdaptiveJacobianController(ApproxJacobianController):
    """Theorem 4.2 (law-III): law-II with the adaptive kinematic estimate.

    ``projection=True`` (default) clips a_hat after each update onto the box ``param_box`` (default
    ``[0.5, 2] x |a_hat0|`` per component, with a_hat0's signs): the paper assumes the parameters lie in a
    known compact set, and without the projection the printed law has a spurious equilibrium at
    ``a_hat = 0`` that captures it far from the target (``docs/physics.md``, "The printed adaptive law stalls
    far from the target"). ``projection=False`` is the printed law.
    """

    name = "adaptive_jacobian"

    def __init__(self, agent: AgentModel, gains: Gains, a_hat0: np.ndarray | None = None,
                 projection: bool = True, param_box: tuple[Any, Any] | None = None):
        super().__init__(agent, gains, a_hat0)
        self.projection = bool(projection)
        if param_box is None:
            magnitude = np.abs(self.a_hat0)
            bounds = np.sign(self.a_hat0) * np.stack([0.5 * magnitude, 2.0 * magnitude])
            self.param_low, self.param_high = bounds.min(axis=0), bounds.max(axis=0)
        else:
            self.param_low = np.broadcast_to(np.asarray(param_box[0], dtype=np.float64), self.a_hat0.shape).copy()
            self.param_high = np.broadcast_to(np.asarray(param_box[1], dtype=np.float64), self.a_hat0.shape).copy()
            if np.any(self.param_low > self.param_high):
                raise ValueError(f"param_box: lower bounds exceed upper bounds: {param_box!r}")
        self._identity = np.eye(len(self.a_hat0))

    def _adapt(self, parts: ObservationParts, e_hat: np.ndarray) -> None:
        regressor = self.agent.chain.regressor(parts.q, e_hat)  # (n, p): J^T e_hat = Z a
        dt, alpha = self.agent.control_dt, self.gains.alpha
        system = self._identity + dt * alpha * (regressor.T @ regressor)
        self.a_hat = np.linalg.solve(system, self.a_hat + dt * (regressor.T @ parts.dq))
        if self.projection:
            np.clip(self.a_hat, self.param_low, self.param_high, out=self.a_hat)


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
