"""The env a learner steps: K copies of the formation env, the learned actions, the shaping and the features.

:class:`BatchedTrainingEnv` is the one training env of every backend, on the batched env
(:func:`ee_formation_env.vector_env`, its array API): each step applies, to the K x N agent rows in one numpy
pass, the training mode's action rule (:meth:`~ee_formation_env.baselines.learned.modes.TrainingMode.action_rows`:
residual corrections on a reference controller, or physically scaled torques) and its reward factors, the
training-only shaping (:func:`~ee_formation_env.baselines.learned.shaping.shaped_rewards`) and the observation
features (:class:`~ee_formation_env.baselines.learned.features.FeatureRows`), all as
:class:`~ee_formation_env.baselines.learned.options.TrainingOptions` say. SB3 steps it
(:class:`ee_formation_env.integrations.sb3.SharedPolicyVecEnv`), BenchMARL through TorchRL
(:meth:`ee_formation_env.integrations.torchrl.BatchedTorchRLEnv.from_batched`); RLlib and the imitation's
demonstrations step one copy as a PettingZoo parallel env, :class:`ParallelTrainingEnv`, a thin adapter.
:func:`batched_env_factory` and :func:`env_factory` build their picklable factories from a run's configuration.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Any, Callable, Mapping, Sequence

import gymnasium
import numpy as np
from pettingzoo.utils.env import ParallelEnv

from ee_formation_env.baselines.learned.action_scale import rescaling
from ee_formation_env.baselines.learned.features import FeatureRows, check_invariant_arms, feature_space
from ee_formation_env.baselines.learned.options import TrainingOptions
from ee_formation_env.baselines.learned.shaping import shaped_rewards
from ee_formation_env.baselines.learned.team import PaddedTeamRows, TeamPadding
from ee_formation_env.scenario_sets import HELD_OUT_SEED_OFFSET
from ee_formation_env.vector import BatchedStep

if TYPE_CHECKING:
    from ee_formation_env.baselines.learned.config import TrainConfig

EVAL_SEED_OFFSET = HELD_OUT_SEED_OFFSET  # held-out evaluation seeds start here; training resets use seeds below it


def batched_env_factory(config: "TrainConfig", overrides: Mapping[str, Any] | None = None
                        ) -> Callable[..., "BatchedTrainingEnv"]:
    """A picklable factory ``(num_envs=K) -> BatchedTrainingEnv`` of the env the learner of ``config``
    (resolved) steps; ``overrides`` default to the configuration's training overrides (episode length, start
    noise)."""
    return functools.partial(BatchedTrainingEnv, config.scenario,
                             config.training_overrides() if overrides is None else dict(overrides),
                             config.options)


def env_factory(config: "TrainConfig", overrides: Mapping[str, Any] | None = None) -> Callable[[], "ParallelTrainingEnv"]:
    """A picklable factory of one copy of the training env as a PettingZoo parallel env (RLlib);
    ``overrides`` as for :func:`batched_env_factory`."""
    return functools.partial(ParallelTrainingEnv, config.scenario,
                             config.training_overrides() if overrides is None else dict(overrides),
                             config.options)


class BatchedTrainingEnv:
    """K copies of the training env (module docstring), with the batched env's array API.

    ``reset_arrays(seed, options)`` and ``step_arrays(actions)`` behave as those of
    :class:`ee_formation_env.vector.VectorFormationEnv` (per-copy seeds, SAME_STEP autoreset, ``reset_mask``;
    actions (K * N, n) or (K, N, n)): the actions are learned actions (the mode's), rewards carry the mode's
    reward factors and the shaping, observations (K, N * size) carry the features (``infos["final_observation"]``
    too: the observation each copy ended in, featured). One policy is shared by every agent: a mixed team
    (agents of different spaces) gets padded spaces (:mod:`~ee_formation_env.baselines.learned.team`,
    ``padding``), its actions (K * N, A) or (K, N, A). The other infos are the batched env's, and so are
    ``state()``, ``state_space`` and the copies' generators ``np_randoms``: it has the array API that
    :class:`ee_formation_env.integrations.torchrl.BatchedTorchRLEnv` wraps (``from_batched``).

    ``overrides``: scenario overrides as given (a caller adds ``options.training_overrides()`` where it wants
    them), always with the options' action convention (``options.env_overrides()``); ``options``: the training options (``None`` fields take the mode's preset); ``num_envs``: K.
    """

    def __init__(self, scenario: Any, overrides: Mapping[str, Any] | None = None,
                 options: TrainingOptions | None = None, num_envs: int = 1):
        from ee_formation_env import vector_env

        if options is None:
            options = TrainingOptions()
        if not isinstance(options, TrainingOptions):
            raise TypeError(f"options: expected TrainingOptions, got {type(options).__name__}")
        self.options = options.resolved()
        self.env = env = vector_env(scenario, num_envs=num_envs, **{**dict(overrides or {}),
                                                                    **self.options.env_overrides()})
        try:
            self._build()
        except Exception:
            env.close()
            raise

    def _build(self) -> None:
        env, options = self.env, self.options
        self.num_envs, self.scenario, self.task = env.num_envs, env.scenario, env.task
        self.possible_agents = self.agents = list(env.possible_agents)
        self.render_mode = None
        if options.obs_features == "invariant":
            check_invariant_arms(self.task)
        copies = [env.copy_view(k) for k in range(self.num_envs)]
        scales = rescaling(self.task, options.action_acceleration)
        #: A mixed team's padded spaces (team.py), or None: a uniform team's agents see their own spaces.
        self.padding = TeamPadding.of_team(env, options.obs_features)
        if self.padding is not None:
            self.action_rows = team = PaddedTeamRows(env, self.padding, options, copies, scales)
            self._layout_rows, self._size = team.layout_rows, team.raw_size
            space = self.padding.observation_space(env, options.obs_features)
            self._observation_spaces = {agent: space for agent in self.possible_agents}
            self._action_space = self.padding.action_space()
            self._raw = None
            return
        spaces = [(env.observation_space(a), env.action_space(a)) for a in self.possible_agents]
        layouts = [env.observation_layout(agent) for agent in self.possible_agents]
        self._size = spaces[0][0].shape[0]
        row_layouts = layouts * self.num_envs  # copy-major rows
        groups: dict[Any, list[int]] = {}
        for row, layout in enumerate(row_layouts):
            groups.setdefault(layout, []).append(row)
        self._layout_rows = [(layout, np.array(rows)) for layout, rows in groups.items()]
        self._features = FeatureRows(row_layouts, [options.obs_features] * len(row_layouts))
        self._observation_spaces = {agent: feature_space(space, layout, options.obs_features)
                                    for agent, (space, _), layout in zip(self.possible_agents, spaces, layouts)}
        self._action_space = None
        self.action_rows = options.training_mode.action_rows(options, copies, self.possible_agents, scales)
        self._raw: np.ndarray | None = None  # the batched env's last observations (K * N, size)

    # -- spaces ---------------------------------------------------------------------------------------
    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        return self._observation_spaces[agent]

    def action_space(self, agent: str) -> gymnasium.spaces.Box:
        return self.env.action_space(agent) if self._action_space is None else self._action_space

    def observation_layout(self, agent: str) -> Any:
        """The layout of the raw part of ``agent``'s observation (the batched env's; features are appended)."""
        return self.env.observation_layout(agent)

    @property
    def joint_slices(self) -> list[slice]:
        """Agent i's joints in the flat actions (K, T) and ``applied_torque``."""
        return self.env.joint_slices

    @property
    def state_space(self) -> gymnasium.spaces.Box:
        """The batched env's global state space (one copy's): the state carries no features."""
        return self.env.state_space

    def state(self) -> np.ndarray:
        """Every copy's global state (K, state_dim), the batched env's."""
        return self.env.state()

    @property
    def np_randoms(self) -> list:
        """The copies' generators (the batched env's list itself, so that assigning into it sets them)."""
        return self.env.np_randoms

    # -- array API ------------------------------------------------------------------------------------
    def reset_arrays(self, seed: int | Sequence[int | None] | None = None, options: dict | None = None
                     ) -> BatchedStep:
        result = self.env.reset_arrays(seed=seed, options=options)
        mask = None if options is None else options.get("reset_mask")
        self.action_rows.reset(None if mask is None else self._copy_rows(np.flatnonzero(mask)))
        self._raw = self._rows(result.observations)
        observations = self._featured(self._raw)
        return result._replace(observations=observations, infos={**result.infos, "final_observation": observations})

    def step_arrays(self, actions: np.ndarray) -> BatchedStep:
        K, N = self.num_envs, len(self.possible_agents)
        learned = self._checked_actions(actions)
        applied, factors = self.action_rows(self._raw, learned)
        result = self.env.step_arrays(applied)
        rewards = result.rewards if factors is None else result.rewards * factors.reshape(K, N)
        ended = np.flatnonzero(result.terminations | result.truncations)
        if len(ended):  # SAME_STEP autoreset: those copies start a new episode, their rules' state too
            self.action_rows.reset(self._copy_rows(ended))
        final = self._rows(result.infos["final_observation"])
        rewards = shaped_rewards(rewards, final, result.infos["contacts"], self._layout_rows,
                                 self.options.hold_penalty, self.options.contact_penalty,
                                 self.options.precision_bonus, self.options.precision_band)
        self._raw = self._rows(result.observations)
        observations = self._featured(self._raw)
        # A copy that did not end ended its step in the observation it returns: only ended copies differ.
        featured_final = observations.copy()
        if len(ended):
            featured_final[ended] = self._featured(final.reshape(K, N, -1)[ended].reshape(-1, self._size),
                                                   copies=len(ended))
        return result._replace(observations=observations, rewards=rewards,
                               infos={**result.infos, "final_observation": featured_final})

    def close(self) -> None:
        self.env.close()

    def __enter__(self) -> "BatchedTrainingEnv":
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.close()

    # -- internals ------------------------------------------------------------------------------------
    def _rows(self, observations: np.ndarray) -> np.ndarray:
        """(K, N * size) -> (K * N, size): one row per agent, copy-major (a mixed team's zero-padded to its
        largest raw size)."""
        if self.padding is not None:
            return self.action_rows.raw_rows(observations)
        return observations.reshape(-1, self._size)

    def _copy_rows(self, copies: np.ndarray) -> np.ndarray:
        """The rows of ``copies``: agent i of copy k is row ``k * N + i``."""
        N = len(self.possible_agents)
        return (np.asarray(copies)[:, None] * N + np.arange(N)).ravel()

    def _featured(self, rows: np.ndarray, copies: int | None = None) -> np.ndarray:
        """(C * N, size) raw rows of ``copies`` = C copies (default all K) -> (C, N * featured size)
        observations with the features appended (a mixed team's padded, with the robot kind's one-hot)."""
        if self.padding is not None:
            return self.action_rows.featured(rows)
        return self._features(rows).reshape(self.num_envs if copies is None else copies, -1)

    def _checked_actions(self, actions: Any) -> np.ndarray:
        """The learned actions (K * N, n) float64 as given (the mode's rule clips them where it uses them, and the
        env counts what it clips), or the batched env's error for bad ones (naming the field) before any copy or
        controller moves."""
        K, N, n = self.num_envs, len(self.possible_agents), self.env.uniform_joints
        if self._raw is None:
            raise RuntimeError("step: call reset() first (the batched env has never been reset)")
        if self.padding is not None:
            return self.action_rows.checked_actions(actions)  # (K * N, A): each rule takes its rows' own joints
        return self.env.checked_action_array(actions).reshape(K * N, n)  # a copy; raises the env's errors


class ParallelTrainingEnv(ParallelEnv):
    """One copy of :class:`BatchedTrainingEnv` as a PettingZoo parallel env (RLlib's and the imitation's view):
    dicts per agent in and out, the same transforms. An episode's end empties ``agents``; the copy has already
    started its next episode (SAME_STEP autoreset), which ``reset()`` without a seed returns, as a fresh reset
    of the env's generator would. Infos per agent are the batched env's entries of the copy."""

    metadata = {"name": "ee_formation_training_v0"}

    def __init__(self, scenario: Any, overrides: Mapping[str, Any] | None = None,
                 options: TrainingOptions | None = None):
        self.batched = BatchedTrainingEnv(scenario, overrides, options, num_envs=1)
        self.possible_agents = list(self.batched.possible_agents)
        self.agents: list[str] = []
        self.task, self.scenario, self.options = self.batched.task, self.batched.scenario, self.batched.options
        self.render_mode = None
        self._size = self.batched.observation_space(self.possible_agents[0]).shape[0]
        self._next: Any = None  # the autoreset's start, after an episode ended

    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        return self.batched.observation_space(agent)

    def action_space(self, agent: str) -> gymnasium.spaces.Box:
        return self.batched.action_space(agent)

    def observation_layout(self, agent: str) -> Any:
        return self.batched.observation_layout(agent)

    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is None and options is None and self._next is not None:
            result = self._next
        else:
            result = self.batched.reset_arrays(seed=None if seed is None else [seed], options=options)
        self._next = None
        self.agents = list(self.possible_agents)
        return self._observations(result.observations), self._infos(result.infos)

    def step(self, actions: Mapping[str, Any]):
        if not self.agents:
            raise RuntimeError("step: the episode has ended (or never started); call reset()")
        result = self.batched.step_arrays(self._action_array(actions))
        observations = self._observations(result.infos["final_observation"])
        rewards = {agent: float(reward) for agent, reward in zip(self.possible_agents, result.rewards[0])}
        terminations = {agent: bool(result.terminations[0]) for agent in self.possible_agents}
        truncations = {agent: bool(result.truncations[0]) for agent in self.possible_agents}
        infos = self._infos(result.infos)
        if result.terminations[0] or result.truncations[0]:
            self.agents = []
            self._next = result._replace(infos={key: value for key, value in result.infos.items()
                                                if key != "final_observation"})
        return observations, rewards, terminations, truncations, infos

    def state(self) -> np.ndarray:
        return self.batched.state()[0]

    def close(self) -> None:
        self.batched.close()

    def _observations(self, observations: np.ndarray) -> dict[str, np.ndarray]:
        return dict(zip(self.possible_agents, observations.reshape(len(self.possible_agents), self._size)))

    def _infos(self, infos: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
        N = len(self.possible_agents)
        out: dict[str, dict[str, Any]] = {agent: {} for agent in self.possible_agents}
        for key, value in infos.items():
            if key == "final_observation" or not isinstance(value, np.ndarray) or len(value) != 1:
                continue
            entry = value[0]
            for i, agent in enumerate(self.possible_agents):
                out[agent][key] = entry[i] if isinstance(entry, np.ndarray) and entry.shape[:1] == (N,) else entry
        return out

    def _action_array(self, actions: Any) -> np.ndarray:
        """(N, n) float64 from the per-agent actions; ``ValueError`` naming the agent for a bad one."""
        if not isinstance(actions, Mapping) or set(actions) != set(self.possible_agents):
            raise ValueError(f"actions: expected a dict with one action per agent {self.possible_agents}, got "
                             f"{sorted(actions) if isinstance(actions, Mapping) else type(actions).__name__}")
        shape = self.action_space(self.possible_agents[0]).shape
        rows = []
        for agent in self.possible_agents:
            try:
                action = np.asarray(actions[agent], dtype=np.float64)
            except (TypeError, ValueError):
                raise ValueError(f"actions[{agent!r}]: expected a numeric array") from None
            if action.shape != shape:
                raise ValueError(f"actions[{agent!r}]: expected shape {shape}, got {action.shape}")
            if not np.isfinite(action).all():
                raise ValueError(f"actions[{agent!r}]: expected finite values")
            rows.append(action)
        return np.stack(rows)
