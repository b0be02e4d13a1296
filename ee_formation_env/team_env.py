"""One env whose team size changes from reset to reset: a team-size family (:mod:`ee_formation_env.team_families`)
at every size of ``team_sizes``, with PettingZoo's semantics (``ee_formation_env.team_parallel_env``,
``ee_formation_env.team_vector_env``).

Rule: ``possible_agents`` are the largest team's ``arm_0 .. arm_{Nmax-1}``. At each of its resets a copy draws
its team size N uniformly from ``team_sizes`` with its own generator, then a reset seed for the family's env at
N, whose episode it then runs (the layout, shape and start drawn as that env draws them); its agents are
``arm_0 .. arm_{N-1}``. Every size's env has the family's largest neighbour-slot count over ``team_sizes``
(the scenario key ``neighbour_slots``: padding slots are zero with mask 0), so one observation space and one
action space serve every agent at every N: the union of the sizes' bounds (a draw's ring grows with N).

**Seeds**: ``reset(seed=s)`` seeds copy k's generator with ``s + k`` (or ``seed[k]``); the same seed gives the
same team size and the same episode, bit for bit, whatever ran before. The episode at seed s is that of
``parallel_env(team_scenario(family, N), neighbour_slots=D)`` reset with the seed the generator drew
(:attr:`TeamVectorEnv.episode_seeds`).

**Array API** (:class:`TeamVectorEnv`, for batched learners): :meth:`~TeamVectorEnv.step_arrays` takes (K,
Nmax * n) or (K, Nmax, n) actions (every arm of a family has the same n joints); an absent agent's entries
are ignored, whatever they hold (NaN too); a live agent's must be finite (else a ``ValueError`` naming it). It returns a :class:`~ee_formation_env.vector.BatchedStep` padded to Nmax
agents: observations (K, Nmax * O) with zeros for absent agents, rewards (K, Nmax) with 0 for them, the
per-agent infos padded with zeros on the agent axis, ``applied_torque`` (K, Nmax * n), plus ``agent_mask``
(K, Nmax) bool (the agents whose rewards and infos the step reports) and ``team_size`` (K,).
:attr:`~TeamVectorEnv.agent_mask` is the mask of the agents of the observations just returned: with the
default ``SAME_STEP`` autoreset, an ended copy's row is already its next episode's first, of its next team
size (the observation it ended in is ``infos["final_observation"]``, padded). ``DISABLED``: an ended copy
stays ended until ``reset(options={"reset_mask": mask})``.

**Parallel env** (:class:`TeamParallelEnv`): one copy without autoreset, per-agent dicts over the live agents
(``agents``: the first N of ``possible_agents`` during an episode, none after it); :attr:`~TeamParallelEnv.current`
is the size-N env of the running episode (a :class:`~ee_formation_env.env.FormationEnv`), for consumers that
need its task, as the reference laws do.

**TorchRL**: ``make_torchrl_env(batched_env=team_vector_env(family, num_envs=K))`` (the ``torchrl`` extra)
gives one group of Nmax agents with ``(group, "mask")`` (K, Nmax) bool, True for the agents of the episode a
step's ``"next"`` belongs to (``agent_mask``, PettingZoo's ``use_mask`` convention in TorchRL).

**Layout**: per copy and team size, one parallel env of the family at that size (one PyBullet client), built
when the copy first draws that size; copy 0's are built for every size at construction, so that every size is
validated before any episode. ``render_mode`` ``"rgb_array"`` (one copy) renders the running episode's env.
"""

from __future__ import annotations

import warnings
from typing import Any, Sequence

import gymnasium
import numpy as np
from gymnasium.utils import seeding
from pettingzoo import ParallelEnv

from ee_formation_env.actions import ActionCheck
from ee_formation_env.env import FormationEnv
from ee_formation_env.infos import PER_AGENT_INFO
from ee_formation_env.inputs import (MAX_NUM_ENVS, check_num_envs, check_steppable, copy_seeds, excerpt, reset_rows,
                                     user_stacklevel)
from ee_formation_env.scenario import load_scenario
from ee_formation_env.team_families import TEAM_FAMILIES, check_team_size, team_scenario
from ee_formation_env.validation import RigidityWarning
from ee_formation_env.vector import AutoresetMode, BatchedStep

__all__ = ["TeamVectorEnv", "TeamParallelEnv", "check_team_sizes", "largest_degree"]

_RESERVED = ("neighbour_slots", "num_envs", "autoreset_mode")  # set by the team env itself


def check_team_sizes(family: Any, team_sizes: Any) -> tuple[int, ...]:
    """``team_sizes`` (None: the family's whole range) as sorted distinct sizes, each within the family's range;
    ``ValueError`` naming ``family`` or ``team_sizes``."""
    if family not in TEAM_FAMILIES:
        raise ValueError(f"family: expected one of {list(TEAM_FAMILIES)}, got {excerpt(family)}")
    low, high = TEAM_FAMILIES[family]
    if team_sizes is None:
        return tuple(range(low, high + 1))
    if isinstance(team_sizes, (str, bytes)) or not isinstance(team_sizes, (Sequence, np.ndarray)) or not len(team_sizes):
        raise ValueError(f"team_sizes: expected a non-empty list of team sizes from {low} to {high}, got "
                         f"{excerpt(team_sizes)}")
    for size in team_sizes:
        try:
            check_team_size(family, size.item() if isinstance(size, np.integer) else size)
        except ValueError as error:
            raise ValueError(f"team_sizes: {str(error).split(': ', 1)[1]}") from None
    return tuple(sorted({int(size) for size in team_sizes}))


def largest_degree(edges: Sequence[Sequence[int]], n_agents: int) -> int:
    """The largest vertex degree of the graph ``edges`` on ``n_agents`` vertices (the neighbour slots it needs)."""
    degrees = np.zeros(n_agents, dtype=np.int64)
    for tail, head in edges:
        degrees[tail] += 1
        degrees[head] += 1
    return int(degrees.max())


def _union_box(boxes: Sequence[gymnasium.spaces.Box]) -> gymnasium.spaces.Box:
    low = np.min([box.low for box in boxes], axis=0)
    high = np.max([box.high for box in boxes], axis=0)
    return gymnasium.spaces.Box(low, high, dtype=boxes[0].dtype)


class TeamVectorEnv:
    """K copies of a team-size family, each drawing its team size at each reset (module docstring). Build it with
    :func:`ee_formation_env.team_vector_env`.

    ================== ======================================================================================
    argument           meaning
    ================== ======================================================================================
    ``family``         ``"planar_team"`` (N = 3..8) or ``"spatial_team"`` (N = 3..6) (``team_families.py``)
    ``num_envs``       K >= 1 copies; K x len(team_sizes) PyBullet clients at most (one per copy and size)
    ``team_sizes``     the sizes drawn from, uniformly (default: the family's whole range)
    ``autoreset_mode`` ``gymnasium.vector.AutoresetMode.SAME_STEP`` (default) or ``DISABLED``
    ``render_mode``    None or ``"rgb_array"`` (``num_envs=1`` only: the running episode's env renders)
    ``**overrides``    top-level scenario keys replaced in every size's scenario (``docs/scenarios.md``)
    ================== ======================================================================================
    """

    metadata = {"name": "ee_formation_team_v0", "render_modes": ["rgb_array"], "render_fps": 30,
                "is_parallelizable": True, "autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(self, family: str = "planar_team", num_envs: int = 1, team_sizes: Sequence[int] | None = None,
                 autoreset_mode: AutoresetMode = AutoresetMode.SAME_STEP, render_mode: str | None = None,
                 **overrides: Any):
        sizes = check_team_sizes(family, team_sizes)
        K = check_num_envs(num_envs)
        if K * len(sizes) > MAX_NUM_ENVS:
            raise ValueError(f"num_envs: {K} copies x {len(sizes)} team sizes need {K * len(sizes)} PyBullet "
                             f"clients, more than {MAX_NUM_ENVS} per process; give fewer copies or team_sizes")
        check_num_envs(K * len(sizes))  # the memory estimate, one client per copy and size
        if autoreset_mode not in (AutoresetMode.SAME_STEP, AutoresetMode.DISABLED):
            raise ValueError(f"autoreset_mode: expected AutoresetMode.SAME_STEP or AutoresetMode.DISABLED, got "
                             f"{excerpt(autoreset_mode)}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode: expected None or 'rgb_array' (one GUI per team size is not offered), "
                             f"got {excerpt(render_mode)}")
        if render_mode is not None and K != 1:
            raise ValueError("render_mode: the team env renders only with num_envs=1")
        for name in _RESERVED:
            if name in overrides:
                raise ValueError(f"{name}: set by the team env, not a key to override")
        self.family, self.team_sizes, self.num_envs = family, sizes, K
        self.max_agents = max(sizes)
        self.metadata = {**type(self).metadata, "autoreset_mode": autoreset_mode}
        self.autoreset = autoreset_mode == AutoresetMode.SAME_STEP
        self.render_mode = render_mode
        data = {size: team_scenario(family, size) for size in sizes}
        self.neighbour_slots = max(largest_degree(d["edges"], size) for size, d in data.items())
        self._overrides = {**overrides, "neighbour_slots": self.neighbour_slots}
        # Every size's scenario is checked (format and keys) before any PyBullet client starts.
        self._scenarios = {size: load_scenario(d, **self._overrides) for size, d in data.items()}
        self._envs: list[dict[int, FormationEnv]] = [{} for _ in range(K)]
        self._warned_rigidity = False  # copy 0's builds below warn it once, for every size (_warn_once)
        warned: list[int] = []  # the sizes whose graph is rigid but not minimally rigid
        others: list[warnings.WarningMessage] = []
        try:
            for size in sizes:  # validates every size (geometry, first draw); their spaces make the union
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always", RigidityWarning)
                    self._env(0, size)
                warned += [size] if any(issubclass(w.category, RigidityWarning) for w in caught) else []
                others += [w for w in caught if not issubclass(w.category, RigidityWarning)]
            self._warn_once(warned, others)  # inside: a filter that turns the warning into an error closes the clients
        except BaseException:
            self.close()
            raise
        first = [self._envs[0][size] for size in sizes]
        largest = self._envs[0][self.max_agents]
        self.scenario = largest.scenario  # the largest team's (its arms name TorchRL's groups)
        self.possible_agents = list(largest.possible_agents)
        self.agents = list(self.possible_agents)
        space = _union_box([env.observation_space(agent) for env in first for agent in env.possible_agents])
        action = _union_box([env.action_space(agent) for env in first for agent in env.possible_agents])
        self.observation_spaces = dict.fromkeys(self.possible_agents, space)
        self.action_spaces = dict.fromkeys(self.possible_agents, action)
        self.n_joints_per_arm = action.shape[0]
        self.observation_size = space.shape[0]
        self.state_space = _union_box([gymnasium.spaces.Box(self._pad_state(env.state_space.low, env),
                                                            self._pad_state(env.state_space.high, env))
                                       for env in first])
        n = self.n_joints_per_arm
        self.joint_slices = [slice(i * n, (i + 1) * n) for i in range(self.max_agents)]
        self.observation_slices = [slice(i * self.observation_size, (i + 1) * self.observation_size)
                                   for i in range(self.max_agents)]
        self.actions_check = ActionCheck(self.possible_agents, self.joint_slices)
        self.np_randoms = [seeding.np_random(None)[0] for _ in range(K)]
        self.team_size = np.full(K, self.max_agents, dtype=np.int64)  # each copy's current N
        self.episode_seeds = np.zeros(K, dtype=np.int64)  # the seed each copy's size-N env was last reset with
        self._ended = np.zeros(K, dtype=bool)
        self._needs_reset = True
        self._last: list[BatchedStep | None] = [None] * K

    # ------------------------------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> gymnasium.spaces.Box:
        return self.action_spaces[agent]

    @property
    def agent_mask(self) -> np.ndarray:
        """(K, Nmax) bool: the agents of each copy's current episode (those of the last observations)."""
        return np.arange(self.max_agents) < self.team_size[:, None]

    def current(self, k: int = 0) -> FormationEnv:
        """Copy ``k``'s env of its current team size (its task, arms and world)."""
        return self._envs[k][int(self.team_size[k])]

    @property
    def connected(self) -> bool:
        return all(env.batch.connected for envs in self._envs for env in envs.values()) and bool(self._envs[0])

    def is_running(self, k: int) -> bool:
        """Whether copy ``k`` is in an episode: reset, not ended (without autoreset), the env connected."""
        return not (self._needs_reset or self._ended[k] or not self.connected)

    # ------------------------------------------------------------------------------------------ array API
    def reset_arrays(self, seed: int | Sequence[int | None] | None = None, options: dict | None = None
                     ) -> BatchedStep:
        """Reset every copy (or those of ``options["reset_mask"]``): each draws its team size, then its episode
        (module docstring). Rewards zero, no termination; the padded arrays of the module docstring."""
        seeds = copy_seeds(seed, self.num_envs)
        rows = reset_rows(options, self.num_envs, self._needs_reset)
        if not self.connected:
            raise RuntimeError("reset: the environment is closed")
        for k in rows:
            if seeds[k] is not None:
                self.np_randoms[k] = seeding.np_random(seeds[k])[0]
            self._reset_copy(k)
        self._needs_reset = False
        result = self._stacked(self._last, self.agent_mask)
        K = self.num_envs
        if self.autoreset:
            result.infos["final_observation"] = result.observations.copy()
        return BatchedStep(result.observations, np.zeros((K, self.max_agents)), np.zeros(K, dtype=bool),
                           np.zeros(K, dtype=bool), result.infos)

    def step_arrays(self, actions: Any) -> BatchedStep:
        """One step of every copy from (K, Nmax * n) or (K, Nmax, n) actions (absent agents' entries ignored);
        checked (numeric, shape, the live agents' finite) before any copy moves."""
        check_steppable(self.connected, self._needs_reset, self._ended)
        K, n = self.num_envs, self.n_joints_per_arm
        flat = self.actions_check.flat_array(actions, K, live=self.agent_mask)
        steps = []
        for k in range(K):
            size = int(self.team_size[k])
            steps.append(self.current(k).batch.step_arrays(flat[k:k + 1, :size * n]))
        result = self._stacked(steps, self.agent_mask)  # the mask of the agents that acted
        self._last = steps
        done = result.terminations | result.truncations
        if not self.autoreset:
            self._ended |= done
            return result
        result.infos["final_observation"] = result.observations.copy()
        for k in np.flatnonzero(done):  # the next episode, of a new team size, in the same row
            self._reset_copy(k)
            result.observations[k] = self._padded_observation(self._last[k].observations[0])
        return result

    def state(self) -> np.ndarray:
        """Every copy's global state (K, state_dim), padded: end-effector positions (Nmax x 3, m), q, dq (Nmax x
        n each), zero for absent agents."""
        return np.stack([self._pad_state(self.current(k).state(), self.current(k)) for k in range(self.num_envs)])

    def render(self) -> np.ndarray | None:
        """The one copy's running episode as an RGB frame (``rgb_array``); None without a render mode."""
        if self.render_mode is None:
            return None
        return self.current(0).render()

    def close(self) -> None:
        """Disconnect every PyBullet client; safe to call more than once."""
        for envs in getattr(self, "_envs", []):
            for env in envs.values():
                env.close()

    def __enter__(self) -> "TeamVectorEnv":
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.close()

    # ------------------------------------------------------------------------------------------ internals
    def _env(self, k: int, size: int) -> FormationEnv:
        """Copy ``k``'s env of team size ``size``, built on first use."""
        env = self._envs[k].get(size)
        if env is None:
            with warnings.catch_warnings():
                if self._warned_rigidity:  # said once, at construction: not again for a copy's later build
                    warnings.simplefilter("ignore", RigidityWarning)
                env = FormationEnv(self._scenarios[size], render_mode=self.render_mode)
            self._envs[k][size] = env
        return env

    def _warn_once(self, warned: Sequence[int], others: Sequence[warnings.WarningMessage]) -> None:
        """One rigidity warning for the team sizes ``warned`` (their builds' own, one per size, held back),
        attributed to the user's line that built the team env; ``others``, the builds' other warnings, as they
        were."""
        for w in others:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno, source=w.source)
        if warned:
            warnings.warn(f"edges: the {self.family} graphs at team sizes {list(warned)} are infinitesimally rigid but "
                          "not minimally rigid; the paper's convergence proof assumes minimal rigidity",
                          RigidityWarning, stacklevel=user_stacklevel())
        self._warned_rigidity = True

    def _reset_copy(self, k: int) -> None:
        generator = self.np_randoms[k]
        size = self.team_sizes[int(generator.integers(len(self.team_sizes)))]
        episode_seed = int(generator.integers(2 ** 31))
        env = self._env(k, size)
        self.team_size[k], self.episode_seeds[k] = size, episode_seed
        self._last[k] = env.batch.reset_arrays(seed=episode_seed)
        self._ended[k] = False

    def _padded_observation(self, row: np.ndarray) -> np.ndarray:
        padded = np.zeros(self.max_agents * self.observation_size, dtype=np.float32)
        padded[:len(row)] = row
        return padded

    def _pad_state(self, state: np.ndarray, env: FormationEnv) -> np.ndarray:
        """A size-N env's state (ee N x 3, q N x n, dq N x n) padded with zeros to Nmax agents."""
        size, N, n = env.task.n_agents, self.max_agents, self.n_joints_per_arm
        parts = np.split(np.asarray(state, dtype=np.float64), [3 * size, 3 * size + size * n])
        widths = (3 * N, N * n, N * n)
        return np.concatenate([np.pad(part, (0, width - len(part))) for part, width in zip(parts, widths)]
                              ).astype(np.float32)

    def _stacked(self, steps: Sequence[BatchedStep], mask: np.ndarray) -> BatchedStep:
        """The copies' one-copy steps stacked, padded to Nmax agents (module docstring)."""
        N = self.max_agents
        observations = np.stack([self._padded_observation(step.observations[0]) for step in steps])
        rewards = np.stack([np.pad(step.rewards[0], (0, N - len(step.rewards[0]))) for step in steps])
        infos: dict[str, np.ndarray] = {}
        for key in steps[0].infos:
            if key == "final_observation":
                continue
            values = [step.infos[key][0] for step in steps]
            if key in PER_AGENT_INFO:
                values = [np.pad(v, [(0, N - len(v))] + [(0, 0)] * (v.ndim - 1)) for v in values]
            elif key == "applied_torque":
                values = [np.pad(v, (0, N * self.n_joints_per_arm - len(v))) for v in values]
            infos[key] = np.stack(values)
        infos["agent_mask"], infos["team_size"] = mask, self.team_size.copy()
        return BatchedStep(observations, rewards, np.concatenate([step.terminations for step in steps]),
                           np.concatenate([step.truncations for step in steps]), infos)


class TeamParallelEnv(ParallelEnv):
    """The PettingZoo parallel env of a team-size family: one copy of :class:`TeamVectorEnv` without autoreset,
    per-agent dicts over the live agents (module docstring). Build it with
    :func:`ee_formation_env.team_parallel_env`; arguments as :class:`TeamVectorEnv`'s, without ``num_envs`` and
    ``autoreset_mode``."""

    metadata = {"name": "ee_formation_team_v0", "render_modes": ["rgb_array"], "render_fps": 30,
                "is_parallelizable": True}

    def __init__(self, family: str = "planar_team", team_sizes: Sequence[int] | None = None,
                 render_mode: str | None = None, **overrides: Any):
        self.team = TeamVectorEnv(family, num_envs=1, team_sizes=team_sizes, autoreset_mode=AutoresetMode.DISABLED,
                                  render_mode=render_mode, **overrides)
        self.possible_agents = self.team.possible_agents
        self.observation_spaces = dict(self.team.observation_spaces)
        self.action_spaces = dict(self.team.action_spaces)
        self.state_space = self.team.state_space
        self.render_mode = render_mode
        self._checks = {size: ActionCheck(self.possible_agents[:size], self.team.joint_slices[:size])
                        for size in self.team.team_sizes}

    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> gymnasium.spaces.Box:
        return self.action_spaces[agent]

    @property
    def agents(self) -> list[str]:
        """The live agents: the first N of ``possible_agents`` during an episode; none before the first reset,
        after the episode's end or after :meth:`close`."""
        return self.possible_agents[:self.team_size] if self.team.is_running(0) else []

    @property
    def team_size(self) -> int:
        """N of the current (or last) episode."""
        return int(self.team.team_size[0])

    @property
    def current(self) -> FormationEnv:
        """The size-N env of the current episode (its task, arms and world: what a reference law is built on)."""
        return self.team.current(0)

    def reset(self, seed: int | None = None, options: dict | None = None):
        """Draw a team size and run that size's episode (module docstring); observations and infos of its agents."""
        result = self.team.reset_arrays(seed=seed, options=options)
        return self._observations(result), self._infos()

    def step(self, actions: dict[str, np.ndarray]):
        """One action per live agent (the dict's keys exactly the live agents); their dicts back."""
        if not self.agents:
            if not self.team.connected:
                raise RuntimeError("step: the environment is closed")
            raise RuntimeError("step: call reset() first (the episode has ended or never started)")
        size = self.team_size
        normalized = self._checks[size].agent_dict(actions, None)
        padded = np.zeros((1, self.team.max_agents * self.team.n_joints_per_arm))
        padded[:, :normalized.shape[1]] = normalized
        result = self.team.step_arrays(padded)
        agents = self.possible_agents[:size]
        ended, truncated = bool(result.terminations[0]), bool(result.truncations[0])
        return (self._observations(result), dict(zip(agents, result.rewards[0, :size].tolist())),
                dict.fromkeys(agents, ended), dict.fromkeys(agents, truncated), self._infos())

    def state(self) -> np.ndarray:
        """The global state, padded to the largest team (:meth:`TeamVectorEnv.state`)."""
        return self.team.state()[0]

    def render(self) -> np.ndarray | None:
        return self.team.render()

    def close(self) -> None:
        if "team" in self.__dict__:
            self.team.close()

    def _observations(self, result: BatchedStep) -> dict[str, np.ndarray]:
        row = result.observations[0]
        return {agent: row[part] for agent, part in zip(self.possible_agents[:self.team_size],
                                                        self.team.observation_slices)}

    def _infos(self) -> dict[str, dict[str, Any]]:
        size = self.team_size
        infos = self.current.agent_infos()  # its agents are the first N of possible_agents
        for info in infos.values():
            info["team_size"] = size
        return infos
