"""Training-side reward shaping for learned policies: hold still once in formation, and do not touch.

The env's reward depends on the edge errors only, so it is blind to a rigid motion of the whole formation
(a distance formation may translate and rotate freely). A torque policy trained on it reached the formation
to ~0.05 tolerances in 1 s, but left the arms moving at ~0.1-0.4 rad/s along that motion: nothing in the
reward damps it (the references damp every joint, ``-K_D dq``), and after 10-15 s an elbow drifted into its
singularity and the formation broke (0 % success over 30 s). :class:`HoldShapingEnv` charges the agent's
own joint speed on the steps where it is in formation:

``r_i' = r_i - hold_penalty * [every incident edge of i within tolerance] * min(1, |dq_i| / SPEED_SCALE)``

read from agent i's own observation. With ``hold_penalty <= 1`` an in-formation step still earns more
than any step outside it (the env gives >= 1 + 0.65 inside, < 1 outside), so leaving the formation never
pays and every reward stays >= 0; reaching is not slowed, since nothing is charged before the tolerance.
Evaluation always uses the env's own reward and metrics.

The env's reward is blind to arm-arm contact too, and on the spatial tetrahedron a residual policy bought
speed with contacts its reference never makes. :class:`ContactShapingEnv` charges every step on which the
agent's arm touches another arm:

``r_i' = r_i - contact_penalty * [arm i has a contact point with another arm]``

from the env's own ``infos[agent]["contacts"]`` (both arms of a contact pay).

``SPEED_SCALE``: with the penalty full from 0.2 rad/s, a policy trained for 30 min held every held-out
formation to < 0.1 tolerances for 10-20 s, but its arms still coasted at ~0.02 rad/s with ~zero torque (a
penalty of 0.05 per step at that speed taught no damping) until the formation broke between 20 and 30 s.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np
from pettingzoo.utils.wrappers import BaseParallelWrapper

SPEED_SCALE = 0.05  # rad/s: joint speed (2-norm over the arm's joints) at which the penalty is full


def check_hold_penalty(hold_penalty: float) -> None:
    """``ValueError`` naming the field for a hold penalty outside [0, 1]."""
    if not 0 <= hold_penalty <= 1:
        raise ValueError(f"hold_penalty: expected a value in [0, 1], got {hold_penalty!r}")


def check_contact_penalty(contact_penalty: float) -> None:
    """``ValueError`` naming the field for a contact penalty that is not a finite value >= 0."""
    if not (np.isfinite(contact_penalty) and contact_penalty >= 0):
        raise ValueError(f"contact_penalty: expected a finite value >= 0, got {contact_penalty!r}")


def hold_penalty_factors(layout: Any, observations: np.ndarray) -> np.ndarray:
    """``[every real slot within tolerance] * min(1, |dq| / SPEED_SCALE)`` for a stack (k, size) of
    observations of one layout: (k,)."""
    ratios, real = layout.error_ratios(observations)  # (k, slots, w), (k, slots)
    inside = np.all((np.abs(ratios) <= 1.0) | ~real[..., None], axis=(1, 2))
    speeds = np.linalg.norm(layout.split(observations).dq, axis=1)
    return np.where(inside, np.minimum(1.0, speeds / SPEED_SCALE), 0.0)


def hold_penalty_factor(layout: Any, observation: np.ndarray) -> float:
    """:func:`hold_penalty_factors` of one observation."""
    return float(hold_penalty_factors(layout, np.asarray(observation)[None])[0])


class HoldShapingEnv(BaseParallelWrapper):
    """A parallel env whose rewards carry the hold penalty (module docstring); all else is the wrapped env's."""

    def __init__(self, env: Any, hold_penalty: float):
        check_hold_penalty(hold_penalty)
        super().__init__(env)
        self.hold_penalty = float(hold_penalty)
        self._layouts = {agent: env.observation_layout(agent) for agent in env.possible_agents}

    def step(self, actions: Mapping[str, np.ndarray]):
        observations, rewards, terminations, truncations, infos = self.env.step(actions)
        shaped = {agent: reward - self.hold_penalty * hold_penalty_factor(self._layouts[agent], observations[agent])
                  for agent, reward in rewards.items()}
        return observations, shaped, terminations, truncations, infos


class ContactShapingEnv(BaseParallelWrapper):
    """A parallel env whose rewards carry the contact penalty (module docstring); all else is the wrapped env's."""

    def __init__(self, env: Any, contact_penalty: float):
        check_contact_penalty(contact_penalty)
        super().__init__(env)
        self.contact_penalty = float(contact_penalty)

    def step(self, actions: Mapping[str, np.ndarray]):
        observations, rewards, terminations, truncations, infos = self.env.step(actions)
        shaped = {agent: reward - self.contact_penalty * float(infos[agent]["contacts"] > 0)
                  for agent, reward in rewards.items()}
        return observations, shaped, terminations, truncations, infos
