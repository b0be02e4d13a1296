"""A BenchMARL group's exported actor in numpy (float64), deterministic: what ``load_benchmarl_policy`` returns
per group and evaluation runs, BenchMARL not needed (the export: :mod:`ee_formation_env.baselines.learned.benchmarl_task`).

Two forms: BenchMARL's MLP on the flat observation, and BenchMARL's ``Deepsets`` on the task's set observations
(:mod:`ee_formation_env.baselines.learned.benchmarl_transforms`, ``observation_sets``), whose shared weights act
on an observation of any slot count, so for any team of the robot it trained with.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Optional

import numpy as np

from ee_formation_env.baselines.learned.policy import ObservationNormalizer
from ee_formation_env.baselines.learned.set_network import POOLINGS, masked_pool, slot_layout

#: Activations the numpy actor computes, by name (BenchMARL's MLP default is Tanh).
ACTIVATIONS: dict[str, Callable[[np.ndarray], np.ndarray]] = {"Tanh": np.tanh, "ReLU": lambda x: np.maximum(x, 0.0)}
#: How a set actor pools its slots (BenchMARL's Deepsets ``aggr`` values the actor computes).
SET_AGGREGATIONS = POOLINGS
#: The action distributions: TorchRL's ``TanhNormal`` and ``IndependentNormal``.
DISTRIBUTION_NAMES = ("tanh_normal", "normal")


def _dense(hidden: np.ndarray, steps: List[tuple[np.ndarray, np.ndarray]],
           activation: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """``hidden`` through linear layers ``(weight (in, out), bias (out,))`` with ``activation`` between them (none
    after the last: BenchMARL's MLPs)."""
    for layer, (weight, bias) in enumerate(steps):
        hidden = hidden @ weight + bias
        if layer < len(steps) - 1:
            hidden = activation(hidden)
    return hidden


@dataclass
class GroupActor:
    """One group's deterministic actor in numpy (float64): an MLP from the observation (obs_dim,) to the
    Gaussian's parameters (2 n,), of which the first n are its mean ``loc``; the action is
    ``(high + low) / 2 + (high - low) / 2 * tanh(loc)`` (``"tanh_normal"``, TorchRL's ``TanhNormal``) or ``loc``
    (``"normal"``).

    ``weights[l]`` (A, in, out) and ``biases[l]`` (A, out) of the l-th linear layer, with ``activation`` between
    layers; A = 1 when the group's agents share parameters, else one row per agent of ``agents``.
    ``observation_loc`` and ``observation_scale`` (n_agents, obs_dim): the task's observation normalization,
    ``(observation - loc) / scale`` per agent before the MLP, or None without it."""

    agents: List[str]
    weights: List[np.ndarray]
    biases: List[np.ndarray]
    activation: str
    distribution: str
    low: np.ndarray  # (n,) the action bounds of the distribution
    high: np.ndarray
    observation_loc: Optional[np.ndarray] = None
    observation_scale: Optional[np.ndarray] = None
    #: BenchMARL's ``Deepsets`` on the task's ``observation_sets`` (None: the MLP): ``slot_size``, ``own_size``,
    #: ``local_layers`` (the first that many layers are phi, applied to every neighbour slot; the rest rho, on
    #: the slots' ``aggregation`` of phi and the own state), ``aggregation`` (``mean``, ``sum`` or ``max``) and
    #: ``masked`` (over the real slots only, mask > 0.5, as the project's ``SlotDeepsets``; else over every
    #: slot, as BenchMARL's own). Its weights are shared and fit any slot count: any team of its robot.
    slots: Optional[Dict[str, Any]] = None

    def __post_init__(self) -> None:
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"activation: expected one of {list(ACTIVATIONS)}, got {self.activation!r}")
        if self.distribution not in DISTRIBUTION_NAMES:
            raise ValueError(f"distribution: expected one of {list(DISTRIBUTION_NAMES)}, got {self.distribution!r}")
        rows = {len(w) for w in self.weights} | {len(b) for b in self.biases}
        if rows not in ({1}, {len(self.agents)}):
            raise ValueError(f"weights: expected 1 (shared) or {len(self.agents)} rows per layer, got {sorted(rows)}")
        if self.slots is not None:
            if set(self.slots) != {"slot_size", "own_size", "local_layers", "aggregation", "masked"} or not self.shared \
                    or self.slots["aggregation"] not in SET_AGGREGATIONS or self.observation_loc is not None:
                raise ValueError(f"set_network: expected slot_size, own_size, local_layers, masked and an aggregation of "
                                 f"{list(SET_AGGREGATIONS)}, shared weights, no normalization; got {self.slots!r}")
        if (self.observation_loc is None) != (self.observation_scale is None):
            raise ValueError("observation_normalization: expected both loc and scale, or neither")
        if self.observation_loc is not None:
            shape = (len(self.agents), self.layer_sizes[0])
            for name in ("observation_loc", "observation_scale"):
                value = np.asarray(getattr(self, name), dtype=np.float64)
                if value.shape != shape or not np.all(np.isfinite(value)):
                    raise ValueError(f"observation_normalization: {name[12:]} must be finite of shape {shape} (agents "
                                     f"x observation size), got {value.shape}")
                setattr(self, name, value)
            if np.any(self.observation_scale <= 0):
                raise ValueError("observation_normalization: scale must be > 0")

    def normalizer(self, agent: str) -> ObservationNormalizer:
        """What the agent's observation goes through before the MLP (the identity without normalization)."""
        if self.slots is not None:  # any observation size
            return ObservationNormalizer(np.zeros(()), np.ones(()), clip=np.inf, epsilon=0.0)
        if self.observation_loc is None:
            return ObservationNormalizer.identity(self.layer_sizes[0])
        row = self.agents.index(agent)
        return ObservationNormalizer(self.observation_loc[row], self.observation_scale[row] ** 2, clip=np.inf,
                                     epsilon=0.0)

    @property
    def shared(self) -> bool:
        return len(self.weights[0]) == 1

    @property
    def layer_sizes(self) -> list[int]:
        """Input, hidden and output widths: (obs_dim, ..., 2 n)."""
        return [int(self.weights[0].shape[1]), *(int(w.shape[2]) for w in self.weights)]

    def _action(self, outputs: np.ndarray) -> np.ndarray:
        loc = outputs[..., :outputs.shape[-1] // 2]
        if self.distribution == "normal":
            return loc
        return (self.high + self.low) / 2 + (self.high - self.low) / 2 * np.tanh(loc)

    def act(self, observations: np.ndarray) -> np.ndarray:
        """The deterministic actions (..., n_agents, n) of the group's agents for raw observations (..., n_agents,
        obs_dim), agents in the order of ``agents`` (normalized first, where the task normalizes)."""
        hidden = np.asarray(observations, dtype=np.float64)
        if self.slots is not None:  # one shared set actor, row by row
            return self.predict(self.agents[0])(hidden.reshape(-1, hidden.shape[-1])).reshape(*hidden.shape[:-1], -1)
        if self.observation_loc is not None:
            hidden = (hidden - self.observation_loc) / self.observation_scale
        hidden = hidden[..., None, :]  # (..., A, 1, in) against (A, in, out)
        activation = ACTIVATIONS[self.activation]
        for layer, (weight, bias) in enumerate(zip(self.weights, self.biases)):
            hidden = hidden @ weight + bias[:, None, :]
            if layer < len(self.weights) - 1:
                hidden = activation(hidden)
        return self._action(hidden[..., 0, :])

    def predict(self, agent: str) -> Callable[[np.ndarray], np.ndarray]:
        """``normalized observation (obs_dim,) or stack (k, obs_dim) -> action`` of one agent (its
        :meth:`normalizer` applied before, by the :class:`LearnedPolicy` around it). A stack gives each row's
        action bit for bit (``predict.stacks``, :class:`~ee_formation_env.baselines.learned.policy.LearnedPolicy`)."""
        row = 0 if self.shared else self.agents.index(agent)
        steps = [(weight[row], bias[row]) for weight, bias in zip(self.weights, self.biases)]
        activation = ACTIVATIONS[self.activation]
        if self.slots is not None:
            return self._set_predict(steps, activation)

        def predict(observation: np.ndarray) -> np.ndarray:
            hidden = np.asarray(observation, dtype=np.float64)
            stack = hidden.ndim == 2
            if stack:  # (k, 1, d) @ (d, h): row by row the products of one observation, exactly
                hidden = hidden[:, None, :]
            hidden = _dense(hidden, steps, activation)
            return self._action(hidden[:, 0, :] if stack else hidden)

        predict.stacks = True
        return predict

    def _set_predict(self, steps: list[tuple[np.ndarray, np.ndarray]], activation: Callable[[np.ndarray], np.ndarray]
                     ) -> Callable[[np.ndarray], np.ndarray]:
        """:meth:`predict` of the set form (:attr:`slots`): observations of any slot count."""
        slot_size, own_size, split = (int(self.slots[key]) for key in ("slot_size", "own_size", "local_layers"))
        aggregation, masked = self.slots["aggregation"], bool(self.slots["masked"])

        def predict(observation: np.ndarray) -> np.ndarray:
            rows = np.asarray(observation, dtype=np.float64)
            single = rows.ndim == 1
            rows = rows[None] if single else rows
            n_slots = (rows.shape[-1] - own_size) // slot_size
            if n_slots * slot_size + own_size != rows.shape[-1]:
                raise ValueError(f"observation: {rows.shape[-1]} entries are not slots of {slot_size} and {own_size} "
                                 "own entries: the set actor cannot act for this team")
            block = n_slots * slot_size
            slots = rows[:, :block].reshape(len(rows), n_slots, slot_size)
            # (k, D, 1): padding slots take no part, where the model masked them (SlotDeepsets) as here
            real = slots[..., :1] > 0.5 if masked else np.ones((*slots.shape[:2], 1), dtype=bool)
            encoded = _dense(slots[..., None, :], steps[:split], activation)[..., 0, :]  # (k, D, h), row by row exactly
            features = np.concatenate([masked_pool(encoded, real, aggregation), rows[:, block:]], axis=1)[:, None, :]
            actions = self._action(_dense(features, steps[split:], activation)[:, 0, :])
            return actions[0] if single else actions

        predict.stacks = True
        return predict

    def serves(self, env: Any) -> None:
        """``ValueError`` naming ``policy`` unless this actor can act for every agent of ``env``: its own agents, or
        for a set actor any agent whose observation has its slot and own sizes (the same robot's)."""
        if self.slots is None:
            missing = [agent for agent in env.possible_agents if agent not in self.agents]
            if missing:
                raise ValueError(f"policy: the actor was trained for {self.agents}; it has no weights for {missing}")
            return
        for agent in env.possible_agents:
            layout = slot_layout(env.observation_layout(agent), "none")
            if (layout.slot_size, layout.own_size) != (self.slots["slot_size"], self.slots["own_size"]):
                raise ValueError(f"policy: {agent}'s observation has slots of {layout.slot_size} and {layout.own_size} "
                                 f"own entries; the set actor reads {self.slots['slot_size']} and "
                                 f"{self.slots['own_size']}: it cannot act for this team")
