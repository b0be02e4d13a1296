"""The permutation-invariant shared policy network (``policy_network: set``): one policy for any team size.

Rule: an agent's observation is ``D`` neighbour slots (mask, z_ij, desired, edge_error; padding slots zero
with mask 0), then its own joint state q, dq (and a manoeuvre's reference entries):
:mod:`ee_formation_env.observation`, the one layout definition, read from the env (:func:`slot_layout`),
never hard-coded. The network (:func:`set_extractor_class`) is

- a slot encoder ``phi`` (two ``tanh`` layers of :data:`SET_HIDDEN` units), the same weights on every slot's
  entries but its mask;
- masked pooling over the real slots: their mean and their element-wise max (padding slots take no part);
- an own-state encoder (one ``tanh`` layer of :data:`SET_HIDDEN` units) of q, dq;
- the three concatenated (``3 x SET_HIDDEN`` features), then the mode's actor and critic heads (SB3's
  ``net_arch`` MLPs) on top.

No weight depends on ``D``, so the weights trained with one team size act for any other (the slot count is
an argument of the network, not a weight). Shuffling the real slots leaves the action unchanged.

Normalization (:class:`PooledRunningMeanStd`): running statistics shared across slots, per slot entry, over
the real slots only, and per own-state entry; the mask passes unchanged. Expanded to any ``D``
(:func:`expanded_statistics`) they normalize an observation of another team size as training normalized
its own. A team the policy cannot serve (other robot, joint count, dim, formation kind, manoeuvre entries)
is refused by :func:`check_serves` with a ``ValueError`` naming the field. Observation features that append
entries mixing slots with the own state (``log-error``, ``invariant``) are refused (``obs_features``).
Docs: docs/training.md, "Team-size transfer".
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from ee_formation_env.baselines.learned.numpy_layers import apply_numpy_layers, numpy_layers

#: ``policy_network`` values: SB3's MLP on the whole observation, or the set network of this module.
POLICY_NETWORKS = ("mlp", "set")
SET_HIDDEN = 64  # units of the slot encoder's two layers and of the own-state encoder
MASK_VARIANCE = 1.0  # the mask's expanded statistics: mean 0, this variance (it passes unchanged)


@dataclass(frozen=True)
class SlotLayout:
    """How the set network reads one observation: ``n_slots`` slots of ``slot_size`` entries (the mask first),
    then ``own_size`` own entries (q, dq and any manoeuvre reference entries)."""

    n_slots: int
    slot_size: int
    own_size: int

    @property
    def size(self) -> int:
        return self.n_slots * self.slot_size + self.own_size

    def split(self, observations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(k, size) -> slots (k, n_slots, slot_size) and own entries (k, own_size)."""
        block = self.n_slots * self.slot_size
        return (observations[..., :block].reshape(*observations.shape[:-1], self.n_slots, self.slot_size),
                observations[..., block:block + self.own_size])

    def to_dict(self) -> dict[str, int]:
        return asdict(self)


def slot_layout(layout: Any, obs_features: str) -> SlotLayout:
    """The set network's view of an observation of ``layout`` (an
    :class:`~ee_formation_env.observation.ObservationLayout`); ``ValueError`` naming ``obs_features`` for a
    feature set that breaks the slot structure."""
    if obs_features != "none":
        raise ValueError(f"obs_features: the set network (policy_network 'set') reads neighbour slots then the own "
                         f"state; {obs_features!r} appends one block after the joint state that mixes per-slot and "
                         "own entries (features.py): use obs_features 'none'")
    return SlotLayout(layout.n_slots, layout.slot_size, 2 * layout.n_joints + layout.reference_size)


def set_description(scenario: Any, obs_features: str) -> dict[str, Any]:
    """What a run saves of its set network (``policy.json``'s ``set_network``): the slot layout of
    ``scenario``'s observation and its team signature (:func:`team_signature`). ``ValueError`` naming the field
    for a mixed team or a feature set that breaks the slots, before any training."""
    from ee_formation_env.env import FormationEnv

    with FormationEnv(scenario) as env:
        team = team_signature(env)
        layout = slot_layout(env.observation_layout(env.possible_agents[0]), obs_features)
    return {"layout": layout.to_dict(), "team": team}


def slot_layout_of(description: Mapping[str, Any]) -> SlotLayout:
    """The slot layout a :func:`set_description` holds."""
    layout = description["layout"]
    return SlotLayout(int(layout["n_slots"]), int(layout["slot_size"]), int(layout["own_size"]))


def team_signature(env: Any) -> dict[str, Any]:
    """What a set policy trained in ``env`` can serve: its robot (URDF file and end-effector link), joint count,
    dim, formation kind and whether a manoeuvre's reference entries are observed. ``ValueError`` naming
    ``policy_network`` for a team whose agents differ in any of them (a mixed team)."""
    signatures = []
    for i, agent in enumerate(env.possible_agents):
        layout = env.observation_layout(agent)
        arm = env.scenario.arms[i]
        signatures.append({"robot": f"{Path(arm.urdf).name}:{arm.ee_link}", "n_joints": layout.n_joints,
                           "dim": layout.dim, "formation": layout.formation_kind,
                           "manoeuvre": bool(layout.reference_size)})
    if any(signature != signatures[0] for signature in signatures):
        raise ValueError(f"policy_network: 'set' shares one network over agents of one robot and layout; scenario "
                         f"{env.scenario.name} mixes {sorted({s['robot'] for s in signatures})}")
    return signatures[0]


def check_serves(trained: Mapping[str, Any], env: Any) -> None:
    """``ValueError`` naming the field where ``env``'s team differs from the ``trained`` signature
    (:func:`team_signature`): the set policy cannot act for it."""
    try:
        team = team_signature(env)
    except ValueError as error:
        raise ValueError(f"policy: {str(error).partition(': ')[2]}") from None
    for field in ("robot", "n_joints", "dim", "formation", "manoeuvre"):
        if team[field] != trained.get(field):
            raise ValueError(f"policy: {field}: the run's set policy was trained with {field} {trained.get(field)!r}; "
                             f"scenario {env.scenario.name} has {team[field]!r}: it cannot act for this team")


# ------------------------------------------------------------------------------------------ normalization
def expanded_statistics(layout: SlotLayout, slot_mean: np.ndarray, slot_var: np.ndarray, own_mean: np.ndarray,
                        own_var: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-entry mean and variance of a whole observation of ``layout`` from the pooled slot and own
    statistics: every slot gets the slot statistics, its mask mean 0 and variance :data:`MASK_VARIANCE`."""
    slot_mean, slot_var = np.array(slot_mean, dtype=np.float64), np.array(slot_var, dtype=np.float64)
    slot_mean[0], slot_var[0] = 0.0, MASK_VARIANCE
    mean = np.concatenate([np.tile(slot_mean, layout.n_slots), np.asarray(own_mean, dtype=np.float64)])
    var = np.concatenate([np.tile(slot_var, layout.n_slots), np.asarray(own_var, dtype=np.float64)])
    return mean, var


def pooled_statistics(layout: SlotLayout, mean: np.ndarray, var: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The inverse of :func:`expanded_statistics`: the slot and own statistics of whole-observation ones (every
    slot holds the same; the first slot's are read). ``ValueError`` if the vectors do not have the layout's size."""
    mean, var = np.asarray(mean, dtype=np.float64), np.asarray(var, dtype=np.float64)
    if mean.shape != (layout.size,) or var.shape != (layout.size,):
        raise ValueError(f"obs_normalizer: expected mean and var of {layout.size} entries ({layout}), got "
                         f"{mean.shape} and {var.shape}")
    block = layout.n_slots * layout.slot_size
    return mean[:layout.slot_size], var[:layout.slot_size], mean[block:], var[block:]


def pooled_running_statistics(layout: SlotLayout) -> Any:
    """A :class:`PooledRunningMeanStd` for ``layout`` (the SB3 backend puts it into ``VecNormalize``)."""
    return _pooled_class()(layout)


@functools.lru_cache(maxsize=None)
def _pooled_class() -> type:
    from stable_baselines3.common.running_mean_std import RunningMeanStd

    class PooledRunningMeanStd(RunningMeanStd):
        """``VecNormalize``'s observation statistics, pooled (module docstring): ``mean`` and ``var`` are the
        whole observation's (expanded), ``update`` learns the slot statistics from real slots only."""

        def __init__(self, layout: SlotLayout, epsilon: float = 1e-4):  # noqa: D107 (no super: own storage)
            self.layout = layout
            self.slot = RunningMeanStd(epsilon, shape=(layout.slot_size,))
            self.own = RunningMeanStd(epsilon, shape=(layout.own_size,))

        def update(self, observations: np.ndarray) -> None:
            slots, own = self.layout.split(np.asarray(observations, dtype=np.float64))
            real = slots[..., 0] > 0.5
            if real.any():
                self.slot.update(slots[real])
            self.own.update(own.reshape(-1, self.layout.own_size))

        def _expanded(self) -> tuple[np.ndarray, np.ndarray]:
            return expanded_statistics(self.layout, self.slot.mean, self.slot.var, self.own.mean, self.own.var)

        @property
        def mean(self) -> np.ndarray:
            return self._expanded()[0]

        @mean.setter
        def mean(self, value: np.ndarray) -> None:
            self.slot.mean, _, self.own.mean, _ = pooled_statistics(self.layout, value, np.ones(self.layout.size))

        @property
        def var(self) -> np.ndarray:
            return self._expanded()[1]

        @var.setter
        def var(self, value: np.ndarray) -> None:
            _, self.slot.var, _, self.own.var = pooled_statistics(self.layout, np.zeros(self.layout.size), value)

        @property
        def count(self) -> float:
            return float(self.own.count)

        @count.setter
        def count(self, value: float) -> None:
            self.slot.count = self.own.count = float(value)

    return PooledRunningMeanStd


# ------------------------------------------------------------------------------------------ the network
#: How a set network pools its encoded slots: their mean, sum or element-wise max, over the real slots only.
POOLINGS = ("mean", "sum", "max")


def masked_pool(encoded: Any, real: Any, pooling: str) -> Any:
    """Encoded slots (..., D, h) pooled over the real ones (``real`` (..., D, 1) bool: mask > 0.5) by ``pooling``
    (:data:`POOLINGS`; a max over no real slot is 0): numpy arrays or torch tensors alike, the one rule of the
    SB3 set network, BenchMARL's set actor and their numpy forms."""
    if isinstance(encoded, np.ndarray):
        if pooling == "max":
            return np.where(real.any(axis=-2), np.where(real, encoded, -np.inf).max(axis=-2), 0.0)
        pooled = np.where(real, encoded, 0.0).sum(axis=-2)
        return pooled / np.maximum(real.sum(axis=-2), 1) if pooling == "mean" else pooled
    import torch

    if pooling == "max":
        peak = torch.where(real, encoded, torch.full_like(encoded, -torch.inf)).max(dim=-2).values
        return torch.where(real.any(dim=-2), peak, torch.zeros_like(peak))
    pooled = torch.where(real, encoded, torch.zeros_like(encoded)).sum(dim=-2)
    return pooled / real.sum(dim=-2).clamp(min=1) if pooling == "mean" else pooled


def sb3_policy_kwargs(plain: Mapping[str, Any]) -> dict[str, Any]:
    """SB3 ``policy_kwargs`` from the plain ones a run saves (``net_arch``, ``log_std_init``, ``use_sde`` with gSDE
    and, for the set network, ``set_network``: the slot layout and the team signature)."""
    kwargs = {key: plain[key] for key in ("net_arch", "log_std_init", "use_sde") if key in plain}
    if "set_network" in plain:
        layout = plain["set_network"]["layout"]
        kwargs["features_extractor_class"] = set_extractor_class()
        kwargs["features_extractor_kwargs"] = {"n_slots": int(layout["n_slots"]), "slot_size": int(layout["slot_size"]),
                                               "own_size": int(layout["own_size"])}
    return kwargs


@functools.lru_cache(maxsize=None)
def set_extractor_class() -> type:
    """The SB3 features extractor of the set network (module docstring), built on first use (torch)."""
    import torch
    from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

    class SlotSetExtractor(BaseFeaturesExtractor):
        """phi on every slot, masked mean and max pooling, the own-state encoder; ``3 x hidden`` features."""

        def __init__(self, observation_space: Any, n_slots: int, slot_size: int, own_size: int,
                     hidden: int = SET_HIDDEN):
            super().__init__(observation_space, features_dim=3 * hidden)
            self.layout = SlotLayout(n_slots, slot_size, own_size)
            self.phi = torch.nn.Sequential(torch.nn.Linear(slot_size - 1, hidden), torch.nn.Tanh(),
                                           torch.nn.Linear(hidden, hidden), torch.nn.Tanh())
            self.own = torch.nn.Sequential(torch.nn.Linear(own_size, hidden), torch.nn.Tanh())

        def forward(self, observations: Any) -> Any:
            slots, own = self.layout.split(observations)
            real = (slots[..., 0] > 0.5).unsqueeze(-1)  # (B, D, 1)
            encoded = self.phi(slots[..., 1:])  # (B, D, hidden)
            return torch.cat([masked_pool(encoded, real, "mean"), masked_pool(encoded, real, "max"), self.own(own)],
                             dim=1)

    return SlotSetExtractor


def numpy_set_actor(policy: Any, layout: SlotLayout) -> Callable[[np.ndarray], np.ndarray]:
    """The set network's deterministic action (the Gaussian's mean) as numpy products for observations of
    ``layout`` (any slot count), one row (size,) or a stack (k, size), each row of a stack bit for bit its
    own call (stacked matrix products)."""
    extractor = policy.features_extractor
    phi, own, head = (numpy_layers(layers) for layers in (extractor.phi, extractor.own,
                                                          [*policy.mlp_extractor.policy_net, policy.action_net]))
    if phi is None or own is None or head is None:
        raise ValueError("policy: the set network's numpy actor needs Linear and Tanh layers only")

    def predict(observation: np.ndarray) -> np.ndarray:
        rows = np.asarray(observation, dtype=np.float64)
        single = rows.ndim == 1
        rows = rows[None] if single else rows
        slots, own_state = layout.split(rows)
        real = slots[..., :1] > 0.5  # (k, D, 1)
        encoded = apply_numpy_layers(phi, slots[..., None, 1:])[..., 0, :]  # (k, D, 1, s) @ (s, h): row by row exactly
        features = np.concatenate([masked_pool(encoded, real, "mean"), masked_pool(encoded, real, "max"),
                                   apply_numpy_layers(own, own_state[:, None, :])[:, 0, :]], axis=1)
        actions = apply_numpy_layers(head, features[:, None, :])[:, 0, :]
        return actions[0] if single else actions

    predict.stacks = True  # LearnedPolicy.stacked: one call for a stack of rows
    return predict
