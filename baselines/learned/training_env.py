"""The env a learner steps: the formation env, in residual form, with training-only shaping and features.

:func:`make_training_env` composes, from the inside out: the formation env (``mode="torque"``: actions are the
normalized torques), :class:`~ee_formation_env.baselines.learned.residual.ResidualActionEnv` (``mode="residual"``:
actions are corrections on a reference controller), :class:`~ee_formation_env.baselines.learned.shaping.HoldShapingEnv`
(``hold_penalty > 0``), :class:`~ee_formation_env.baselines.learned.shaping.ContactShapingEnv`
(``contact_penalty > 0``) and :class:`~ee_formation_env.baselines.learned.features.FeatureEnv` (``obs_features``).
It is a module-level function so that ``functools.partial(make_training_env, ...)`` pickles into worker
processes; :func:`env_factory` builds that partial from a run's configuration.

:class:`BatchedTrainingEnv` is the same env for K copies at once, on the batched env
(:func:`ee_formation_env.vector_env`): the residual rule, the shaping and the features applied to the K x N
agents in one numpy pass. Copy k reproduces one :func:`make_training_env` env reset with its seed, bit for bit
(``tests/baselines/learned/test_training_env.py``). The SB3 trainer steps it
(:class:`ee_formation_env.integrations.sb3.SharedPolicyVecEnv`); :func:`batched_env_factory` builds its
factory from a run's configuration. RLlib steps the single env.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Any, Callable, Mapping, Sequence

import gymnasium
import numpy as np

from ee_formation_env import baselines
from ee_formation_env.baselines.learned.action_scale import (DEFAULT_ACTION_ACCELERATION, ScaledActionEnv,
                                                             check_action_acceleration, rescaling)
from ee_formation_env.baselines.learned.features import (FEATURE_SETS, FeatureEnv, check_invariant_arms, feature_space,
                                                         transform_stack)
from ee_formation_env.baselines.learned.residual import ResidualActionEnv, ResidualRows, check_residual_settings
from ee_formation_env.baselines.learned.shaping import (ContactShapingEnv, HoldShapingEnv, check_contact_penalty,
                                                       check_hold_penalty, hold_penalty_factors)
from ee_formation_env.scenario_sets import HELD_OUT_SEED_OFFSET
from ee_formation_env.vector import BatchedStep

if TYPE_CHECKING:
    from ee_formation_env.baselines.learned.config import TrainConfig

TRAINING_MODES = ("torque", "residual")
EVAL_SEED_OFFSET = HELD_OUT_SEED_OFFSET  # held-out evaluation seeds start here; training resets use seeds below it


def make_training_env(scenario: Any, overrides: Mapping[str, Any] | None = None, mode: str = "torque",
                      reference: str = "adaptive_jacobian", residual_scale: float = 0.1,
                      correction_penalty: float = 0.5, gate: bool = False, hold_penalty: float = 0.0,
                      obs_features: str = "none", action_acceleration: float = DEFAULT_ACTION_ACCELERATION,
                      contact_penalty: float = 0.0) -> Any:
    """The training env of ``scenario`` (plus ``overrides``) in ``mode``, shaped and featured (module docstring);
    learned actions in the physical units of ``action_acceleration`` (rad/s^2, :mod:`.action_scale`)."""
    from ee_formation_env import parallel_env

    if mode not in TRAINING_MODES:
        raise ValueError(f"mode: expected 'torque' or 'residual', got {mode!r}")
    if obs_features not in FEATURE_SETS:
        raise ValueError(f"obs_features: expected one of {FEATURE_SETS}, got {obs_features!r}")
    check_action_acceleration(action_acceleration)
    check_contact_penalty(contact_penalty)
    env = parallel_env(scenario, **dict(overrides or {}))
    try:
        if obs_features == "invariant":
            check_invariant_arms(env.task)
        scales = rescaling(env.task, action_acceleration)
        if mode == "residual":
            env = ResidualActionEnv(env, reference=reference, scale=residual_scale,
                                    correction_penalty=correction_penalty, gate=gate, joint_scales=scales)
        elif scales is not None:
            env = ScaledActionEnv(env, scales)
        if hold_penalty > 0:
            env = HoldShapingEnv(env, hold_penalty)
        if contact_penalty > 0:
            env = ContactShapingEnv(env, contact_penalty)
        return env if obs_features == "none" else FeatureEnv(env, obs_features)
    except Exception:
        env.close()
        raise


def env_factory(config: "TrainConfig", overrides: Mapping[str, Any] | None = None) -> Callable[[], Any]:
    """A picklable factory of the env the learner of ``config`` (resolved) steps; ``overrides`` default to
    the configuration's training overrides (episode length, start noise)."""
    return functools.partial(make_training_env, config.scenario,
                             config.training_overrides() if overrides is None else dict(overrides), config.mode,
                             config.reference, config.residual_scale, config.correction_penalty,
                             config.residual_gate, config.hold_penalty, config.obs_features,
                             config.action_acceleration, config.contact_penalty)


def batched_env_factory(config: "TrainConfig", overrides: Mapping[str, Any] | None = None
                        ) -> Callable[..., "BatchedTrainingEnv"]:
    """A picklable factory ``(num_envs=K) -> BatchedTrainingEnv`` of the env the SB3 learner of ``config``
    (resolved) steps; ``overrides`` as for :func:`env_factory`."""
    return functools.partial(BatchedTrainingEnv, config.scenario,
                             config.training_overrides() if overrides is None else dict(overrides), config.mode,
                             config.reference, config.residual_scale, config.correction_penalty,
                             config.residual_gate, config.hold_penalty, config.obs_features,
                             config.action_acceleration, config.contact_penalty)


class BatchedTrainingEnv:
    """K copies of :func:`make_training_env`'s env in one, with the batched env's array API.

    ``reset_arrays(seed, options)`` and ``step_arrays(actions)`` behave as those of
    :class:`ee_formation_env.vector.VectorFormationEnv` (per-copy seeds, SAME_STEP autoreset, ``reset_mask``;
    actions (K * N, n) or (K, N, n)): in residual mode the actions are corrections, rewards carry the
    correction factor, the hold penalty and the contact penalty, observations (K, N * size) carry the features
    (``infos["final_observation"]`` too: the observation each copy ended in, featured). Every agent must have
    the same observation size and joints (one policy is shared by all). The other infos are the batched env's,
    and so are ``state()``, ``state_space`` and the copies' generators ``np_randoms``: it has the array API
    that :class:`ee_formation_env.integrations.torchrl.BatchedTorchRLEnv` wraps (``from_batched``).

    Arguments: those of :func:`make_training_env`, and ``num_envs`` (K).
    """

    def __init__(self, scenario: Any, overrides: Mapping[str, Any] | None = None, mode: str = "torque",
                 reference: str = "adaptive_jacobian", residual_scale: float = 0.1,
                 correction_penalty: float = 0.5, gate: bool = False, hold_penalty: float = 0.0,
                 obs_features: str = "none", action_acceleration: float = DEFAULT_ACTION_ACCELERATION,
                 contact_penalty: float = 0.0, num_envs: int = 1):
        from ee_formation_env import vector_env

        if mode not in TRAINING_MODES:
            raise ValueError(f"mode: expected 'torque' or 'residual', got {mode!r}")
        if obs_features not in FEATURE_SETS:
            raise ValueError(f"obs_features: expected one of {FEATURE_SETS}, got {obs_features!r}")
        if mode == "residual":
            check_residual_settings(reference, residual_scale, correction_penalty)
        check_hold_penalty(hold_penalty)
        check_contact_penalty(contact_penalty)
        check_action_acceleration(action_acceleration)
        self.contact_penalty = float(contact_penalty)
        self.env = env = vector_env(scenario, num_envs=num_envs, **dict(overrides or {}))
        try:
            self._build(mode, reference, residual_scale, correction_penalty, gate, hold_penalty, obs_features,
                        action_acceleration)
        except Exception:
            env.close()
            raise

    def _build(self, mode: str, reference: str, residual_scale: float, correction_penalty: float, gate: bool,
               hold_penalty: float, obs_features: str, action_acceleration: float) -> None:
        env = self.env
        self.num_envs, self.scenario, self.task = env.num_envs, env.scenario, env.task
        self.possible_agents = self.agents = list(env.possible_agents)
        self.render_mode = None
        spaces = [(env.observation_space(a), env.action_space(a)) for a in self.possible_agents]
        if any(space != spaces[0] for space in spaces) or env.uniform_joints is None:
            raise ValueError("agents: parameter sharing needs identical observation and action spaces for every agent")
        self.mode, self.hold_penalty, self.obs_features = mode, float(hold_penalty), obs_features
        self.correction_penalty = float(correction_penalty)
        layouts = [env.observation_layout(agent) for agent in self.possible_agents]
        self._size = spaces[0][0].shape[0]
        # Rows of one layout are transformed together: (layout, rows of the (K * N) stack).
        groups: dict[Any, list[int]] = {}
        for k in range(self.num_envs):
            for i, layout in enumerate(layouts):
                groups.setdefault(layout, []).append(k * len(layouts) + i)
        self._layout_rows = [(layout, np.array(rows)) for layout, rows in groups.items()]
        self._features = [transform_stack(layout, obs_features) for layout, _ in self._layout_rows]
        self._observation_spaces = {agent: feature_space(space, layout, obs_features)
                                    for agent, (space, _), layout in zip(self.possible_agents, spaces, layouts)}
        self._featured_size = self._observation_spaces[self.possible_agents[0]].shape[0]
        if obs_features == "invariant":
            check_invariant_arms(self.task)
        scales = rescaling(self.task, action_acceleration)
        # Torque mode: the learned actions' per-joint scales as flat rows (K, T); None: the env's own actions.
        self._action_scales = None if scales is None or mode == "residual" else np.tile(
            np.concatenate([scales[agent] for agent in self.possible_agents]), (self.num_envs, 1))
        self.residuals = None
        if mode == "residual":
            teams = [baselines.make_policies(reference, env.copy_view(k)) for k in range(self.num_envs)]
            gate_layouts = dict(zip(self.possible_agents, layouts)) if gate else None
            self.residuals = ResidualRows(teams, self.possible_agents, residual_scale, gate_layouts, scales)
        self._raw: np.ndarray | None = None  # the batched env's last observations (K * N, size)

    # -- spaces ---------------------------------------------------------------------------------------
    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        return self._observation_spaces[agent]

    def action_space(self, agent: str) -> gymnasium.spaces.Box:
        return self.env.action_space(agent)

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
        if self.residuals is not None:
            mask = None if options is None else options.get("reset_mask")
            self.residuals.reset(None if mask is None else np.flatnonzero(mask))
        self._raw = self._rows(result.observations)
        observations = self._featured(self._raw)
        return result._replace(observations=observations, infos={**result.infos, "final_observation": observations})

    def step_arrays(self, actions: np.ndarray) -> BatchedStep:
        K, N = self.num_envs, len(self.possible_agents)
        if self.residuals is None:
            if self._action_scales is not None:
                actions = np.clip(self.env.checked_action_array(actions), -1.0, 1.0) * self._action_scales
            result = self.env.step_arrays(actions)
            rewards = result.rewards
        else:
            residuals = self._checked_residuals(actions)
            combined, penalties = self.residuals(self._raw, residuals)
            result = self.env.step_arrays(combined)
            rewards = result.rewards
            if self.correction_penalty > 0:
                rewards = rewards * (1.0 - self.correction_penalty * penalties).reshape(K, N)
            ended = np.flatnonzero(result.terminations | result.truncations)
            if len(ended):  # SAME_STEP autoreset: those copies start a new episode, their references too
                self.residuals.reset(ended)
        final = self._rows(result.infos["final_observation"])
        if self.hold_penalty > 0:  # charged on the observation each step ended in
            factors = np.empty(K * N)
            for layout, rows in self._layout_rows:
                factors[rows] = hold_penalty_factors(layout, final[rows])
            rewards = rewards - self.hold_penalty * factors.reshape(K, N)
        if self.contact_penalty > 0:
            rewards = rewards - self.contact_penalty * (result.infos["contacts"] > 0)
        self._raw = self._rows(result.observations)
        observations = self._featured(self._raw)
        # A copy that did not end ended its step in the observation it returns: only ended copies differ.
        featured_final = observations.copy()
        ended = np.flatnonzero(result.terminations | result.truncations)
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
        """(K, N * size) -> (K * N, size): one row per agent, copy-major."""
        return observations.reshape(-1, self._size)

    def _featured(self, rows: np.ndarray, copies: int | None = None) -> np.ndarray:
        """(C * N, size) raw rows of ``copies`` = C copies (default all K) -> (C, N * featured size)
        observations with the features appended."""
        copies = self.num_envs if copies is None else copies
        if self.obs_features == "none":
            return rows.reshape(copies, -1)
        out = np.empty((len(rows), self._featured_size), dtype=np.float32)
        for (_, part), apply in zip(self._layout_rows, self._features):
            part = part[part < len(rows)]  # rows of one layout: agent-major positions repeat per copy
            out[part] = apply(rows[part])
        return out.reshape(copies, -1)

    def _checked_residuals(self, actions: Any) -> np.ndarray:
        """Residuals (K * N, n) float64 clipped to [-1, 1], or the batched env's error for bad ones (naming
        the field) before any copy or controller moves."""
        K, N, n = self.num_envs, len(self.possible_agents), self.env.uniform_joints
        if self._raw is None:
            raise RuntimeError("step: call reset() first (the batched env has never been reset)")
        residuals = self.env.checked_action_array(actions)  # (K, T) float64, a copy; raises the env's errors
        return np.clip(residuals.reshape(K * N, n), -1.0, 1.0)
