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
    parts = layout.split(observation)
    real = parts.mask > 0.5
    errors = np.linalg.norm(parts.edge_errors[real], axis=1)
    if layout.error_width == 1:
        tolerances = 2.0 * parts.desired[real, 0] * position_tolerance
    else:
        tolerances = np.full(len(errors), position_tolerance)
    return min(1.0, float(np.mean(errors / tolerances)))


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
        self.gate_layouts = {agent: env.observation_layout(agent) for agent in env.possible_agents} if gate else None
        self.references = baselines.make_policies(reference, env, **dict(reference_kwargs or {}))
        self._observations: dict[str, np.ndarray] = {}

    def __getattr__(self, name: str) -> Any:
        if name == "env":  # not set yet (e.g. during unpickling): no delegation loop
            raise AttributeError(name)
        return getattr(self.env, name)

    def reset(self, seed: int | None = None, options: dict | None = None):
        self._observations, infos = self.env.reset(seed=seed, options=options)
        for policy in self.references.values():
            policy.reset()
        return self._observations, infos

    def step(self, actions: Mapping[str, np.ndarray]):
        residuals = {agent: np.asarray(action, dtype=np.float64) for agent, action in actions.items()}
        combined = {agent: combine(self.references[agent](self._observations[agent]), residual, self._scale(agent))
                    for agent, residual in residuals.items()}
        observations, rewards, terminations, truncations, infos = self.env.step(combined)
        self._observations = observations
        if self.correction_penalty > 0:
            rewards = {agent: reward * correction_factor(residuals[agent], self.correction_penalty)
                       for agent, reward in rewards.items()}
        return observations, rewards, terminations, truncations, infos

    def _scale(self, agent: str) -> float:
        if self.gate_layouts is None:
            return self.scale
        return self.scale * error_gate(self.gate_layouts[agent], self._observations[agent])

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
