"""The PettingZoo parallel environment: N torque-controlled arms whose end-effectors hold a formation."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any, Mapping

import gymnasium
import numpy as np
from gymnasium.utils import seeding
from pettingzoo import ParallelEnv

from ee_formation_env.formation import Formation, FormationGraph, formation_error_from_squares
from ee_formation_env.generators import distribution_bounds, sample_task
from ee_formation_env.inputs import check_seed, excerpt, numeric_action
from ee_formation_env.kinematics import SerialChain
from ee_formation_env.manoeuvre import ReferenceMotion
from ee_formation_env.observation import ObservationBuilder, ObservationLayout, observation_table
from ee_formation_env.rendering import SceneRenderer, validate_render_options
from ee_formation_env.robot import PYBULLET_MAX_JOINT_VELOCITY, Arm, ArmSet, check_start_contacts
from ee_formation_env.sensing import Sensor
from ee_formation_env.scenario import Scenario, load_scenario
from ee_formation_env.reward import agent_error_ratios, edge_tolerances, rewards_from_ratios
from ee_formation_env.task import build_task
from ee_formation_env.world import PhysicsWorld

# ``info["physics_fault"]`` codes (0: none). The last fault's full reason (arm, speed) is ``env.physics_fault_reason``.
PHYSICS_FAULTS: dict[int, str] = {0: "none", 1: "non-finite joint state", 2: "joint speed above max_joint_velocity"}


@dataclass(frozen=True, slots=True)
class Measurement:
    """What the env measured at the last reset or step (world frame unless said otherwise)."""

    q: np.ndarray  # (T,) every arm's joint positions, flat, rad (unwrapped)
    dq: np.ndarray  # (T,) rad/s
    q_observed: np.ndarray  # (T,) q with continuous joints wrapped to [-pi, pi), rad
    ee_world: np.ndarray  # (N, 3) end-effector positions, m
    edge_errors: np.ndarray  # (E,) m^2 (distance) or (E, dim) m (displacement)
    edge_squares: np.ndarray  # (E,) |e_k|^2
    slot_z: np.ndarray  # (S, dim) every real neighbour slot's z_ij in its agent's base frame, m
    slot_errors: np.ndarray  # (S,) or (S, dim) the slots' edge errors in their agents' base frames
    singularity_margins: np.ndarray  # (N,) m
    fault: int  # a PHYSICS_FAULTS code, 0 if none
    fault_reason: str  # "" or why the episode must end


class FormationEnv(ParallelEnv):
    """End-effector formation control of N robot arms (Wu et al., "Distributed formation control for
    manipulator end-effectors"), one agent per arm, simulated by PyBullet in torque-control mode.

    Build it with :func:`ee_formation_env.parallel_env` (``scenario`` = a built-in name, a YAML/JSON path
    or a dict; ``**overrides`` replace top-level scenario keys). Agents are ``arm_0 .. arm_{N-1}``.

    **Action** of agent ``i``: ``Box(-1, 1, (n_i,), float32)``, joint torques divided by the per-joint
    torque limits (N m). Values outside [-1, 1] are clipped; the clipping is reported in ``info``.
    The torque is held for ``frame_skip`` physics steps and re-sent before each of them.

    **Observation** of agent ``i``: ``Box(float32)``, everything in the agent's own base frame
    (:mod:`ee_formation_env.observation`; ``m`` = ``dim``, ``w`` = 1 for distance and ``m`` for
    displacement formations, ``D`` = the graph's largest degree):

{observation_table}

    **Reward** of agent ``i`` (:mod:`ee_formation_env.reward`, settings in ``scenario.reward``, see
    :class:`RewardConfig`): ``formation * clip(log10(c / (x_i + f)) / log10(c / f), 0, 1) + in_tolerance *
    [all its edges within tolerance]`` (``c = 100``, ``f = 0.1`` by default), with ``x_i`` the mean over its
    incident edges of ``|e_k| / tol_k`` and ``tol_k`` the edge error of an edge 1 cm (``position_tolerance``)
    off its length; or the team mean with ``team = True``. In [0, 2]; never negative, so ending an episode
    early never pays.

    **Info** of agent ``i``, numeric and of fixed shape (so that TorchRL and RLlib can stack it):
    ``formation_error`` (RMS over all edges of |e_k|, m^2 or m), ``edge_errors`` (its slots' errors, own
    frame, padded with zeros to ``D`` slots: (D,) m^2 or (D, m) m), ``edge_mask`` ((D,) bool, True for a real
    slot), ``singularity_margin`` (smallest singular value of its Jacobian's first m rows, m),
    ``torque_saturation`` (fraction of its joints clipped this step), ``clipped_actions`` (count of its
    action entries outside [-1, 1] so far this episode), ``applied_torque`` (the joint torques applied during
    the step, N m), ``contacts`` (contact points with other arms), ``physics_fault`` (int code, 0 for none,
    see :data:`PHYSICS_FAULTS`; the full reason is :attr:`physics_fault_reason`), ``sim_time`` (s).

    **Manoeuvre** (scenario ``manoeuvre``, :mod:`ee_formation_env.manoeuvre`): the observations end with the
    reference motion in each agent's frame; :meth:`reference_centroid`, :meth:`centroid_tracking_error` and
    :meth:`orientation_tracking_error` measure the tracking (no info key is added).

    **Scenario distributions** (scenario key ``distribution``, :mod:`ee_formation_env.distribution`): every
    ``reset`` draws a validated problem (layout, shape, start) for the same team from the env's generator;
    ``task`` is the current draw, ``scenario`` the distribution; the spaces hold over every draw.

    **Episode end**: truncation after ``episode_seconds``; termination on a physics fault (non-finite
    state or |dq| > ``max_joint_velocity``) or, if ``terminate_on_contact``, on contact between arms.

    Parts: :class:`~ee_formation_env.task.FormationTask` (everything derived from the scenario),
    :class:`~ee_formation_env.world.PhysicsWorld` (the PyBullet client), :class:`~ee_formation_env.robot.ArmSet`
    (the arms, their torques and joint states), :class:`~ee_formation_env.observation.ObservationBuilder`
    (layouts, spaces, observations), :class:`Measurement` (what one state read found).
    """

    metadata = {
        "name": "ee_formation_v0",
        "render_modes": ["human", "rgb_array"],
        "render_fps": 30,
        "is_parallelizable": True,
    }

    def __init__(self, scenario: str | os.PathLike | Mapping[str, Any] | Scenario = "planar_square",
                 render_mode: str | None = None, render_width: int = 480, render_height: int = 360,
                 real_time: bool = False, **overrides: Any):
        """``render_width`` x ``render_height``: pixels of ``rgb_array`` frames (16 to 4096 each).
        ``real_time``: in ``human`` mode, ``render()`` waits so that the GUI plays at simulated speed."""
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode: expected None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        self.render_width, self.render_height, real_time = validate_render_options(render_width, render_height,
                                                                                    real_time)
        self.scenario = load_scenario(scenario, **overrides)
        self.task = build_task(self.scenario)  # validates: raises before any physics starts
        self.render_mode = render_mode
        self.possible_agents = self.task.agents
        self.agents: list[str] = []
        self.world, self.arm_set = build_world(self.task, render_mode)
        self._bounds = None
        if self.scenario.distribution.active:  # one draw now: an infeasible distribution is refused here
            try:
                self.task = sample_task(self.scenario, np.random.default_rng(0), self._start_problem)
            except BaseException:
                self.world.close()
                raise
            self._bounds = distribution_bounds(self.scenario, self.task)
        # The manoeuvre's reference (manoeuvre.py); without one the observations are the plain task's.
        self._motion = ReferenceMotion(self.scenario.manoeuvre, self.task)
        self._reference = self._motion if self.scenario.manoeuvre.active else None
        self._observer = ObservationBuilder(self.task, self.scenario.max_joint_velocity, self._bounds, self._reference)
        sensing = self.scenario.sensing
        self._sensor = Sensor(sensing, self.task, self._observer) if sensing.active else None
        self._observation_spaces = dict(zip(self.possible_agents, self._observer.spaces))
        self._action_spaces = {agent: gymnasium.spaces.Box(-1.0, 1.0, (model.n_joints,), dtype=np.float32)
                               for agent, model in zip(self.possible_agents, self.task.models)}
        self.state_space = self._observer.state_space
        self.observation_spaces = dict(self._observation_spaces)  # PettingZoo's dict attributes
        self.action_spaces = dict(self._action_spaces)

        self._torque_limits_flat = np.concatenate(self.task.torque_limits)
        self._edge_tolerances = edge_tolerances(self.task.formation.kind,
                                                np.linalg.norm(self.task.formation.desired_vectors, axis=1),
                                                self.scenario.reward.position_tolerance)
        continuous = self.arm_set.continuous
        # Continuous joints are observed wrapped to [-pi, pi): None (no joint), True (every joint) or a mask.
        self._wrap = None if not continuous.any() else True if continuous.all() else continuous
        self.np_random, _ = seeding.np_random(None)
        self._renderer = SceneRenderer(self.world, self.task.formation, self.task.dim, self.render_width,
                                       self.render_height, real_time)
        self._step_count = 0
        self._clipped_actions = np.zeros(self.task.n_agents, dtype=np.int64)
        self._measurement: Measurement | None = None
        self._start_points = np.zeros((1, self.task.n_agents, self.task.dim))  # at the motion's start (m)
        self._needs_reset = True

    # ------------------------------------------------------------------------------------------ the task
    @property
    def formation(self) -> Formation:
        return self.task.formation

    @property
    def graph(self) -> FormationGraph:
        return self.task.graph

    @property
    def dim(self) -> int:
        return self.task.dim

    @property
    def nominal_models(self) -> tuple[SerialChain, ...]:
        """The arms' nominal kinematic models (what controllers may know)."""
        return self.task.models

    @property
    def torque_limits(self) -> tuple[np.ndarray, ...]:
        """Per-arm, per-joint torque limits, N m."""
        return self.task.torque_limits

    @property
    def arms(self) -> list[Arm]:
        """The simulated arms, in agent order."""
        return self.arm_set.arms

    # ------------------------------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        return self._observation_spaces[agent]

    def action_space(self, agent: str) -> gymnasium.spaces.Box:
        return self._action_spaces[agent]

    def observation_layout(self, agent: str) -> ObservationLayout:
        """How ``agent``'s observation vector is laid out (see the class docstring)."""
        return self._observer.layouts[self.task.agent_index(agent)]

    # ------------------------------------------------------------------------------------------ API
    def reset(self, seed: int | None = None, options: dict | None = None):
        """Restore the world saved at construction, then randomize the initial joint positions.

        ``seed`` re-seeds the env's generator: the same seed gives bit-identical episodes whatever ran
        before. Initial joint positions are the scenario's plus uniform noise of half-width
        ``initial_q_noise`` (rad), clipped to the joint limits; velocities are zero.
        """
        seed = check_seed(seed)  # numpy integers are seeds too; negative ones are refused before any change
        if not self.world.connected:
            raise RuntimeError("reset: the environment is closed")
        if seed is not None:
            self.np_random, _ = seeding.np_random(seed)
        if self.scenario.distribution.active:  # this episode's draw, from the episode's generator
            self._use_task(sample_task(self.scenario, self.np_random, self._start_problem))
        reset_world(self.world, self.arm_set, self.task, self.np_random)
        self.agents = list(self.possible_agents)
        self._step_count = 0
        self._clipped_actions = np.zeros(len(self.agents), dtype=np.int64)
        self._needs_reset = False
        self._measurement = measured = self._measure()
        self._start_points = measured.ee_world[None, :, :self.task.dim].copy()
        observations = self._observations(measured, reset=True)
        infos = self._infos(measured, np.zeros(len(self.arms), dtype=np.int64), [0] * len(self.arms),
                            np.zeros(len(self._torque_limits_flat)))
        return observations, infos

    def step(self, actions: Mapping[str, np.ndarray]):
        """Apply one action per live agent for ``frame_skip`` physics steps."""
        if self._needs_reset or not self.agents:
            raise RuntimeError("step: call reset() first (the episode has ended or never started)")
        normalized, clipped = self._check_actions(actions)
        torques = normalized * self._torque_limits_flat  # every agent's joint torques, N m, one flat vector
        self.arm_set.step(torques, self.scenario.frame_skip)
        self._step_count += 1
        self._measurement = measured = self._measure()
        holding = self._step_count * self.scenario.control_dt <= self.scenario.manoeuvre.start
        if self._reference is not None and holding:  # the motion's start points, kept while the formation holds
            self._start_points = measured.ee_world[None, :, :self.task.dim].copy()
        contacts = self.arm_set.contacts_per_arm()

        observations = self._observations(measured)
        rewards = self._rewards(measured)
        infos = self._infos(measured, clipped, contacts, torques)
        ended = measured.fault != 0 or (self.scenario.terminate_on_contact and any(contacts))
        truncated = not ended and self._step_count >= self.scenario.max_steps
        terminations = dict.fromkeys(self.agents, ended)
        truncations = dict.fromkeys(self.agents, truncated)
        if ended or truncated:
            self.agents = []
            self._needs_reset = True
        return observations, rewards, terminations, truncations, infos

    @property
    def physics_fault_reason(self) -> str:
        """Why the last step ended the episode ("" if it did not): the arm and the fault, in words."""
        return self._last().fault_reason

    def end_effector_positions(self) -> np.ndarray:
        """World-frame end-effector positions (N, 3), m, at the last reset/step."""
        return self._last().ee_world.copy()

    def reference_centroid(self) -> np.ndarray:
        """The manoeuvre's reference centroid c*(t) (dim,), world, m, at the last reset/step: until the motion's
        start t0 the end-effectors' current centroid, then that of t0 moved along the path (without a
        manoeuvre, the centroid at reset: a reference at rest)."""
        self._last()
        return self._motion.world(self._times(), self._start_points.mean(axis=-2))[0][0]

    def centroid_tracking_error(self) -> float:
        """|c - c*| (m): the end-effectors' centroid against :meth:`reference_centroid`."""
        return float(self._motion.centroid_errors(self._times(), self._start_points.mean(axis=-2),
                                                  self._last().ee_world[None])[0])

    def orientation_tracking_error(self) -> float:
        """The formation's orientation error (rad) against the manoeuvre's turn theta*(t): the best-fit
        rotation's angle (:mod:`ee_formation_env.manoeuvre`); 0 before the motion starts."""
        return float(self._motion.orientation_errors(self._times(), self._start_points, self._last().ee_world[None])[0])

    def edge_errors(self) -> np.ndarray:
        """Every edge's error e_k (world frame for displacement formations), at the last reset/step."""
        return self._last().edge_errors.copy()

    def joint_positions(self) -> list[np.ndarray]:
        """Each arm's joint positions (rad, unwrapped) at the last reset/step."""
        q = self._last().q
        return [q[joints].copy() for joints in self.arm_set.joint_slices]

    def joint_velocities(self) -> list[np.ndarray]:
        """Each arm's joint velocities (rad/s) at the last reset/step."""
        dq = self._last().dq
        return [dq[joints].copy() for joints in self.arm_set.joint_slices]

    def state(self) -> np.ndarray:
        """Global state for centralized critics: all end-effector positions (world, m), all q, all dq."""
        measured = self._last()
        return self._observer.state(measured.ee_world, measured.q_observed, measured.dq)

    def render(self) -> np.ndarray | None:
        """``rgb_array``: an RGB frame (render_height, render_width, 3) uint8 of every arm, the current
        formation's edges in red and the target formation (placed at the best fit) as a light blue ghost.
        ``human``: the PyBullet GUI with the same camera and lines; returns None. Without a display, a
        ``human`` env simulates headless (warning once) and this does nothing. See ``rendering.py``."""
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without a render_mode; pass render_mode to parallel_env")
            return None
        ee = self._last().ee_world
        if self._renderer.camera is None or self._step_count == 0:  # one camera per episode: no shaking
            self._renderer.frame([arm.body for arm in self.arms], ee)
        if self.render_mode == "human":
            self._renderer.render_human(ee, self._step_count * self.scenario.control_dt)
            return None
        return self._renderer.render_rgb(ee)

    def close(self) -> None:
        """Disconnect the physics client; safe to call more than once."""
        if hasattr(self, "world"):
            self.world.close()
        self.agents = []

    def __enter__(self) -> "FormationEnv":
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.close()

    def __del__(self) -> None:
        self.close()  # PhysicsWorld.close stays safe at interpreter exit

    # Copies (pickle, deepcopy, subprocess workers) rebuild the env from its scenario in a new world.
    def __getstate__(self) -> dict[str, Any]:
        return {"scenario": self.scenario, "render_mode": self.render_mode, "render_width": self.render_width,
                "render_height": self.render_height, "real_time": self._renderer.real_time}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state.pop("scenario"), **state)

    # ------------------------------------------------------------------------------------------ internals
    def _start_problem(self, task: Any) -> str | None:
        """Why a drawn task cannot start in this world (arms in contact at their initial configurations), or
        None; the arms are left placed there."""
        return start_problem(self.arm_set, task)

    def _use_task(self, task: Any) -> None:
        """Make a drawn task the current one: its observer (same spaces: the distribution's bounds), edge
        tolerances and ghost."""
        self.task = task
        self._observer = ObservationBuilder(task, self.scenario.max_joint_velocity, self._bounds)
        self._edge_tolerances = edge_tolerances(task.formation.kind, np.linalg.norm(task.formation.desired_vectors,
                                                                                    axis=1),
                                                self.scenario.reward.position_tolerance)
        self._renderer.formation = task.formation
    def _times(self) -> np.ndarray:
        """The simulated time (1,), s, of the last reset/step (the manoeuvre's functions take K copies')."""
        return np.array([self._step_count * self.scenario.control_dt])

    def _last(self) -> Measurement:
        """The last measurement (taken now if the env was never reset)."""
        if self._measurement is None:
            self._measurement = self._measure()
        return self._measurement

    def _check_actions(self, actions: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Validate one action per live agent; return every agent's action clipped to [-1, 1] as one flat
        vector (float64) and the number of entries clipped per agent. Raises before anything changes."""
        if not isinstance(actions, Mapping):
            raise TypeError(f"actions: expected a dict agent -> array, got {type(actions).__name__}")
        if actions.keys() != self._action_spaces.keys():
            missing = [a for a in self.agents if a not in actions]
            unknown = [a for a in actions if a not in self.agents]
            raise ValueError(f"actions: missing agents {missing}, unknown agents {unknown}; expected keys {self.agents}")
        parts = [actions[agent] for agent in self.agents]
        # The common case in one call: numpy arrays of the right shapes; anything else gets the detailed check.
        if all(getattr(part, "shape", None) == space.shape for part, space in zip(parts, self._action_spaces.values())):
            try:
                normalized = np.concatenate(parts, dtype=np.float64)
            except (TypeError, ValueError):
                normalized = self._checked_concatenation(parts)
        else:
            normalized = self._checked_concatenation(parts)
        if not np.isfinite(normalized).all():
            self._raise_if_not_finite([np.asarray(part, dtype=np.float64) for part in parts])
        clipped = np.add.reduceat(np.abs(normalized) > 1.0, self.arm_set.joint_starts, dtype=np.int64)
        np.minimum(np.maximum(normalized, -1.0, out=normalized), 1.0, out=normalized)  # np.clip, without its overhead
        self._clipped_actions += clipped
        return normalized, clipped

    def _checked_concatenation(self, parts: list[Any]) -> np.ndarray:
        """The agents' actions as one float64 vector, or the error of the first bad one (in agent order)."""
        checked = []
        for agent, part in zip(self.agents, parts):
            try:
                checked.append(self._action_array(agent, part))
            except ValueError:
                self._raise_if_not_finite(checked)
                raise
        return np.concatenate(checked)

    def _action_array(self, agent: str, action: Any) -> np.ndarray:
        return numeric_action(agent, action, self._action_spaces[agent].shape)

    def check_action(self, agent: str, action: Any) -> None:
        """Check one agent's action as :meth:`step` does (a numeric array of its action space's shape, finite);
        ``ValueError`` naming the agent otherwise. Changes nothing (the AEC form checks each action with it
        when it is given, before buffering it)."""
        if agent not in self._action_spaces:
            raise ValueError(f"actions: unknown agent {excerpt(agent)}; expected one of {self.possible_agents}")
        array = self._action_array(agent, action)
        if not np.all(np.isfinite(array)):
            shape = self._action_spaces[agent].shape
            raise ValueError(f"actions[{agent!r}]: expected finite values of shape {shape}, got {array.tolist()}")

    def _raise_if_not_finite(self, parts: list[np.ndarray]) -> None:
        """The error of the first of the (agent-ordered) actions with a non-finite entry, if any."""
        for agent, action in zip(self.agents, parts):
            if not np.all(np.isfinite(action)):
                shape = self._action_spaces[agent].shape
                raise ValueError(f"actions[{agent!r}]: expected finite values of shape {shape}, got {action.tolist()}")

    def _observations(self, measured: Measurement, reset: bool = False) -> dict[str, np.ndarray]:
        """Every live agent's observation of ``measured``: its z_ij as its sensor reports them (sensing.py)."""
        slot_z, slot_errors = measured.slot_z, measured.slot_errors
        if self._sensor is not None:  # one copy of the sensor's batched form
            if reset:
                self._sensor.reset(slot_z[None], [0])
            sensed_z, sensed_errors = self._sensor.sense(slot_z[None], [0], [self.np_random])
            slot_z, slot_errors = sensed_z[0], sensed_errors[0]
        if self._reference is None:
            return self._observer.observations(self.agents, slot_z, slot_errors, measured.q_observed, measured.dq)
        reference = self._reference.observation_block(self._times(), self._start_points.mean(axis=-2))[0]
        return self._observer.observations(self.agents, slot_z, slot_errors, measured.q_observed, measured.dq,
                                           reference)

    def _measure(self) -> Measurement:
        """Read the joint states and compute everything derived from them (a physics fault included)."""
        q, dq = self.arm_set.read_states()
        fault, reason = 0, ""
        # One test for both faults: NaN fails the comparison, and a non-finite q makes its sum non-finite.
        if not (np.abs(dq).max() <= self.scenario.max_joint_velocity and math.isfinite(q.sum())):
            q, dq, fault, reason = physics_fault(q, dq, self.arm_set.joint_slices, self.scenario.max_joint_velocity)
        return measure(self.task, self._observer, self.arm_set.kinematics, self._wrap, q, dq, fault, reason)

    def _rewards(self, measured: Measurement) -> dict[str, float]:
        rewards = reward_array(measured.edge_squares, self._edge_tolerances, self._observer, self.scenario.reward)
        return dict(zip(self.agents, rewards.tolist()))

    def _infos(self, measured: Measurement, clipped: np.ndarray, contacts: list[int],
               torques: np.ndarray) -> dict[str, dict[str, Any]]:
        formation_error = formation_error_from_squares(measured.edge_squares)
        sim_time = self._step_count * self.scenario.control_dt
        margins = measured.singularity_margins.tolist()
        saturation = (clipped / self.arm_set.joint_counts).tolist()
        clipped_so_far = self._clipped_actions.tolist()
        errors = self._observer.padded_slot_errors(measured.slot_errors)
        # A fresh (N, D) copy of the constant masks: infos of different calls must share no object (gymnasium
        # 1.4's check_env tests it, 1.2's does not).
        masks, joint_slices = np.array(self._observer.slot_masks), self.arm_set.joint_slices
        infos = {}
        # edge_errors, edge_mask and applied_torque are views of arrays made for this step only, one disjoint
        # slice per agent.
        for i, agent in enumerate(self.agents):
            infos[agent] = {
                "formation_error": formation_error,
                "edge_errors": errors[i],
                "edge_mask": masks[i],
                "singularity_margin": margins[i],
                "torque_saturation": saturation[i],
                "applied_torque": torques[joint_slices[i]],
                "clipped_actions": clipped_so_far[i],
                "contacts": contacts[i],
                "physics_fault": measured.fault,
                "sim_time": sim_time,
            }
        return infos


# ---------------------------------------------------------------------------------------------- shared arithmetic
# The single env and the batched env (:mod:`ee_formation_env.vector`) share these: the single env calls them
# on one formation's arrays ((T,) joints), the batched env on K copies' stacked arrays ((K, T)) in one pass.

def build_world(task: Any, render_mode: str | None = None) -> tuple[PhysicsWorld, ArmSet]:
    """One PyBullet client holding the task's arms at their initial configurations (start contacts refused
    while ``arm_collisions`` is on), its state saved for :func:`reset_world`."""
    scenario = task.scenario
    world = PhysicsWorld(scenario.physics_hz, scenario.gravity, render_mode)
    try:  # a refusal after connecting (a URDF PyBullet rejects, arms in contact) leaves no client behind
        arm_set = ArmSet(world, task)
        arm_set.reset(list(task.initial_q))
        if scenario.arm_collisions:
            check_start_contacts(arm_set)
    except BaseException:
        world.close()
        raise
    world.save_snapshot()
    return world, arm_set


def start_problem(arm_set: ArmSet, task: Any) -> str | None:
    """Place ``arm_set``'s arms as ``task`` (a scenario distribution's draw) has them, at its initial
    configurations; why they cannot start there (arms in contact, while ``arm_collisions`` is on), or None."""
    arm_set.place_bases(task)
    arm_set.reset(list(task.initial_q))
    if task.scenario.arm_collisions:
        try:
            check_start_contacts(arm_set)
        except ValueError as error:
            return str(error)
    return None


def reset_world(world: PhysicsWorld, arm_set: ArmSet, task: Any, rng: np.random.Generator) -> None:
    """Restore the saved world, then place the arms at the scenario's initial joint positions plus uniform
    noise of half-width ``initial_q_noise`` drawn from ``rng`` (clipped to the joint limits), at rest. A task
    whose bases are not the saved ones (a scenario distribution's draw) has its bases moved there first."""
    world.restore_snapshot()
    if any(arm.config is not config for arm, config in zip(arm_set.arms, task.scenario.arms)):
        arm_set.place_bases(task)
    noise = task.scenario.initial_q_noise
    starts = []
    for arm, q0 in zip(arm_set.arms, task.initial_q):
        q = q0 + rng.uniform(-noise, noise, size=q0.shape) if noise > 0 else q0.copy()
        starts.append(np.clip(q, arm.model.lower, arm.model.upper))
    arm_set.reset(starts)


def physics_fault(q: np.ndarray, dq: np.ndarray, joint_slices: list[slice], limit: float
                  ) -> tuple[np.ndarray, np.ndarray, int, str]:
    """One formation's joint states (T,) with non-finite values replaced by finite ones, and the first arm's
    fault (non-finite state, or a joint speed over ``limit`` = ``max_joint_velocity``): its code and reason."""
    for i, joints in enumerate(joint_slices):
        if not (np.all(np.isfinite(q[joints])) and np.all(np.isfinite(dq[joints]))):
            return np.nan_to_num(q), np.nan_to_num(dq), 1, f"arm_{i}: non-finite joint state"
        if np.max(np.abs(dq[joints])) > limit:
            speed = float(np.max(np.abs(dq[joints])))
            # At PyBullet's own clamp the true speed is unknown, only that it is at least that.
            shown = f"at least {speed:.0f}" if speed >= 0.999 * PYBULLET_MAX_JOINT_VELOCITY else f"{speed:.1f}"
            return (np.nan_to_num(q), np.nan_to_num(dq), 2,
                    f"arm_{i}: joint speed {shown} rad/s exceeds max_joint_velocity {limit} rad/s")
    raise AssertionError("physics_fault called without a fault")


def measure(task: Any, observer: ObservationBuilder, kinematics: Any, wrap: Any, q: np.ndarray, dq: np.ndarray,
            fault: Any, reason: Any) -> Measurement:
    """Everything derived from the joint states ``q``, ``dq`` (finite): one formation's (T,), or K copies'
    stacked (K, T), whose results get a leading K axis (each row bit for bit the single formation's).
    ``wrap``: None, True or a mask of the joints observed wrapped to [-pi, pi)."""
    ee_base, margins = kinematics.positions_and_margins(q, task.dim)
    ee_world = (task.base_rotations @ ee_base[..., None])[..., 0] + task.base_positions
    if wrap is None:
        q_observed = q
    else:
        wrapped = (q + math.pi) % (2 * math.pi) - math.pi
        q_observed = wrapped if wrap is True else np.where(wrap, wrapped, q)
    z = task.graph.edge_vectors(ee_world[..., :task.dim])
    edge_errors = task.formation.edge_errors(z)
    errors = edge_errors.reshape(*q.shape[:-1], task.graph.n_edges, -1)
    slot_z, slot_errors = observer.slots_in_own_frames(z, edge_errors)
    return Measurement(q=q, dq=dq, q_observed=q_observed, ee_world=ee_world, edge_errors=edge_errors,
                       edge_squares=np.add.reduce(errors * errors, axis=-1), slot_z=slot_z,
                       slot_errors=slot_errors, singularity_margins=margins, fault=fault, fault_reason=reason)


def reward_array(edge_squares: np.ndarray, tolerances: np.ndarray, observer: ObservationBuilder,
                 config: Any) -> np.ndarray:
    """Every agent's reward (N,) from the edges' squared errors (E,); or (K, N) from K copies' (K, E)."""
    ratios, within = agent_error_ratios(np.sqrt(edge_squares), tolerances, observer.slot_edge,
                                        observer.slot_starts, observer.slot_degrees)
    return rewards_from_ratios(ratios, within, config)


FormationEnv.__doc__ = FormationEnv.__doc__.replace(
    "{observation_table}", "\n".join("    " + line for line in observation_table().splitlines()))
