"""The PettingZoo parallel environment: N torque-controlled arms whose end-effectors hold a formation."""

from __future__ import annotations

import math
import os
import tempfile
from typing import Any, Mapping

import gymnasium
import numpy as np
from gymnasium.utils import seeding
from pettingzoo import ParallelEnv

from ee_formation_env.formation import Formation, FormationGraph
from ee_formation_env.kinematics import SerialChain
from ee_formation_env.mismatch import write_perturbed_urdf
from ee_formation_env.observation import ObservationLayout
from ee_formation_env.robot import PYBULLET_MAX_JOINT_VELOCITY, Arm
from ee_formation_env.scenario import Scenario, load_scenario
from ee_formation_env.validation import initial_configuration, validate_scenario, workspace
from ee_formation_env.rendering import SceneRenderer, validate_render_options
from ee_formation_env.world import PhysicsWorld


def smallest_singular_values(matrices: np.ndarray) -> np.ndarray:
    """Smallest singular value of each matrix of a stack (k, r, c).

    2 x 2 matrices [[a, b], [c, d]] use the closed form sigma_min = |hypot(a + d, b - c) - hypot(a - d, b + c)| / 2
    (the two hypotenuses are sigma_max + sigma_min and sigma_max - sigma_min), accurate to rounding relative to
    sigma_max and much cheaper than a LAPACK call at this size; other shapes use ``np.linalg.svd``.
    """
    if matrices.shape[1:] == (2, 2):
        a, b, c, d = matrices[:, 0, 0], matrices[:, 0, 1], matrices[:, 1, 0], matrices[:, 1, 1]
        return 0.5 * np.abs(np.hypot(a + d, b - c) - np.hypot(a - d, b + c))
    return np.linalg.svd(matrices, compute_uv=False).min(axis=1)


class FormationEnv(ParallelEnv):
    """End-effector formation control of N robot arms (Wu et al., "Distributed formation control for
    manipulator end-effectors"), one agent per arm, simulated by PyBullet in torque-control mode.

    Build it with :func:`ee_formation_env.parallel_env` (``scenario`` = a built-in name, a YAML/JSON path
    or a dict; ``**overrides`` replace top-level scenario keys). Agents are ``arm_0 .. arm_{N-1}``.

    **Action** of agent ``i``: ``Box(-1, 1, (n_i,), float32)``, joint torques divided by the per-joint
    torque limits (N m). Values outside [-1, 1] are clipped; the clipping is reported in ``info``.
    The torque is held for ``frame_skip`` physics steps and re-sent before each of them.

    **Observation** of agent ``i``: ``Box(float32)``, everything in the agent's own base frame.
    ``m`` = scenario ``dim`` (2 or 3), ``w`` = 1 for distance and ``m`` for displacement formations,
    ``D`` = the graph's largest degree. Neighbour slots follow the order of the agent's edges in the
    scenario; slots beyond the agent's degree are zero with mask 0.

    ==========================  =========  ==================================================
    entries                     size       meaning (unit)
    ==========================  =========  ==================================================
    slot s, ``mask``            1          1 if slot s holds a neighbour j, else 0
    slot s, ``z_ij``            m          x_i - x_j, end-effector displacement (m)
    slot s, ``desired``         w          d*_ij (m) or z*_ij = x*_i - x*_j (m)
    slot s, ``edge_error``      w          |z_ij|^2 - d*_ij^2 (m^2) or z_ij - z*_ij (m)
    (the 1 + m + 2w slot entries repeat for s = 0 .. D-1)
    ``q``                       n_i        joint positions (rad; continuous joints wrapped to [-pi, pi))
    ``dq``                      n_i        joint velocities (rad/s)
    ==========================  =========  ==================================================

    Bounds are finite: |z| is bounded by base distances plus reaches, ``q`` by the joint limits, ``dq``
    by ``max_joint_velocity`` (faster is a physics fault). Observations are clipped into them.

    **Reward** of agent ``i``, in [0, 1] (weights in ``scenario.reward``, see :class:`RewardConfig`):
    ``1 - formation * tanh(mean_k(|e_k| / s_k) / formation_scale) - velocity * tanh(|dq_i| / velocity_scale)
    - torque * mean(a_i^2)`` over its incident edges (``s_k = d*_k^2`` or ``|z*_k|``: relative edge errors),
    or the team mean with ``team = True``. Never negative, so ending an episode early never pays.

    **Info** of agent ``i``: ``formation_error`` (RMS over all edges of |e_k|, m^2 or m),
    ``edge_errors`` (its slots' errors, own frame), ``singularity_margin`` (smallest singular value of its
    Jacobian's first m rows, m), ``torque_saturation`` (fraction of its joints clipped this step),
    ``clipped_actions`` (count of its action entries outside [-1, 1] so far this episode),
    ``applied_torque`` (the joint torques applied during the step, N m), ``contacts``
    (contact points with other arms), ``physics_fault`` ("" or the reason the episode was terminated),
    ``sim_time`` (s).

    **Episode end**: truncation after ``episode_seconds``; termination on a physics fault (non-finite
    state or |dq| > ``max_joint_velocity``) or, if ``terminate_on_contact``, on contact between arms.
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
        # The nominal kinematic models (what controllers may know); raises before any physics starts.
        self.nominal_models = validate_scenario(self.scenario)
        self.render_mode = render_mode
        sc = self.scenario
        self.formation = Formation(FormationGraph(sc.n_agents, sc.edges), sc.formation, np.asarray(sc.shape))
        self.graph = self.formation.graph
        self.dim = sc.dim
        self.possible_agents = [f"arm_{i}" for i in range(sc.n_agents)]
        self.agents: list[str] = []
        self.torque_limits = [self._torque_limits(i) for i in range(sc.n_agents)]
        self._nominal_q = [initial_configuration(arm, model) for arm, model in zip(sc.arms, self.nominal_models)]
        self._reaches = [workspace(arm.urdf, arm.ee_link, sc.dim).reach for arm in sc.arms]
        self._build_spaces()
        self.observation_spaces = dict(self._observation_spaces)  # PettingZoo's dict attributes
        self.action_spaces = dict(self._action_spaces)

        self.world = PhysicsWorld(sc.physics_hz, sc.gravity, render_mode)
        self.arms = self._load_arms()
        self._body_to_agent = {arm.body: i for i, arm in enumerate(self.arms)}
        self._build_step_tables()
        for arm, q in zip(self.arms, self._nominal_q):
            arm.reset_state(q)
        self.world.save_snapshot()
        self.np_random, _ = seeding.np_random(None)
        self._renderer = SceneRenderer(self.world, self.formation, self.dim, self.render_width, self.render_height,
                                       real_time)
        self._step_count = 0
        self._needs_reset = True

    def _load_arms(self) -> list[Arm]:
        """Load every arm once: the nominal URDF, or a perturbed copy under ``model_mismatch``."""
        sc = self.scenario
        if not sc.model_mismatch.active:
            return [Arm(self.world, arm, model, sc.joint_damping, sc.arm_collisions)
                    for arm, model in zip(sc.arms, self.nominal_models)]
        rng = np.random.default_rng(sc.model_mismatch.seed)
        arms = []
        with tempfile.TemporaryDirectory(prefix="ee_formation_") as directory:
            for arm, model in zip(sc.arms, self.nominal_models):
                joints = [joint.name for joint in model.joints]
                links = [joint.child for joint in model.joints]
                length_scales = 1.0 + rng.uniform(-sc.model_mismatch.length, sc.model_mismatch.length, len(joints))
                mass_scales = 1.0 + rng.uniform(-sc.model_mismatch.mass, sc.model_mismatch.mass, len(links))
                urdf = write_perturbed_urdf(arm.urdf, joints, links, length_scales, mass_scales, directory)
                true_model = SerialChain.from_urdf(urdf, arm.ee_link)
                arms.append(Arm(self.world, arm, true_model, sc.joint_damping, sc.arm_collisions, urdf=urdf))
        return arms

    # ------------------------------------------------------------------------------------------ spaces
    def _torque_limits(self, index: int) -> np.ndarray:
        limits = self.scenario.torque_limits
        model = self.nominal_models[index]
        if limits is None:
            values = model.effort_limits
            if not np.all(np.isfinite(values) & (values > 0)):
                raise ValueError(
                    f"torque_limits: arms[{index}] URDF has joints without a positive effort limit; set torque_limits"
                )
            return values.astype(np.float64)
        if isinstance(limits, float):
            return np.full(model.n_joints, limits)
        row = limits[index] if isinstance(limits[0], tuple) else limits
        return np.asarray(row, dtype=np.float64)

    def _build_spaces(self) -> None:
        sc, formation, graph = self.scenario, self.formation, self.graph
        m, w, slots = self.dim, formation.error_width, graph.max_degree
        self._slot_size = 1 + m + 2 * w
        bases = np.asarray([arm.base_position for arm in sc.arms])
        self._observation_spaces: dict[str, gymnasium.spaces.Box] = {}
        self._action_spaces: dict[str, gymnasium.spaces.Box] = {}
        # One bound on |z_ij| for every agent (the largest base distance plus reaches over all edges), so
        # that identical arms get identical spaces and can share one policy.
        z_bound = max(float(np.max(np.abs(formation.desired))), max(
            float(np.linalg.norm(bases[tail] - bases[head])) + self._reaches[tail] + self._reaches[head]
            for tail, head in graph.edges))
        for i, agent in enumerate(self.possible_agents):
            if sc.formation == "distance":
                desired_low, desired_high, error_bound = 0.0, z_bound, z_bound**2
            else:
                desired_low, desired_high, error_bound = -z_bound, z_bound, 2 * z_bound
            slot_low = np.concatenate([[0.0], np.full(m, -z_bound), np.full(w, desired_low), np.full(w, -error_bound)])
            slot_high = np.concatenate([[1.0], np.full(m, z_bound), np.full(w, desired_high), np.full(w, error_bound)])
            model = self.nominal_models[i]
            q_low = np.where(model.continuous, -math.pi, model.lower)
            q_high = np.where(model.continuous, math.pi, model.upper)
            v = np.full(model.n_joints, sc.max_joint_velocity)
            low = np.concatenate([np.tile(slot_low, slots), q_low, -v]).astype(np.float32)
            high = np.concatenate([np.tile(slot_high, slots), q_high, v]).astype(np.float32)
            self._observation_spaces[agent] = gymnasium.spaces.Box(low, high, dtype=np.float32)
            self._action_spaces[agent] = gymnasium.spaces.Box(-1.0, 1.0, (model.n_joints,), dtype=np.float32)

        ee_bound = max(float(np.max(np.abs(bases[:, :m]))) + max(self._reaches), 1.0)
        state_low = [np.full(sc.n_agents * m, -ee_bound)]
        state_high = [np.full(sc.n_agents * m, ee_bound)]
        for space in self._observation_spaces.values():
            n = (space.shape[0] - slots * self._slot_size) // 2
            state_low.append(space.low[slots * self._slot_size:slots * self._slot_size + n])
            state_high.append(space.high[slots * self._slot_size:slots * self._slot_size + n])
        for space in self._observation_spaces.values():
            n = (space.shape[0] - slots * self._slot_size) // 2
            state_low.append(space.low[-n:])
            state_high.append(space.high[-n:])
        self.state_space = gymnasium.spaces.Box(np.concatenate(state_low).astype(np.float32),
                                                np.concatenate(state_high).astype(np.float32), dtype=np.float32)

    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        return self._observation_spaces[agent]

    def observation_layout(self, agent: str) -> ObservationLayout:
        """How ``agent``'s observation vector is laid out (see the class docstring)."""
        i = self.possible_agents.index(agent)
        return ObservationLayout(self.graph.max_degree, self.dim, self.formation.error_width, self.nominal_models[i].n_joints)

    def action_space(self, agent: str) -> gymnasium.spaces.Box:
        return self._action_spaces[agent]

    # ------------------------------------------------------------------------------------------ API
    def reset(self, seed: int | None = None, options: dict | None = None):
        """Restore the world saved at construction, then randomize the initial joint positions.

        ``seed`` re-seeds the env's generator: the same seed gives bit-identical episodes whatever ran
        before. Initial joint positions are the scenario's plus uniform noise of half-width
        ``initial_q_noise`` (rad), clipped to the joint limits; velocities are zero.
        """
        if seed is not None:
            self.np_random, _ = seeding.np_random(seed)
        if not self.world.connected:
            raise RuntimeError("reset: the environment is closed")
        self.world.restore_snapshot()
        noise = self.scenario.initial_q_noise
        for arm, q0 in zip(self.arms, self._nominal_q):
            q = q0 + self.np_random.uniform(-noise, noise, size=q0.shape) if noise > 0 else q0.copy()
            arm.reset_state(np.clip(q, arm.model.lower, arm.model.upper))
        self.agents = list(self.possible_agents)
        self._step_count = 0
        self._clipped_actions = np.zeros(len(self.agents), dtype=np.int64)
        self._needs_reset = False
        self._read_state()
        observations = self._observations()
        infos = self._infos(np.zeros(len(self.arms), dtype=np.int64), self._no_contacts, "",
                            np.zeros(len(self._torque_limits_flat)))
        return observations, infos

    def step(self, actions: Mapping[str, np.ndarray]):
        """Apply one action per live agent for ``frame_skip`` physics steps."""
        if self._needs_reset or not self.agents:
            raise RuntimeError("step: call reset() first (the episode has ended or never started)")
        normalized, clipped = self._check_actions(actions)
        torques = normalized * self._torque_limits_flat  # every agent's joint torques, N m, one flat vector
        torque_values = torques.tolist()
        commands = [(arm.body, arm.joint_indices, torque_values[joints]) for arm, joints in zip(self.arms, self._joint_slices)]
        self.world.step_with_torques(commands, self.scenario.frame_skip)  # Arm.apply_torques + step, frame_skip times
        self._step_count += 1
        fault = self._read_state()
        contacts = self._count_contacts()

        observations = self._observations()
        rewards = self._rewards(normalized)
        infos = self._infos(clipped, contacts, fault, torques)
        ended = bool(fault) or (self.scenario.terminate_on_contact and any(contacts))
        truncated = not ended and self._step_count >= self.scenario.max_steps
        terminations = dict.fromkeys(self.agents, ended)
        truncations = dict.fromkeys(self.agents, truncated)
        if ended or truncated:
            self.agents = []
            self._needs_reset = True
        return observations, rewards, terminations, truncations, infos

    def end_effector_positions(self) -> np.ndarray:
        """World-frame end-effector positions (N, 3), m, at the last reset/step."""
        return self._ee_world.copy()

    def edge_errors(self) -> np.ndarray:
        """Every edge's error e_k (world frame for displacement formations), at the last reset/step."""
        return self._edge_errors.copy()

    def joint_positions(self) -> list[np.ndarray]:
        """Each arm's joint positions (rad, unwrapped) at the last reset/step."""
        return [self._q[joints].copy() for joints in self._joint_slices]

    def joint_velocities(self) -> list[np.ndarray]:
        """Each arm's joint velocities (rad/s) at the last reset/step."""
        return [self._dq[joints].copy() for joints in self._joint_slices]

    def nominal_initial_q(self, agent: str) -> np.ndarray:
        """The scenario's initial joint positions of ``agent`` (rad), before reset noise."""
        return self._nominal_q[self.possible_agents.index(agent)].copy()

    def gravity_in_base_frame(self, agent: str) -> np.ndarray:
        """World gravity (m/s^2) expressed in ``agent``'s base frame: what its own mounting tells it."""
        arm = self.arms[self.possible_agents.index(agent)]
        return arm.base_rotation.T @ np.asarray(self.scenario.gravity)

    def state(self) -> np.ndarray:
        """Global state for centralized critics: all end-effector positions (world, m), all q, all dq."""
        state = np.concatenate([self._ee_world[:, :self.dim].ravel(), self._q_observed, self._dq])
        return np.clip(state, self.state_space.low, self.state_space.high).astype(np.float32)

    def render(self) -> np.ndarray | None:
        """``rgb_array``: an RGB frame (render_height, render_width, 3) uint8 of every arm, the current
        formation's edges in red and the target formation (placed at the best fit) as a light blue ghost.
        ``human``: the PyBullet GUI with the same camera and lines; returns None. Without a display, a
        ``human`` env simulates headless (warning once) and this does nothing. See ``rendering.py``."""
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without a render_mode; pass render_mode to parallel_env")
            return None
        if not hasattr(self, "_ee_world"):
            self._read_state()
        if self._renderer.camera is None or self._step_count == 0:  # one camera per episode: no shaking
            self._renderer.frame([arm.body for arm in self.arms], self._ee_world)
        if self.render_mode == "human":
            self._renderer.render_human(self._ee_world, self._step_count * self.scenario.control_dt)
            return None
        return self._renderer.render_rgb(self._ee_world)

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
    # The step is vectorized over agents: per-agent quantities live in flat arrays indexed by the tables
    # below, so that one numpy call serves every agent (the cost of a step is mostly per call, not per
    # element, at these sizes).
    def _build_step_tables(self) -> None:
        """Index tables of the vectorized step, built once.

        - Joints: arm i's joints are ``self._joint_slices[i]`` of every flat joint vector (q, dq, actions,
          torques).
        - Kinematics: arms that share one kinematic model object are evaluated in one batch.
        - Slots: the real neighbour slots of all agents, agent by agent (``_slot_edge``, ``_slot_sign``,
          ``_slot_rotation``); agent i's are ``self._slot_slices[i]``. Padding slots are never computed.
        - Observations: all agents' observations are gathered by one index (``_obs_gather``) from one
          source vector ``[0, 1, desired (S w), z (S m), e (S w), q_observed (T), dq (T)]`` (S real slots,
          T joints); agent i's is ``self._obs_slices[i]`` of the result.
        """
        m, w, n_slots = self.dim, self.formation.error_width, self.graph.max_degree
        n_agents = len(self.arms)
        sizes = [arm.n_joints for arm in self.arms]
        joint_bounds = np.concatenate([[0], np.cumsum(sizes)]).astype(np.intp)
        n_total = int(joint_bounds[-1])
        self._n_joints_total = n_total
        self._joint_slices = [slice(int(a), int(b)) for a, b in zip(joint_bounds[:-1], joint_bounds[1:])]
        self._joint_starts = joint_bounds[:-1]
        self._joint_counts = np.asarray(sizes, dtype=np.float64)
        self._action_shapes = [(n,) for n in sizes]
        self._agent_set = frozenset(self.possible_agents)
        self._torque_limits_flat = np.concatenate(self.torque_limits)
        continuous = np.concatenate([arm.model.continuous for arm in self.arms])
        # Continuous joints are observed wrapped to [-pi, pi): None (no joint), True (every joint) or a mask.
        self._wrap = None if not continuous.any() else True if continuous.all() else continuous
        self._no_contacts = [0] * n_agents

        groups: dict[int, list[int]] = {}
        for i, arm in enumerate(self.arms):
            groups.setdefault(id(arm.model), []).append(i)
        self._kinematic_groups: list[tuple[SerialChain, np.ndarray, np.ndarray | None]] = []
        for members in groups.values():
            joints = np.concatenate([np.arange(joint_bounds[i], joint_bounds[i + 1]) for i in members])
            in_order = len(members) == n_agents and np.array_equal(joints, np.arange(n_total))
            self._kinematic_groups.append((self.arms[members[0]].model, np.array(members), None if in_order else joints))
        self._base_rotations = np.stack([arm.base_rotation for arm in self.arms])  # base -> world
        self._base_positions = np.stack([arm.base_position for arm in self.arms])

        neighbors = self.graph.neighbors
        degrees = [len(slots) for slots in neighbors]
        slot_bounds = np.concatenate([[0], np.cumsum(degrees)]).astype(np.intp)
        slot_agent = np.array([i for i, slots in enumerate(neighbors) for _ in slots], dtype=np.intp)
        self._slot_edge = np.array([n.edge for slots in neighbors for n in slots], dtype=np.intp)
        self._slot_sign = np.array([[float(n.sign)] for slots in neighbors for n in slots])  # (S, 1)
        self._slot_rotation = self._base_rotations[slot_agent][:, :m, :m]  # row-vector @ R: world -> own base
        self._slot_starts = slot_bounds[:-1]
        self._slot_degrees = np.asarray(degrees, dtype=np.float64)
        self._slot_slices = [slice(int(a), int(b)) for a, b in zip(slot_bounds[:-1], slot_bounds[1:])]

        # The desired relations in each agent's own frame are constants.
        desired = []
        for i, slots in enumerate(neighbors):
            edges = np.array([n.edge for n in slots], dtype=np.intp)
            if self.formation.kind == "distance":
                desired.append(self.formation.desired[edges])
            else:
                signs = np.array([n.sign for n in slots], dtype=np.float64)
                rotation = self.arms[i].base_rotation[:m, :m]
                desired.append((signs[:, None] * self.formation.desired_vectors[edges]) @ rotation)
        n_real = int(slot_bounds[-1])
        self._obs_constants = np.concatenate([[0.0, 1.0], *(d.ravel() for d in desired)])
        offset_desired, offset_z = 2, 2 + n_real * w
        offset_e = offset_z + n_real * m
        offset_q = offset_e + n_real * w
        offset_dq = offset_q + n_total
        gather, obs_bounds = [], [0]
        for i in range(n_agents):
            for k in range(n_slots):
                if k < degrees[i]:
                    r = int(slot_bounds[i]) + k
                    gather += [1, *range(offset_z + r * m, offset_z + (r + 1) * m),
                               *range(offset_desired + r * w, offset_desired + (r + 1) * w),
                               *range(offset_e + r * w, offset_e + (r + 1) * w)]
                else:
                    gather += [0] * self._slot_size
            gather += [*range(offset_q + joint_bounds[i], offset_q + joint_bounds[i + 1]),
                       *range(offset_dq + joint_bounds[i], offset_dq + joint_bounds[i + 1])]
            obs_bounds.append(len(gather))
        self._obs_gather = np.array(gather, dtype=np.intp)
        self._obs_slices = [slice(a, b) for a, b in zip(obs_bounds[:-1], obs_bounds[1:])]
        spaces = [self._observation_spaces[agent] for agent in self.possible_agents]
        self._obs_low = np.concatenate([space.low for space in spaces]).astype(np.float64)
        self._obs_high = np.concatenate([space.high for space in spaces]).astype(np.float64)

    def _check_actions(self, actions: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Validate one action per live agent; return every agent's action clipped to [-1, 1] as one flat
        vector (float64) and the number of entries clipped per agent. Raises before anything changes."""
        if not isinstance(actions, Mapping):
            raise TypeError(f"actions: expected a dict agent -> array, got {type(actions).__name__}")
        if actions.keys() != self._agent_set:
            missing = [a for a in self.agents if a not in actions]
            unknown = [a for a in actions if a not in self.agents]
            raise ValueError(f"actions: missing agents {missing}, unknown agents {unknown}; expected keys {self.agents}")
        parts = []
        for agent, shape in zip(self.agents, self._action_shapes):
            try:
                action = np.asarray(actions[agent], dtype=np.float64)
            except (TypeError, ValueError):
                self._raise_if_not_finite(parts)
                raise ValueError(f"actions[{agent!r}]: expected a numeric array of shape {shape}") from None
            if action.shape != shape:
                self._raise_if_not_finite(parts)
                raise ValueError(f"actions[{agent!r}]: expected shape {shape}, got {action.shape}")
            parts.append(action)
        normalized = np.concatenate(parts)
        if not np.isfinite(normalized).all():
            self._raise_if_not_finite(parts)
        clipped = np.add.reduceat(np.abs(normalized) > 1.0, self._joint_starts, dtype=np.int64)
        np.minimum(np.maximum(normalized, -1.0, out=normalized), 1.0, out=normalized)  # np.clip, without its overhead
        self._clipped_actions += clipped
        return normalized, clipped

    def _raise_if_not_finite(self, parts: list[np.ndarray]) -> None:
        """The error of the first of the (agent-ordered) actions with a non-finite entry, if any."""
        for agent, action in zip(self.agents, parts):
            if not np.all(np.isfinite(action)):
                shape = self._action_spaces[agent].shape
                raise ValueError(f"actions[{agent!r}]: expected finite values of shape {shape}, got {action.tolist()}")

    def _read_state(self) -> str:
        """Read joint states, compute end-effector positions, Jacobians and edge errors; return a fault
        reason or ""."""
        states = [arm.read_state() for arm in self.arms]
        joint_state = np.concatenate([state[0] for state in states] + [state[1] for state in states])
        q, dq = joint_state[:self._n_joints_total], joint_state[self._n_joints_total:]
        fault = ""
        if not np.isfinite(joint_state).all() or np.abs(dq).max() > self.scenario.max_joint_velocity:
            q, dq, fault = self._physics_fault(states)
        self._q, self._dq = q, dq

        positions, self._group_jacobians = [], []
        for model, members, joints in self._kinematic_groups:
            position, jacobian = model.forward_and_jacobian_batch((q if joints is None else q[joints]).reshape(len(members), -1))
            positions.append(position)
            self._group_jacobians.append(jacobian)
        if len(positions) == 1:
            ee_base = positions[0]
        else:
            ee_base = np.empty((len(self.arms), 3))
            for (_, members, _), position in zip(self._kinematic_groups, positions):
                ee_base[members] = position
        self._ee_world = (self._base_rotations @ ee_base[:, :, None])[:, :, 0] + self._base_positions
        if self._wrap is None:
            self._q_observed = q
        else:
            wrapped = (q + math.pi) % (2 * math.pi) - math.pi
            self._q_observed = wrapped if self._wrap is True else np.where(self._wrap, wrapped, q)
        self._z = self.graph.edge_vectors(self._ee_world[:, :self.dim])
        self._edge_errors = self.formation.edge_errors(self._z)
        errors = self._edge_errors.reshape(self.graph.n_edges, -1)
        self._edge_squares = np.add.reduce(errors * errors, axis=1)  # |e_k|^2
        self._slot_z, self._slot_errors = self._slots_in_own_frames()
        return fault

    def _physics_fault(self, states: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, str]:
        """The first arm's fault (non-finite state, or a joint speed over ``max_joint_velocity``) and the
        joint states with non-finite values replaced by finite ones."""
        fault, qs, dqs = "", [], []
        limit = self.scenario.max_joint_velocity
        for i, (q, dq) in enumerate(states):
            if not (np.all(np.isfinite(q)) and np.all(np.isfinite(dq))):
                fault = fault or f"arm_{i}: non-finite joint state"
                q, dq = np.nan_to_num(q), np.nan_to_num(dq)
            elif np.max(np.abs(dq)) > limit:
                speed = float(np.max(np.abs(dq)))
                # At PyBullet's own clamp the true speed is unknown, only that it is at least that.
                shown = f"at least {speed:.0f}" if speed >= 0.999 * PYBULLET_MAX_JOINT_VELOCITY else f"{speed:.1f}"
                fault = fault or f"arm_{i}: joint speed {shown} rad/s exceeds max_joint_velocity {limit} rad/s"
            qs.append(q)
            dqs.append(dq)
        return np.concatenate(qs), np.concatenate(dqs), fault

    def _count_contacts(self) -> list[int]:
        """Contact points of each agent with other arms."""
        pairs = self.world.contact_pairs()
        if not pairs:
            return self._no_contacts
        counts = [0] * len(self.arms)
        for body_a, body_b in pairs:
            a, b = self._body_to_agent.get(body_a), self._body_to_agent.get(body_b)
            if a is not None and b is not None and a != b:
                counts[a] += 1
                counts[b] += 1
        return counts

    def _slots_in_own_frames(self) -> tuple[np.ndarray, np.ndarray]:
        """Every real slot's z_ij (S, m) and edge error ((S,) or (S, m)), each in its agent's base frame."""
        z_slots = self._slot_sign * self._z[self._slot_edge]  # z_ij = x_i - x_j, world frame
        if self.formation.kind == "distance":
            return (z_slots[:, None, :] @ self._slot_rotation)[:, 0], self._edge_errors[self._slot_edge]
        errors = self._slot_sign * self._edge_errors[self._slot_edge]
        rotated = np.stack([z_slots, errors], axis=1) @ self._slot_rotation
        return rotated[:, 0], rotated[:, 1]

    def _observations(self) -> dict[str, np.ndarray]:
        source = np.concatenate([self._obs_constants, self._slot_z.ravel(), self._slot_errors.ravel(),
                                 self._q_observed, self._dq])
        observation = source[self._obs_gather]
        np.minimum(np.maximum(observation, self._obs_low, out=observation), self._obs_high, out=observation)  # clip
        observation = observation.astype(np.float32)
        return {agent: observation[part] for agent, part in zip(self.agents, self._obs_slices)}

    def _rewards(self, normalized: np.ndarray) -> dict[str, float]:
        weights = self.scenario.reward
        relative = np.sqrt(self._edge_squares) / self.formation.error_scales  # |e_k| / s_k
        formation = np.add.reduceat(relative[self._slot_edge], self._slot_starts) / self._slot_degrees
        speed = np.sqrt(np.add.reduceat(self._dq * self._dq, self._joint_starts))
        effort = np.add.reduceat(normalized * normalized, self._joint_starts) / self._joint_counts
        rewards = 1.0 - (weights.formation * np.tanh(formation / weights.formation_scale)
                         + weights.velocity * np.tanh(speed / weights.velocity_scale) + weights.torque * effort)
        if weights.team:
            rewards[:] = rewards.mean()
        return dict(zip(self.agents, rewards.tolist()))

    def _singularity_margins(self) -> list[float]:
        """Smallest singular value of each arm's Jacobian restricted to the formation's axes, m."""
        if len(self._group_jacobians) == 1:  # every arm has the same model, in agent order
            return smallest_singular_values(self._group_jacobians[0][:, :self.dim]).tolist()
        margins = np.empty(len(self.arms))
        for (_, members, _), jacobians in zip(self._kinematic_groups, self._group_jacobians):
            margins[members] = smallest_singular_values(jacobians[:, :self.dim])
        return margins.tolist()

    def _infos(self, clipped: np.ndarray, contacts: list[int], fault: str,
               torques: np.ndarray) -> dict[str, dict[str, Any]]:
        formation_error = math.sqrt(float(self._edge_squares.sum()) / self.graph.n_edges)  # RMS of |e_k|
        sim_time = self._step_count * self.scenario.control_dt
        margins = self._singularity_margins()
        saturation = (clipped / self._joint_counts).tolist()
        clipped_so_far = self._clipped_actions.tolist()
        errors = self._slot_errors
        infos = {}
        # edge_errors and applied_torque are views of arrays made for this step only, one disjoint slice per agent.
        for i, agent in enumerate(self.agents):
            infos[agent] = {
                "formation_error": formation_error,
                "edge_errors": errors[self._slot_slices[i]],
                "singularity_margin": margins[i],
                "torque_saturation": saturation[i],
                "applied_torque": torques[self._joint_slices[i]],
                "clipped_actions": clipped_so_far[i],
                "contacts": contacts[i],
                "physics_fault": fault,
                "sim_time": sim_time,
            }
        return infos
