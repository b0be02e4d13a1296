"""A team's policies called together (:class:`PolicyTeam`), and the two policies that are not laws (zero and
random torques, the lower references)."""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from ee_formation_env.baselines.reference.controllers import ControllerBatch, FormationController


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


class PolicyTeam:
    """Every agent's policy of one env, called on all observations at once: agents whose controllers can
    share a :class:`ControllerBatch` (same law, chain, layout and options) are evaluated in one batch; any
    other policy (``zero``, ``random``, a learned one) is called agent by agent. Gives each agent exactly
    the action its own policy gives alone.
    """

    def __init__(self, policies: Mapping[str, Any]):
        self.policies = dict(policies)
        groups: dict[tuple, list[str]] = {}
        self._single: list[str] = []
        for agent, policy in self.policies.items():
            if isinstance(policy, FormationController):
                key = (type(policy), id(policy.agent.chain), policy.agent.layout, policy.agent.formation_kind,
                       policy.agent.control_dt, policy.options())
                groups.setdefault(key, []).append(agent)
            else:
                self._single.append(agent)
        self._batches = [(agents, ControllerBatch([self.policies[a] for a in agents])) for agents in groups.values()]
        row = {agent: k for k, agent in enumerate(self.policies)}  # each agent's row in act_on_stack's stacks
        self._batch_rows = [np.array([row[a] for a in agents]) for agents, _ in self._batches]
        self._single_rows = [(row[agent], agent) for agent in self._single]

    def reset(self) -> None:
        for policy in self.policies.values():
            policy.reset()

    def __call__(self, observations: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Every agent's action (normalized, float32) from its observation."""
        actions = {agent: self.policies[agent](observations[agent]) for agent in self._single}
        for agents, batch in self._batches:
            actions.update(zip(agents, batch(np.stack([observations[agent] for agent in agents]))))
        return actions

    def act_on_stack(self, observations: np.ndarray) -> np.ndarray:
        """Every agent's action (k, n) (normalized, float32) from a stack (k, size) of their observations, both
        in the order the policies were given; the same actions as :meth:`__call__`. Every agent must have the
        same number n of joints (and of observation entries)."""
        if len(observations) != len(self.policies):
            raise ValueError(f"observations: expected a stack of {len(self.policies)} rows (one per agent), "
                             f"got {len(observations)}")
        actions = None
        for rows, (_, batch) in zip(self._batch_rows, self._batches):
            stacked = batch(observations[rows])
            if actions is None:
                actions = np.empty((len(observations), stacked.shape[1]), dtype=np.float32)
            actions[rows] = stacked
        for row, agent in self._single_rows:
            action = np.asarray(self.policies[agent](observations[row]), dtype=np.float32)
            if actions is None:
                actions = np.empty((len(observations), len(action)), dtype=np.float32)
            actions[row] = action
        return actions
