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
  the printed law has ``Gamma = 1`` (``Gains.adaptation_gain``, the default).

Saturated springs (``Gains.spring_force`` = F finite; ``inf``, the default, is the paper's law): distance
formations use ``e_hat_i = 2 sum_j clip(e_ij, -c_ij, c_ij) z_ij`` with ``c_k = F / (2 K_P d_k)`` (the
gradient of a Huber potential, equal to the paper's near the target); displacement formations scale each
``e_k`` to length at most ``F / K_P``. Every law uses this e_hat (law-III also in its regressor).

Gradient-rate damping (``Gains.rate_gain`` = K_R > 0; 0, the default, is the paper's law): the spring
term acts on ``e_hat + K_R d(e_hat)/dt``, the derivative the backward difference of the agent's own e_hat
over one control step; law-III adapts with e_hat itself.

Each law is written once, for a stack of agents (``batch_torques``): :class:`ControllerBatch` evaluates the
agents that share a law, a chain and an observation layout in one set of numpy calls, and
:class:`~ee_formation_env.baselines.reference.team.PolicyTeam` groups a team's policies into such batches.
A controller called alone is a batch of one and gives bit for bit the same actions and internal states. ``J(q, a)^T e_hat = Z(q, e_hat) a``: the
torque and law-III's adaptation share one chain evaluation.

Manoeuvre feedforward (only when the observation carries a scenario ``manoeuvre``'s reference block;
without one every law is exactly the paper's): the damping term becomes ``-K_D (dq - dq*)`` with
``dq* = J^T (J J^T + lambda^2 I)^-1 v*``, the damped least-squares inverse (``lambda`` =
:data:`FEEDFORWARD_DAMPING`) of the first ``dim`` rows of the agent's Jacobian ``J(q, a_hat0)`` at its
initial estimate (the nominal model by default; law-III's running estimate is pulled by the commanded
motion and is not used: docs/manoeuvres.md), and ``v* = dc*/dt + omega* x (x_i - c*)``, the rigid-body velocity of the
reference at the agent's own end-effector: ``x_i`` from its nominal forward kinematics, ``c* - b_i``,
``dc*/dt`` and ``omega*`` from its observation, all in its base frame. The reference hold
(``Gains.reference_stiffness`` = K_X > 0) adds the position level, ``J^T K_X (x_i* - x_i)``: until the reference
first moves, ``x_i* = x_i`` (the agent keeps ``p_i = x_i - c*`` as its anchor, so the term is zero); from then
on ``x_i* = c* + R_i p_i``, ``R_i`` the turn the agent integrates from ``omega*`` (trapezoidal rule, one step
``dt``). The velocity loop alone leaves a distance formation's turn to the damping term, which an unmodelled
torque along the turn (gravity, under law-II and law-III) overrides: docs/manoeuvres.md.

Internal states are integrated once per control step ``dt``: ``eta`` by explicit Euler, ``a_hat`` by the
linearly implicit Euler step ``(I + dt Gamma alpha Z^T Z) a_hat+ = a_hat + dt Gamma Z^T dq`` (stable for
every dt, same fixed points).

Why each of these choices, with the measurements: see docs/controllers.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any, Callable, Sequence

import numpy as np

from ee_formation_env.formation import agent_gradient
from ee_formation_env.kinematics import SerialChain
from ee_formation_env.manoeuvre import rotation_about
from ee_formation_env.observation import ObservationLayout, ObservationParts
from ee_formation_env.baselines.reference.dynamics import NominalDynamics

FEEDFORWARD_DAMPING = 0.01  # m: lambda of the feedforward's damped least-squares inverse (module docstring)


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
    default, is the paper's law;
    ``reference_stiffness``: K_X, N/m, of the manoeuvre's reference hold (module docstring, "Manoeuvre
    feedforward"); 0, the default, is the velocity feedforward alone. Without a manoeuvre it has no effect.
    """

    kp: Any = 5.0
    kd: Any = 20.0
    ki: Any = 0.0
    alpha: float = 0.02
    spring_force: Any = math.inf
    adaptation_gain: float = 1.0
    rate_gain: float = 0.0
    reference_stiffness: float = 0.0

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
        if isinstance(self.reference_stiffness, bool) or not isinstance(self.reference_stiffness, (int, float)) \
                or not (self.reference_stiffness >= 0 and math.isfinite(self.reference_stiffness)):
            raise ValueError("gains.reference_stiffness: expected a finite value >= 0 N/m, "
                             f"got {self.reference_stiffness!r}")
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


class FormationController:
    """One agent's controller: its model, gains and internal state.

    The laws are written once, for a stack of agents (:meth:`batch_torques`, evaluated by
    :class:`ControllerBatch`); calling a controller on one observation evaluates a batch of one.
    """

    name = "formation_controller"

    def __init__(self, agent: AgentModel, gains: Gains, a_hat0: np.ndarray | None = None):
        self.agent = agent
        self.a_hat0 = np.array(agent.chain.nominal_params if a_hat0 is None else a_hat0, dtype=np.float64)
        if self.a_hat0.shape != agent.chain.nominal_params.shape:
            raise ValueError(
                f"a_hat0: expected {len(agent.chain.nominal_params)} values {list(agent.chain.param_names)}, "
                f"got {self.a_hat0.shape}"
            )
        self.set_gains(gains)
        self.reset()

    def set_gains(self, gains: Gains) -> None:
        """Use ``gains`` from now on (validated; a batch holding this controller takes them at its next call)."""
        self.gains = gains = gains.validated(self.agent.chain.n_joints)
        agent = self.agent
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
        self._alone: ControllerBatch | None = None

    #: Set by :func:`ee_formation_env.baselines.make_policy` on a scenario distribution: the gains of the env's
    #: current draw, taken at every reset (each draw has its own layout and shape, so its own gains).
    gains_source: Callable[[], Gains] | None = None

    def reset(self) -> None:
        """Clear internal state (start of an episode); take the current draw's gains if they follow the env."""
        if self.gains_source is not None:
            self.set_gains(self.gains_source())
        self._previous_e_hat: np.ndarray | None = None  # gradient-rate damping's one state
        # The manoeuvre's reference hold (module docstring), in the agent's base frame:
        m = self.agent.layout.dim
        self.reference_anchor = np.zeros(m)  # p_i = x_i - c* when the reference first moved, m
        self.reference_turn = np.eye(m)  # R_i, the reference turn integrated since then
        self.reference_rate = np.zeros(1 if m == 2 else 3)  # the previous step's omega*, rad/s
        self.reference_moving = np.array(False)  # the reference has moved since the reset

    def options(self) -> tuple:
        """The law's options; controllers batched together must share them."""
        return ()

    def gradient(self, parts: ObservationParts) -> np.ndarray:
        """e_hat_i in the base frame, padded to 3 components (edge errors saturated if ``spring_force`` is finite)."""
        return self._batch_of_one().gradients(_stacked(parts))[0]

    def saturated_errors(self, edge_errors: np.ndarray, desired: np.ndarray) -> np.ndarray:
        """Edge errors (slots, w) clipped at each spring's saturation level (:meth:`ControllerBatch.saturated_errors`)."""
        return self._batch_of_one().saturated_errors(edge_errors[None], desired[None])[0]

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        return self._batch_of_one()(np.asarray(observation)[None])[0]

    def _batch_of_one(self) -> "ControllerBatch":
        if self._alone is None:
            self._alone = ControllerBatch([self])
        return self._alone

    @classmethod
    def batch_torques(cls, batch: "ControllerBatch", parts: ObservationParts) -> np.ndarray:
        """The law: torques (k, n), N m, of the batch's k agents from their observation parts (leading axis k)."""
        raise NotImplementedError


class GradientController(FormationController):
    """Theorem 3.1 (law-I): exact nominal Jacobian and gravity compensation, no internal state."""

    name = "gradient"

    @classmethod
    def batch_torques(cls, batch: "ControllerBatch", parts: ObservationParts) -> np.ndarray:
        spring = batch.spring_gradients(batch.gradients(parts))
        regressors = batch.chain.regressor_batch(parts.q, spring)  # J(q, a)^T spring = Z(q, spring) a
        gravity = np.stack([member.agent.dynamics.gravity_torque(q, member.agent.gravity_in_base)
                            for member, q in zip(batch.members, parts.q)])
        return (-batch.kp * (regressors @ batch.a_hat0[:, :, None])[:, :, 0]
                + batch.damping_torques(parts, batch.a_hat0) + gravity)


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

    def options(self) -> tuple:
        return (self.anti_windup,)

    @classmethod
    def batch_torques(cls, batch: "ControllerBatch", parts: ObservationParts) -> np.ndarray:
        e_hat = batch.gradients(parts)
        spring = batch.spring_gradients(e_hat)
        if spring is e_hat:  # no rate damping: one regressor serves the adaptation and the torque
            regressors = spring_regressors = batch.chain.regressor_batch(parts.q, e_hat)
        else:  # both in one call: Z(q, e_hat) adapts, Z(q, spring) a_hat = J(q, a_hat)^T spring pulls
            both = batch.chain.regressor_batch(np.concatenate([parts.q, parts.q]), np.concatenate([e_hat, spring]))
            regressors, spring_regressors = both[:len(e_hat)], both[len(e_hat):]
        eta = batch.gather("eta")
        a_hat = cls.adapt(batch, parts, regressors, batch.gather("a_hat"))
        u = (-batch.kp * (spring_regressors @ a_hat[:, :, None])[:, :, 0]
             + batch.damping_torques(parts, batch.a_hat0) + batch.ki * eta)
        applied = np.clip(u, -batch.torque_limits, batch.torque_limits) if batch.members[0].anti_windup else u
        batch.scatter("eta", eta + batch.control_dt * (-batch.ki * eta + applied))
        batch.scatter("a_hat", a_hat)
        return u

    @classmethod
    def adapt(cls, batch: "ControllerBatch", parts: ObservationParts, regressors: np.ndarray,
              a_hat: np.ndarray) -> np.ndarray:
        """The estimates (k, p) after this step: law-II keeps them fixed."""
        return a_hat


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

    def reset(self) -> None:
        super().reset()
        self.adaptation_steps = 0
        self.boundary_steps = 0

    def options(self) -> tuple:
        return (self.anti_windup, self.projection)

    @property
    def boundary_fraction(self) -> float:
        """Fraction of adaptation steps that ended with a_hat on the box boundary (0 before any step)."""
        return self.boundary_steps / self.adaptation_steps if self.adaptation_steps else 0.0

    @classmethod
    def adapt(cls, batch: "ControllerBatch", parts: ObservationParts, regressors: np.ndarray,
              a_hat: np.ndarray) -> np.ndarray:
        """One linearly implicit Euler step of the adaptive law (module docstring), then the projection."""
        transposed = regressors.transpose(0, 2, 1)  # Z^T, (k, p, n)
        step = batch.control_dt * batch.adaptation_gain  # (k,)
        system = batch.identity + (step * batch.alpha)[:, None, None] * (transposed @ regressors)
        a_hat = np.linalg.solve(system, (a_hat + step[:, None] * (transposed @ parts.dq[:, :, None])[:, :, 0])[:, :, None])[:, :, 0]
        for member in batch.members:
            member.adaptation_steps += 1
        if batch.members[0].projection:
            np.clip(a_hat, batch.param_low, batch.param_high, out=a_hat)
            on_boundary = np.any((a_hat == batch.param_low) | (a_hat == batch.param_high), axis=1)
            for member, boundary in zip(batch.members, on_boundary):
                member.boundary_steps += int(boundary)
        return a_hat


class ControllerBatch:
    """Controllers of one law, one kinematic chain, one observation layout and one control step, evaluated
    together: ``batch(observations)`` maps a stack (k, size) of their observations to their normalized
    actions (k, n), with one set of numpy calls for the whole stack instead of one per agent (at these sizes
    a call costs about the same for 1 agent or 16). Gains, limits and estimates may differ per agent; the
    internal states stay on the controllers, so a controller gives the same actions alone or in a batch.
    """

    def __init__(self, controllers: Sequence[FormationController]):
        if not controllers:
            raise ValueError("controllers: expected at least one controller")
        first = controllers[0]
        for other in controllers[1:]:
            if (type(other) is not type(first) or other.agent.chain is not first.agent.chain
                    or other.agent.layout != first.agent.layout or other.agent.formation_kind != first.agent.formation_kind
                    or other.agent.control_dt != first.agent.control_dt or other.options() != first.options()):
                raise ValueError("controllers: a batch needs one law, one kinematic chain, one observation layout, "
                                 "one control step and the same options")
        self.members = list(controllers)
        self.law = type(first)
        self.chain, self.layout, self.kind = first.agent.chain, first.agent.layout, first.agent.formation_kind
        self.control_dt = first.agent.control_dt
        self._take_gains()
        self.identity = np.eye(self.chain.n_params)
        self._states: dict[str, tuple[np.ndarray, list[np.ndarray]]] = {}  # gather/scatter cache
        if isinstance(first, AdaptiveJacobianController):
            self.param_low = np.stack([c.param_low for c in controllers])
            self.param_high = np.stack([c.param_high for c in controllers])

    def _take_gains(self) -> None:
        """Stack the members' gains (taken again when a member's gains change: a scenario distribution's draw)."""
        controllers = self.members
        self._gains = [c.gains for c in controllers]
        n = self.chain.n_joints
        self.kp = np.stack([np.broadcast_to(c._kp, (n,)) for c in controllers])  # (k, n)
        self.kd = np.stack([np.broadcast_to(c._kd, (n,)) for c in controllers])  # (k, n), N m s/rad
        self.ki = np.stack([np.broadcast_to(c._ki, (n,)) for c in controllers])  # (k, n), 1/s
        self.spring_force = np.stack([c._spring_force for c in controllers])  # (k, slots), N
        self.saturated = bool(np.any(np.isfinite(self.spring_force)))  # then each kp is a scalar (Gains.validated)
        self.torque_limits = np.stack([c.agent.torque_limits for c in controllers]).astype(np.float64)  # (k, n)
        self.a_hat0 = np.stack([c.a_hat0 for c in controllers])  # (k, p)
        self.alpha = np.array([c.gains.alpha for c in controllers], dtype=np.float64)
        self.adaptation_gain = np.array([c.gains.adaptation_gain for c in controllers], dtype=np.float64)
        self.rate_gain = np.array([c.gains.rate_gain for c in controllers], dtype=np.float64)  # (k,), s
        self.reference_stiffness = np.array([c.gains.reference_stiffness for c in controllers],
                                            dtype=np.float64)  # (k,), N/m

    def gather(self, name: str) -> np.ndarray:
        """The members' internal state ``name`` stacked (k, ...): the array :meth:`scatter` last wrote while
        every member still holds its row of it, else a fresh stack (e.g. after a reset)."""
        stacked, rows = self._states.get(name, (None, ()))
        if stacked is not None and all(getattr(member, name) is row for member, row in zip(self.members, rows)):
            return stacked
        return np.stack([getattr(member, name) for member in self.members])

    def scatter(self, name: str, stacked: np.ndarray) -> None:
        """Give each member its row of ``stacked`` as its internal state ``name``."""
        rows = list(stacked)
        for member, row in zip(self.members, rows):
            setattr(member, name, row)
        self._states[name] = (stacked, rows)

    def __call__(self, observations: np.ndarray) -> np.ndarray:
        if any(member.gains is not gains for member, gains in zip(self.members, self._gains)):
            self._take_gains()
        parts = self.layout.split(observations)
        return (self.law.batch_torques(self, parts) / self.torque_limits).astype(np.float32)

    def gradients(self, parts: ObservationParts) -> np.ndarray:
        """e_hat (k, 3) in each base frame, padded to 3 components (edge errors saturated if ``spring_force``
        is finite)."""
        mask = parts.mask[:, :, None]
        errors = self.saturated_errors(parts.edge_errors * mask, parts.desired * mask)
        e_hat = agent_gradient(self.kind, parts.relative_positions * mask,
                               errors[:, :, 0] if self.kind == "distance" else errors)
        padded = np.zeros((len(e_hat), 3))
        padded[:, :e_hat.shape[1]] = e_hat
        return padded

    def damping_torques(self, parts: ObservationParts, a_hat: np.ndarray) -> np.ndarray:
        """The damping term (k, n), N m: ``-K_D dq`` without a manoeuvre block; with one ``-K_D (dq - dq*)``,
        plus the reference hold ``J^T K_X (x_i* - x_i)`` where K_X > 0 (module docstring, "Manoeuvre
        feedforward"). ``a_hat``: the estimates whose Jacobian and kinematics the feedforward uses."""
        if not self.layout.reference_size:
            return -self.kd * parts.dq
        offsets, rows = self.reference_geometry(parts, a_hat)
        torques = -self.kd * (parts.dq - self.reference_joint_velocities(parts, offsets, rows))
        if np.any(self.reference_stiffness):
            torques = torques + (rows.transpose(0, 2, 1) @ self.reference_hold_forces(parts, offsets)[:, :, None])[:, :, 0]
        return torques

    def damped_velocities(self, parts: ObservationParts, a_hat: np.ndarray) -> np.ndarray:
        """What the damping term ``-K_D (.)`` acts on (k, n): ``dq`` itself (the same object) without a
        manoeuvre block, else ``dq - dq*`` (module docstring, "Manoeuvre feedforward")."""
        if not self.layout.reference_size:
            return parts.dq
        return parts.dq - self.reference_joint_velocities(parts, *self.reference_geometry(parts, a_hat))

    def reference_geometry(self, parts: ObservationParts, a_hat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each agent's ``x_i - c*`` (k, m), m, from its nominal forward kinematics and its observation, and the
        first ``m`` rows of its Jacobian ``J(q, a_hat)`` (k, m, n), all in its own base frame."""
        q, m = parts.q, self.layout.dim
        k, n = q.shape
        offsets = self.chain.forward_batch(q)[:, :m] - parts.reference_centroid  # x_i - c*, own frame, m
        # J(q, a)^T e_j = Z(q, e_j) a: the Jacobian's first m rows from the regressor, for any estimate a.
        units = np.tile(np.eye(m), (k, 1))
        regressors = self.chain.regressor_batch(np.repeat(q, m, axis=0), units)  # (k m, n, p)
        rows = (regressors @ np.repeat(a_hat, m, axis=0)[:, :, None]).reshape(k, m, n)  # J, (k, m, n)
        return offsets, rows

    def reference_joint_velocities(self, parts: ObservationParts, offsets: np.ndarray, rows: np.ndarray
                                   ) -> np.ndarray:
        """dq* (k, n), rad/s: the joint velocities that move each agent's end-effector with the reference's
        rigid-body velocity v* (module docstring), from its own observation and models only (``offsets``
        and ``rows`` from :meth:`reference_geometry`)."""
        m = self.layout.dim
        omega = parts.reference_angular_velocity
        if m == 2:  # omega about z: omega x r = omega (-r_y, r_x)
            turn = omega * np.stack([-offsets[:, 1], offsets[:, 0]], axis=1)
        else:
            turn = np.cross(omega, offsets)
        velocity = parts.reference_velocity + turn  # v*, m/s
        system = rows @ rows.transpose(0, 2, 1) + FEEDFORWARD_DAMPING ** 2 * np.eye(m)
        return (rows.transpose(0, 2, 1) @ np.linalg.solve(system, velocity[:, :, None]))[:, :, 0]

    def reference_hold_forces(self, parts: ObservationParts, offsets: np.ndarray) -> np.ndarray:
        """``K_X (x_i* - x_i)`` (k, m), N, in each agent's base frame, and one step of the hold's state
        (module docstring, "Manoeuvre feedforward"): the anchor follows ``x_i - c*`` until the reference first
        moves; from then on it stays, and the turn integrates ``omega*``."""
        m = self.layout.dim
        omega = parts.reference_angular_velocity
        was_moving, was_anchor, was_turn, rate = (self.gather(name) for name in (
            "reference_moving", "reference_anchor", "reference_turn", "reference_rate"))
        moving = was_moving | np.any(parts.reference_velocity != 0.0, axis=1) | np.any(omega != 0.0, axis=1)
        anchor = np.where(moving[:, None], was_anchor, offsets)
        step = turn_rotations(0.5 * self.control_dt * (rate + omega), m)
        turn = np.where(moving[:, None, None], step @ was_turn, np.eye(m))
        targets = (turn @ anchor[:, :, None])[:, :, 0]  # x_i* - c*
        held = self.reference_stiffness > 0.0  # a member without the hold keeps no state, alone or in a batch
        self.scatter("reference_moving", np.where(held, moving, was_moving))
        self.scatter("reference_anchor", np.where(held[:, None], anchor, was_anchor))
        self.scatter("reference_turn", np.where(held[:, None, None], turn, was_turn))
        self.scatter("reference_rate", np.where(held[:, None], omega, rate))
        return self.reference_stiffness[:, None] * (targets - offsets)

    def spring_gradients(self, e_hat: np.ndarray) -> np.ndarray:
        """``e_hat + K_R (e_hat - e_hat_prev) / dt`` (k, 3): what the spring term ``-K_P J^T (.)`` acts on
        (module docstring, "Gradient-rate damping"); remembers ``e_hat`` as each member's previous value.
        ``e_hat`` itself (the same object) when no member has a rate gain; a member's first step after a
        reset has no previous value and gets its ``e_hat``."""
        if not np.any(self.rate_gain):
            return e_hat
        previous = np.stack([current if member._previous_e_hat is None else member._previous_e_hat
                             for member, current in zip(self.members, e_hat)])
        for member, current, rate in zip(self.members, e_hat, self.rate_gain):
            if rate:  # a member without the term keeps no state, alone or in a batch
                member._previous_e_hat = current
        return e_hat + (self.rate_gain / self.control_dt)[:, None] * (e_hat - previous)

    def saturated_errors(self, edge_errors: np.ndarray, desired: np.ndarray) -> np.ndarray:
        """Edge errors (k, slots, w) clipped at each spring's saturation level (module docstring); unchanged
        if unsaturated.

        Distance: ``clip(e_k, -c_k, c_k)`` with ``c_k = F / (2 K_P d_k)``; displacement: ``e_k`` scaled to
        length at most ``F / K_P``. Padding slots (``d_k = 0``) carry zero errors and stay zero; an agent
        with K_P = 0 is never saturated.
        """
        if not self.saturated:
            return edge_errors
        force = self.spring_force[:, :, None]  # (k, slots, 1), N
        kp = self.kp[:, :1, None]  # (k, 1, 1): scalar per agent
        with np.errstate(divide="ignore"):
            if self.kind == "distance":
                lengths = np.abs(desired)
                level = np.where(lengths > 0, force / (2.0 * kp * np.maximum(lengths, 1e-12)), 0.0)
                return np.clip(edge_errors, -level, level)
            norms = np.linalg.norm(edge_errors, axis=2, keepdims=True)
            return edge_errors * np.minimum(1.0, (force / kp) / np.maximum(norms, 1e-300))


def turn_rotations(angles: np.ndarray, dim: int) -> np.ndarray:
    """Rotations (k, dim, dim) by rotation vectors ``angles`` (rad): (k, 1) about z for ``dim`` 2, (k, 3) for 3
    (Rodrigues' formula)."""
    if dim == 2:
        return rotation_about(None, angles[:, 0], 2)
    theta = np.linalg.norm(angles, axis=1)
    axes = angles / np.where(theta > 0.0, theta, 1.0)[:, None]
    skew = np.zeros((len(angles), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -axes[:, 2], axes[:, 1], -axes[:, 0]
    skew = skew - skew.transpose(0, 2, 1)
    return (np.eye(3) + np.sin(theta)[:, None, None] * skew
            + (1.0 - np.cos(theta))[:, None, None] * (skew @ skew))


def _stacked(parts: ObservationParts) -> ObservationParts:
    """One agent's parts as a batch of one."""
    return ObservationParts(*(None if getattr(parts, field.name) is None else getattr(parts, field.name)[None]
                              for field in fields(ObservationParts)))
