"""Residual actions: a learned correction added to a reference controller's torque.

``action = reference(observation) + scale * residual`` in the env's normalized units. The same rule is
used during training (:class:`ResidualActionEnv`, the env the learner steps) and evaluation
(:class:`ResidualPolicy`, a per-agent policy for :func:`baselines.metrics.run_episode`). A zero residual
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

from typing import Any, Mapping

import numpy as np

import baselines
from baselines.controllers import PolicyTeam
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
    errors = np.linalg.norm(parts.edge_errors, axis=2)
    if layout.error_width == 1:
        tolerances = np.where(real, 2.0 * parts.desired[:, :, 0] * position_tolerance, 1.0)
    else:
        tolerances = np.full(errors.shape, position_tolerance)
    ratios = np.where(real, errors / tolerances, 0.0)
    return np.minimum(1.0, ratios.sum(axis=1) / real.sum(axis=1))


class ResidualPolicy:
    """Per-agent policy: a reference controller plus a scaled learned residual (gated by the agent's error
    with ``gate_layout``, the agent's observation layout)."""

    def __init__(self, reference: Any, learned: Any, scale: float, gate_layout: ObservationLayout | None = None):
        self.reference, self.learned, self.scale, self.gate_layout = reference, learned, scale, gate_layout

    def reset(self) -> None:
        self.reference.reset()
        self.learned.reset()

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        scale = self.scale if self.gate_layout is None else self.scale * error_gate(self.gate_layout, observation)
        return combine(self.reference(observation), self.learned(observation), scale)


class ResidualActionEnv:
    """A parallel env whose actions are residuals on top of one reference controller per agent.

    Observations and spaces are the wrapped env's; each agent's reward is the env's times
    :func:`correction_factor` of its residual.
    """

    def __init__(self, env: Any, reference: str = "adaptive_jacobian", scale: float = 0.1,
                 reference_kwargs: Mapping[str, Any] | None = None, correction_penalty: float = 0.5,
                 gate: bool = False):
        if reference not in baselines.MODEL_BASED_POLICIES:
            raise ValueError(f"reference: expected a model-based controller, got {reference!r}")
        if not 0 < scale <= 1:
            raise ValueError(f"residual_scale: expected a value in (0, 1], got {scale!r}")
        if not 0 <= correction_penalty <= 1:
            raise ValueError(f"correction_penalty: expected a value in [0, 1], got {correction_penalty!r}")
        self.env, self.scale, self.correction_penalty = env, float(scale), float(correction_penalty)
        self.agents_in_order = list(env.possible_agents)
        shapes = {env.action_space(agent).shape for agent in self.agents_in_order}
        self._uniform = len(shapes) == 1
        self._action_shape = next(iter(shapes))
        self.gate_layouts = {agent: env.observation_layout(agent) for agent in env.possible_agents} if gate else None
        # Agents sharing an observation layout get their gates in one call: (layout, their rows).
        self._gate_groups: list[tuple[ObservationLayout, list[int]]] = []
        if gate:
            groups: dict[ObservationLayout, list[int]] = {}
            for k, agent in enumerate(self.agents_in_order):
                groups.setdefault(self.gate_layouts[agent], []).append(k)
            self._gate_groups = list(groups.items())
        self.references = PolicyTeam(baselines.make_policies(reference, env, **dict(reference_kwargs or {})))
        self._observations: dict[str, np.ndarray] = {}

    def __getattr__(self, name: str) -> Any:
        if name == "env":  # not set yet (e.g. during unpickling): no delegation loop
            raise AttributeError(name)
        return getattr(self.env, name)

    def reset(self, seed: int | None = None, options: dict | None = None):
        self._observations, infos = self.env.reset(seed=seed, options=options)
        self.references.reset()
        return self._observations, infos

    def step(self, actions: Mapping[str, np.ndarray]):
        if not isinstance(actions, Mapping) or actions.keys() != set(self.agents_in_order):
            return self.env.step(actions)  # the env raises its error, naming the agents
        agents = self.agents_in_order
        if self._uniform:  # every agent's residual in one (N, n) array: a few calls for the whole team
            try:
                residuals = np.array([actions[agent] for agent in agents], dtype=np.float64)
            except (TypeError, ValueError):
                residuals = None
            if residuals is None or residuals.shape != (len(agents), *self._action_shape) \
                    or not np.isfinite(residuals).all():
                # The env raises its error, naming the agent, before anything (the references' states too) moves.
                return self.env.step(actions)
            np.clip(residuals, -1.0, 1.0, out=residuals)
            penalties = np.mean(residuals * residuals, axis=1)
        else:
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
        combined = {agent: references[agent] + scale * residual
                    for agent, scale, residual in zip(agents, self._scales(), residuals)}
        observations, rewards, terminations, truncations, infos = self.env.step(combined)
        self._observations = observations
        if self.correction_penalty > 0:  # the factor of correction_factor (residuals are clipped already)
            factors = (1.0 - self.correction_penalty * penalties).tolist()
            rewards = {agent: rewards[agent] * factor for agent, factor in zip(agents, factors)}
        return observations, rewards, terminations, truncations, infos

    def _scales(self) -> np.ndarray:
        """Every agent's correction scale (agent order): ``scale``, times its error gate if gated."""
        if self.gate_layouts is None:
            return np.full(len(self.agents_in_order), self.scale)
        gates = np.empty(len(self.agents_in_order))
        for layout, rows in self._gate_groups:
            gates[rows] = error_gates(layout, np.stack([self._observations[self.agents_in_order[k]] for k in rows]))
        return self.scale * gates

    def close(self) -> None:
        self.env.close()


def make_training_env(scenario: Any, overrides: Mapping[str, Any] | None = None, mode: str = "torque",
                      reference: str = "adaptive_jacobian", residual_scale: float = 0.1,
                      correction_penalty: float = 0.5, gate: bool = False) -> Any:
    """The env a learner steps: the formation env (``mode="torque"``) or its residual form.

    A module-level function so that ``functools.partial(make_training_env, ...)`` pickles into workers.
    """
    from ee_formation_env import parallel_env

    env = parallel_env(scenario, **dict(overrides or {}))
    if mode == "torque":
        return env
    if mode == "residual":
        return ResidualActionEnv(env, reference=reference, scale=residual_scale, correction_penalty=correction_penalty,
                                 gate=gate)
    env.close()
    raise ValueError(f"mode: expected 'torque' or 'residual', got {mode!r}")
