"""Residual actions: a learned correction added to a reference controller's torque.

``action = reference(observation) + scale * joint_scale * residual`` in the env's normalized units, with
``joint_scale`` the per-joint physical scale of a learned action
(:mod:`~ee_formation_env.baselines.learned.action_scale`; 1 on the built-in robots). The same rule is
used during training (:class:`ResidualActionEnv`, the env the learner steps) and evaluation
(:class:`ResidualPolicy`, a per-agent policy for :func:`ee_formation_env.baselines.metrics.run_episode`). A zero residual
applies the reference's action exactly (bit for bit).

Training regularizes the *correction*, never the applied torque (the reference needs its full torque):
each agent's reward is scaled by ``1 - correction_penalty * mean(residual^2)``. Without it PPO learned a
constant bias that held the formation ~1 cm off (0 % success); the factor keeps rewards >= 0 (ending an
episode early never pays), and a zero correction receives exactly the env's reward.

``gate=True`` (optional) multiplies the correction by ``min(1, x)``, ``x`` being the agent's mean edge error
in success tolerances as its own observation shows it (:func:`error_gate`): the correction fades out at the
goal by construction, so a learned bias cannot hold the formation off it.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from ee_formation_env import baselines
from ee_formation_env.baselines.reference.controllers import PolicyTeam
from pettingzoo.utils.wrappers import BaseParallelWrapper

from ee_formation_env.observation import ObservationLayout
from ee_formation_env.reward import DEFAULT_POSITION_TOLERANCE


def combine(reference_action: np.ndarray, residual_action: np.ndarray, scale: float) -> np.ndarray:
    """The applied normalized action: ``reference + scale * clip(residual, -1, 1)``."""
    return reference_action + scale * np.clip(residual_action, -1.0, 1.0)


def correction_factor(residual_action: np.ndarray, correction_penalty: float) -> float:
    """The reward factor ``1 - correction_penalty * mean(clip(residual, -1, 1)^2)``, in [0, 1]."""
    residual = np.clip(residual_action, -1.0, 1.0)
    return 1.0 - correction_penalty * float(np.mean(residual * residual))


def error_gate(layout: ObservationLayout, observation: np.ndarray,
               position_tolerance: float = DEFAULT_POSITION_TOLERANCE) -> float:
    """``min(1, x)``: ``x`` the mean over the agent's neighbour slots of ``|e_ij| / tol_ij`` read from its
    observation, with ``tol_ij = 2 d*_ij delta`` (distance, one error entry per slot) or ``delta``
    (displacement), ``delta = position_tolerance`` (m): the reward's error ratio, seen by the agent."""
    return float(error_gates(layout, np.asarray(observation)[None], position_tolerance)[0])


def error_gates(layout: ObservationLayout, observations: np.ndarray,
                position_tolerance: float = DEFAULT_POSITION_TOLERANCE) -> np.ndarray:
    """:func:`error_gate` of a stack of k observations (k, size) of one layout: (k,)."""
    parts = layout.split(observations)
    real = parts.mask > 0.5  # (k, slots)
    errors = np.linalg.norm(parts.edge_errors, axis=2)  # |e_ij| per slot
    ratios = np.where(real, errors / layout.slot_tolerances(parts, position_tolerance), 0.0)
    return np.minimum(1.0, ratios.sum(axis=1) / real.sum(axis=1))


class ResidualPolicy:
    """Per-agent policy: a reference controller plus a scaled learned residual (gated by the agent's error
    with ``gate_layout``, the agent's observation layout). ``joint_scale`` (n,): the per-joint physical scale
    of the residual (:mod:`~ee_formation_env.baselines.learned.action_scale`); None: 1 on every joint."""

    def __init__(self, reference: Any, learned: Any, scale: float, gate_layout: ObservationLayout | None = None,
                 joint_scale: np.ndarray | None = None):
        self.reference, self.learned, self.scale, self.gate_layout = reference, learned, scale, gate_layout
        self.joint_scale = None if joint_scale is None else np.asarray(joint_scale, dtype=np.float64)

    def reset(self) -> None:
        self.reference.reset()
        self.learned.reset()

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        scale = self.scale if self.gate_layout is None else self.scale * error_gate(self.gate_layout, observation)
        if self.joint_scale is not None:
            scale = scale * self.joint_scale
        return combine(self.reference(observation), self.learned(observation), scale)

    @classmethod
    def stacked(cls, policies: Sequence["ResidualPolicy"]):
        """A stack of residual policies as one callable ``(k, size) -> (k, n)``, each row its policy's action
        bit for bit: the references batched as a team (:func:`~ee_formation_env.baselines.metrics.stack_policies`),
        the learned parts as one stack, the gates per layout in one call."""
        from ee_formation_env.baselines.metrics import stack_policies

        policies = list(policies)
        references = stack_policies([policy.reference for policy in policies])
        learned = stack_policies([policy.learned for policy in policies])
        scales = np.array([policy.scale for policy in policies], dtype=np.float64)
        joint_scales = joint_scale_rows([policy.joint_scale for policy in policies])
        groups: dict[Any, list[int]] = {}
        for row, policy in enumerate(policies):
            if policy.gate_layout is not None:
                groups.setdefault(policy.gate_layout, []).append(row)
        gated = [(layout, np.array(rows)) for layout, rows in groups.items()]

        def act(observations: np.ndarray) -> np.ndarray:
            scale = scales.copy()
            for layout, rows in gated:
                scale[rows] = scales[rows] * error_gates(layout, observations[rows])
            scale = scale[:, None] if joint_scales is None else scale[:, None] * joint_scales
            return combine(np.asarray(references(observations)), np.asarray(learned(observations)), scale)

        return act


def joint_scale_rows(joint_scales: Sequence[np.ndarray | None]) -> np.ndarray | None:
    """Rows' per-joint scales stacked (rows, n), ones for a row without; None if no row has one."""
    given = [scale for scale in joint_scales if scale is not None]
    if not given:
        return None
    ones = np.ones_like(given[0])
    return np.stack([ones if scale is None else scale for scale in joint_scales])


def check_residual_settings(reference: str, scale: float, correction_penalty: float) -> None:
    """``ValueError`` naming the field for a reference that is not model-based, a scale outside (0, 1] or a
    correction penalty outside [0, 1]."""
    if reference not in baselines.MODEL_BASED_POLICIES:
        raise ValueError(f"reference: expected a model-based controller, got {reference!r}")
    if not 0 < scale <= 1:
        raise ValueError(f"residual_scale: expected a value in (0, 1], got {scale!r}")
    if not 0 <= correction_penalty <= 1:
        raise ValueError(f"correction_penalty: expected a value in [0, 1], got {correction_penalty!r}")


class ResidualRows:
    """The residual rule over a stack of agent rows, in one set of batched calls: every row's reference action
    (the controllers of all rows as one :class:`~ee_formation_env.baselines.reference.controllers.PolicyTeam`),
    its error gate (rows of one observation layout in one call) and its combined action.

    ``teams``: one dict agent -> reference controller per copy; the rows are copy-major (row ``k * N + i`` is
    agent i of copy k). ``gate_layouts``: agent -> observation layout when the correction is gated, else None.
    The single :class:`ResidualActionEnv` (one copy) and the batched training env (K copies) both use it, so a
    copy gets the same actions in either, bit for bit.
    """

    def __init__(self, teams: Sequence[Mapping[str, Any]], agents: Sequence[str], scale: float,
                 gate_layouts: Mapping[str, ObservationLayout] | None = None,
                 joint_scales: Mapping[str, np.ndarray] | None = None):
        self.teams, self.agents = list(teams), list(agents)
        self.team = PolicyTeam({(k, agent): team[agent] for k, team in enumerate(self.teams) for agent in self.agents})
        self.scales = np.full(len(self.teams) * len(self.agents), float(scale))
        self.joint_scales = None if joint_scales is None else np.tile(
            np.stack([joint_scales[agent] for agent in self.agents]), (len(self.teams), 1))  # (rows, n)
        groups: dict[ObservationLayout, list[int]] = {}
        if gate_layouts is not None:
            for k in range(len(self.teams)):
                for i, agent in enumerate(self.agents):
                    groups.setdefault(gate_layouts[agent], []).append(k * len(self.agents) + i)
        self.gate_groups = [(layout, np.array(rows)) for layout, rows in groups.items()]

    def reset(self, copies: Sequence[int] | np.ndarray | None = None) -> None:
        """Reset the reference controllers of ``copies`` (default: all), at the start of their episodes."""
        for k in range(len(self.teams)) if copies is None else copies:
            for policy in self.teams[int(k)].values():
                policy.reset()

    def __call__(self, observations: np.ndarray, residuals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The applied actions (rows, n) (:func:`combine` of each row's reference action and its clipped
        residual ``residuals``, float64) and each row's mean squared correction (rows,), for the rows'
        observations (rows, size)."""
        references = self.team.act_on_stack(observations)
        scales = self.scales.copy()
        for layout, rows in self.gate_groups:
            scales[rows] *= error_gates(layout, observations[rows])
        scales = scales[:, None] if self.joint_scales is None else scales[:, None] * self.joint_scales
        return references + scales * residuals, np.mean(residuals * residuals, axis=1)


class ResidualActionEnv(BaseParallelWrapper):
    """A parallel env whose actions are residuals on top of one reference controller per agent.

    Observations and spaces are the wrapped env's; each agent's reward is the env's times
    :func:`correction_factor` of its residual. The batched training env applies the same rule to K copies
    (:class:`ResidualRows`).
    """

    def __init__(self, env: Any, reference: str = "adaptive_jacobian", scale: float = 0.1,
                 reference_kwargs: Mapping[str, Any] | None = None, correction_penalty: float = 0.5,
                 gate: bool = False, joint_scales: Mapping[str, np.ndarray] | None = None):
        check_residual_settings(reference, scale, correction_penalty)
        super().__init__(env)
        self.scale, self.correction_penalty = float(scale), float(correction_penalty)
        self.joint_scales = joint_scales
        self.agents_in_order = list(env.possible_agents)
        shapes = {env.action_space(agent).shape for agent in self.agents_in_order}
        self._uniform = len(shapes) == 1
        self._action_shape = next(iter(shapes))
        self.gate_layouts = {agent: env.observation_layout(agent) for agent in env.possible_agents} if gate else None
        self.references = PolicyTeam(baselines.make_policies(reference, env, **dict(reference_kwargs or {})))
        self._observations: dict[str, np.ndarray] = {}
        # Agents of one robot type: the team in one array (a few calls for the whole team); mixed robots agent
        # by agent.
        self._rows = (ResidualRows([self.references.policies], self.agents_in_order, self.scale, self.gate_layouts,
                                   joint_scales) if self._uniform else None)

    def reset(self, seed: int | None = None, options: dict | None = None):
        self._observations, infos = self.env.reset(seed=seed, options=options)
        self.references.reset()
        return self._observations, infos

    def step(self, actions: Mapping[str, np.ndarray]):
        if self._rows is not None:
            residuals = self._checked_residuals(actions)
            if residuals is None:
                return self.env.step(actions)  # the env raises its error, naming the agent, before anything moves
            observations = np.stack([self._observations[agent] for agent in self.agents_in_order])
            combined, penalties = self._rows(observations, residuals)
            return self._apply(dict(zip(self.agents_in_order, combined)), penalties)
        if not isinstance(actions, Mapping) or actions.keys() != set(self.agents_in_order):
            return self.env.step(actions)  # the env raises its error, naming the agents
        agents = self.agents_in_order
        try:
            residuals = [np.asarray(actions[agent], dtype=np.float64) for agent in agents]
        except (TypeError, ValueError):
            return self.env.step(actions)
        if any(r.shape != self.env.action_space(a).shape or not np.isfinite(r).all()
               for a, r in zip(agents, residuals)):
            return self.env.step(actions)
        residuals = [np.clip(residual, -1.0, 1.0) for residual in residuals]
        penalties = np.array([np.mean(residual * residual) for residual in residuals])
        references = self.references(self._observations)
        if self.gate_layouts is None:
            scales = np.full(len(agents), self.scale)
        else:
            scales = self.scale * np.array([error_gate(self.gate_layouts[agent], self._observations[agent])
                                            for agent in agents])
        if self.joint_scales is not None:
            scales = [scale * self.joint_scales[agent] for agent, scale in zip(agents, scales)]
        combined = {agent: references[agent] + scale * residual
                    for agent, scale, residual in zip(agents, scales, residuals)}
        return self._apply(combined, penalties)

    def _checked_residuals(self, actions: Any) -> np.ndarray | None:
        """Every agent's residual (N, n), float64, clipped to [-1, 1]; None if the env would reject the actions
        (wrong agents, shapes or types, non-finite values) or the episode needs a reset."""
        agents = self.agents_in_order
        if not self.env.agents or not isinstance(actions, Mapping) or actions.keys() != set(agents):
            return None
        try:
            residuals = np.array([actions[agent] for agent in agents], dtype=np.float64)
        except (TypeError, ValueError):
            return None
        if residuals.shape != (len(agents), *self._action_shape) or not np.isfinite(residuals).all():
            return None
        return np.clip(residuals, -1.0, 1.0, out=residuals)

    def _apply(self, combined: Mapping[str, np.ndarray], penalties: np.ndarray):
        """Step the env with the combined actions; scale each agent's reward by its correction factor
        (:func:`correction_factor` of its clipped residual, ``penalties`` the mean squares, agent order)."""
        observations, rewards, terminations, truncations, infos = self.env.step(combined)
        self._observations = observations
        if self.correction_penalty > 0:
            factors = (1.0 - self.correction_penalty * penalties).tolist()
            rewards = {agent: rewards[agent] * factor for agent, factor in zip(self.agents_in_order, factors)}
        return observations, rewards, terminations, truncations, infos
