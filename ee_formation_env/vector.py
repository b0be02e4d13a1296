"""The env's one implementation: K copies of one scenario stepped by one call (``ee_formation_env.vector_env``).

The PettingZoo parallel env (:class:`ee_formation_env.env.FormationEnv`) is this env at K = 1 without
autoreset, seen through per-agent dicts; every action check, step, reset, measurement, observation, reward and
info is computed here, on a leading K axis.

Quick use::

    import numpy as np
    import ee_formation_env

    env = ee_formation_env.vector_env("planar_square", num_envs=16)
    observations, infos = env.reset(seed=0)            # copy k is seeded with 0 + k
    actions = {agent: np.zeros((16, 2), np.float32) for agent in env.possible_agents}
    observations, rewards, terminations, truncations, infos = env.step(actions)  # arm_0's: (16, obs_dim), (16,), ...

**Conventions** (Gymnasium's vector conventions for seeds, VMAS's for per-agent batches): ``reset(seed=s)``
seeds copy ``k`` with ``s + k`` (or ``seed=[s_0, ..., s_K-1]``, None for a copy's own generator), and copy
``k`` then reproduces ``parallel_env(scenario).reset(seed=s + k)`` step for step, bit for bit; an unseeded
``reset()`` continues every copy's generator. Observations: agent -> ``(K, obs_dim)`` float32; actions: agent
-> ``(K, act_dim)`` (numeric, finite; clipped to [-1, 1]); rewards: agent -> ``(K,)`` float64; terminations
and truncations: agent -> ``(K,)`` bool; infos: agent -> the parallel env's keys with a leading K axis, plus
``physics_fault_reason`` (K,) and, with autoreset, ``final_observation`` (K, obs_dim)
(:mod:`ee_formation_env.infos`). ``observation_space(agent)``, ``action_space(agent)`` and ``state_space`` are
one copy's; ``batched_*`` have the K axis; ``state()`` is ``(K, state_dim)``. ``agents`` is always
``possible_agents``.

**Autoreset** (``autoreset_mode``, also in ``metadata``): Gymnasium 1.x's ``SAME_STEP`` (default): a copy that
ends in a step returns that step's rewards, terminations/truncations and infos, while its row of the
observations is already its next episode's first (drawn from its own generator); the observation it ended
in is ``infos[agent]["final_observation"][k]``. ``DISABLED``: an ended copy stays as it ended, and a step
before it is reset (``reset(options={"reset_mask": mask})``) is refused.

**Partial reset**: ``reset(seed=None, options={"reset_mask": mask})`` resets the copies where the (K,) bool
``mask`` is True (seeded ``seed + k`` when given); the others keep their state, step counts and generators.

**Array API** for batched learners (TorchRL, SB3, batched evaluation): :meth:`step_arrays` takes all actions as
one array, (K, T) (agents' joints in order) or (K * N, n) / (K, N, n) when every arm has n joints, and returns
a :class:`BatchedStep` of stacked arrays (observations (K, O), agent i's part ``observation_slices[i]``;
rewards (K, N); terminations, truncations (K,); infos (K, N, ...) per agent, (K,) per copy);
:meth:`reset_arrays` is its reset. The dict API wraps it.

**Physics layout**: one PyBullet client per copy, each the parallel env's own world, so each copy's physics
is one env's by construction; torques, ``stepSimulation``, state reads and contacts are per client, the rest
is one numpy pass over the K x N agents (measurements: ``docs/performance.md``, "Batched env").

**Scenario distributions**: each copy draws its own problem at each of its resets (``tasks[k]``;
``copy_view(k)`` is the copy as a per-copy policy source sees it). **Rendering**: with ``num_envs=1`` only.
**Errors**: bad input raises before any copy moves (``actions['arm_0']: ...``, ``seed: ...``).

Arguments of ``ee_formation_env.vector_env``:

================== ========================================================================================
argument           meaning
================== ========================================================================================
``scenario``       a built-in name, a YAML/JSON path, a dict or a :class:`~ee_formation_env.scenario.Scenario`
``num_envs``       1 <= K <= 1024, the number of copies (each one PyBullet client, about 30 MB resident:
                   :func:`ee_formation_env.inputs.check_num_envs` refuses more than memory holds)
``max_cycles``     truncate episodes after this many env steps (as :func:`ee_formation_env.parallel_env`)
``autoreset_mode`` ``gymnasium.vector.AutoresetMode.SAME_STEP`` (default) or ``DISABLED``
``render_mode``    None, ``"human"`` or ``"rgb_array"`` (``num_envs=1`` only); ``render_width``,
                   ``render_height`` (pixels, 16 to 4096) and ``real_time`` as for the parallel env
``**overrides``    top-level scenario keys replaced (as :func:`ee_formation_env.parallel_env`)
================== ========================================================================================
"""

from __future__ import annotations

import os
from typing import Any, Mapping, Sequence

import gymnasium
import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector.utils import batch_space

from ee_formation_env.actions import ActionCheck
from ee_formation_env.formation import formation_error_from_squares, formation_errors_from_squares
from ee_formation_env.generators import distribution_bounds, first_draw, sample_task
from ee_formation_env.infos import (PER_AGENT_INFO, PER_COPY_INFO, copies_info_dicts, one_copy_info_dicts,
                                    stacked_infos)
from ee_formation_env.inputs import check_num_envs, check_steppable, copy_seeds, excerpt, reset_rows
from ee_formation_env.manoeuvre import ReferenceMotion
from ee_formation_env.measurement import PHYSICS_FAULTS, Measurement, measure, physics_faults, reward_array
from ee_formation_env.observation import ObservationBuilder, ObservationLayout
from ee_formation_env.rendering import SceneRenderer, validate_render_options
from ee_formation_env.reward import task_edge_tolerances
from ee_formation_env.engines import check_engine
from ee_formation_env.robot import ArmSet, build_world, reset_world, start_problem
from ee_formation_env.scenario import Scenario, load_scenario
from ee_formation_env.sensing import Sensor
from ee_formation_env.task import build_task
from ee_formation_env.vector_views import BatchedStep, CopyView
from ee_formation_env.world import Engine

__all__ = ["VectorFormationEnv", "BatchedStep", "PHYSICS_FAULTS", "PER_AGENT_INFO", "PER_COPY_INFO"]

AutoresetMode = gymnasium.vector.AutoresetMode
RENDER_MODES = ("human", "rgb_array")
# ONE_COPY_FAST_PATH: with one copy, the same functions on its own arrays, then given the K axis back (cheaper).

class VectorFormationEnv:
    """K copies of one formation scenario, stepped by one call (module docstring: conventions, autoreset,
    layout). Build it with :func:`ee_formation_env.vector_env`."""

    metadata = {"name": "ee_formation_vector_v0", "render_modes": list(RENDER_MODES), "render_fps": 30,
                "is_parallelizable": True, "autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(self, scenario: str | os.PathLike | Mapping[str, Any] | Scenario = "planar_square",
                 num_envs: int = 1, autoreset_mode: AutoresetMode = AutoresetMode.SAME_STEP,
                 render_mode: str | None = None, render_width: int = 480, render_height: int = 360,
                 real_time: bool = False, **overrides: Any):
        num_envs = check_num_envs(num_envs)
        if autoreset_mode not in (AutoresetMode.SAME_STEP, AutoresetMode.DISABLED):
            raise ValueError(f"autoreset_mode: expected AutoresetMode.SAME_STEP or AutoresetMode.DISABLED, got "
                             f"{excerpt(autoreset_mode)}")
        if render_mode not in (None, *RENDER_MODES):
            raise ValueError(f"render_mode: expected None or one of {list(RENDER_MODES)}, got {render_mode!r}")
        if render_mode is not None and num_envs != 1:
            raise ValueError("render_mode: the batched env renders only with num_envs=1; render one copy with "
                             "parallel_env")
        render_width, render_height, real_time = validate_render_options(render_width, render_height, real_time)
        self.num_envs = K = int(num_envs)
        self.metadata = {**type(self).metadata, "autoreset_mode": autoreset_mode}
        self.autoreset = autoreset_mode == AutoresetMode.SAME_STEP
        self.scenario = scenario = load_scenario(scenario, **overrides)
        self.task = build_task(self.scenario)  # validates: raises before any physics starts
        check_engine(self.scenario.engine, K, render_mode)
        self.render_mode = render_mode
        self.possible_agents = self.task.agents
        self.agents = list(self.possible_agents)
        self._worlds, self._arm_sets = [], []
        try:
            for _ in range(K):
                world, arm_set = build_world(self.task, render_mode)
                self._worlds.append(world)
                self._arm_sets.append(arm_set)
            self._bounds = None
            self._sampled = self.scenario.distribution.active
            if self._sampled:  # one draw now: an infeasible distribution is refused here
                self.task = first_draw(self.scenario, self._arm_sets[0])
                self._bounds = distribution_bounds(self.scenario, self.task)
            # The manoeuvre's reference (manoeuvre.py); without one the observations are the plain task's.
            self._motion = ReferenceMotion(self.scenario.manoeuvre, self.task)
            self._reference = self._motion if self.scenario.manoeuvre.active else None
            self._tracks = self._reference is not None and self.scenario.reward.tracking > 0  # reward term
            self._observer = ObservationBuilder(self.task, scenario.max_joint_velocity, self._bounds, self._reference,
                                                scenario.neighbour_slots)
        except BaseException:
            self.close()
            raise
        sensing = self.scenario.sensing
        self._sensor = Sensor(sensing, self.task, self._observer, K) if sensing.active else None
        self._sensed: tuple[np.ndarray, np.ndarray] | None = None  # the copies' measured slot z and errors
        self._observation_spaces = dict(zip(self.possible_agents, self._observer.spaces))
        self._action_spaces = {agent: gymnasium.spaces.Box(-1.0, 1.0, (m.n_joints,), np.float32)
                               for agent, m in zip(self.possible_agents, self.task.models)}
        self.state_space = self._observer.state_space
        self.observation_spaces = dict(self._observation_spaces)  # PettingZoo's dict attributes
        self.action_spaces = dict(self._action_spaces)
        self._batched_observation_spaces = {a: batch_space(s, K) for a, s in self._observation_spaces.items()}
        self._batched_action_spaces = {a: batch_space(s, K) for a, s in self._action_spaces.items()}
        self.batched_state_space = batch_space(self.state_space, K)

        arm_set = self._arm_sets[0]
        # Every copy's arms are the same robots (under model_mismatch, the same perturbation seed): copy 0's
        # models evaluate all K copies in one batched call.
        self._kinematics = arm_set.kinematics
        self._joint_slices, self._joint_counts = arm_set.joint_slices, arm_set.joint_counts
        self.actions_check = ActionCheck(self.possible_agents, self._joint_slices)
        self.n_joints = arm_set.n_joints
        self.uniform_joints = self.actions_check.uniform_joints  # n when every arm has n joints
        continuous = arm_set.continuous
        # Continuous joints are observed wrapped to [-pi, pi): None (no joint), True (every joint) or a mask.
        self._wrap = None if not continuous.any() else True if continuous.all() else continuous
        self._torque_limits_flat = np.concatenate(self.task.torque_limits)
        # A scenario distribution: each copy's current draw, its observer and its edge tolerances.
        self.tasks = [self.task] * K
        self._observers = [self._observer] * K
        self._copy_tolerances = [task_edge_tolerances(self.task)] * K
        self.np_randoms = [seeding.np_random(None)[0] for _ in range(K)]
        n = self.task.n_agents
        self._step_counts, self._max_steps = np.zeros(K, dtype=np.int64), self.scenario.max_steps
        self._clipped_actions = np.zeros((K, n), dtype=np.int64)  # so far this episode
        self._clipped_step = np.zeros((K, n), dtype=np.int64)  # at the last step
        self._contacts = np.zeros((K, n), dtype=np.int64)
        self._torques = np.zeros((K, self.n_joints))
        self._measurement: Measurement | None = None
        self._last_reasons = np.full(K, "", dtype=object)
        self._ended = np.zeros(K, dtype=bool)  # without autoreset: the copies whose episode has ended
        self._start_points = np.zeros((K, n, self.task.dim))  # each copy's end-effectors at the motion's start
        masks = np.array(self._observer.slot_masks)
        self._edge_masks = np.broadcast_to(masks, (K, *masks.shape))
        self._renderer = None if render_mode is None else SceneRenderer(
            self._worlds[0], self.task.formation, self.task.dim, render_width, render_height, real_time)
        self._every = np.arange(K)
        self._needs_reset = True

    # ------------------------------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> gymnasium.spaces.Box:  # one copy's: what a policy sees
        return self._observation_spaces[agent]

    def action_space(self, agent: str) -> gymnasium.spaces.Box:  # one copy's
        return self._action_spaces[agent]

    def batched_observation_space(self, agent: str) -> gymnasium.spaces.Box:  # all K copies': a leading K axis
        return self._batched_observation_spaces[agent]

    def batched_action_space(self, agent: str) -> gymnasium.spaces.Box:  # all K copies': a leading K axis
        return self._batched_action_spaces[agent]

    def observation_layout(self, agent: str, copy: int = 0) -> ObservationLayout:
        """How ``agent``'s observation is laid out in copy ``copy`` (its current draw's layout)."""
        return self._observers[copy].layouts[self.task.agent_index(agent)]

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
        """Per-arm, per-joint torque limits, N m."""
        return self.task.torque_limits

    @property
    def connected(self) -> bool:
        """Whether every copy's physics client is connected (False after :meth:`close`)."""
        return bool(self._worlds) and all(world.connected for world in self._worlds)

    def copy_view(self, k: int) -> CopyView:
        """Copy ``k`` as a per-copy consumer (a policy source, a controller) sees it: ``task`` is its current one."""
        return CopyView(self, k)

    # ------------------------------------------------------------------------------------------ one copy
    def world(self, k: int) -> Engine:
        """Copy ``k``'s physics world (the scenario's engine)."""
        return self._worlds[k]

    def arm_set(self, k: int) -> ArmSet:
        """Copy ``k``'s simulated arms (their torques and joint states)."""
        return self._arm_sets[k]

    def step_count(self, k: int) -> int:
        """Env steps of copy ``k`` since its last reset."""
        return int(self._step_counts[k])

    def is_running(self, k: int) -> bool:
        """Whether copy ``k`` is in an episode: reset, not ended (without autoreset), its client connected."""
        return not (self._needs_reset or self._ended[k] or not self._worlds[k].connected)

    def fault_reason(self, k: int) -> str:
        """Copy ``k``'s fault at its last reset/step, in words ("" for none; after an autoreset, the new episode's)."""
        return str(self._last().fault_reason[k])

    def copy_infos(self, k: int) -> dict[str, dict[str, Any]]:
        """agent -> copy ``k``'s info dict at its last reset/step: the array API's row ``k`` less
        ``physics_fault_reason``, taken from the step's values (stacking, then splitting, costs more per step)."""
        m = self._last()
        return one_copy_info_dicts(
            self.possible_agents, self._joint_slices, formation_error_from_squares(m.edge_squares[k]),
            int(self._step_counts[k]) * self.scenario.control_dt, int(m.fault[k]),
            self._observer.padded_slot_errors(m.slot_errors[k]), self._edge_masks[k].copy(),
            m.singularity_margins[k].tolist(), (self._clipped_step[k] / self._joint_counts).tolist(),
            self._torques[k], self._clipped_actions[k].tolist(), self._contacts[k].tolist())

    @property
    def renderer(self) -> SceneRenderer | None:
        """The one copy's renderer (None without a ``render_mode``)."""
        return self._renderer

    # ------------------------------------------------------------------------------------------ dict API
    def reset(self, seed: int | Sequence[int | None] | None = None, options: dict | None = None):
        """Reset every copy (or those of ``options["reset_mask"]``); copy k seeded ``seed + k`` when a seed is
        given, or ``seed[k]`` when it is a sequence of K seeds (each an integer or None: Gymnasium's vector
        convention). Returns observations agent -> (K, obs_dim) and infos agent -> dict of (K, ...) arrays."""
        result = self.reset_arrays(seed=seed, options=options)
        return self._observation_dict(result.observations), self._info_dicts(result.infos)

    def step(self, actions: Mapping[str, np.ndarray]):
        """Apply agent -> (K, act_dim) actions to every copy for ``frame_skip`` physics steps (ended copies
        restart at once with SAME_STEP autoreset, module docstring)."""
        self.check_running()
        normalized = self.actions_check.agent_dict(actions, self.num_envs)
        result = self.step_checked(normalized, self.actions_check.clip(normalized))
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
        seeds = copy_seeds(seed, self.num_envs)
        rows = reset_rows(options, self.num_envs, self._needs_reset)
        if not self.connected:
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
        if self.autoreset:
            infos["final_observation"] = observations.copy()
        K, n = self.num_envs, self.task.n_agents
        return BatchedStep(observations, np.zeros((K, n)), np.zeros(K, dtype=bool), np.zeros(K, dtype=bool), infos)

    def step_arrays(self, actions: np.ndarray) -> BatchedStep:
        """One step of every copy from one array of actions: (K, T) (all joints, agents in order), or, when
        every arm has n joints, (K * N, n) or (K, N, n). Checked (numeric, finite) before any copy moves."""
        self.check_running()
        normalized = self.actions_check.flat_array(actions, self.num_envs)
        return self.step_checked(normalized, self.actions_check.clip(normalized))

    def checked_action_array(self, actions: Any) -> np.ndarray:
        """A fresh float64 (K, T) copy of the array API's actions, or a ``ValueError`` starting ``actions:``
        (what :meth:`step_arrays` checks; for wrappers that transform actions before stepping)."""
        return self.actions_check.flat_array(actions, self.num_envs)

    def step_checked(self, normalized: np.ndarray, clipped: np.ndarray, info_arrays: bool = True) -> BatchedStep:
        """Step every copy with checked, clipped actions (K, T) (``clipped``: the entries clipped per (copy, agent));
        ended copies restart with SAME_STEP autoreset. ``info_arrays=False``: the infos are left out (``{}``; the
        parallel env reads its own, :meth:`ee_formation_env.env.FormationEnv.agent_infos`)."""
        torques = normalized * self._torque_limits_flat  # (K, T), N m
        if self.scenario.gravity_compensation:  # each arm's own g(q) added, within its limits (gravity.py)
            torques = np.clip(torques + self.gravity_torques(), -self._torque_limits_flat, self._torque_limits_flat)
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
        # New arrays each step, never changed in place: the infos hand them out without copies.
        self._step_counts += 1
        self._clipped_actions = self._clipped_actions + clipped
        self._clipped_step = clipped
        self._contacts = np.array(contacts, dtype=np.int64)
        self._torques = torques
        every = self._every
        states = np.array((positions, velocities)).reshape(2, self.num_envs, self.n_joints)
        self._measurement = measured = self._derive(states[0], states[1], every)
        if self._reference is not None:  # the motion's start points, kept while the formation holds
            holding = self._times() <= self.scenario.manoeuvre.start
            self._start_points[holding] = measured.ee_world[holding, :, :self.task.dim]

        if self._sensor is not None:
            self._sense(measured.slot_z, every)
        observations = self._observation_matrix(*self._observed_slots(), measured.q_observed, measured.dq, every,
                                                *self._reference_blocks())
        tracking = self._motion.tracking_ratios(self._times(), self._start_points, measured.ee_world,
                                                self.scenario.reward.tracking_tolerance) if self._tracks else None
        if self._sampled:  # (a distribution has no manoeuvre: no tracking term)
            rewards = np.concatenate([reward_array(measured.edge_squares[k:k + 1], self._copy_tolerances[k],
                                                   self._observers[k], self.scenario.reward) for k in every])
        elif self.num_envs == 1:  # one copy: on its own arrays (ONE_COPY_FAST_PATH)
            rewards = reward_array(measured.edge_squares[0], self._copy_tolerances[0], self._observer,
                                   self.scenario.reward, None if tracking is None else tracking[0])[None]
        else:
            rewards = reward_array(measured.edge_squares, self._copy_tolerances[0], self._observer,
                                   self.scenario.reward, tracking)
        infos = self._info_arrays(measured) if info_arrays else {}
        ended = measured.fault != 0
        if self.scenario.terminate_on_contact:
            ended = ended | (self._contacts > 0).any(axis=1)
        truncated = ~ended & (self._step_counts >= self._max_steps)
        self._last_reasons = measured.fault_reason
        done_mask = ended | truncated
        any_done = np.count_nonzero(done_mask) > 0  # ndarray.any() costs several times more on K = 1
        if not self.autoreset and any_done:
            self._ended |= done_mask
        elif self.autoreset:
            infos["final_observation"] = observations.copy()
            if any_done:
                done = np.flatnonzero(done_mask)
                self._reset_copies(done)
                part = self._measurement
                slot_z, slot_errors = self._observed_slots()
                references = tuple(block[done] for block in self._reference_blocks())
                observations[done] = self._observation_matrix(slot_z[done], slot_errors[done],
                                                              part.q_observed[done], part.dq[done], done, *references)
        return BatchedStep(observations, rewards, ended, truncated, infos)

    # ------------------------------------------------------------------------------------------ state
    def state(self) -> np.ndarray:
        """Every copy's global state (K, state_dim): end-effector positions (world, m), q, dq."""
        measured = self._last()
        return self._observer.state(measured.ee_world, measured.q_observed, measured.dq)

    def end_effector_positions(self) -> np.ndarray:
        """World-frame end-effector positions (K, N, 3), m, at the last reset/step."""
        return self._last().ee_world.copy()

    def edge_errors(self) -> np.ndarray:
        """Every copy's edge errors e_k (K, E) m^2 or (K, E, dim) m (world frame), at the last reset/step."""
        return self._last().edge_errors.copy()

    def joint_positions(self) -> np.ndarray:
        """Every copy's joint positions (K, T), rad (unwrapped), at the last reset/step."""
        return self._last().q.copy()

    def joint_velocities(self) -> np.ndarray:
        """Every copy's joint velocities (K, T), rad/s, at the last reset/step."""
        return self._last().dq.copy()

    def formation_errors(self) -> np.ndarray:
        """Every copy's formation error (K,) (RMS over the edges of |e_k|, m^2 or m) at its last reset/step."""
        return formation_errors_from_squares(self._last().edge_squares)

    def gravity_torques(self) -> np.ndarray:
        """Each copy's arms' own g(q) (K, T), N m, at the last reset/step: what the next step adds to the actions'
        torques under ``gravity_compensation`` (:mod:`ee_formation_env.gravity`)."""
        return np.stack([arm_set.gravity_torques(q, task.gravity_in_base_frames())
                         for arm_set, task, q in zip(self._arm_sets, self.tasks, self._last().q)])

    def reference_centroid(self) -> np.ndarray:
        """Every copy's manoeuvre reference centroid c*(t) (K, dim), world, m, at the last reset/step (the
        parallel env's :meth:`~ee_formation_env.env.FormationEnv.reference_centroid`, per copy)."""
        self._last()
        return self._motion.world(self._times(), self._start_points.mean(axis=-2))[0]

    def centroid_tracking_error(self) -> np.ndarray:
        """Every copy's |c - c*| (K,), m: the end-effectors' centroid against :meth:`reference_centroid`."""
        return self._motion.centroid_errors(self._times(), self._start_points.mean(axis=-2), self._last().ee_world)

    def orientation_tracking_error(self) -> np.ndarray:
        """Every copy's orientation error (K,), rad, against the manoeuvre's turn theta*(t) (0 before it starts)."""
        return self._motion.orientation_errors(self._times(), self._start_points, self._last().ee_world)

    @property
    def physics_fault_reason(self) -> np.ndarray:
        """Each copy's fault at the last step (K,) ("" for none); an autoreset copy's is its ended episode's."""
        return np.array(self._last_reasons, dtype=object)

    def render(self) -> np.ndarray | None:
        """The one copy (``num_envs=1``): an RGB frame (``rgb_array``) or the GUI updated (``human``, returns
        None); :meth:`ee_formation_env.rendering.SceneRenderer.render_copy`."""
        if self._renderer is None:
            gymnasium.logger.warn("render() called without a render_mode; pass render_mode to parallel_env")
            return None
        return self._renderer.render_copy(self.render_mode, self._arm_sets[0].arms, self._last().ee_world[0],
                                          self.tasks[0].formation, int(self._step_counts[0]), self.scenario.control_dt)

    def close(self) -> None:
        """Disconnect every copy's physics client; safe to call more than once."""
        for world in getattr(self, "_worlds", []):
            world.close()

    def __enter__(self) -> "VectorFormationEnv":
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.close()

    def __del__(self) -> None:
        self.close()  # PhysicsWorld.close stays safe at interpreter exit

    # Copies (pickle, deepcopy, subprocess workers) rebuild the env from its scenario in new worlds.
    def __getstate__(self) -> dict[str, Any]:
        r = self._renderer
        render = {} if r is None else {"render_mode": self.render_mode, "render_width": r.width,
                                       "render_height": r.height, "real_time": r.real_time}
        return {"scenario": self.scenario, "num_envs": self.num_envs,
                "autoreset_mode": self.metadata["autoreset_mode"], **render}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state.pop("scenario"), **state)

    # ------------------------------------------------------------------------------------------ internals
    def check_running(self) -> None:
        """Refuse a step of a closed env, of one never reset, or (without autoreset) of ended copies."""
        check_steppable(self.connected, self._needs_reset, self._ended)

    def _times(self) -> np.ndarray:  # each copy's simulated time (K,), s, at its last reset/step
        return self._step_counts * self.scenario.control_dt

    def _reference_blocks(self) -> tuple[np.ndarray, ...]:
        """``(blocks,)``: every copy's manoeuvre reference blocks (K, N r'), or () without a manoeuvre."""
        if self._reference is None:
            return ()
        return (self._reference.observation_block(self._times(), self._start_points.mean(axis=-2)),)

    def _last(self) -> Measurement:  # the last measurement (taken now if the env was never reset)
        if self._measurement is None:
            self._measurement = self._measure_rows(np.arange(self.num_envs))
        return self._measurement

    def _reset_copies(self, rows: np.ndarray) -> None:
        """Reset the copies ``rows`` with their own generators and re-measure them."""
        for k in rows:
            if self._sampled:  # this episode's draw, from the copy's generator
                self._use_task(k, sample_task(self.scenario, self.np_randoms[k],
                                              lambda task, k=k: start_problem(self._arm_sets[k], task)))
            reset_world(self._worlds[k], self._arm_sets[k], self.tasks[k], self.np_randoms[k])
        self._step_counts[rows] = 0
        zeroed = np.isin(self._every, rows)[:, None]  # new arrays, not changed in place: earlier infos hold the old
        self._clipped_actions, self._clipped_step, self._contacts, self._torques = (
            np.where(zeroed, 0, values) for values in (self._clipped_actions, self._clipped_step, self._contacts,
                                                       self._torques))
        self._ended[rows] = False
        part = self._measure_rows(rows)
        if self._measurement is None or len(rows) == self.num_envs:
            self._measurement = part
        else:
            self._measurement = self._measurement.with_rows(rows, part)
        self._start_points[rows] = part.ee_world[..., :self.task.dim]
        if self._sensor is not None:  # a fresh sensor: it holds the start displacement through its delay
            self._sensor.reset(part.slot_z, rows)
            self._sense(part.slot_z, rows)

    def _use_task(self, k: int, task: Any) -> None:
        """Make a drawn task copy ``k``'s current one: its observer (same spaces and slots) and edge tolerances."""
        self.tasks[k], scenario = task, self.scenario
        self._observers[k] = ObservationBuilder(task, scenario.max_joint_velocity, self._bounds, None,
                                                scenario.neighbour_slots)
        self._copy_tolerances[k] = task_edge_tolerances(task)

    def _observation_matrix(self, slot_z: np.ndarray, slot_errors: np.ndarray, q_observed: np.ndarray,
                            dq: np.ndarray, rows: np.ndarray, *references: np.ndarray) -> np.ndarray:
        """The observations (len(rows), O) of the copies ``rows`` from their stacked arrays (and a manoeuvre's
        reference blocks): one batched pass, or, on a scenario distribution (no manoeuvre), each copy with its
        own draw's observer."""
        if not self._sampled:
            if len(rows) == 1:  # one copy: on its own arrays (ONE_COPY_FAST_PATH)
                return self._observer.observation_matrix(slot_z[0], slot_errors[0], q_observed[0], dq[0],
                                                         *(block[0] for block in references))[None]
            return self._observer.observation_matrix(slot_z, slot_errors, q_observed, dq, *references)
        return np.concatenate([self._observers[k].observation_matrix(slot_z[r:r + 1], slot_errors[r:r + 1],
                                                                     q_observed[r:r + 1], dq[r:r + 1])
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

    def _measure_rows(self, rows: np.ndarray) -> Measurement:
        """Read the joint states of the copies ``rows`` (one PyBullet read per arm) and derive everything."""
        positions: list[float] = []
        velocities: list[float] = []
        for k in rows:
            for arm in self._arm_sets[k].arms:
                q, dq = arm.read_state_lists()
                positions += q
                velocities += dq
        shape = (len(rows), self.n_joints)
        return self._derive(np.array(positions).reshape(shape), np.array(velocities).reshape(shape), rows)

    def _derive(self, q: np.ndarray, dq: np.ndarray, rows: np.ndarray) -> Measurement:
        """Everything derived from the stacked joint states (len(rows), T) of the copies ``rows``, in one batched
        pass (faults per copy); on a scenario distribution, each copy with its own draw."""
        faults, reasons = physics_faults(q, dq, self._joint_slices, self.scenario.max_joint_velocity)
        if not self._sampled:
            if len(rows) == 1:  # one copy: on its own arrays (ONE_COPY_FAST_PATH)
                return measure(self.task, self._observer, self._kinematics, self._wrap, q[0], dq[0], faults,
                               reasons, one_copy=True)
            return measure(self.task, self._observer, self._kinematics, self._wrap, q, dq, faults, reasons)
        return Measurement.stacked([measure(self.tasks[k], self._observers[k], self._kinematics, self._wrap,
                                            q[r:r + 1], dq[r:r + 1], faults[r:r + 1], reasons[r:r + 1])
                                    for r, k in enumerate(rows)])

    def _info_arrays(self, measured: Measurement) -> dict[str, np.ndarray]:
        return stacked_infos(measured, self._observer.padded_slot_errors(measured.slot_errors), self._edge_masks,
                             self._clipped_step / self._joint_counts, self._torques, self._clipped_actions,
                             self._contacts, self._times())

    def _observation_dict(self, observations: np.ndarray) -> dict[str, np.ndarray]:
        return {agent: observations[:, part] for agent, part in zip(self.possible_agents, self.observation_slices)}

    def _info_dicts(self, infos: dict[str, np.ndarray]) -> dict[str, dict[str, np.ndarray]]:
        """agent -> dict of (K, ...) arrays, from the stacked infos."""
        return copies_info_dicts(infos, self.possible_agents, self._joint_slices, self.observation_slices)
