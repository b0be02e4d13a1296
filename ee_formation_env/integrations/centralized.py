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
from ee_formation_env.infos import copies_info_dicts
from ee_formation_env.inputs import check_seed


def joint_spaces(env: Any) -> tuple[gymnasium.spaces.Box, gymnasium.spaces.Box]:
    """The centralized observation and action spaces of ``env``: every agent's single-copy Box, concatenated in
    agent order."""
    agents = env.possible_agents
    spaces = ([env.observation_space(agent) for agent in agents], [env.action_space(agent) for agent in agents])
    return tuple(gymnasium.spaces.Box(np.concatenate([s.low for s in group]), np.concatenate([s.high for s in group]),
                                      dtype=np.float32) for group in spaces)


class CentralizedFormationEnv(gymnasium.Env):
    """Gymnasium env over :class:`FormationEnv` with one joint observation and action.

    ``info`` carries the team's ``formation_error`` and the per-agent infos under ``agents``.
    """

    metadata = {"render_modes": FormationEnv.metadata["render_modes"], "render_fps": FormationEnv.metadata["render_fps"]}

    def __init__(self, scenario: Any = "planar_square", render_mode: str | None = None, **overrides: Any):
        self.parallel_env = FormationEnv(scenario, render_mode=render_mode, **overrides)
        self.render_mode = render_mode
        self.observation_space, self.action_space = joint_spaces(self.parallel_env)
        self._splits = np.cumsum([self.parallel_env.action_space(agent).shape[0]
                                  for agent in self.parallel_env.possible_agents])[:-1]

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        seed = check_seed(seed)  # numpy integers too; a negative seed is a ValueError naming seed, nothing reset
        super().reset(seed=seed)
        observations, infos = self.parallel_env.reset(seed=seed, options=options)
        return self._joint(observations), self._info(infos)

    def step(self, action: np.ndarray):
        agents = self.parallel_env.agents
        array = np.asarray(action)
        if array.shape != self.action_space.shape:  # the joint shape the caller gave wrong, before any split
            raise ValueError(f"action: expected the joint action of shape {self.action_space.shape} (every agent's "
                             f"joints in agent order), got shape {array.shape}")
        # Split as given: the parallel env checks each part (numeric, finite) before anything changes.
        actions = dict(zip(agents, np.split(array, self._splits)))
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


class CentralizedFormationVectorEnv(gymnasium.vector.VectorEnv):
    """K copies of :class:`CentralizedFormationEnv` as one Gymnasium ``VectorEnv`` over the batched env
    (:func:`ee_formation_env.vector_env`): what ``gymnasium.make_vec(id, num_envs=K,
    vectorization_mode="vector_entry_point")`` builds for every registered id.

    Copy k of ``reset(seed=s)`` is ``CentralizedFormationEnv`` reset with ``s + k``, bit for bit. Observations
    (K, O) float32 (the agents' observations concatenated), actions (K, A) (their actions concatenated),
    rewards (K,) (the mean over agents), terminations and truncations (K,). Autoreset: Gymnasium's SAME_STEP
    mode: an ended copy's row is already its next episode's first observation; ``infos["final_obs"]`` (object
    array, ``infos["_final_obs"]`` its mask) holds the observation it ended in and ``infos["final_info"]``
    its last ``formation_error``. ``infos["formation_error"]`` (K,) is the team's, ``infos["agents"]`` the
    batched env's per-agent infos (agent -> dict of (K, ...) arrays). ``max_episode_steps`` (from the
    registration or given) truncates as Gymnasium's ``TimeLimit`` does on the single env.
    """

    metadata = {"render_modes": [], "autoreset_mode": gymnasium.vector.AutoresetMode.SAME_STEP}

    def __init__(self, scenario: Any = "planar_square", num_envs: int = 1, max_episode_steps: int | None = None,
                 **overrides: Any):
        from ee_formation_env.scenario import load_scenario
        from ee_formation_env.vector import VectorFormationEnv

        if max_episode_steps is not None:
            if isinstance(max_episode_steps, bool) or not isinstance(max_episode_steps, (int, np.integer)) \
                    or max_episode_steps < 1:
                raise ValueError(f"max_episode_steps: expected an integer >= 1, got {max_episode_steps!r}")
            loaded = load_scenario(scenario, **overrides)
            if max_episode_steps < loaded.max_steps:  # TimeLimit's truncation, done by the env itself
                overrides = {**overrides, "episode_seconds": int(max_episode_steps) * loaded.control_dt}
        self.batched_env = VectorFormationEnv(scenario, num_envs=num_envs, **overrides)
        self.num_envs = self.batched_env.num_envs
        self.render_mode = None
        self.single_observation_space, self.single_action_space = joint_spaces(self.batched_env)
        self.observation_space = gymnasium.vector.utils.batch_space(self.single_observation_space, self.num_envs)
        self.action_space = gymnasium.vector.utils.batch_space(self.single_action_space, self.num_envs)

    def reset(self, *, seed: int | list[int] | None = None, options: dict | None = None):
        if isinstance(seed, (list, tuple)):
            raise ValueError("seed: expected one integer (copy k gets seed + k) or None, got a list")
        result = self.batched_env.reset_arrays(seed=seed, options=options)
        return result.observations, self._infos(result)

    def step(self, actions: np.ndarray):
        result = self.batched_env.step_arrays(actions)
        rewards = result.rewards.mean(axis=1)
        infos = self._infos(result)
        ended = np.flatnonzero(result.terminations | result.truncations)
        if len(ended):  # SAME_STEP: the main infos are the new episodes', the ended ones' under final_*
            new_errors = self.batched_env.formation_errors()
            for k in ended:
                infos = self._add_info(infos, {"final_obs": result.infos["final_observation"][k],
                                               "final_info": {"formation_error": float(infos["formation_error"][k])}},
                                       int(k))
            infos["formation_error"] = infos["formation_error"].copy()
            infos["formation_error"][ended] = new_errors[ended]
        return result.observations, rewards, result.terminations, result.truncations, infos

    def _infos(self, result: Any) -> dict[str, Any]:
        env = self.batched_env
        return {"formation_error": result.infos["formation_error"],
                "_formation_error": np.ones(self.num_envs, dtype=bool),
                "agents": copies_info_dicts(result.infos, env.possible_agents, env.joint_slices,
                                            env.observation_slices)}

    def close_extras(self, **kwargs: Any) -> None:
        self.batched_env.close()
