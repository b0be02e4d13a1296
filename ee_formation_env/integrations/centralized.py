"""A centralized single-agent Gymnasium view of the formation env (joint observation and action).

Useful for single-agent RL baselines and for ``gymnasium.utils.env_checker.check_env``. The observation
is the agents' observations concatenated in agent order; the action is their actions concatenated; the
reward is the mean of the agents' rewards; the episode terminates / truncates when the team's does.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np

from ee_formation_env.env import FormationEnv
from ee_formation_env.inputs import check_seed


class CentralizedFormationEnv(gymnasium.Env):
    """Gymnasium env over :class:`FormationEnv` with one joint observation and action.

    ``info`` carries the team's ``formation_error`` and the per-agent infos under ``agents``.
    """

    metadata = {"render_modes": FormationEnv.metadata["render_modes"], "render_fps": FormationEnv.metadata["render_fps"]}

    def __init__(self, scenario: Any = "planar_square", render_mode: str | None = None, **overrides: Any):
        self.parallel_env = FormationEnv(scenario, render_mode=render_mode, **overrides)
        self.render_mode = render_mode
        agents = self.parallel_env.possible_agents
        observation_spaces = [self.parallel_env.observation_space(a) for a in agents]
        action_spaces = [self.parallel_env.action_space(a) for a in agents]
        self.observation_space = gymnasium.spaces.Box(
            np.concatenate([s.low for s in observation_spaces]), np.concatenate([s.high for s in observation_spaces]),
            dtype=np.float32)
        self.action_space = gymnasium.spaces.Box(
            np.concatenate([s.low for s in action_spaces]), np.concatenate([s.high for s in action_spaces]),
            dtype=np.float32)
        self._splits = np.cumsum([s.shape[0] for s in action_spaces])[:-1]

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        seed = check_seed(seed)  # numpy integers too; a negative seed is a ValueError naming seed, nothing reset
        super().reset(seed=seed)
        observations, infos = self.parallel_env.reset(seed=seed, options=options)
        return self._joint(observations), self._info(infos)

    def step(self, action: np.ndarray):
        agents = self.parallel_env.agents
        # Split as given: the parallel env checks each part (numeric, shape, finite) before anything changes.
        actions = dict(zip(agents, np.split(np.asarray(action), self._splits)))
        observations, rewards, terminations, truncations, infos = self.parallel_env.step(actions)
        reward = float(np.mean(list(rewards.values())))
        return (self._joint(observations), reward, any(terminations.values()), any(truncations.values()),
                self._info(infos))

    def render(self):
        return self.parallel_env.render()

    def close(self) -> None:
        self.parallel_env.close()

    def _joint(self, observations: dict[str, np.ndarray]) -> np.ndarray:
        return np.concatenate([observations[a] for a in self.parallel_env.possible_agents])

    @staticmethod
    def _info(infos: dict[str, dict[str, Any]]) -> dict[str, Any]:
        first = next(iter(infos.values()))
        return {"formation_error": first["formation_error"], "agents": infos}
