"""Residual actions: a learned correction added to a reference controller's torque.

``action = reference(observation) + scale * residual`` in the env's normalized units. The same rule is
used during training (:class:`ResidualActionEnv`, the env the learner steps) and evaluation
(:class:`ResidualPolicy`, a per-agent policy for :func:`baselines.metrics.run_episode`).
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

import baselines


def combine(reference_action: np.ndarray, residual_action: np.ndarray, scale: float) -> np.ndarray:
    """The applied normalized action: ``reference + scale * clip(residual, -1, 1)``."""
    return reference_action + scale * np.clip(residual_action, -1.0, 1.0)


class ResidualPolicy:
    """Per-agent policy: a reference controller plus a scaled learned residual."""

    def __init__(self, reference: Any, learned: Any, scale: float):
        self.reference, self.learned, self.scale = reference, learned, scale

    def reset(self) -> None:
        self.reference.reset()
        self.learned.reset()

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        return combine(self.reference(observation), self.learned(observation), self.scale)


class ResidualActionEnv:
    """A parallel env whose actions are residuals on top of one reference controller per agent.

    Everything but ``step``'s action semantics is the wrapped env's (observations, rewards, spaces).
    """

    def __init__(self, env: Any, reference: str = "adaptive_jacobian", scale: float = 0.1,
                 reference_kwargs: Mapping[str, Any] | None = None):
        if reference not in baselines.MODEL_BASED_POLICIES:
            raise ValueError(f"reference: expected a model-based controller, got {reference!r}")
        if not 0 < scale <= 1:
            raise ValueError(f"residual_scale: expected a value in (0, 1], got {scale!r}")
        self.env, self.scale = env, float(scale)
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
        combined = {agent: combine(self.references[agent](self._observations[agent]),
                                   np.asarray(action, dtype=np.float64), self.scale)
                    for agent, action in actions.items()}
        result = self.env.step(combined)
        self._observations = result[0]
        return result

    def close(self) -> None:
        self.env.close()


def make_training_env(scenario: Any, overrides: Mapping[str, Any] | None = None, mode: str = "torque",
                      reference: str = "adaptive_jacobian", residual_scale: float = 0.1) -> Any:
    """The env a learner steps: the formation env (``mode="torque"``) or its residual form.

    A module-level function so that ``functools.partial(make_training_env, ...)`` pickles into workers.
    """
    from ee_formation_env import parallel_env

    env = parallel_env(scenario, **dict(overrides or {}))
    if mode == "torque":
        return env
    if mode == "residual":
        return ResidualActionEnv(env, reference=reference, scale=residual_scale)
    env.close()
    raise ValueError(f"mode: expected 'torque' or 'residual', got {mode!r}")
