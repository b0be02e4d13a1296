"""TorchRL and BenchMARL support (the ``torchrl`` extra): the env as a TorchRL ``PettingZooWrapper``.

    from ee_formation_env.integrations.torchrl import make_torchrl_env
    env = make_torchrl_env("planar_square")          # groups: {"planar_2link": ["arm_0", ..., "arm_3"]}
    rollout = env.rollout(100)                       # rollout["planar_2link", "observation"]: (100, 4, 19)

**Groups.** TorchRL stacks the tensors of the agents of one group, so a group's agents need identical
observation and action spaces. :func:`group_map` puts agents with identical spaces in one group, named
after their robot (``planar_2link``, or a URDF's robot name such as ``lbr_iiwa`` and ``panda``): one group for the built-in scenarios, one per
robot kind for mixed teams (e.g. an ``lbr_iiwa`` group of KUKA arms and a ``panda`` group of Franka
arms: both have 7 joints, but different joint limits and so different observation bounds). Pass
``group_map=MarlGroupMapType.ONE_GROUP_PER_AGENT`` for one group per arm (no stacking at all).
TorchRL's default, grouping by the name before the last ``_`` (every agent is ``arm_<i>``), puts mixed
robots in one group and fails to stack their actions.

Every info entry is numeric and fixed-shape per agent, so TorchRL builds specs from it.

**Batched** (``num_envs=K``): :class:`BatchedTorchRLEnv`, a native TorchRL ``EnvBase`` over
:func:`ee_formation_env.vector_env` (VMAS's layout: batch size ``[K]``, each group's agents stacked)::

    env = make_torchrl_env("planar_square", num_envs=32, seed=0)   # copy k seeded 0 + k
    td = env.rollout(100, break_when_any_done=False)   # td["planar_2link", "observation"]: (32, 100, 4, 19)

Keys: per group ``(group, "observation")`` (K, n, obs_dim), ``(group, "action")`` (K, n, n_joints) in
[-1, 1], ``(group, "reward")`` (K, n, 1), ``(group, "done" | "terminated" | "truncated")`` (K, n, 1) and
``(group, "info", key)`` (K, n, ...) float32 (the single env's numeric infos; per-copy ones repeated per
agent); at the root ``"done"``, ``"terminated"``, ``"truncated"`` (K, 1) and ``"state"`` (K, state_dim).

**Done and reset handling.** It drives the vector env through its array API (``step_arrays`` /
``reset_arrays``). The vector env autoresets an ended copy within the step (SAME_STEP); TorchRL instead
wants the step's ``"next"`` observation to be the one the episode ended in, and resets done copies itself
through ``_reset``. So:

- a step returns, for every copy, ``infos["final_observation"]`` (the observation it ended in; equal to
  the returned observation for copies that did not end), with its rewards and dones;
- the copies that ended are marked *started*: the vector env has already begun their next episode, drawn
  from their own generators (what the single env's ``reset()`` without a seed would draw next);
- ``_reset`` resets the copies of its ``_reset`` mask (root ``"_reset"`` (K, 1) or any agent's
  ``(group, "_reset")``) that are not marked started through ``reset_arrays(options={"reset_mask": ...})``,
  and returns the started ones' first observations as they are (no second draw). After ``set_seed(s)``
  every requested copy is reset, copy k seeded ``s + k``.

So copy k of ``make_torchrl_env(S, num_envs=K, seed=s)`` replays, step for step and episode after
episode, ``parallel_env(S)`` reset with seed ``s + k`` and then without a seed
(``tests/integrations/test_torchrl.py``). Stepping again without a reset after a done continues the
started episode.

**Any batched env with the array API**: :meth:`BatchedTorchRLEnv.from_batched` (or
``make_torchrl_env(batched_env=env)``) wraps an env built already, e.g. the learning wing's training env
(residual actions, observation features, shaped rewards), which this package never imports: the wing hands
it over. What the wrapper needs of it is listed in :data:`BATCHED_ENV_API`. Each agent's observation columns
come from the env's own observation sizes (agents concatenated in order), not from the raw env's layout, so
feature-augmented observations fit. An env whose infos carry ``agent_mask`` (K, N) bool (the team env,
:mod:`ee_formation_env.team_env`, whose copies differ in team size) adds ``(group, "mask")`` (K, n) bool: True
for the agents of the episode the observations belong to; absent agents' observations and rewards are zero.
"""

from __future__ import annotations

from typing import Any
from xml.etree import ElementTree

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase
from torchrl.envs.libs.pettingzoo import PettingZooWrapper
from torchrl.envs.utils import MarlGroupMapType, check_marl_grouping

import ee_formation_env


def robot_name(env: Any, index: int) -> str:
    """The robot of arm ``index``: its built-in name, else the ``<robot name=...>`` of its URDF."""
    arm = env.scenario.arms[index]
    if arm.robot:
        return arm.robot
    return ElementTree.parse(arm.urdf).getroot().get("name") or f"robot_{index}"


def group_map(env: Any) -> dict[str, list[str]]:
    """Agents with identical observation and action spaces share a group, named after their robot
    (with a numeric suffix if one robot has arms with different spaces)."""
    groups: dict[str, list[str]] = {}
    signatures: dict[str, tuple[Any, Any]] = {}
    for i, agent in enumerate(env.possible_agents):
        signature = (env.observation_space(agent), env.action_space(agent))
        base = robot_name(env, i)
        name, suffix = base, 1
        while name in signatures and signatures[name] != signature:
            suffix += 1
            name = f"{base}_{suffix}"
        signatures[name] = signature
        groups.setdefault(name, []).append(agent)
    return groups


def make_torchrl_env(scenario: Any = "planar_square", group_map_type: MarlGroupMapType | dict | None = None,
                     return_state: bool = True, seed: int | None = None, device: Any = "cpu",
                     num_envs: int | None = None, batched_env: Any = None, **overrides: Any) -> EnvBase:
    """The formation env (built-in name, file or dict ``scenario``, with scenario ``overrides``) as a TorchRL
    env. ``group_map_type``: None for :func:`group_map`, a ``MarlGroupMapType`` or an explicit dict.
    ``return_state``: include ``env.state()`` as ``"state"`` (for centralized critics, e.g. MAPPO).
    ``num_envs``: None for one env in TorchRL's ``PettingZooWrapper`` (batch size ``[]``); K >= 1 for
    :class:`BatchedTorchRLEnv` over ``vector_env(scenario, num_envs=K)`` (batch size ``[K]``).
    ``batched_env``: a batched env built already (:data:`BATCHED_ENV_API`) to wrap as
    :meth:`BatchedTorchRLEnv.from_batched` does; ``scenario`` and ``overrides`` are then its own, and
    ``num_envs``, if given, must be its number of copies."""
    if batched_env is not None:
        if overrides:
            raise ValueError(f"overrides: the batched env is built already (its scenario is its own), got "
                             f"{sorted(overrides)}")
        if num_envs is not None and num_envs != batched_env.num_envs:
            raise ValueError(f"num_envs: the batched env has {batched_env.num_envs} copies, got {num_envs!r}")
        return BatchedTorchRLEnv.from_batched(batched_env, group_map_type=group_map_type, return_state=return_state,
                                              seed=seed, device=device)
    if num_envs is not None:
        return BatchedTorchRLEnv(scenario, num_envs=num_envs, group_map_type=group_map_type,
                                 return_state=return_state, seed=seed, device=device, **overrides)
    env = ee_formation_env.parallel_env(scenario, **overrides)
    groups = group_map(env) if group_map_type is None else group_map_type
    return PettingZooWrapper(env, group_map=groups, return_state=return_state, use_mask=False,
                             categorical_actions=False, seed=seed, device=device)


# The vector env's numeric infos in the batched TorchRL env (float32, per agent): (K, N, ...) ones, the
# per-copy (K,) ones repeated over the agents, and applied_torque (K, T) split by joints.
_AGENT_INFO = ("edge_errors", "edge_mask", "singularity_margin", "torque_saturation", "clipped_actions",
               "contacts")
_COPY_INFO = ("formation_error", "physics_fault", "sim_time")
_DONE_KEYS = ("done", "terminated", "truncated")

#: What :class:`BatchedTorchRLEnv` uses of the batched env it steps (``ee_formation_env.vector.VectorFormationEnv``
#: has all of it): ``num_envs`` (K), ``possible_agents``, ``scenario`` (the group names read its arms),
#: ``observation_space(agent)`` and ``action_space(agent)`` (one copy's), ``joint_slices`` (agent i's joints in
#: the flat actions (K, T) and ``applied_torque``), ``np_randoms`` (the copies' generators: put back after the
#: probe reset that sizes the info specs), ``reset_arrays(seed, options)`` and ``step_arrays(actions (K, T))``
#: returning a ``BatchedStep`` whose observations (K, O) are the agents' observations concatenated in agent
#: order and whose infos carry the vector env's numeric keys and ``final_observation``, ``close()``; with
#: ``return_state``, ``state()`` (K, state_dim) and ``state_space``.
BATCHED_ENV_API = ("num_envs", "possible_agents", "scenario", "observation_space", "action_space", "joint_slices",
                   "np_randoms", "reset_arrays", "step_arrays", "close")


def _box_spec(space: Any, count: int, device: Any) -> Bounded | Unbounded:
    """``count`` stacked copies of a gymnasium Box as a (count, *shape) float32 spec."""
    low = np.broadcast_to(space.low, (count, *space.shape)).astype(np.float32)
    high = np.broadcast_to(space.high, (count, *space.shape)).astype(np.float32)
    if np.isfinite(low).all() and np.isfinite(high).all():
        return Bounded(low=torch.from_numpy(low), high=torch.from_numpy(high), shape=low.shape,
                       dtype=torch.float32, device=device)
    return Unbounded(shape=low.shape, dtype=torch.float32, device=device)


def _tensor(array: np.ndarray, device: Any) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32)).to(device)


class BatchedTorchRLEnv(EnvBase):
    """K copies of one formation scenario as one native TorchRL env, batch size ``[K]`` (module docstring:
    keys, done and reset handling). Build it with ``make_torchrl_env(scenario, num_envs=K)``, or around a
    batched env built already with :meth:`from_batched` (``batched_env``: then ``scenario``, ``num_envs`` and
    ``overrides`` are not used; the TorchRL env owns it and closes it).

    ``group_map`` (attribute): group -> agents, as :func:`group_map` (or ``group_map_type``) gives it.
    ``vector_env`` (attribute): the batched env it steps: the :class:`ee_formation_env.vector.VectorFormationEnv`
    of ``scenario``, or the env given to :meth:`from_batched`."""

    def __init__(self, scenario: Any = "planar_square", num_envs: int = 1,
                 group_map_type: MarlGroupMapType | dict | None = None, return_state: bool = True,
                 seed: int | None = None, device: Any = "cpu", batched_env: Any = None, **overrides: Any):
        if batched_env is None:
            vec = ee_formation_env.vector_env(scenario, num_envs=num_envs, **overrides)
        else:
            missing = [name for name in (*BATCHED_ENV_API, *(("state", "state_space") if return_state else ()))
                       if not hasattr(batched_env, name)]
            if missing:
                raise TypeError(f"batched_env: {type(batched_env).__name__} lacks {missing} of the array API "
                                "(BATCHED_ENV_API)")
            vec = batched_env
        super().__init__(device=device, batch_size=torch.Size([vec.num_envs]))
        self.vector_env = vec
        self.return_state = return_state
        agents = list(vec.possible_agents)
        if group_map_type is None:
            groups = group_map(vec)
        elif isinstance(group_map_type, MarlGroupMapType):
            groups = group_map_type.get_group_map(agents)
        else:
            groups = {name: list(members) for name, members in group_map_type.items()}
        check_marl_grouping(groups, agents)
        self.group_map = groups
        index = {agent: i for i, agent in enumerate(agents)}
        self._agent_rows: dict[str, np.ndarray] = {}
        self._obs_columns: dict[str, Any] = {}
        self._joint_columns: dict[str, Any] = {}
        self._shapes: dict[str, tuple[int, int, int]] = {}
        observation_slices = _observation_slices(vec)
        self._n_joints = max(part.stop for part in vec.joint_slices)
        for group, members in groups.items():
            rows = np.array([index[a] for a in members])
            obs = np.concatenate([np.arange(observation_slices[i].start, observation_slices[i].stop) for i in rows])
            joints = np.concatenate([np.arange(vec.joint_slices[i].start, vec.joint_slices[i].stop) for i in rows])
            self._agent_rows[group] = rows
            self._obs_columns[group] = _as_slice(obs)
            self._joint_columns[group] = _as_slice(joints)
            self._shapes[group] = (len(rows), len(obs) // len(rows), len(joints) // len(rows))
        self._make_specs()
        self._started = np.zeros(vec.num_envs, dtype=bool)  # autoreset by the vector env, not yet handed over
        self._never_reset = True
        self._pending_seed: int | None = None
        if seed is not None:
            self.set_seed(seed)

    @classmethod
    def from_batched(cls, env: Any, group_map_type: MarlGroupMapType | dict | None = None, return_state: bool = True,
                     seed: int | None = None, device: Any = "cpu") -> "BatchedTorchRLEnv":
        """The TorchRL env around ``env``, a batched env built already with the array API
        (:data:`BATCHED_ENV_API`; e.g. the learning wing's ``BatchedTrainingEnv``). Keys, done and reset
        handling as for a scenario; each agent's observation is its part of the env's observations, sized by
        ``env.observation_space(agent)``. It owns ``env`` (``close()`` closes it)."""
        return cls(batched_env=env, group_map_type=group_map_type, return_state=return_state, seed=seed,
                   device=device)

    # ------------------------------------------------------------------------------------------ specs
    def _make_specs(self) -> None:
        vec, device = self.vector_env, self.device
        generators = list(vec.np_randoms)
        probe = vec.reset_arrays(seed=0)  # the info shapes; the copies' own generators are put back
        vec.np_randoms[:] = generators
        self._masked = "agent_mask" in probe.infos  # copies of different team sizes (ee_formation_env.team_env)
        observations, actions, rewards = Composite(device=device), Composite(device=device), Composite(device=device)
        done = Composite({key: Categorical(2, shape=(1,), dtype=torch.bool, device=device) for key in _DONE_KEYS},
                         device=device)
        for group, members in self.group_map.items():
            n, _, n_joints = self._shapes[group]
            first = members[0]
            info = Composite({key: Unbounded(shape=value.shape[1:], dtype=torch.float32, device=device)
                              for key, value in self._info(probe.infos, group).items()}, shape=(n,), device=device)
            observations[group] = Composite({"observation": _box_spec(vec.observation_space(first), n, device),
                                             "info": info}, shape=(n,), device=device)
            actions[group] = Composite({"action": _box_spec(vec.action_space(first), n, device)}, shape=(n,),
                                       device=device)
            rewards[group] = Composite({"reward": Unbounded(shape=(n, 1), dtype=torch.float32, device=device)},
                                       shape=(n,), device=device)
            done[group] = Composite({key: Categorical(2, shape=(n, 1), dtype=torch.bool, device=device)
                                     for key in _DONE_KEYS}, shape=(n,), device=device)
            if self._masked:
                observations[group]["mask"] = Categorical(2, shape=(n,), dtype=torch.bool, device=device)
        if self.return_state:
            observations["state"] = _box_spec(vec.state_space, 1, device).squeeze(0)
        self.full_observation_spec_unbatched = observations
        self.full_action_spec_unbatched = actions
        self.full_reward_spec_unbatched = rewards
        self.full_done_spec_unbatched = done

    # ------------------------------------------------------------------------------------------ conversions
    def _info(self, infos: dict[str, np.ndarray], group: str) -> dict[str, torch.Tensor]:
        rows, (n, _, n_joints) = self._agent_rows[group], self._shapes[group]
        K = self.vector_env.num_envs
        out = {key: _tensor(infos[key][:, rows], self.device) for key in _AGENT_INFO}
        for key in _COPY_INFO:
            out[key] = _tensor(np.broadcast_to(infos[key][:, None], (K, n)), self.device)
        out["applied_torque"] = _tensor(infos["applied_torque"][:, self._joint_columns[group]].reshape(K, n, n_joints),
                                        self.device)
        return out

    def _output(self, observations: np.ndarray, result: Any, rewards: bool) -> TensorDictBase:
        K, device = self.vector_env.num_envs, self.device
        terminated = torch.from_numpy(result.terminations).to(device).unsqueeze(-1)
        truncated = torch.from_numpy(result.truncations).to(device).unsqueeze(-1)
        finished = terminated | truncated
        source: dict[str, Any] = {"done": finished, "terminated": terminated, "truncated": truncated}
        for group in self.group_map:
            n, obs_dim, _ = self._shapes[group]
            entry = {"observation": _tensor(observations[:, self._obs_columns[group]].reshape(K, n, obs_dim), device),
                     "info": TensorDict(self._info(result.infos, group), batch_size=(K, n), device=device),
                     "done": finished.unsqueeze(1).expand(K, n, 1).clone(),
                     "terminated": terminated.unsqueeze(1).expand(K, n, 1).clone(),
                     "truncated": truncated.unsqueeze(1).expand(K, n, 1).clone()}
            if rewards:
                entry["reward"] = _tensor(result.rewards[:, self._agent_rows[group], None], device)
            if self._masked:  # the agents of the episode these observations belong to
                entry["mask"] = torch.from_numpy(result.infos["agent_mask"][:, self._agent_rows[group]]).to(device)
            source[group] = TensorDict(entry, batch_size=(K, n), device=device)
        if self.return_state:
            source["state"] = _tensor(self.vector_env.state(), device)
        return TensorDict(source, batch_size=self.batch_size, device=device)

    # ------------------------------------------------------------------------------------------ EnvBase
    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        vec = self.vector_env
        K = vec.num_envs
        actions = np.empty((K, self._n_joints), dtype=np.float32)
        for group in self.group_map:
            action = tensordict.get((group, "action"))
            actions[:, self._joint_columns[group]] = action.detach().reshape(K, -1).cpu().numpy()
        result = vec.step_arrays(actions)
        # The observation each copy ended in (SAME_STEP already started the next episode of ended copies).
        self._started = result.terminations | result.truncations
        return self._output(result.infos["final_observation"], result, rewards=True)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        vec = self.vector_env
        requested = self._reset_mask(tensordict)
        seed, self._pending_seed = self._pending_seed, None
        if self._never_reset or (seed is not None and requested.all()):
            result = vec.reset_arrays(seed=seed)
        else:
            rows = requested if seed is not None else requested & ~self._started
            result = vec.reset_arrays(seed=seed, options={"reset_mask": rows})
        self._never_reset = False
        self._started[:] = False
        return self._output(result.observations, result, rewards=False)

    def _reset_mask(self, tensordict: TensorDictBase | None) -> np.ndarray:
        """The (K,) copies a reset asks for: the root ``_reset``, or any agent's ``(group, "_reset")``."""
        K = self.vector_env.num_envs
        if tensordict is None:
            return np.ones(K, dtype=bool)
        masks = []
        if "_reset" in tensordict.keys():
            masks.append(tensordict.get("_reset").reshape(K, -1).any(-1))
        for group in self.group_map:
            if (group, "_reset") in tensordict.keys(True):
                masks.append(tensordict.get((group, "_reset")).reshape(K, -1).any(-1))
        if not masks:
            return np.ones(K, dtype=bool)
        return torch.stack(masks).any(0).cpu().numpy()

    def _set_seed(self, seed: int | None) -> None:
        self._pending_seed = seed

    def close(self, *args: Any, **kwargs: Any) -> None:
        self.vector_env.close()
        super().close(*args, **kwargs)

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(scenario={self.vector_env.scenario.name!r}, num_envs={self.vector_env.num_envs}, "
                f"groups={ {g: len(a) for g, a in self.group_map.items()} }, device={self.device})")


def _observation_slices(env: Any) -> list[slice]:
    """Agent i's columns of the batched env's observations (K, O): the agents' observations concatenated in
    agent order, each as long as its ``observation_space`` (for the vector env: its ``observation_slices``)."""
    slices, start = [], 0
    for agent in env.possible_agents:
        size = int(np.prod(env.observation_space(agent).shape))
        slices.append(slice(start, start + size))
        start += size
    return slices


def _as_slice(columns: np.ndarray) -> slice | np.ndarray:
    """A contiguous run of columns as a slice (a view, no copy), else the index array."""
    if len(columns) and np.array_equal(columns, np.arange(columns[0], columns[0] + len(columns))):
        return slice(int(columns[0]), int(columns[0]) + len(columns))
    return columns
