"""Episode metrics: the one definition of success and settling, and the one episode loop.

Used by ``ee_formation_env.baselines.evaluate``, ``train.py`` and every study (``studies.reproduce``,
``studies.robustness``, ``studies.random_scenarios``).

A policy here is anything with ``reset()`` and ``__call__(observation) -> action`` (normalized torques),
one per agent. :func:`run_episode` rolls one seeded episode and returns :class:`EpisodeMetrics`; its
success and settling time come from :func:`settle`: the formation error (RMS over edges of ``|e_k|``)
below :func:`formation_tolerance` from the settling time to the end of the episode, held at least
:data:`DEFAULT_HOLD_SECONDS`, with no physics fault.

Precision is judged in metres of edge length (:func:`edge_length_errors`: ``| |z_k| - d_k |`` for distance
formations, ``|z_k - z*_k|`` for displacement ones): the time to the :data:`PRECISION_TOLERANCE` band (every
edge within 1 mm, by the same :func:`settle`), the steady-state error over the last
:data:`STEADY_STATE_SECONDS` (RMS and worst edge) and the smoothness of the torques (mean ``|dtau| / dt``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Mapping, NamedTuple, Protocol, Sequence

import numpy as np

from ee_formation_env.baselines.reference.controllers import FormationController
from ee_formation_env.baselines.reference.team import PolicyTeam, RandomPolicy, ZeroPolicy
from ee_formation_env.env import FormationEnv
from ee_formation_env.vector import BatchedStep, VectorFormationEnv
from ee_formation_env.reward import DEFAULT_POSITION_TOLERANCE, edge_tolerances
from ee_formation_env.reward import edge_length_errors as reward_edge_length_errors


class Policy(Protocol):
    def reset(self) -> None: ...

    def __call__(self, observation: np.ndarray) -> np.ndarray: ...


DEFAULT_HOLD_SECONDS = 1.0  # s: the formation must be held at least this long before the episode ends
PRECISION_TOLERANCE = 1e-3  # m: the precision band: every edge's length error below it (settling_time_1mm)
STEADY_STATE_SECONDS = 1.0  # s: the steady-state errors are taken over the episode's last this many seconds


def edge_length_errors(formation: Any, edge_errors: np.ndarray) -> np.ndarray:
    """Each edge's length error in metres from its edge errors ``e_k`` (..., E) m^2 or (..., E, dim) m of a
    :class:`~ee_formation_env.formation.Formation` (or anything with a ``formation``): ``| |z_k| - d_k |`` for
    distance formations, ``|z_k - z*_k|`` for displacement ones (:func:`ee_formation_env.reward.edge_length_errors`).
    (..., E)."""
    formation = getattr(formation, "formation", formation)
    return reward_edge_length_errors(formation.kind, np.linalg.norm(formation.desired_vectors, axis=1), edge_errors)


def settle(errors: Sequence[float] | np.ndarray, tolerance: float, dt: float,
           hold_seconds: float = DEFAULT_HOLD_SECONDS, faulted: bool = False) -> tuple[bool, float]:
    """Success and settling time of an episode: the one definition (every study and ``run_episode`` use it).

    ``errors``: the formation error after each control step (formation units: m^2 for distance formations,
    m for displacement ones), sample ``i`` at the end of step ``i + 1``; ``tolerance``: the threshold in the
    same units (:func:`formation_tolerance`); ``dt``: the control step (s); ``hold_seconds`` (s);
    ``faulted``: the episode had a physics fault.

    The settling index is one past the last sample not below ``tolerance`` (a NaN counts as not below), and
    the settling time (s) is that index times ``dt``: the time after which the error stays below the
    tolerance to the end. It is NaN if the error never settles (its last sample is not below) or the
    episode faulted. Success: settled, and the error was held below for at least ``hold_seconds``
    (``(len(errors) - index) * dt``). Returns ``(success, settling_time)``.
    """
    series = np.asarray(errors, dtype=np.float64)
    above = np.flatnonzero(~(series < tolerance))
    settle_index = 0 if len(above) == 0 else int(above[-1]) + 1
    settled = settle_index < len(series) and not faulted
    settling_time = settle_index * dt if settled else math.nan
    held = (len(series) - settle_index) * dt if settled else 0.0
    return bool(settled and held >= hold_seconds), float(settling_time)


class Step(NamedTuple):
    """One env step as :func:`run_episode` saw it (handed to its ``on_transition`` hook)."""

    index: int  # 1 for the first step after the reset
    actions: Mapping[str, np.ndarray]  # what the policies returned (normalized, before the env's clipping)
    observations: Mapping[str, np.ndarray]  # after the step
    rewards: Mapping[str, float]
    terminations: Mapping[str, bool]
    truncations: Mapping[str, bool]
    infos: Mapping[str, Mapping[str, Any]]


def formation_tolerance(formation: Any, position_tolerance: float = DEFAULT_POSITION_TOLERANCE) -> float:
    """Formation-error threshold (formation units) equivalent to an edge accuracy ``position_tolerance`` (m), of
    a :class:`~ee_formation_env.formation.Formation` (or of anything with a ``formation``: an env, a task).

    The formation error is the RMS of ``|e_k|``; the threshold is the RMS of the per-edge tolerances of the
    reward (:func:`ee_formation_env.reward.edge_tolerances`): ``2 rms(d*) delta`` (m^2) for distance
    formations (``e = |z|^2 - d^2 ~ 2 d delta``), ``delta`` (m) for displacement formations. So every edge
    within its tolerance (the reward's in-tolerance term on every agent) implies success's threshold.
    """
    formation = getattr(formation, "formation", formation)
    lengths = np.linalg.norm(formation.desired_vectors, axis=1)
    return float(np.sqrt(np.mean(edge_tolerances(formation.kind, lengths, position_tolerance) ** 2)))


@dataclass
class EpisodeMetrics:
    """What one episode achieved. Units: formation units (m^2 distance, m displacement), s, N m."""

    success: bool  # :func:`settle`: error below tolerance from settling_time to the end, for >= hold_seconds
    final_formation_error: float
    settling_time: float  # s, :func:`settle`: time after which the error stays below tolerance; nan if never
    control_energy: float  # sum over agents of the integral of |tau|^2 dt, N^2 m^2 s
    peak_torque: float  # N m, over all joints and steps
    saturation_fraction: float  # fraction of (step, joint) action entries clipped at the torque limit
    min_singularity_margin: float  # m, smallest Jacobian singular value seen
    contact_steps: int  # env steps with any contact between arms
    centroid_drift: float  # m, displacement of the end-effectors' centroid from start to end
    mean_return: float  # mean over agents of the summed reward
    sim_time: float  # s
    physics_fault: str = ""  # "" or why the env ended the episode (its physics_fault_reason)
    # Precision and effort (module docstring): every edge's length error in metres, the torques' rate of change.
    success_1mm: bool = False  # :func:`settle` of the worst edge's length error in the PRECISION_TOLERANCE band
    settling_time_1mm: float = math.nan  # s, time after which every edge stays within 1 mm; nan if never
    steady_rms_edge_error: float = math.nan  # m, RMS over edges and steps of the last STEADY_STATE_SECONDS
    steady_worst_edge_error: float = math.nan  # m, largest edge length error over the last STEADY_STATE_SECONDS
    torque_rate: float = math.nan  # N m/s, mean over steps (from the second) and joints of |tau_t - tau_t-1| / dt
    trajectory: dict[str, np.ndarray] | None = field(default=None, repr=False)

    def as_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data.pop("trajectory")
        return data


def run_episode(env: FormationEnv, policies: Mapping[str, Policy], seed: int,
                position_tolerance: float = DEFAULT_POSITION_TOLERANCE, hold_seconds: float = DEFAULT_HOLD_SECONDS,
                record: bool = False, on_step: Callable[[FormationEnv], None] | None = None,
                on_reset: Callable[[FormationEnv], None] | None = None,
                on_transition: Callable[[FormationEnv, Step], bool | None] | None = None) -> EpisodeMetrics:
    """Roll one episode of the parallel env ``env`` from ``reset(seed=seed)`` to its end with one policy per
    agent: the episode loop of :func:`run_episodes` on the env's one copy (``env.batch``).

    ``record=True`` keeps time series (``t``, ``formation_error``, ``edge_errors`` per edge, ``ee`` world
    positions, ``q``, ``dq``, ``torque``) in ``metrics.trajectory``; ``on_step(env)`` is called after
    each step (e.g. to log a controller's internal state), ``on_reset(env)`` once after the reset.
    ``on_transition(env, step)`` is called after each step too (after ``on_step``) with the :class:`Step`
    (actions, observations, rewards, terminations, truncations, infos); a true return value stops the
    episode there (the metrics then cover the steps run; success still needs the hold). Success and
    settling time: :func:`settle` on the formation error after each step.
    """
    if not isinstance(env, FormationEnv):
        raise TypeError(f"env: expected the parallel env (ee_formation_env.parallel_env), got {type(env).__name__}; "
                        "a wrapper's own step would be bypassed")
    hooks = _EpisodeHooks(env, record, on_step, on_reset, on_transition)
    return _run_round(env.batch, _BatchedTeams(env.batch, [policies]), [seed], position_tolerance, hold_seconds,
                      hooks)[0]


class _EpisodeHooks:
    """What :func:`run_episode` adds to the loop for its one copy: the callers' hooks and the recorded series."""

    def __init__(self, env: FormationEnv, record: bool, on_step: Callable | None, on_reset: Callable | None,
                 on_transition: Callable | None):
        self.env, self.record = env, record
        self.on_step, self.on_reset, self.on_transition = on_step, on_reset, on_transition
        self.series: dict[str, list] = {key: [] for key in ("t", "formation_error", "edge_errors", "ee", "q", "dq",
                                                           "torque")}

    def after_reset(self, infos: Mapping[str, np.ndarray]) -> None:
        if self.on_reset is not None:
            self.on_reset(self.env)
        if self.record:
            self._record(0.0, infos["formation_error"][0], np.zeros(self.env.batch.n_joints))

    def after_step(self, index: int, actions: np.ndarray, result: BatchedStep) -> bool:
        """Record, call the hooks; True when ``on_transition`` stops the episode."""
        infos = result.infos
        if self.record:
            self._record(float(infos["sim_time"][0]), infos["formation_error"][0], infos["applied_torque"][0])
        if self.on_step is not None:
            self.on_step(self.env)
        if self.on_transition is None:
            return False
        env = self.env
        agents = env.possible_agents
        action_dict = {agent: actions[0, joints] for agent, joints in zip(agents, env.batch.joint_slices)}
        ended, truncated = bool(result.terminations[0]), bool(result.truncations[0])
        step = Step(index, action_dict, env.agent_observations(result.observations),
                    dict(zip(agents, result.rewards[0].tolist())), dict.fromkeys(agents, ended),
                    dict.fromkeys(agents, truncated), env.agent_infos())
        return bool(self.on_transition(env, step))

    def _record(self, t: float, formation_error: float, torque: np.ndarray) -> None:
        env, series = self.env, self.series
        series["t"].append(t)
        series["formation_error"].append(float(formation_error))
        series["edge_errors"].append(env.edge_errors())
        series["ee"].append(env.end_effector_positions())
        series["q"].append(env.batch.joint_positions()[0])
        series["dq"].append(env.batch.joint_velocities()[0])
        series["torque"].append(np.array(torque))

    def trajectory(self) -> dict[str, np.ndarray] | None:
        return {key: np.asarray(values) for key, values in self.series.items()} if self.record else None


SUMMARY_FIELDS = ("final_formation_error", "settling_time", "settling_time_1mm", "steady_rms_edge_error",
                  "steady_worst_edge_error", "control_energy", "torque_rate", "peak_torque", "saturation_fraction",
                  "min_singularity_margin", "contact_steps", "centroid_drift", "mean_return")
#: Fields averaged over the episodes that reached them only (nan elsewhere): settling times.
_OVER_SUCCESSES = ("settling_time", "settling_time_1mm")


def summarize(episodes: Sequence[EpisodeMetrics]) -> dict[str, Any]:
    """Success rate and the mean / std of every metric over episodes (settling time over successes only)."""
    reasons: dict[str, int] = {}
    for episode in episodes:
        if episode.physics_fault:
            reasons[episode.physics_fault] = reasons.get(episode.physics_fault, 0) + 1
    summary: dict[str, Any] = {"episodes": len(episodes),
                               "success_rate": float(np.mean([e.success for e in episodes])),
                               "success_rate_1mm": float(np.mean([e.success_1mm for e in episodes])),
                               "physics_faults": int(sum(reasons.values())),
                               "physics_fault_reasons": reasons}
    for name in SUMMARY_FIELDS:
        values = np.array([getattr(e, name) for e in episodes], dtype=np.float64)
        if name in _OVER_SUCCESSES:
            values = values[np.isfinite(values)]
        summary[name] = float(values.mean()) if len(values) else math.nan
        summary[f"{name}_std"] = float(values.std()) if len(values) else math.nan
    summary["min_singularity_margin"] = float(min(e.min_singularity_margin for e in episodes))  # worst case
    summary["steady_worst_edge_error_max"] = float(max(e.steady_worst_edge_error for e in episodes))  # worst case
    return summary


# The tables of the summaries (columns, markdown, fault notes) live in metric_tables; read through this module too.
from ee_formation_env.baselines.metric_tables import (METRIC_COLUMNS, MetricColumn, fault_kind,  # noqa: E402,F401
                                                      fault_kinds, fault_notes, format_table, metric_definitions)


# ------------------------------------------------------------------------------------------ batched episodes
class EvaluationVectorEnv(VectorFormationEnv):
    """The batched env (:class:`ee_formation_env.vector.VectorFormationEnv`) as :func:`run_episodes` steps it:
    the same copies, plus ``ended_end_effectors`` (K, N, 3) and ``ended_edge_errors`` (K, E) or (K, E, dim): each
    copy's end-effector positions and edge errors just before its last autoreset (SAME_STEP autoreset replaces
    an ended copy's state at once, and the centroid drift and the precision metrics need its final one)."""

    def __init__(self, scenario: Any, num_envs: int = 1, **overrides: Any):
        super().__init__(scenario, num_envs=num_envs, **overrides)
        self.ended_end_effectors = np.zeros((self.num_envs, self.task.n_agents, 3))
        self.ended_edge_errors: np.ndarray | None = None

    def _reset_copies(self, rows: np.ndarray) -> None:
        if self._measurement is not None:
            self.ended_end_effectors[rows] = self._measurement.ee_world[rows]
            if self.ended_edge_errors is None:
                self.ended_edge_errors = np.zeros_like(self._measurement.edge_errors)
            self.ended_edge_errors[rows] = self._measurement.edge_errors[rows]
        super()._reset_copies(rows)


def stack_policies(policies: Sequence[Policy]) -> Callable[[np.ndarray], np.ndarray]:
    """One callable for a stack of agents' policies: ``(k, size)`` observations (row r is policy r's) ->
    ``(k, n)`` actions, each row exactly (bit for bit) the action policy r returns alone.

    A policy class may batch its own kind with a ``stacked(policies)`` classmethod (the learned policies do);
    reference controllers are batched by :class:`PolicyTeam` (one :class:`ControllerBatch` per law and
    chain, across agents and copies); anything else is called row by row. A mixed stack is split by kind.
    """
    policies = list(policies)
    groups: dict[Any, list[int]] = {}
    for row, policy in enumerate(policies):
        kind = type(policy)
        key = kind if getattr(kind, "stacked", None) is not None else (
            "team" if isinstance(policy, (FormationController, ZeroPolicy, RandomPolicy)) else "rows")
        groups.setdefault(key, []).append(row)
    callers = [(np.array(rows), _stack_of_one_kind(key, [policies[r] for r in rows])) for key, rows in groups.items()]
    if len(callers) == 1:
        return callers[0][1]

    def act(observations: np.ndarray) -> np.ndarray:
        parts = [(rows, np.asarray(caller(observations[rows]))) for rows, caller in callers]
        actions = np.empty((len(observations), parts[0][1].shape[1]), dtype=np.result_type(*(p for _, p in parts)))
        for rows, part in parts:
            actions[rows] = part
        return actions

    return act


def _stack_of_one_kind(key: Any, policies: list) -> Callable[[np.ndarray], np.ndarray]:
    if key == "team":
        return PolicyTeam(dict(enumerate(policies))).act_on_stack  # float32 actions, as each policy's
    if key == "rows":
        return lambda observations: np.stack([np.asarray(policy(row)) for policy, row in zip(policies, observations)])
    return key.stacked(policies)


class _BatchedTeams:
    """The policies of K copies of one team, called on the batched env's observations (K, O) -> actions (K, T):
    all K x N agents as one stack when every agent has the same observation size and joints, else one stack
    per agent."""

    def __init__(self, env: VectorFormationEnv, teams: Sequence[Mapping[str, Policy]]):
        agents = list(env.possible_agents)
        self.teams, self.K, self.N = list(teams), len(teams), len(agents)
        slices = env.observation_slices
        sizes = {part.stop - part.start for part in slices}
        contiguous = all(a.stop == b.start for a, b in zip(slices, slices[1:])) and slices[0].start == 0
        if len(sizes) == 1 and env.uniform_joints is not None and contiguous:
            self.size, self.n = sizes.pop(), env.uniform_joints
            self.whole = stack_policies([team[agent] for team in self.teams for agent in agents])
            self.parts = None
        else:
            self.whole = None
            self.parts = [(part, stack_policies([team[agent] for team in self.teams])) for agent, part in
                          zip(agents, slices)]

    def reset(self) -> None:
        for team in self.teams:
            for policy in team.values():
                policy.reset()

    def __call__(self, observations: np.ndarray) -> np.ndarray:
        if self.whole is not None:
            actions = self.whole(observations[:, :self.size * self.N].reshape(self.K * self.N, self.size))
            return np.asarray(actions).reshape(self.K, self.N * self.n)
        return np.concatenate([np.asarray(act(observations[:, part])) for part, act in self.parts], axis=1)


PolicySource = Any  # a policy name (baselines.POLICIES) or a callable env -> {agent: policy}, called once per copy

DEFAULT_EVALUATION_COPIES = 16  # copies of the scenario stepped together by run_episodes (~30 MB each)


def evaluation_env(scenario: Any, num_envs: int, **overrides: Any) -> EvaluationVectorEnv:
    """The batched env :func:`run_episodes` steps (``num_envs`` copies, scenario ``overrides``)."""
    return EvaluationVectorEnv(scenario, num_envs=num_envs, **overrides)


def run_episodes(scenario: Any, policy: PolicySource, seeds: Sequence[int],
                 position_tolerance: float = DEFAULT_POSITION_TOLERANCE, hold_seconds: float = DEFAULT_HOLD_SECONDS,
                 overrides: Mapping[str, Any] | None = None, policy_kwargs: Mapping[str, Any] | None = None,
                 num_envs: int | None = None, env: EvaluationVectorEnv | None = None,
                 stop_on_precision_hold: bool = False) -> list[EpisodeMetrics]:
    """The episodes ``reset(seed=s)`` for every ``s`` of ``seeds``, run together on the batched env: the
    :class:`EpisodeMetrics` of each, in the order of ``seeds``, equal field for field to what
    :func:`run_episode` gives for that seed (``tests/baselines/test_metrics_batched.py``).

    ``policy``: a reference policy's name (built by ``baselines.make_policies(name, env, **policy_kwargs)``)
    or a callable ``env -> {agent: policy}``, called once per copy (each copy's policies keep their own
    internal state; stateless parts may be shared). ``scenario`` and ``overrides`` as for
    :func:`ee_formation_env.parallel_env`; ``env``: a batched env from :func:`evaluation_env` to reuse
    (then ``scenario`` and ``overrides`` are ignored); else one of ``num_envs`` copies (default: one per seed,
    at most :data:`DEFAULT_EVALUATION_COPIES`) is built and closed for each round of at most that many seeds,
so that every episode starts from a fresh world (a world that ran another contact-rich episode need not
replay it bit for bit).

    Each copy runs its episode to its end (termination or truncation); the SAME_STEP autoreset then starts
    it again, and what it does afterwards is ignored, while the other copies finish theirs. Recording,
    rendering and the hooks of :func:`run_episode` are not available here (use :func:`run_episode`).

    ``stop_on_precision_hold``: a copy's episode ends once every edge has stayed within
    :data:`PRECISION_TOLERANCE` for ``hold_seconds`` (the gain tuner's episodes: nothing after that changes its
    time to the band); the metrics then cover the steps run.
    """
    seeds = [int(seed) for seed in seeds]
    unique = sorted(set(seeds))
    if not unique:
        return []
    if isinstance(policy, str):
        from ee_formation_env.baselines import make_policies

        name, kwargs = policy, dict(policy_kwargs or {})
        policy = lambda copy_env: make_policies(name, copy_env, **kwargs)  # noqa: E731
    results: dict[int, EpisodeMetrics] = {}
    count = env.num_envs if env is not None else num_envs or min(len(unique), DEFAULT_EVALUATION_COPIES)
    for start in range(0, len(unique), count):
        chunk = unique[start:start + count]
        # Without a given env, each round gets a fresh one: every episode then starts from a fresh world.
        round_env = env if env is not None else evaluation_env(scenario, count, **dict(overrides or {}))
        try:
            teams = _BatchedTeams(round_env, [policy(round_env.copy_view(k)) for k in range(round_env.num_envs)])
            results.update(zip(chunk, _run_round(round_env, teams, chunk, position_tolerance, hold_seconds,
                                                 stop_on_precision_hold=stop_on_precision_hold)))
        finally:
            if env is None:
                round_env.close()
    return [results[seed] for seed in seeds]


def run_policies(scenario: Any, policies: Mapping[str, PolicySource], seeds: Sequence[int],
                 position_tolerance: float = DEFAULT_POSITION_TOLERANCE, hold_seconds: float = DEFAULT_HOLD_SECONDS,
                 overrides: Mapping[str, Any] | None = None, max_copies: int = 64,
                 stop_on_precision_hold: bool = False, on_steps: Callable[[int], None] | None = None
                 ) -> dict[str, list[EpisodeMetrics]]:
    """:func:`run_episodes` of several policies on the same ``seeds``, all (policy, seed) episodes as the copies
    of one batched env (``len(policies) x len(seeds)`` copies, in rounds of at most ``max_copies``; each copy
    runs one episode from a fresh world): ``{name: [metrics per seed]}``. ``stop_on_precision_hold``: as for
    :func:`run_episodes`. ``on_steps(n)``: after each step of the batched env, with the number of episodes that
    took it (a progress bar's feed)."""
    seeds = [int(seed) for seed in seeds]
    unique = sorted(set(seeds))
    jobs = [(name, seed) for name in policies for seed in unique]
    results: dict[tuple[str, int], EpisodeMetrics] = {}
    per_round = max(1, max_copies // len(unique)) * len(unique) if len(unique) <= max_copies else max_copies
    for start in range(0, len(jobs), per_round):
        chunk = jobs[start:start + per_round]
        with evaluation_env(scenario, len(chunk), **dict(overrides or {})) as env:
            sources = {name: _policy_source(policies[name]) for name in dict.fromkeys(name for name, _ in chunk)}
            teams = _BatchedTeams(env, [sources[name](env.copy_view(k)) for k, (name, _) in enumerate(chunk)])
            copy_seeds = [seed for _, seed in chunk]
            results.update(zip(chunk, _run_round(env, teams, copy_seeds, position_tolerance, hold_seconds,
                                                 stop_on_precision_hold=stop_on_precision_hold, on_steps=on_steps)))
    return {name: [results[(name, seed)] for seed in seeds] for name in policies}


def _policy_source(policy: PolicySource) -> Callable[[Any], Mapping[str, Policy]]:
    if isinstance(policy, str):
        from ee_formation_env.baselines import make_policies

        return lambda copy_env: make_policies(policy, copy_env)
    return policy


def _run_round(env: VectorFormationEnv, teams: _BatchedTeams, seeds: Sequence[int], position_tolerance: float,
               hold_seconds: float, hooks: _EpisodeHooks | None = None, stop_on_precision_hold: bool = False,
               on_steps: Callable[[int], None] | None = None) -> list[EpisodeMetrics]:
    """The episode loop: one episode per seed (at most K of them) on the copies 0.. of ``env``, copy k reset with
    ``seeds[k]``; the copies beyond them run too (seeded after the last) and are ignored. ``env`` autoresets
    (an :class:`EvaluationVectorEnv`, which keeps each ended copy's final end-effectors) or, with one copy, does
    not (a parallel env's ``batch``, with :func:`run_episode`'s ``hooks``)."""
    K, N = env.num_envs, env.task.n_agents
    wanted = len(seeds)
    copy_seeds = list(seeds) + [max(seeds) + 1 + j for j in range(K - wanted)]
    result = env.reset_arrays(seed=copy_seeds)
    margins = result.infos["singularity_margin"].copy()  # (K, N) at each copy's reset
    observations = result.observations
    teams.reset()
    if hooks is not None:
        hooks.after_reset(result.infos)
    dt = env.scenario.control_dt
    tolerances = [formation_tolerance(env.tasks[k], position_tolerance) for k in range(wanted)]
    formations = [env.tasks[k].formation for k in range(wanted)]  # this episode's draws, before any autoreset
    hold_steps = int(math.ceil(hold_seconds / dt - 1e-9))
    start = env.end_effector_positions()
    start_centroids = [start[k].mean(axis=0) for k in range(wanted)]
    joint_slices = env.joint_slices
    uniform = env.uniform_joints
    T = env.n_joints
    active = np.zeros(K, dtype=bool)
    active[:wanted] = True
    errors: list[list[float]] = [[] for _ in range(wanted)]
    length_errors: list[list[np.ndarray]] = [[] for _ in range(wanted)]  # (E,) m per step
    within_steps = np.zeros(K, dtype=np.int64)  # steps since every edge last left the precision band
    previous_torques: np.ndarray | None = None
    rate_sums = np.zeros(K)
    energy, peak = np.zeros(K), np.zeros(K)
    clipped, entries, contact_steps = np.zeros(K, dtype=np.int64), np.zeros(K, dtype=np.int64), np.zeros(K, dtype=np.int64)
    returns = np.zeros((K, N))
    min_margin = margins.min(axis=1)
    faults = [""] * wanted
    end_centroids: list[np.ndarray | None] = [None] * wanted
    steps = 0
    while active.any():
        actions = teams(observations)
        result = env.step_arrays(actions)
        observations, infos = result.observations, result.infos
        torques = infos["applied_torque"]  # (K, T)
        # Per agent |tau|^2 as run_episode's float(tau @ tau): a stacked matmul gives each row's dot bit for bit.
        if uniform is not None:
            split = torques.reshape(K, N, 1, uniform)
            squares = (split @ split.reshape(K, N, uniform, 1))[:, :, 0, 0]
        else:
            squares = np.stack([(torques[:, part][:, None, :] @ torques[:, part][:, :, None])[:, 0, 0]
                                for part in joint_slices], axis=1)
        step_energy = squares[:, 0]
        for i in range(1, N):
            step_energy = step_energy + squares[:, i]
        rows = np.flatnonzero(active)
        if on_steps is not None:
            on_steps(len(rows))
        energy[rows] += step_energy[rows] * dt
        peak[rows] = np.maximum(peak[rows], np.abs(torques[rows]).max(axis=1))
        clipped[rows] += np.count_nonzero(np.abs(np.asarray(actions, dtype=np.float64).reshape(K, T)[rows]) > 1.0,
                                          axis=1)
        entries[rows] += T
        contact_steps[rows] += (infos["contacts"][rows] > 0).any(axis=1)
        min_margin[rows] = np.minimum(min_margin[rows], infos["singularity_margin"][rows].min(axis=1))
        returns[rows] += result.rewards[rows]
        if previous_torques is not None:
            rate_sums[rows] += np.abs(torques[rows] - previous_torques[rows]).mean(axis=1) / dt
        previous_torques = torques
        formation_error = infos["formation_error"]
        fault_flags, reasons = infos["physics_fault"], infos["physics_fault_reason"]
        ended = result.terminations | result.truncations
        steps += 1
        if hooks is not None and hooks.after_step(steps, actions, result):
            ended = np.ones(K, dtype=bool)  # the one copy stops here
        edge_errors = env.edge_errors()
        if env.autoreset and ended[rows].any():  # an ended copy's measurement is its next episode's start
            done = rows[ended[rows]]
            edge_errors[done] = env.ended_edge_errors[done]
        for k in rows:
            errors[k].append(float(formation_error[k]))
            lengths = edge_length_errors(formations[k], edge_errors[k])
            length_errors[k].append(lengths)
            within_steps[k] = within_steps[k] + 1 if float(lengths.max()) < PRECISION_TOLERANCE else 0
            if fault_flags[k] and not faults[k]:
                faults[k] = str(reasons[k])
            if stop_on_precision_hold and within_steps[k] >= hold_steps and not ended[k]:
                ended[k] = True  # held long enough: the copy's episode ends here (its state is this step's)
                end_centroids[k] = env.end_effector_positions()[k].mean(axis=0)
                active[k] = False
                continue
            if ended[k]:
                final = env.ended_end_effectors[k] if env.autoreset else env.end_effector_positions()[k]
                end_centroids[k] = final.mean(axis=0)
                active[k] = False
    metrics = []
    steady_steps = max(1, int(round(STEADY_STATE_SECONDS / dt)))
    for k in range(wanted):
        series = np.asarray(errors[k])
        success, settling_time = settle(series, tolerances[k], dt, hold_seconds, faulted=bool(faults[k]))
        lengths = np.asarray(length_errors[k])  # (steps, E) m
        success_1mm, settling_time_1mm = settle(lengths.max(axis=1), PRECISION_TOLERANCE, dt, hold_seconds,
                                                faulted=bool(faults[k]))
        steady = lengths[-steady_steps:]
        metrics.append(EpisodeMetrics(
            success=success,
            final_formation_error=float(series[-1]),
            settling_time=settling_time,
            control_energy=float(energy[k]),
            peak_torque=float(peak[k]),
            saturation_fraction=int(clipped[k]) / max(int(entries[k]), 1),
            min_singularity_margin=float(min_margin[k]),
            contact_steps=int(contact_steps[k]),
            centroid_drift=float(np.linalg.norm(end_centroids[k] - start_centroids[k])),
            mean_return=float(np.mean(list(returns[k]))),
            sim_time=len(series) * dt,
            physics_fault=faults[k],
            success_1mm=success_1mm,
            settling_time_1mm=settling_time_1mm,
            steady_rms_edge_error=float(np.sqrt(np.mean(steady**2))),
            steady_worst_edge_error=float(steady.max()),
            torque_rate=float(rate_sums[k] / (len(series) - 1)) if len(series) > 1 else 0.0,
            trajectory=None if hooks is None else hooks.trajectory(),
        ))
    return metrics
