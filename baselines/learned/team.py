"""Mixed teams: one shared policy over arms of different robots, through padded spaces and a robot-kind input.

A team is *uniform* when every agent has the same observation and action space (bounds included): then
nothing here applies, and its agents see their own (featured) observations and act with their own joints.
Any other team is *mixed* (:meth:`TeamPadding.of_team`), and every agent gets the same spaces:

- observation: the agent's own observation, featured as the run's ``obs_features`` say, zero-padded to the
  team's largest featured size P, then a one-hot of its robot kind over the team's kinds (width P + kinds);
- action: A entries, A the team's largest joint count; agent i applies the first n_i (its own joints, in its
  action space's order) and ignores the others (they are neither applied nor penalized).

A robot kind is ``<robot>:<ee_link>`` (:func:`robot_kind`): the built-in robot's name, or the URDF's path
inside ``pybullet_data`` (else its file name), with the end-effector link; the kinds are sorted by that
name. Every per-agent rule (the mode's action rule, the features, the shaping) runs on each agent's own rows,
grouped by observation layout (:class:`PaddedTeamRows`). A run saves its :class:`TeamPadding` in its
``config.json`` (``team_padding``), and evaluation pads each agent as training did; an agent of a kind the run
never trained on, or whose sizes differ from its kind's in training, is refused before any episode
(:meth:`TeamPadding.agent_paddings`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import gymnasium
import numpy as np

from ee_formation_env.actions import numeric_action_array
from ee_formation_env.baselines.learned.features import FeatureRows, feature_size, feature_space

TEAM_PADDING_KEY = "team_padding"  # the run's config.json key


def robot_kind(arm: Any) -> str:
    """The robot kind of a scenario arm (module docstring): ``"pera_arm:ee_link"``,
    ``"kuka_iiwa/model.urdf:lbr_iiwa_link_7"``."""
    if arm.robot:
        return f"{arm.robot}:{arm.ee_link}"
    import pybullet_data

    path = Path(arm.urdf).resolve()
    try:
        name = path.relative_to(Path(pybullet_data.getDataPath()).resolve()).as_posix()
    except ValueError:
        name = path.name
    return f"{name}:{arm.ee_link}"


def agent_kinds(env: Any) -> dict[str, str]:
    """Agent -> the robot kind of its arm (``env.scenario.arms`` in agent order)."""
    return {agent: robot_kind(arm) for agent, arm in zip(env.possible_agents, env.scenario.arms)}


def uniform_team(env: Any) -> bool:
    """Whether every agent of ``env`` has the same observation and action space (module docstring)."""
    spaces = [(env.observation_space(agent), env.action_space(agent)) for agent in env.possible_agents]
    return all(space == spaces[0] for space in spaces)


@dataclass(frozen=True)
class AgentPadding:
    """How one agent's featured observation (``featured_size`` entries) and joints (``joints``) sit in the padded
    spaces: the one-hot entry ``observation_size + kind_index``, the width ``observation_size + kinds``."""

    featured_size: int
    joints: int
    kind_index: int
    observation_size: int
    width: int


class PaddingRows:
    """The padding of a stack of rows of one featured size and joint count (``paddings``, one per row): padded
    observations in, the rows' own joints out. Called with fewer rows R' than given, it pads the first R'."""

    def __init__(self, paddings: Sequence[AgentPadding]):
        sizes = {(padding.featured_size, padding.joints, padding.width) for padding in paddings}
        if len(sizes) != 1:
            raise ValueError(f"team_padding: rows of one stack must have one featured size and joint count, got "
                             f"{sorted(sizes)}")
        self.featured_size, self.joints, self.width = sizes.pop()
        self._columns = np.array([padding.observation_size + padding.kind_index for padding in paddings])

    def observations(self, featured: np.ndarray) -> np.ndarray:
        """(R', featured size) -> (R', width) float32: zero-padded, the one-hot set."""
        count = len(featured)
        out = np.zeros((count, self.width), dtype=np.float32)
        out[:, :self.featured_size] = featured
        out[np.arange(count), self._columns[:count]] = 1.0
        return out

    def actions(self, learned: np.ndarray) -> np.ndarray:
        """(R', A) -> (R', joints): each row's own joints."""
        return learned[:, :self.joints]


@dataclass(frozen=True)
class TeamPadding:
    """The padded spaces of a mixed team (module docstring): its robot ``kinds`` (sorted) and, per kind, the
    featured observation size and joint count (``kind_sizes``) the policy was trained with."""

    kinds: tuple[str, ...]
    kind_sizes: tuple[tuple[int, int], ...]  # per kind: (featured observation entries, joints)

    @property
    def observation_size(self) -> int:
        """P: the largest featured observation size (the one-hot follows)."""
        return max(size for size, _ in self.kind_sizes)

    @property
    def action_size(self) -> int:
        """A: the largest joint count."""
        return max(joints for _, joints in self.kind_sizes)

    @property
    def width(self) -> int:
        """The padded observation's entries: P + the number of kinds."""
        return self.observation_size + len(self.kinds)

    @classmethod
    def of_team(cls, env: Any, obs_features: str) -> "TeamPadding | None":
        """The padding of ``env``'s team, or None for a uniform team (module docstring). Two agents of one kind
        with different sizes are refused (``ValueError`` naming them)."""
        if uniform_team(env):
            return None
        sizes: dict[str, tuple[int, int]] = {}
        owners: dict[str, str] = {}
        for agent, kind in agent_kinds(env).items():
            size = _agent_sizes(env, agent, obs_features)
            if sizes.setdefault(kind, size) != size:
                raise ValueError(f"agents: {owners[kind]} and {agent} are both robot kind {kind} but have "
                                 f"{sizes[kind]} and {size} (featured observation entries, joints): one kind, one "
                                 "size, for a shared policy")
            owners.setdefault(kind, agent)
        kinds = tuple(sorted(sizes))
        return cls(kinds, tuple(sizes[kind] for kind in kinds))

    def agent_paddings(self, env: Any, obs_features: str) -> dict[str, AgentPadding]:
        """Agent -> its padding, for a team the policy can act for; else a one-line ``ValueError`` naming the first
        agent it cannot serve and why (a robot kind the run never trained on, or other sizes than its kind's)."""
        paddings = {}
        for agent, kind in agent_kinds(env).items():
            if kind not in self.kinds:
                raise ValueError(f"policy: {agent} of scenario {env.scenario.name} is robot kind {kind}, which the "
                                 f"run's policy never trained on (its kinds: {', '.join(self.kinds)}): it cannot act "
                                 "for this team")
            index = self.kinds.index(kind)
            featured, joints = _agent_sizes(env, agent, obs_features)
            if (featured, joints) != self.kind_sizes[index]:
                raise ValueError(f"policy: {agent} of scenario {env.scenario.name} ({kind}) has {featured} featured "
                                 f"observation entries and {joints} joints, the run's policy trained that kind with "
                                 f"{self.kind_sizes[index][0]} and {self.kind_sizes[index][1]}: it cannot act for "
                                 "this team")
            paddings[agent] = AgentPadding(featured, joints, index, self.observation_size, self.width)
        return paddings

    def check_fits(self, observation_size: int, action_size: int) -> None:
        """``ValueError`` naming ``team_padding`` unless a policy of these sizes is the padding's."""
        if (observation_size, action_size) != (self.width, self.action_size):
            raise ValueError(f"team_padding: the run's policy takes {observation_size} observation entries and gives "
                             f"{action_size} joint actions, its saved padding says {self.width} and "
                             f"{self.action_size}: restore the config.json the run wrote")

    def observation_space(self, env: Any, obs_features: str) -> gymnasium.spaces.Box:
        """Every agent's padded observation space: the agents' featured bounds padded with 0, their union, then
        the one-hot's [0, 1]."""
        lows, highs = [], []
        for agent in env.possible_agents:
            space = feature_space(env.observation_space(agent), env.observation_layout(agent), obs_features)
            pad = np.zeros(self.observation_size - space.shape[0], dtype=np.float32)
            lows.append(np.concatenate([space.low, pad]))
            highs.append(np.concatenate([space.high, pad]))
        ones = np.ones(len(self.kinds), dtype=np.float32)
        low = np.concatenate([np.min(lows, axis=0), 0 * ones]).astype(np.float32)
        high = np.concatenate([np.max(highs, axis=0), ones]).astype(np.float32)
        return gymnasium.spaces.Box(low, high, dtype=np.float32)

    def action_space(self) -> gymnasium.spaces.Box:
        return gymnasium.spaces.Box(-1.0, 1.0, (self.action_size,), np.float32)

    def to_dict(self) -> dict[str, Any]:
        """As a run's ``config.json`` saves it (:data:`TEAM_PADDING_KEY`)."""
        return {"kinds": list(self.kinds), "observation_size": self.observation_size, "action_size": self.action_size,
                "kind_sizes": {kind: {"observation": size, "joints": joints}
                               for kind, (size, joints) in zip(self.kinds, self.kind_sizes)}}

    @classmethod
    def from_saved(cls, config: Mapping[str, Any]) -> "TeamPadding | None":
        """The padding a run's configuration saved, or None (a uniform team's run); a malformed entry is a
        ``ValueError`` naming ``team_padding``."""
        data = config.get(TEAM_PADDING_KEY)
        if data is None:
            return None
        try:
            kinds = tuple(data["kinds"])
            sizes = tuple((int(data["kind_sizes"][kind]["observation"]), int(data["kind_sizes"][kind]["joints"]))
                          for kind in kinds)
            padding = cls(kinds, sizes)
            ok = (kinds and list(kinds) == sorted(set(kinds)) and all(isinstance(k, str) for k in kinds)
                  and all(size > 0 and joints > 0 for size, joints in sizes)
                  and (data["observation_size"], data["action_size"]) == (padding.observation_size,
                                                                          padding.action_size))
        except (KeyError, TypeError, ValueError):
            ok = False
        if not ok:
            raise ValueError(f"{TEAM_PADDING_KEY}: malformed ({str(data)[:200]}): restore the config.json the run "
                             "wrote")
        return padding


def _agent_sizes(env: Any, agent: str, obs_features: str) -> tuple[int, int]:
    """(featured observation entries, joints) of ``agent``."""
    featured = env.observation_space(agent).shape[0] + feature_size(env.observation_layout(agent), obs_features)
    return featured, env.action_space(agent).shape[0]


def layout_groups(env: Any, agents: Sequence[str]) -> list[tuple[Any, list[str]]]:
    """The agents grouped by observation layout (each group: one raw size and joint count), in first-seen order."""
    groups: dict[Any, list[str]] = {}
    for agent in agents:
        groups.setdefault(env.observation_layout(agent), []).append(agent)
    return list(groups.items())


def agent_rules(mode: Any, options: Any, copy_env: Any, joint_scales: Any) -> dict[str, Any]:
    """Agent -> the mode's action rule of its one row in ``copy_env``, the rules built per observation layout (a
    rule stacks rows of one joint count): for a uniform team, ``mode.action_rows`` of every agent, split."""
    rules = {}
    for _, agents in layout_groups(copy_env, list(copy_env.possible_agents)):
        rules.update(zip(agents, mode.action_rows(options, [copy_env], agents, joint_scales).split()))
    return rules


class PaddedTeamRows:
    """A mixed team's transforms over the K x N agent rows of a batched env (copy-major: row ``k * N + i``), for
    the training env: raw observations as zero-padded rows, the padded featured observations, the learned
    actions checked and sliced, and the mode's action rule per observation layout (each on its agents' rows).

    Called as an action rule (``rows(raw, learned)``) it returns the applied actions (K, T) (the batched env's
    flat joints) and the reward factors (K * N,) or None; ``reset(rows)`` resets the rows' rules.
    """

    def __init__(self, env: Any, padding: TeamPadding, options: Any, copies: Sequence[Any],
                 joint_scales: Mapping[str, np.ndarray] | None):
        agents = list(env.possible_agents)
        K, N = env.num_envs, len(agents)
        self.K, self.N, self.T = K, N, env.n_joints
        self.padding, self.width, self.action_size = padding, padding.width, padding.action_size
        paddings = padding.agent_paddings(env, options.obs_features)
        index = {agent: i for i, agent in enumerate(agents)}
        slices, joints = env.observation_slices, env.joint_slices
        self.raw_size = max(part.stop - part.start for part in slices)
        O = slices[-1].stop
        # Gathers (K, O) observations into zero-padded (K * N, raw_size) rows.
        source, target = [], []
        for k in range(K):
            for i, part in enumerate(slices):
                source.append(k * O + np.arange(part.start, part.stop))
                target.append((k * N + i) * self.raw_size + np.arange(part.stop - part.start))
        self._source, self._target = np.concatenate(source), np.concatenate(target)
        self.layout_rows, self._groups = [], []
        self._group_of, self._local = np.empty(K * N, dtype=np.intp), np.empty(K * N, dtype=np.intp)
        mode = options.training_mode
        for group, (layout, members) in enumerate(layout_groups(env, agents)):
            rows = np.array([k * N + index[agent] for k in range(K) for agent in members])
            self.layout_rows.append((layout, rows))
            self._group_of[rows], self._local[rows] = group, np.arange(len(rows))
            columns = np.array([k * self.T + np.arange(joints[index[agent]].start, joints[index[agent]].stop)
                                for k in range(K) for agent in members])  # (rows, n) into the flat (K * T)
            rule = mode.action_rows(options, copies, members, joint_scales)
            features = FeatureRows([layout] * len(rows), [options.obs_features] * len(rows))
            self._groups.append((layout, rows, columns, rule, features,
                                 PaddingRows([paddings[agents[row % N]] for row in rows])))

    def raw_rows(self, observations: np.ndarray) -> np.ndarray:
        """(C, O) observations of the first C copies -> (C * N, raw_size) rows, each zero-padded."""
        count = len(observations)
        out = np.zeros(count * self.N * self.raw_size, dtype=observations.dtype)
        keep = self._target < len(out)
        out[self._target[keep]] = observations.reshape(-1)[self._source[keep]]
        return out.reshape(count * self.N, self.raw_size)

    def featured(self, raw: np.ndarray) -> np.ndarray:
        """(C * N, raw_size) raw rows of the first C copies -> (C, N * width) padded featured observations."""
        out = np.empty((len(raw), self.width), dtype=np.float32)
        for layout, rows, _, _, features, padding in self._groups:
            rows = rows[rows < len(raw)]
            out[rows] = padding.observations(features(raw[rows, :layout.size]))
        return out.reshape(len(raw) // self.N, self.N * self.width)

    def checked_actions(self, actions: Any) -> np.ndarray:
        """The learned actions (K * N, A) float64 from (K * N, A) or (K, N, A); a ``ValueError`` starting
        ``actions:`` for bad ones."""
        K, N, A = self.K, self.N, self.action_size
        return numeric_action_array(actions, [(K * N, A), (K, N, A)], (K * N, A), rows_per_copy=N)

    def reset(self, rows: Sequence[int] | np.ndarray | None = None) -> None:
        for group, (_, _, _, rule, _, _) in enumerate(self._groups):
            if rows is None:
                rule.reset()
            else:
                rows = np.asarray(rows, dtype=np.intp)
                rule.reset(self._local[rows[self._group_of[rows] == group]])

    def __call__(self, raw: np.ndarray, learned: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        applied = np.zeros(self.K * self.T)
        factors = None
        for layout, rows, columns, rule, _, padding in self._groups:
            actions, part = rule(raw[rows, :layout.size], padding.actions(learned[rows]))
            applied[columns] = actions
            if part is not None:
                if factors is None:
                    factors = np.ones(self.K * self.N)
                factors[rows] = part
        return applied.reshape(self.K, self.T), factors


def refuse_mixed_team(env: Any, backend: str) -> None:
    """For a backend that cannot train a mixed team: close the training env ``env`` and raise a one-line
    ``ValueError`` naming ``backend`` if its team is mixed (``env.padding``)."""
    if env.padding is not None:
        env.close()
        raise ValueError(f"scenario: {backend} cannot train a mixed team yet ({env.scenario.name}: "
                         f"{', '.join(env.padding.kinds)}); train it with train.py --backend sb3")
