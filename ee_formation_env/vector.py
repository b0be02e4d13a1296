"""The batched env: K copies of one scenario stepped by one call (``ee_formation_env.vector_env``).

Quick use::

    import numpy as np
    import ee_formation_env

    env = ee_formation_env.vector_env("planar_square", num_envs=16)
    observations, infos = env.reset(seed=0)            # copy k is seeded with 0 + k
    actions = {agent: np.zeros((16, 2), np.float32) for agent in env.possible_agents}
    observations, rewards, terminations, truncations, infos = env.step(actions)
    observations["arm_0"].shape                         # (16, obs_dim), float32
    rewards["arm_0"].shape, terminations["arm_0"].shape  # (16,), (16,)

**Conventions** (Gymnasium's vector conventions for seeds, VMAS's for per-agent batches):

- ``reset(seed=s)`` seeds copy ``k`` with ``s + k`` (``reset(seed=[s_0, ..., s_K-1])``: copy k with ``s_k``,
  None for its own generator): copy ``k`` then reproduces
  ``parallel_env(scenario).reset(seed=s + k)`` step for step under the same actions, bit for bit
  (``tests/test_vector.py``). ``reset()`` without a seed continues every copy's own generator, as the single
  env's unseeded reset does.
- Observations: dict agent -> ``(K, obs_dim)`` float32. Actions: dict agent -> ``(K, act_dim)`` (numeric,
  finite; clipped to [-1, 1] as in the single env). Rewards: agent -> ``(K,)`` float64; terminations and
  truncations: agent -> ``(K,)`` bool (equal for every agent of a copy). Infos: agent -> dict of the single
  env's keys, each an array with a leading K axis (``formation_error`` (K,), ``edge_errors`` (K, D) or
  (K, D, m), ``edge_mask`` (K, D), ``singularity_margin``, ``torque_saturation``, ``clipped_actions``,
  ``contacts``, ``physics_fault`` (K,), ``applied_torque`` (K, n_i), ``sim_time`` (K,)), plus
  ``physics_fault_reason`` (K,) (the copy's fault in words, "" if none) and ``final_observation``
  (K, obs_dim) (below).
- Spaces: ``observation_space(agent)`` / ``action_space(agent)`` and ``state_space`` are the single copy's
  (what a policy sees); ``batched_observation_space(agent)``, ``batched_action_space(agent)`` and
  ``batched_state_space`` are the same with a leading K axis. ``state()`` is ``(K, state_dim)``.
- Agents never leave: ``agents`` is always ``possible_agents``, every copy restarts when it ends.

**Autoreset: Gymnasium 1.x's SAME_STEP mode** (``metadata["autoreset_mode"]``). When copy ``k`` terminates
or truncates in a step, that step returns its rewards, terminations/truncations and infos (those of the
final transition), while its row of the returned observations is already the first observation of its
next episode; the observation it ended in is ``infos[agent]["final_observation"][k]`` (for copies that did
not end, that row equals the returned observation). The new episode is drawn from the copy's own generator
(the same draw as the single env's ``reset(seed=None)`` after that episode): a copy seeded ``s + k``
replays, episode after episode, what one single env reset with ``s + k`` and then reset without a seed
gives. ``state()`` after the step is the new episode's.

**Partial reset**: ``reset(seed=None, options={"reset_mask": mask})`` resets only the copies where the
(K,) bool ``mask`` is True (seeded ``seed + k`` when a seed is given, else from their own generators);
the others keep their state, step counts and generators. It returns every copy's observations; infos of
the copies left alone describe their last step.

**Array API** for batched learners (TorchRL, SB3 VecEnvs, batched evaluation): :meth:`step_arrays` takes
every copy's actions as one array, (K, T) (T = all joints, agents in order) or (K * N, n) / (K, N, n) when
every arm has n joints, and returns a :class:`BatchedStep` of stacked arrays without dicts:
observations (K, O) (agent i's part: ``observation_slices[i]``), rewards (K, N), terminations and
truncations (K,), infos of (K, N, ...) per-agent and (K,) per-copy arrays. The dict API wraps it.
:meth:`reset_arrays` is the same for resets.

**Physics layout: one PyBullet client per copy**, each the single env's own world (same bodies, same
saved state, same solver settings), so each copy's physics is the single env's bit for bit by
construction (an ended copy's world is restored from its own snapshot, contact caches included). It was
measured against the other layout, all K formations in one client placed 10 m apart (their bodies never
meet in the broadphase, so they never collide), by ``python -m benchmarks.run --sections vector``: at
K >= 16 the K clients stepped in turn are the faster floor (planar_square 59k vs 56k formation physics
steps/s at K = 16, 64k vs 31k at K = 64; spatial_tetrahedron 19k vs 15k and 19k vs 2.8k), since one
``stepSimulation`` over one big world costs more than linearly in its bodies. The price is memory: about
30 MB per copy (one client each) against 1-8 MB per formation sharing a client (``docs/performance.md``,
"Batched env"). The PyBullet calls (torques, ``stepSimulation``,
joint-state reads, contacts) are per client, as PyBullet has no batched query; everything else
(kinematics, singularity margins, edges, observations, rewards, infos, fault and action checks) is one
numpy pass over the K x N agents, with the single env's own functions
(:func:`ee_formation_env.env.measure`, :func:`~ee_formation_env.env.reward_array`, the
:class:`~ee_formation_env.observation.ObservationBuilder`) given a leading K axis.

**Scenario distributions**: each copy draws its own problem at each of its resets (the single env's draw for
its seed, bit for bit; ``tasks[k]`` is copy k's, ``copy_view(k)`` the copy as a per-copy policy source sees
it), and its measurements, observations and rewards are computed with its own draw, copy by copy.

**Errors**: bad input raises before any copy moves, with the single env's messages (they start with the
field: ``actions['arm_0']: ...``, ``seed: ...``, ``options['reset_mask']: ...``).

**Rendering**: none (``render_mode`` is not supported); render a copy with a single env reset with its
seed.

Arguments of ``ee_formation_env.vector_env``:

============== ============================================================================================
argument       meaning
============== ============================================================================================
``scenario``   a built-in name, a YAML/JSON path, a dict or a :class:`~ee_formation_env.scenario.Scenario`
``num_envs``   K >= 1, the number of copies (each one PyBullet client, about 30 MB resident)
``max_cycles`` truncate episodes after this many env steps (as :func:`ee_formation_env.parallel_env`)
``**overrides`` top-level scenario keys replaced (as :func:`ee_formation_env.parallel_env`)
============== ============================================================================================
"""

from __future__ import annotations

import os
from typing import Any, Mapping, NamedTuple, Sequence

import gymnasium
import numpy as np
from gymnasium.utils import seeding

from ee_formation_env.env import (PHYSICS_FAULTS, Measurement, build_world, measure, physics_fault, reward_array,
                                  reset_world, start_problem)
from ee_formation_env.formation import formation_errors_from_squares
from ee_formation_env.generators import distribution_bounds, sample_task
from ee_formation_env.inputs import check_seed, excerpt, numeric_action
from ee_formation_env.manoeuvre import ReferenceMotion
from ee_formation_env.observation import ObservationBuilder, ObservationLayout
from ee_formation_env.reward import edge_tolerances
from ee_formation_env.scenario import Scenario, load_scenario
from ee_formation_env.sensing import Sensor
from ee_formation_env.task import build_task

__all__ = ["VectorFormationEnv", "BatchedStep", "PHYSICS_FAULTS"]

# Info keys with one value per agent (K, N, ...) in the array API; the others are per copy (K,).
PER_AGENT_INFO = ("edge_errors", "edge_mask", "singularity_margin", "torque_saturation", "clipped_actions",
                  "contacts")
PER_COPY_INFO = ("formation_error", "physics_fault", "physics_fault_reason", "sim_time")


class BatchedStep(NamedTuple):
    """One batched step (or reset) as stacked arrays: what :meth:`VectorFormationEnv.step_arrays` returns.

    ``observations`` (K, O) float32, agents concatenated (agent i's: ``env.observation_slices[i]``);
    ``rewards`` (K, N) float64; ``terminations``, ``truncations`` (K,) bool; ``infos``: per-agent keys
    (:data:`PER_AGENT_INFO`) (K, N, ...), per-copy keys (:data:`PER_COPY_INFO`) (K,), ``applied_torque``
    (K, T) N m and ``final_observation`` (K, O) (SAME_STEP autoreset: the observation each copy ended in).
    """

    observations: np.ndarray
    rewards: np.ndarray
    terminations: np.ndarray
    truncations: np.ndarray
    infos: dict[str, np.ndarray]


class VectorFormationEnv:
    """K copies of one formation scenario, stepped by one call (module docstring: conventions, autoreset,
    layout). Build it with :func:`ee_formation_env.vector_env`."""

    metadata = {"name": "ee_formation_vector_v0", "render_modes": [], "is_parallelizable": True,
                "autoreset_mode": gymnasium.vector.AutoresetMode.SAME_STEP}

    def __init__(self, scenario: str | os.PathLike | Mapping[str, Any] | Scenario = "planar_square",
                 num_envs: int = 1, **overrides: Any):
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs: expected an integer >= 1 (copies of the scenario), got {excerpt(num_envs)}")
        if overrides.get("render_mode") is not None:
            raise ValueError("render_mode: the batched env does not render; render one copy with parallel_env")
        overrides.pop("render_mode", None)
        self.num_envs = K = int(num_envs)
        self.scenario = load_scenario(scenario, **overrides)
        self.task = build_task(self.scenario)  # validates: raises before any physics starts
        self.render_mode = None
        self.possible_agents = self.task.agents
        self.agents = list(self.possible_agents)
        self._worlds, self._arm_sets = [], []
        try:
            for _ in range(K):
                world, arm_set = build_world(self.task)
                self._worlds.append(world)
                self._arm_sets.append(arm_set)
            self._bounds = None
            self._sampled = self.scenario.distribution.active
            if self._sampled:  # the single env's construction draw: an infeasible distribution is refused here
                self.task = sample_task(self.scenario, np.random.default_rng(0),
                                        lambda task: start_problem(self._arm_sets[0], task))
                self._bounds = distribution_bounds(self.scenario, self.task)
        except BaseException:
            self.close()
            raise
        self._motion = ReferenceMotion(self.scenario.manoeuvre, self.task)  # the single env's (manoeuvre.py)
        self._reference = self._motion if self.scenario.manoeuvre.active else None
        self._observer = ObservationBuilder(self.task, self.scenario.max_joint_velocity, self._bounds, self._reference)
        sensing = self.scenario.sensing
        self._sensor = Sensor(sensing, self.task, self._observer, K) if sensing.active else None
        self._sensed: tuple[np.ndarray, np.ndarray] | None = None  # the copies' measured slot z and errors
        self._observation_spaces = dict(zip(self.possible_agents, self._observer.spaces))
        self._action_spaces = {agent: gymnasium.spaces.Box(-1.0, 1.0, (model.n_joints,), dtype=np.float32)
                               for agent, model in zip(self.possible_agents, self.task.models)}
        self.state_space = self._observer.state_space
        self.observation_spaces = dict(self._observation_spaces)
        self.action_spaces = dict(self._action_spaces)
        self._batched_observation_spaces = {a: _batched(s, K) for a, s in self._observation_spaces.items()}
        self._batched_action_spaces = {a: _batched(s, K) for a, s in self._action_spaces.items()}
        self.batched_state_space = _batched(self.state_space, K)

        arm_set = self._arm_sets[0]
        # Every copy's arms are the same robots (under model_mismatch, the same perturbation seed): copy 0's
        # models evaluate all K copies in one batched call.
        self._kinematics = arm_set.kinematics
        self._joint_slices, self._joint_starts, self._joint_counts = (arm_set.joint_slices, arm_set.joint_starts,
                                                                      arm_set.joint_counts)
        self.n_joints = arm_set.n_joints
        sizes = {arm.n_joints for arm in arm_set.arms}
        self.uniform_joints = sizes.pop() if len(sizes) == 1 else None  # n when every arm has n joints
        continuous = arm_set.continuous
        self._wrap = None if not continuous.any() else True if continuous.all() else continuous
        self._torque_limits_flat = np.concatenate(self.task.torque_limits)
        self._edge_tolerances = edge_tolerances(self.task.formation.kind,
                                                np.linalg.norm(self.task.formation.desired_vectors, axis=1),
                                                self.scenario.reward.position_tolerance)
        # A scenario distribution: each copy's current draw, its observer and its edge tolerances (K,).
        self.tasks = [self.task] * K
        self._observers = [self._observer] * K
        self._copy_tolerances = [self._edge_tolerances] * K
        self.np_randoms = [seeding.np_random(None)[0] for _ in range(K)]
        n = self.task.n_agents
        self._step_counts = np.zeros(K, dtype=np.int64)
        self._clipped_actions = np.zeros((K, n), dtype=np.int64)  # so far this episode
        self._clipped_step = np.zeros((K, n), dtype=np.int64)  # at the last step
        self._contacts = np.zeros((K, n), dtype=np.int64)
        self._torques = np.zeros((K, self.n_joints))
        self._measurement: Measurement | None = None
        self._last_reasons = np.full(K, "", dtype=object)
        self._start_points = np.zeros((K, n, self.task.dim))  # each copy's end-effectors at the motion's start
        masks = np.array(self._observer.slot_masks)
        self._edge_masks = np.broadcast_to(masks, (K, *masks.shape))
        self._needs_reset = True

    # ------------------------------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        """One copy's observation space of ``agent`` (what a policy sees)."""
        return self._observation_spaces[agent]

    def action_space(self, agent: str) -> gymnasium.spaces.Box:
        """One copy's action space of ``agent``."""
        return self._action_spaces[agent]

    def batched_observation_space(self, agent: str) -> gymnasium.spaces.Box:
        """``agent``'s observations of all K copies: the single space with a leading K axis."""
        return self._batched_observation_spaces[agent]

    def batched_action_space(self, agent: str) -> gymnasium.spaces.Box:
        """``agent``'s actions of all K copies: the single space with a leading K axis."""
        return self._batched_action_spaces[agent]

    def observation_layout(self, agent: str) -> ObservationLayout:
        """How ``agent``'s observation is laid out (one copy's; the single env's ``observation_layout``)."""
        return self._observer.layouts[self.task.agent_index(agent)]

    @property
    def observation_slices(self) -> list[slice]:
        """Agent i's part of the array API's observations (K, O)."""
        return self._observer.observation_slices

    @property
    def joint_slices(self) -> list[slice]:
        """Agent i's joints in the array API's flat actions (K, T) and ``applied_torque``."""
        return self._joint_slices

    @property
    def torque_limits(self) -> tuple[np.ndarray, ...]:
        return self.task.torque_limits

    def copy_view(self, k: int) -> "CopyView":
        """Copy ``k`` as a per-copy consumer (a policy source, a reference controller) sees it: this env, with
        ``task`` copy k's current one (on a scenario distribution, its current draw)."""
        return CopyView(self, k)

    # ------------------------------------------------------------------------------------------ dict API
    def reset(self, seed: int | Sequence[int | None] | None = None, options: dict | None = None):
        """Reset every copy (or those of ``options["reset_mask"]``); copy k seeded ``seed + k`` when a seed is
        given, or ``seed[k]`` when it is a sequence of K seeds (each an integer or None: Gymnasium's vector
        convention). Returns observations agent -> (K, obs_dim) and infos agent -> dict of (K, ...) arrays."""
        result = self.reset_arrays(seed=seed, options=options)
        return self._observation_dict(result.observations), self._info_dicts(result.infos)

    def step(self, actions: Mapping[str, np.ndarray]):
        """Apply agent -> (K, act_dim) actions to every copy for ``frame_skip`` physics steps; copies that end
        restart at once (SAME_STEP autoreset, module docstring)."""
        self._check_running()
        normalized, clipped = self._check_actions(actions)
        result = self._step(normalized, clipped)
        rewards = result.rewards.T.copy()
        terminations, truncations = result.terminations, result.truncations
        return (self._observation_dict(result.observations),
                {agent: rewards[i] for i, agent in enumerate(self.possible_agents)},
                {agent: terminations.copy() for agent in self.possible_agents},
                {agent: truncations.copy() for agent in self.possible_agents},
                self._info_dicts(result.infos))

    # ------------------------------------------------------------------------------------------ array API
    def reset_arrays(self, seed: int | Sequence[int | None] | None = None, options: dict | None = None
                     ) -> BatchedStep:
        """:meth:`reset` as stacked arrays (rewards zero, no termination)."""
        seeds = self._copy_seeds(seed)
        rows = self._reset_rows(options)
        if not self._worlds or not all(world.connected for world in self._worlds):
            raise RuntimeError("reset: the environment is closed")
        for k in rows:
            if seeds[k] is not None:
                self.np_randoms[k] = seeding.np_random(seeds[k])[0]
        if len(rows):  # an all-False mask resets nothing and returns every copy's current observations
            self._reset_copies(rows)
        self._needs_reset = False
        measured = self._measurement
        observations = self._observation_matrix(*self._observed_slots(), measured.q_observed, measured.dq,
                                                np.arange(self.num_envs), *self._reference_blocks())
        infos = self._info_arrays(measured)
        infos["final_observation"] = observations.copy()
        K, n = self.num_envs, self.task.n_agents
        return BatchedStep(observations, np.zeros((K, n)), np.zeros(K, dtype=bool), np.zeros(K, dtype=bool), infos)

    def step_arrays(self, actions: np.ndarray) -> BatchedStep:
        """One step of every copy from one array of actions: (K, T) (all joints, agents in order), or, when
        every arm has n joints, (K * N, n) or (K, N, n). Checked (numeric, finite) before any copy moves."""
        self._check_running()
        normalized = self.checked_action_array(actions)
        clipped = np.add.reduceat(np.abs(normalized) > 1.0, self._joint_starts, axis=1, dtype=np.int64)
        np.minimum(np.maximum(normalized, -1.0, out=normalized), 1.0, out=normalized)
        return self._step(normalized, clipped)

    # ------------------------------------------------------------------------------------------ state
    def state(self) -> np.ndarray:
        """Every copy's global state (K, state_dim): end-effector positions, q, dq (as the single env's)."""
        measured = self._last()
        return self._observer.state(measured.ee_world, measured.q_observed, measured.dq)

    def end_effector_positions(self) -> np.ndarray:
        """World-frame end-effector positions (K, N, 3), m, at the last reset/step."""
        return self._last().ee_world.copy()

    def joint_positions(self) -> np.ndarray:
        """Every copy's joint positions (K, T), rad (unwrapped), at the last reset/step."""
        return self._last().q.copy()

    def joint_velocities(self) -> np.ndarray:
        """Every copy's joint velocities (K, T), rad/s, at the last reset/step."""
        return self._last().dq.copy()

    def reference_centroid(self) -> np.ndarray:
        """Every copy's reference centroid c*(t) (K, dim), world, m (the single env's, per copy)."""
        self._last()
        return self._motion.world(self._times(), self._start_points.mean(axis=-2))[0]

    def centroid_tracking_error(self) -> np.ndarray:
        """Every copy's |c - c*| (K,), m."""
        return self._motion.centroid_errors(self._times(), self._start_points.mean(axis=-2), self._last().ee_world)

    def orientation_tracking_error(self) -> np.ndarray:
        """Every copy's orientation error (K,), rad (the single env's ``orientation_tracking_error``)."""
        return self._motion.orientation_errors(self._times(), self._start_points, self._last().ee_world)

    @property
    def physics_fault_reason(self) -> np.ndarray:
        """Each copy's fault at the last step (K,) ("" for none); an autoreset copy's is its ended episode's."""
        return np.array(self._last_reasons, dtype=object)

    def close(self) -> None:
        """Disconnect every copy's physics client; safe to call more than once."""
        for world in getattr(self, "_worlds", []):
            world.close()

    def __enter__(self) -> "VectorFormationEnv":
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.close()

    def __del__(self) -> None:
        self.close()

    def __getstate__(self) -> dict[str, Any]:
        return {"scenario": self.scenario, "num_envs": self.num_envs}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["scenario"], num_envs=state["num_envs"])

    # ------------------------------------------------------------------------------------------ internals
    def _check_running(self) -> None:
        if self._needs_reset:
            raise RuntimeError("step: call reset() first (the batched env has never been reset)")
        if not all(world.connected for world in self._worlds):
            raise RuntimeError("step: the environment is closed")

    def _times(self) -> np.ndarray:
        """Each copy's simulated time (K,), s, at its last reset/step."""
        return self._step_counts * self.scenario.control_dt

    def _reference_blocks(self) -> tuple[np.ndarray, ...]:
        """``(blocks,)``: every copy's manoeuvre reference blocks (K, N r'), or () without a manoeuvre."""
        if self._reference is None:
            return ()
        return (self._reference.observation_block(self._times(), self._start_points.mean(axis=-2)),)

    def _last(self) -> Measurement:
        if self._measurement is None:
            self._measurement = self._measure_rows(np.arange(self.num_envs))
        return self._measurement

    def _copy_seeds(self, seed: Any) -> list[int | None]:
        """Each copy's seed (K,) from ``reset``'s ``seed``: None, an integer s (copy k: s + k) or K seeds."""
        K = self.num_envs
        if isinstance(seed, (list, tuple, np.ndarray)):
            if len(seed) != K:
                raise ValueError(f"seed: expected None, an integer or a sequence of {K} seeds (one per copy), "
                                 f"got {len(seed)} seeds")
            seeds = []
            for k, value in enumerate(seed):
                try:
                    seeds.append(check_seed(value))
                except (TypeError, ValueError) as error:
                    raise type(error)(f"seed[{k}]{str(error)[len('seed'):]}") from None
            return seeds
        first = check_seed(seed)
        return [None if first is None else first + k for k in range(K)]

    def _reset_rows(self, options: Any) -> np.ndarray:
        """The copies to reset: all, or ``options["reset_mask"]``'s; checked before anything changes."""
        K = self.num_envs
        if options is None or "reset_mask" not in options:
            return np.arange(K)
        if not isinstance(options, Mapping):
            raise TypeError(f"options: expected a dict, got {type(options).__name__}")
        mask = options["reset_mask"]
        array = np.asarray(mask)
        if array.dtype != bool or array.shape != (K,):
            raise ValueError(f"options['reset_mask']: expected a bool array of shape ({K},), got "
                             f"{array.dtype} {array.shape} {excerpt(mask)}")
        if self._needs_reset and not array.all():
            raise RuntimeError("options['reset_mask']: the first reset must reset every copy (call reset() "
                               "without a mask first)")
        return np.flatnonzero(array)

    def _reset_copies(self, rows: np.ndarray) -> None:
        """Reset the copies ``rows`` with their own generators and re-measure them."""
        for k in rows:
            if self._sampled:  # this episode's draw, from the copy's generator (the single env's draw)
                self._use_task(k, sample_task(self.scenario, self.np_randoms[k],
                                              lambda task, k=k: start_problem(self._arm_sets[k], task)))
            reset_world(self._worlds[k], self._arm_sets[k], self.tasks[k], self.np_randoms[k])
        self._step_counts[rows] = 0
        self._clipped_actions[rows] = 0
        self._clipped_step[rows] = 0
        self._contacts[rows] = 0
        self._torques[rows] = 0.0
        part = self._measure_rows(rows)
        if self._measurement is None or len(rows) == self.num_envs:
            self._measurement = part
        else:
            self._measurement = _with_rows(self._measurement, rows, part)
        m = self.task.dim
        self._start_points[rows] = part.ee_world[..., :m]
        if self._sensor is not None:  # a fresh sensor: it holds the start displacement through its delay
            self._sensor.reset(part.slot_z, rows)
            self._sense(part.slot_z, rows)

    def _use_task(self, k: int, task: Any) -> None:
        """Make a drawn task copy ``k``'s current one (the single env's ``_use_task``)."""
        self.tasks[k] = task
        self._observers[k] = ObservationBuilder(task, self.scenario.max_joint_velocity, self._bounds)
        self._copy_tolerances[k] = edge_tolerances(task.formation.kind,
                                                   np.linalg.norm(task.formation.desired_vectors, axis=1),
                                                   self.scenario.reward.position_tolerance)

    def _observation_matrix(self, slot_z: np.ndarray, slot_errors: np.ndarray, q_observed: np.ndarray,
                            dq: np.ndarray, rows: np.ndarray, *references: np.ndarray) -> np.ndarray:
        """The observations (len(rows), O) of the copies ``rows`` from their stacked arrays (and a manoeuvre's
        reference blocks): one batched pass, or, on a scenario distribution (no manoeuvre), each copy with its
        own draw's observer."""
        if not self._sampled:
            return self._observer.observation_matrix(slot_z, slot_errors, q_observed, dq, *references)
        return np.stack([self._observers[k].observation_matrix(slot_z[r], slot_errors[r], q_observed[r], dq[r])
                         for r, k in enumerate(rows)])

    def _sense(self, slot_z: np.ndarray, rows: np.ndarray) -> None:
        """Push the copies ``rows``' true slot displacements ``slot_z`` (len(rows), S, m) through the sensor and
        keep what they measure."""
        sensed_z, sensed_errors = self._sensor.sense(slot_z, rows, self.np_randoms)
        if self._sensed is None:
            self._sensed = (np.zeros((self.num_envs, *sensed_z.shape[1:])),
                            np.zeros((self.num_envs, *sensed_errors.shape[1:])))
        self._sensed[0][rows], self._sensed[1][rows] = sensed_z, sensed_errors

    def _observed_slots(self) -> tuple[np.ndarray, np.ndarray]:
        """Every copy's slot displacements and edge errors as its agents observe them (sensing.py)."""
        if self._sensor is None:
            return self._measurement.slot_z, self._measurement.slot_errors
        return self._sensed

    def _read_states(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The joint states (len(rows), T) of the copies ``rows``: one PyBullet read per arm, one array."""
        positions: list[float] = []
        velocities: list[float] = []
        for k in rows:
            for arm in self._arm_sets[k].arms:
                q, dq = arm.read_state_lists()
                positions += q
                velocities += dq
        shape = (len(rows), self.n_joints)
        return np.array(positions).reshape(shape), np.array(velocities).reshape(shape)

    def _measure_rows(self, rows: np.ndarray) -> Measurement:
        """Read the copies ``rows`` and derive everything in one batched pass (faults per copy)."""
        return self._derive(*self._read_states(rows), rows)

    def _derive(self, q: np.ndarray, dq: np.ndarray, rows: np.ndarray) -> Measurement:
        """Everything derived from the stacked joint states (len(rows), T) of the copies ``rows``, in one batched
        pass (faults per copy); on a scenario distribution, each copy with its own draw."""
        count = q.shape[0]
        limit = self.scenario.max_joint_velocity
        faults = np.zeros(count, dtype=np.int64)
        reasons = np.full(count, "", dtype=object)
        # The single env's test, per copy: NaN fails the comparison, a non-finite q makes its row sum non-finite.
        healthy = (np.abs(dq).max(axis=1) <= limit) & np.isfinite(q.sum(axis=1))
        if not healthy.all():
            for r in np.flatnonzero(~healthy):
                q[r], dq[r], faults[r], reasons[r] = physics_fault(q[r], dq[r], self._joint_slices, limit)
        if not self._sampled:
            return measure(self.task, self._observer, self._kinematics, self._wrap, q, dq, faults, reasons)
        parts = [measure(self.tasks[k], self._observers[k], self._kinematics, self._wrap, q[r], dq[r], faults[r],
                         reasons[r]) for r, k in enumerate(rows)]
        return Measurement(**{name: np.array([getattr(part, name) for part in parts],
                                             dtype=object if name == "fault_reason" else None)
                              for name in Measurement.__slots__})

    def _check_actions(self, actions: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Every copy's actions (K, T) float64 clipped to [-1, 1], and the entries clipped per (copy, agent);
        the single env's errors otherwise (shapes with the leading K axis)."""
        if not isinstance(actions, Mapping):
            raise TypeError(f"actions: expected a dict agent -> array, got {type(actions).__name__}")
        if actions.keys() != self._action_spaces.keys():
            missing = [a for a in self.possible_agents if a not in actions]
            unknown = [a for a in actions if a not in self.possible_agents]
            raise ValueError(f"actions: missing agents {missing}, unknown agents {unknown}; expected keys "
                             f"{self.possible_agents}")
        K = self.num_envs
        parts = [actions[agent] for agent in self.possible_agents]
        normalized = None
        if all(getattr(part, "shape", None) == (K, *space.shape) for part, space in
               zip(parts, self._action_spaces.values())):
            try:
                normalized = np.concatenate(parts, axis=1, dtype=np.float64)
            except (TypeError, ValueError):
                normalized = None
        if normalized is None:
            normalized = np.concatenate([self._action_array(agent, part) for agent, part in
                                         zip(self.possible_agents, parts)], axis=1)
        if not np.isfinite(normalized).all():
            for agent, joints in zip(self.possible_agents, self._joint_slices):
                bad = ~np.isfinite(normalized[:, joints]).all(axis=1)
                if bad.any():
                    raise ValueError(f"actions[{agent!r}]: expected finite values of shape "
                                     f"{(K, *self._action_spaces[agent].shape)}, got non-finite values in copies "
                                     f"{np.flatnonzero(bad).tolist()}: {normalized[bad][:, joints].tolist()[:3]}")
        clipped = np.add.reduceat(np.abs(normalized) > 1.0, self._joint_starts, axis=1, dtype=np.int64)
        np.minimum(np.maximum(normalized, -1.0, out=normalized), 1.0, out=normalized)
        return normalized, clipped

    def _action_array(self, agent: str, action: Any) -> np.ndarray:
        return numeric_action(agent, action, (self.num_envs, *self._action_spaces[agent].shape))

    def checked_action_array(self, actions: Any) -> np.ndarray:
        """A fresh float64 (K, T) copy of the array API's actions, or a ``ValueError`` starting ``actions:``."""
        K, T, n = self.num_envs, self.n_joints, self.uniform_joints
        shapes = [(K, T)] + ([(K * self.task.n_agents, n), (K, self.task.n_agents, n)] if n else [])
        try:
            raw = np.asarray(actions)
            if raw.dtype.kind not in "biuf":
                raise ValueError
        except (TypeError, ValueError):
            raise ValueError(f"actions: expected a numeric array of shape {' or '.join(map(str, shapes))}, got "
                             f"{type(actions).__name__} {excerpt(actions)}") from None
        if raw.shape not in shapes:
            raise ValueError(f"actions: expected shape {' or '.join(map(str, shapes))}, got {raw.shape}")
        normalized = raw.reshape(K, T).astype(np.float64)  # always a copy: clipped in place
        if not np.isfinite(normalized).all():
            bad = np.flatnonzero(~np.isfinite(normalized).all(axis=1)).tolist()
            raise ValueError(f"actions: expected finite values, got non-finite values in copies {bad}")
        return normalized

    def _step(self, normalized: np.ndarray, clipped: np.ndarray) -> BatchedStep:
        """Step every copy with checked, clipped actions (K, T); the SAME_STEP autoreset of ended copies."""
        torques = normalized * self._torque_limits_flat  # (K, T), N m
        frame_skip = self.scenario.frame_skip
        contacts, positions, velocities = [], [], []
        # Each copy is read right after it steps, while its client's state is still in the CPU caches.
        for arm_set, row in zip(self._arm_sets, torques):
            arm_set.step(row, frame_skip)
            for arm in arm_set.arms:
                q, dq = arm.read_state_lists()
                positions += q
                velocities += dq
            contacts.append(arm_set.contacts_per_arm())
        self._step_counts += 1
        self._clipped_actions += clipped
        self._clipped_step = clipped
        self._contacts = np.array(contacts, dtype=np.int64).reshape(self.num_envs, self.task.n_agents)
        self._torques = torques
        shape = (self.num_envs, self.n_joints)
        every = np.arange(self.num_envs)
        self._measurement = measured = self._derive(np.array(positions).reshape(shape),
                                                    np.array(velocities).reshape(shape), every)
        if self._reference is not None:  # the motion's start points, kept while the formation holds
            holding = self._times() <= self.scenario.manoeuvre.start
            self._start_points[holding] = measured.ee_world[holding, :, :self.task.dim]

        if self._sensor is not None:
            self._sense(measured.slot_z, every)
        observations = self._observation_matrix(*self._observed_slots(), measured.q_observed, measured.dq, every,
                                                *self._reference_blocks())
        if self._sampled:
            rewards = np.stack([reward_array(measured.edge_squares[k], self._copy_tolerances[k], self._observers[k],
                                             self.scenario.reward) for k in every])
        else:
            rewards = reward_array(measured.edge_squares, self._edge_tolerances, self._observer, self.scenario.reward)
        infos = self._info_arrays(measured)
        ended = measured.fault != 0
        if self.scenario.terminate_on_contact:
            ended = ended | (self._contacts > 0).any(axis=1)
        truncated = ~ended & (self._step_counts >= self.scenario.max_steps)
        infos["final_observation"] = observations.copy()
        self._last_reasons = measured.fault_reason
        done = np.flatnonzero(ended | truncated)
        if len(done):
            self._reset_copies(done)
            part = self._measurement
            slot_z, slot_errors = self._observed_slots()
            references = tuple(block[done] for block in self._reference_blocks())
            observations[done] = self._observation_matrix(slot_z[done], slot_errors[done], part.q_observed[done],
                                                          part.dq[done], done, *references)
        return BatchedStep(observations, rewards, ended, truncated, infos)

    def _info_arrays(self, measured: Measurement) -> dict[str, np.ndarray]:
        """The infos of every (copy, agent) as stacked arrays (the array API's form)."""
        return {
            "formation_error": formation_errors_from_squares(measured.edge_squares),
            "edge_errors": self._observer.padded_slot_errors(measured.slot_errors),
            "edge_mask": self._edge_masks.copy(),  # fresh each call: infos of different calls share no object
            "singularity_margin": measured.singularity_margins,
            "torque_saturation": self._clipped_step / self._joint_counts,
            "applied_torque": self._torques.copy(),
            "clipped_actions": self._clipped_actions.copy(),
            "contacts": self._contacts.copy(),
            "physics_fault": np.asarray(measured.fault).copy(),
            "physics_fault_reason": np.asarray(measured.fault_reason, dtype=object).copy(),
            "sim_time": self._step_counts * self.scenario.control_dt,
        }

    def _observation_dict(self, observations: np.ndarray) -> dict[str, np.ndarray]:
        return {agent: observations[:, part] for agent, part in zip(self.possible_agents, self.observation_slices)}

    def _info_dicts(self, infos: dict[str, np.ndarray]) -> dict[str, dict[str, np.ndarray]]:
        """agent -> dict of (K, ...) arrays, from the stacked infos."""
        per_agent = {key: infos[key].swapaxes(0, 1) for key in PER_AGENT_INFO}  # agent-major views
        result = {}
        for i, (agent, joints, part) in enumerate(zip(self.possible_agents, self._joint_slices, self.observation_slices)):
            info = {key: values[i] for key, values in per_agent.items()}
            info["applied_torque"] = infos["applied_torque"][:, joints]
            info["final_observation"] = infos["final_observation"][:, part]
            for key in PER_COPY_INFO:
                info[key] = infos[key].copy() if i else infos[key]
            result[agent] = info
        return result


class CopyView:
    """One copy of a batched env (:meth:`VectorFormationEnv.copy_view`): the env's attributes, with ``task`` the
    copy's current one, read when asked (so a controller built on it follows the copy's draws)."""

    def __init__(self, env: VectorFormationEnv, k: int):
        self._env, self._k = env, k

    @property
    def task(self) -> Any:
        return self._env.tasks[self._k]

    def __getattr__(self, name: str) -> Any:
        return getattr(self._env, name)


def _batched(space: gymnasium.spaces.Box, count: int) -> gymnasium.spaces.Box:
    """``space`` with a leading axis of ``count``."""
    return gymnasium.spaces.Box(np.broadcast_to(space.low, (count, *space.shape)),
                                np.broadcast_to(space.high, (count, *space.shape)), dtype=space.dtype)


def _with_rows(full: Measurement, rows: np.ndarray, part: Measurement) -> Measurement:
    """``full`` with the copies ``rows`` replaced by ``part``'s (fresh arrays; ``full`` is not changed)."""
    values = {}
    for name in Measurement.__slots__:
        array = np.array(getattr(full, name), dtype=object if name == "fault_reason" else None)
        array[rows] = getattr(part, name)
        values[name] = array
    return Measurement(**values)
