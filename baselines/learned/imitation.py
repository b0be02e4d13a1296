"""Demonstrations of a reference controller, for a learned policy to start from (DAgger).

A torque-mode policy outputs the joint torques itself, to 1 cm on 3 m edges. Learned from the reward it
gets there with log-scaled error features, a hold penalty and half an hour of training (README,
"Training"); started as a copy of a reference controller it gets there in minutes, because the copy is
close enough that the formation's own stiffness holds it. :func:`demonstrations`
rolls episodes and labels every agent's observation with the reference's normalized action (clipped to
the action space, as the env applies it). In the first round the reference drives; in later rounds the
learner drives for a share of the steps, so that the data covers the states the learner itself visits
and the reference says what it would do there (DAgger: Ross, Gordon and Bagnell, 2011).

Labels come from one reference policy per agent, reset with each episode; the reference must be one of
the model-based laws. ``gradient`` (law-I) is stateless, so its label depends on the observation only;
law-II and law-III carry internal states along the trajectory that was actually driven.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping

import numpy as np

from ee_formation_env import baselines
from ee_formation_env.baselines.reference.controllers import PolicyTeam

Learner = Callable[[np.ndarray], np.ndarray]  # stacked observations (k, size) -> actions (k, n)


def demonstrations(env: Any, reference: str, episodes: int, seeds: np.ndarray,
                   learner: Learner | None = None, learner_share: float = 0.0,
                   rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Roll ``episodes`` episodes of ``env`` (reset seeds ``seeds``) and return every agent's observations
    (samples, size) and the reference's normalized actions there (samples, n), clipped to [-1, 1].

    The reference drives, except that with ``learner`` given each step is driven by the learner (all
    agents, its actions clipped to [-1, 1]) with probability ``learner_share`` (``rng`` decides).
    Agents must share one observation and action size (the learner is shared).
    """
    if reference not in baselines.MODEL_BASED_POLICIES:
        raise ValueError(f"reference: expected one of {list(baselines.MODEL_BASED_POLICIES)}, got {reference!r}")
    if not isinstance(episodes, int) or episodes < 1 or len(seeds) < episodes:
        raise ValueError(f"episodes: expected an integer >= 1 with as many seeds, got {episodes!r} and {len(seeds)} seeds")
    if not 0.0 <= learner_share <= 1.0:
        raise ValueError(f"learner_share: expected a value in [0, 1], got {learner_share!r}")
    if learner_share > 0 and learner is None:
        raise ValueError("learner: a learner_share above 0 needs a learner")
    rng = rng or np.random.default_rng(0)
    team = PolicyTeam(baselines.make_policies(reference, env))
    agents = list(env.possible_agents)
    observations_seen, labels = [], []
    for episode in range(episodes):
        observations, _ = env.reset(seed=int(seeds[episode]))
        team.reset()
        while env.agents:
            stacked = np.stack([observations[agent] for agent in agents])
            reference_actions = team(observations)
            wanted = np.clip(np.stack([reference_actions[agent] for agent in agents]), -1.0, 1.0)
            observations_seen.append(stacked)
            labels.append(wanted)
            driving = wanted
            if learner is not None and learner_share > 0 and rng.random() < learner_share:
                driving = np.clip(learner(stacked), -1.0, 1.0)
            observations, *_ = env.step(_per_agent(agents, driving))
    return np.concatenate(observations_seen).astype(np.float64), np.concatenate(labels).astype(np.float64)


def _per_agent(agents: list[str], actions: np.ndarray) -> Mapping[str, np.ndarray]:
    return {agent: np.asarray(action, dtype=np.float32) for agent, action in zip(agents, actions)}
