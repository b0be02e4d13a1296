"""The TorchRL transforms a BenchMARL formation task adds to its envs (the ``torchrl`` extra): observation
normalization, reward scaling or normalization and the slot split of the observations for set models; which of
them a task uses is its :class:`TaskTransforms` (``docs/training.md``, "TorchRL and BenchMARL").

The slot split (``observation_sets``): each group's ``observation`` (..., n_agents, O) becomes a nested entry
of two parts, ``("observation", "neighbour_slots")`` (..., n_agents, D, slot_size: per neighbour slot its mask,
z_ij, desired and edge error, :mod:`ee_formation_env.observation`) and ``("observation", "own_state")``
(..., n_agents, own_size: q, dq and any manoeuvre entries), which BenchMARL's ``Deepsets`` model reads as a
set and a vector: ``rho(own_state, aggregate over slots of phi(slot))``. No weight depends on D, so a policy
trained with one team size acts for another (:mod:`ee_formation_env.baselines.learned.benchmarl_export`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, List, Mapping, Optional, Sequence

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.data import Composite, Unbounded
from torchrl.envs import EnvBase, ExcludeTransform, RewardScaling, Transform
from torchrl.envs.transforms.vecnorm import VecNormV2

from ee_formation_env.baselines.learned.set_network import SlotLayout


class RunningObservationNorm(VecNormV2):
    """TorchRL's ``VecNormV2`` (stateful, infinite memory: ``decay=1``, statistics over the copies) with two
    changes. Its statistics are made at once from ``env``'s specs and **shared by its clones**: BenchMARL clones
    a task's transforms into its test env and into every training env it makes, and the task reads the
    statistics training updated from the one it made (:meth:`statistics`). And its variance
    ``E[x²] - E[x]²``, which rounds below 0 in float32 for a feature that never changes (a slot's tolerance, a
    mask entry) and which torchrl 0.11 then turns into NaN through the square root, is held at 0 or above
    before ``eps`` clamps the scale as ``VecNormV2`` does."""

    def __init__(self, in_keys: List[Any], env: EnvBase):
        super().__init__(in_keys=in_keys, decay=1.0, reduce_batch_dims=True)
        sample = env.fake_tensordict().get("next").select(*in_keys, strict=True)
        sample = sample.mean(dim=tuple(range(sample.ndim))).float()  # one statistic per agent and feature
        self._loc, self._var = torch.zeros_like(sample), torch.zeros_like(sample)
        self._count = torch.zeros_like(sample, dtype=torch.float32).mean().to(torch.int64)
        self.initialized.fill_(True)

    def clone(self) -> "RunningObservationNorm":
        other = super().clone()
        other._loc, other._var, other._count = self._loc, self._var, self._count  # shared, not copied
        return other

    def _norm(self, data: Any, loc: Any, var: Any, count: Any) -> Any:
        return super()._norm(data, loc, var.apply(lambda second, mean: torch.maximum(second, mean.pow(2)), loc), count)

    def statistics(self, key: Any) -> tuple[np.ndarray, np.ndarray]:
        """(loc, scale) of ``key`` as :meth:`_norm` applies them, ``(x - loc) / scale``, float64."""
        loc, second = self._loc[key].detach().cpu(), self._var[key].detach().cpu()
        scale = (torch.maximum(second, loc.pow(2)) - loc.pow(2)).sqrt().clamp_min(self.eps)
        return loc.numpy().astype(np.float64), scale.numpy().astype(np.float64)


class ReturnNormalizedReward(Transform):
    """SB3's ``VecNormalize`` reward normalization as a TorchRL transform: each group's reward divided by the
    running standard deviation of its discounted return, ``r / sqrt(var(G) + epsilon)`` clipped to
    ``[-clip, clip]``, where ``G <- gamma * G + r`` per copy and agent, reset to 0 when the agent's episode ends,
    and ``var(G)`` the running variance (infinite memory) over every copy, agent and step seen so far. The mean
    is not subtracted: a reward's sign, and so the value of ending an episode early, stay what they are.

    The statistics are **shared by its clones** (BenchMARL clones a task's transforms into each env it makes);
    each clone keeps its own returns, whose shape is its env's. :meth:`take_env_reward` gives the mean of the
    rewards before normalization since its last call (a learning curve in the env's units)."""

    def __init__(self, groups: Sequence[str], gamma: float, clip: float = 10.0, epsilon: float = 1e-8):
        keys = [(group, "reward") for group in groups]
        super().__init__(in_keys=keys, out_keys=keys)
        self.groups, self.gamma, self.clip, self.epsilon = list(groups), float(gamma), float(clip), float(epsilon)
        # Running mean, variance and count of the returns, per group (float64; SB3's RunningMeanStd start values)
        # and the env rewards' running sum and count for take_env_reward: one dict, shared by the clones.
        self._statistics = {group: torch.tensor([0.0, 1.0, 1e-4], dtype=torch.float64) for group in self.groups}
        self._statistics["env_reward"] = torch.zeros(2, dtype=torch.float64)
        self._returns: dict[str, torch.Tensor] = {}

    def clone(self) -> "ReturnNormalizedReward":
        other = ReturnNormalizedReward(self.groups, self.gamma, self.clip, self.epsilon)
        other._statistics = self._statistics  # shared, not copied
        return other

    def return_std(self, group: str) -> float:
        """The running standard deviation of the group's discounted return that divides its rewards now."""
        return float(self._statistics[group][1].add(self.epsilon).sqrt())

    def take_env_reward(self) -> float:
        """The mean reward per agent step before normalization since the last call (NaN when none)."""
        tally = self._statistics["env_reward"]
        mean = float(tally[0] / tally[1]) if tally[1] > 0 else float("nan")
        tally.zero_()
        return mean

    def _update(self, group: str, returns: torch.Tensor) -> None:
        statistics = self._statistics[group]
        mean, var, count = statistics.tolist()
        batch = returns.detach().to(torch.float64).flatten()
        batch_mean, batch_var, batch_count = float(batch.mean()), float(batch.var(unbiased=False)), batch.numel()
        delta, total = batch_mean - mean, count + batch_count  # Chan et al.'s parallel update, as SB3's
        m2 = var * count + batch_var * batch_count + delta ** 2 * count * batch_count / total
        statistics.copy_(torch.tensor([mean + delta * batch_count / total, m2 / total, total], dtype=torch.float64))

    def _step(self, tensordict: Any, next_tensordict: Any) -> Any:
        for group in self.groups:
            reward = next_tensordict.get((group, "reward"))
            returns = self._returns.get(group)
            if returns is None or returns.shape != reward.shape:
                returns = torch.zeros_like(reward, dtype=torch.float64)
            returns = returns * self.gamma + reward.to(torch.float64)
            self._update(group, returns)
            tally = self._statistics["env_reward"]
            tally += torch.tensor([float(reward.sum()), reward.numel()], dtype=torch.float64)
            normalized = (reward.to(torch.float64) / (self._statistics[group][1] + self.epsilon).sqrt())
            next_tensordict.set((group, "reward"), normalized.clamp(-self.clip, self.clip).to(reward.dtype))
            done = next_tensordict.get((group, "done"), None)
            self._returns[group] = returns if done is None else returns.masked_fill(done.expand_as(returns), 0.0)
        return next_tensordict

    def _reset(self, tensordict: Any, tensordict_reset: Any) -> Any:
        return tensordict_reset

    def forward(self, tensordict: Any) -> Any:  # not on stored batches: the returns are the env's own history
        raise RuntimeError("ReturnNormalizedReward acts on an env's steps only")


class SlotSplit(Transform):
    """Each group's flat ``observation`` as its neighbour slots and own state (module docstring), in place;
    ``layout``: the slot layout of the task's observations (:func:`~ee_formation_env.baselines.learned.set_network.slot_layout`)."""

    def __init__(self, groups: Sequence[str], layout: SlotLayout):
        keys = [(group, "observation") for group in groups]
        super().__init__(in_keys=keys, out_keys=keys)
        self.layout = layout

    def _split(self, observation: torch.Tensor) -> TensorDict:
        layout, lead = self.layout, observation.shape[:-1]
        block = layout.n_slots * layout.slot_size
        return TensorDict({"neighbour_slots": observation[..., :block].reshape(*lead, layout.n_slots, layout.slot_size),
                           "own_state": observation[..., block:]}, batch_size=lead, device=observation.device)

    def _call(self, next_tensordict: Any) -> Any:
        for key in self.in_keys:
            observation = next_tensordict.get(key, None)
            if isinstance(observation, torch.Tensor):
                next_tensordict.del_(key)
                next_tensordict.set(key, self._split(observation))
        return next_tensordict

    def _reset(self, tensordict: Any, tensordict_reset: Any) -> Any:
        return self._call(tensordict_reset)

    def forward(self, tensordict: Any) -> Any:  # as a module or on a replay buffer's samples: the same split
        return self._call(tensordict)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        layout = self.layout
        for key in self.in_keys:
            spec = observation_spec[key]
            if isinstance(spec, Composite):  # already split
                continue
            if spec.shape[-1] != layout.size:
                raise ValueError(f"observation_sets: {key} has {spec.shape[-1]} entries, the slot layout {layout}")
            lead = spec.shape[:-1]
            parts = {"neighbour_slots": Unbounded(shape=(*lead, layout.n_slots, layout.slot_size), dtype=spec.dtype,
                                                  device=spec.device),
                     "own_state": Unbounded(shape=(*lead, layout.own_size), dtype=spec.dtype, device=spec.device)}
            del observation_spec[key]
            observation_spec[key] = Composite(parts, shape=lead, device=spec.device)
        return observation_spec


@dataclass(frozen=True)
class TaskTransforms:
    """The TorchRL transforms a task adds to its envs (BenchMARL's ``get_env_transforms``), in this order; both
    off by default, so that a task without them steps exactly the training env. Checked on construction."""

    #: Each group's observations by a running mean and standard deviation per agent and feature, over every
    #: copy, with infinite memory (:class:`RunningObservationNorm`, TorchRL's ``VecNormV2``): SB3's
    #: ``VecNormalize`` of observations, without its clipping. The statistics are exported with the actor.
    observation_normalization: bool = False
    #: With ``observation_normalization``, the global ``state`` too where the env returns it (the input of
    #: MAPPO's centralized critic), per feature, the same way (docs/results.md: measured, not adopted).
    state_normalization: bool = False
    #: The env's global ``state`` (end-effector positions in m, q, dq) kept for centralized critics (MAPPO's and
    #: MASAC's read it where the task has one). False: removed (TorchRL's ``ExcludeTransform``), so BenchMARL's
    #: centralized critics read every agent's observation instead, normalized and featured as the actors see
    #: them (BenchMARL's rule for a task without a state).
    global_state: bool = True
    #: Every reward multiplied by this (TorchRL's ``RewardScaling``), > 0 (the env's rewards are in [0, 2] per step).
    reward_scale: float = 1.0
    #: Every reward divided by the running standard deviation of its discounted return, clipped to [-10, 10]
    #: (:class:`ReturnNormalizedReward`: SB3's ``VecNormalize`` of rewards, what ``train.py``'s PPO trains
    #: with). Not with ``reward_scale``, which it replaces.
    reward_normalization: bool = False
    #: The discount of those returns, in (0, 1]: the experiment's ``gamma`` (SB3's ``VecNormalize`` takes PPO's).
    reward_normalization_gamma: float = 0.99
    #: Each group's observation split into its neighbour slots and own state (:class:`SlotSplit`, module
    #: docstring), for a set model such as BenchMARL's ``Deepsets`` (``model/layers/deepsets.yaml``). Not with
    #: ``observation_normalization``, whose statistics are per agent and entry, which another team size cannot use.
    observation_sets: bool = False

    def __post_init__(self) -> None:
        for name in ("observation_normalization", "state_normalization", "global_state", "observation_sets",
                     "reward_normalization"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"{name}: expected True or False, got {getattr(self, name)!r}")
        if self.observation_sets and self.observation_normalization:
            raise ValueError("observation_sets: not with observation_normalization (its statistics are per agent and "
                             "entry; a set policy must not depend on the team size)")
        if self.state_normalization and not self.observation_normalization:
            raise ValueError("state_normalization: needs observation_normalization (the one normalization transform)")
        if self.state_normalization and not self.global_state:
            raise ValueError("state_normalization: the task has no state without global_state")
        scale = self.reward_scale
        if isinstance(scale, bool) or not isinstance(scale, (int, float)):
            raise TypeError(f"reward_scale: expected a number > 0, got {type(scale).__name__} {scale!r}")
        if not (np.isfinite(scale) and scale > 0):
            raise ValueError(f"reward_scale: expected a finite number > 0, got {scale!r}")
        object.__setattr__(self, "reward_scale", float(scale))
        gamma = self.reward_normalization_gamma
        if isinstance(gamma, bool) or not isinstance(gamma, (int, float)):
            raise TypeError(f"reward_normalization_gamma: expected a number in (0, 1], got {type(gamma).__name__} "
                            f"{gamma!r}")
        if not 0.0 < gamma <= 1.0:
            raise ValueError(f"reward_normalization_gamma: expected a number in (0, 1], got {gamma!r}")
        object.__setattr__(self, "reward_normalization_gamma", float(gamma))
        if self.reward_normalization and self.reward_scale != 1.0:
            raise ValueError("reward_normalization: not with reward_scale (it replaces the fixed scale); set "
                             f"reward_scale to 1.0, got {self.reward_scale!r}")

    @classmethod
    def fields(cls) -> tuple[str, ...]:
        return tuple(field.name for field in dataclasses.fields(cls))

    def transforms(self, env: EnvBase, groups: Mapping[str, Any], layout: Optional[SlotLayout] = None
                   ) -> list[Transform]:
        """The transforms for ``env`` and its agent groups ``groups`` (group -> agents); ``layout``: the slot
        layout of its observations, which ``observation_sets`` needs."""
        transforms: list[Transform] = []
        if not self.global_state and "state" in env.observation_spec.keys():
            transforms.append(ExcludeTransform("state"))
        if self.observation_sets:
            if layout is None:
                raise ValueError("observation_sets: needs the observations' slot layout")
            transforms.append(SlotSplit(list(groups), layout))
        if self.observation_normalization:
            state = ["state"] if self.state_normalization and "state" in env.observation_spec.keys() else []
            transforms.append(RunningObservationNorm([(group, "observation") for group in groups] + state, env))
        if self.reward_scale != 1.0:
            transforms.append(RewardScaling(loc=0.0, scale=self.reward_scale,
                                            in_keys=[(group, "reward") for group in groups]))
        if self.reward_normalization:
            transforms.append(ReturnNormalizedReward(list(groups), self.reward_normalization_gamma))
        return transforms



def task_transforms(config: Mapping[str, Any]) -> TaskTransforms:
    """The :class:`TaskTransforms` of a task config (its fields; the others are not read here)."""
    return TaskTransforms(**{key: config[key] for key in TaskTransforms.fields() if key in config})


