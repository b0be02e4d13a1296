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
from ee_formation_env.robot import Arm
from ee_formation_env.scenario import Scenario, load_scenario
from ee_formation_env.validation import initial_configuration, validate_scenario, workspace
from ee_formation_env.world import PhysicsWorld, draw_segment, project_points

_EDGE_COLOR = (220, 30, 30)


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

    **Reward** of agent ``i`` (weights in ``scenario.reward``): ``-(formation * mean_k |e_k| + velocity *
    |dq_i|^2 + torque * |a_i|^2)`` over its incident edges, or the team mean with ``team = True``.

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

    render_width = 480
    render_height = 360

    def __init__(self, scenario: str | os.PathLike | Mapping[str, Any] | Scenario = "planar_square",
                 render_mode: str | None = None, **overrides: Any):
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode: expected None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        self.scenario = scenario if isinstance(scenario, Scenario) and not overrides else load_scenario(
            scenario.to_dict() | {"name": scenario.name} if isinstance(scenario, Scenario) else scenario, **overrides)
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

        self.world = PhysicsWorld(sc.physics_hz, sc.gravity, render_mode)
        self.arms = self._load_arms()
        self._body_to_agent = {arm.body: i for i, arm in enumerate(self.arms)}
        for arm, q in zip(self.arms, self._nominal_q):
            arm.reset_state(q)
        self.world.save_snapshot()
        self.np_random, _ = seeding.np_random(None)
        self._debug_lines = [-1] * self.graph.n_edges
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
        self._slot_edges: list[np.ndarray] = []
        self._slot_signs: list[np.ndarray] = []
        self._observation_spaces: dict[str, gymnasium.spaces.Box] = {}
        self._action_spaces: dict[str, gymnasium.spaces.Box] = {}
        # One bound on |z_ij| for every agent (the largest base distance plus reaches over all edges), so
        # that identical arms get identical spaces and can share one policy.
        z_bound = max(float(np.max(np.abs(formation.desired))), max(
            float(np.linalg.norm(bases[tail] - bases[head])) + self._reaches[tail] + self._reaches[head]
            for tail, head in graph.edges))
        for i, agent in enumerate(self.possible_agents):
            neighbors = graph.neighbors[i]
            self._slot_edges.append(np.array([n.edge for n in neighbors], dtype=np.int64))
            self._slot_signs.append(np.array([n.sign for n in neighbors], dtype=np.float64))
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
        zero = [np.zeros(arm.n_joints) for arm in self.arms]
        observations = self._observations()
        infos = self._infos([z.astype(bool) for z in zero], np.zeros(len(self.arms), dtype=np.int64), "", zero)
        return observations, infos

    def step(self, actions: Mapping[str, np.ndarray]):
        """Apply one action per live agent for ``frame_skip`` physics steps."""
        if self._needs_reset or not self.agents:
            raise RuntimeError("step: call reset() first (the episode has ended or never started)")
        normalized, saturation = self._check_actions(actions)
        torques = [a * limit for a, limit in zip(normalized, self.torque_limits)]
        torque_lists = [tau.tolist() for tau in torques]
        for _ in range(self.scenario.frame_skip):
            for arm, tau in zip(self.arms, torque_lists):
                arm.apply_torques(tau)
            self.world.step()
        self._step_count += 1
        fault = self._read_state()
        contacts = self._count_contacts()

        observations = self._observations()
        rewards = self._rewards(normalized)
        infos = self._infos(saturation, contacts, fault, torques)
        ended = bool(fault) or (self.scenario.terminate_on_contact and bool(contacts.any()))
        truncated = not ended and self._step_count >= self.scenario.max_steps
        terminations = {agent: ended for agent in self.agents}
        truncations = {agent: truncated for agent in self.agents}
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
        return [q.copy() for q in self._q]

    def joint_velocities(self) -> list[np.ndarray]:
        """Each arm's joint velocities (rad/s) at the last reset/step."""
        return [dq.copy() for dq in self._dq]

    def nominal_initial_q(self, agent: str) -> np.ndarray:
        """The scenario's initial joint positions of ``agent`` (rad), before reset noise."""
        return self._nominal_q[self.possible_agents.index(agent)].copy()

    def gravity_in_base_frame(self, agent: str) -> np.ndarray:
        """World gravity (m/s^2) expressed in ``agent``'s base frame: what its own mounting tells it."""
        arm = self.arms[self.possible_agents.index(agent)]
        return arm.base_rotation.T @ np.asarray(self.scenario.gravity)

    def state(self) -> np.ndarray:
        """Global state for centralized critics: all end-effector positions (world, m), all q, all dq."""
        n = len(self.arms)
        state = np.concatenate([self._ee_world[:, :self.dim].ravel(), *self._q_observed, *self._dq])
        del n
        return np.clip(state, self.state_space.low, self.state_space.high).astype(np.float32)

    def render(self) -> np.ndarray | None:
        """``rgb_array``: an RGB frame (H, W, 3) uint8 framing every arm, formation edges in red.
        ``human``: the PyBullet GUI, with the formation edges drawn as debug lines."""
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without a render_mode; pass render_mode to parallel_env")
            return None
        if not hasattr(self, "_ee_world"):
            self._read_state()
        ee = self._ee_world
        if self.render_mode == "human":
            for k, (tail, head) in enumerate(self.graph.edges):
                self._debug_lines[k] = self.world.draw_line(ee[tail], ee[head], (0.9, 0.1, 0.1), self._debug_lines[k])
            return None
        target, distance, yaw, pitch = self._camera()
        image, world_to_clip = self.world.render(target, distance, yaw, pitch, self.render_width, self.render_height)
        pixels = project_points(world_to_clip, ee, self.render_width, self.render_height)
        for tail, head in self.graph.edges:
            draw_segment(image, pixels[tail], pixels[head], _EDGE_COLOR)
        return image

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
        self.close()

    # Copies (pickle, deepcopy, subprocess workers) rebuild the env from its scenario in a new world.
    def __getstate__(self) -> dict[str, Any]:
        return {"scenario": self.scenario, "render_mode": self.render_mode}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["scenario"], render_mode=state["render_mode"])

    # ------------------------------------------------------------------------------------------ internals
    def _check_actions(self, actions: Mapping[str, np.ndarray]) -> tuple[list[np.ndarray], list[np.ndarray]]:
        if not isinstance(actions, Mapping):
            raise TypeError(f"actions: expected a dict agent -> array, got {type(actions).__name__}")
        missing = [a for a in self.agents if a not in actions]
        unknown = [a for a in actions if a not in self.agents]
        if missing or unknown:
            raise ValueError(f"actions: missing agents {missing}, unknown agents {unknown}; expected keys {self.agents}")
        normalized, saturation = [], []
        for i, agent in enumerate(self.agents):
            shape = self._action_spaces[agent].shape
            try:
                action = np.asarray(actions[agent], dtype=np.float64)
            except (TypeError, ValueError):
                raise ValueError(f"actions[{agent!r}]: expected a numeric array of shape {shape}") from None
            if action.shape != shape:
                raise ValueError(f"actions[{agent!r}]: expected shape {shape}, got {action.shape}")
            if not np.all(np.isfinite(action)):
                raise ValueError(f"actions[{agent!r}]: expected finite values of shape {shape}, got {action.tolist()}")
            outside = np.abs(action) > 1.0
            normalized.append(np.clip(action, -1.0, 1.0))
            saturation.append(outside)
        for i, outside in enumerate(saturation):
            self._clipped_actions[i] += int(outside.sum())
        return normalized, saturation

    def _read_state(self) -> str:
        """Read joint states, compute end-effector positions and Jacobians; return a fault reason or ""."""
        self._q, self._dq, self._jacobians, ee = [], [], [], []
        fault = ""
        for i, arm in enumerate(self.arms):
            q, dq = arm.read_state()
            if not (np.all(np.isfinite(q)) and np.all(np.isfinite(dq))):
                fault = fault or f"arm_{i}: non-finite joint state"
                q, dq = np.nan_to_num(q), np.nan_to_num(dq)
            elif np.max(np.abs(dq)) > self.scenario.max_joint_velocity:
                fault = fault or (f"arm_{i}: joint speed {np.max(np.abs(dq)):.1f} rad/s exceeds "
                                  f"max_joint_velocity {self.scenario.max_joint_velocity} rad/s")
            position, jacobian = arm.model.forward_and_jacobian(q)
            self._q.append(q)
            self._dq.append(dq)
            self._jacobians.append(jacobian)
            ee.append(arm.to_world(position))
        self._ee_world = np.asarray(ee)
        self._q_observed = [np.where(arm.model.continuous, (q + math.pi) % (2 * math.pi) - math.pi, q)
                            for arm, q in zip(self.arms, self._q)]
        self._z = self.graph.edge_vectors(self._ee_world[:, :self.dim])
        self._edge_errors = self.formation.edge_errors(self._z)
        return fault

    def _count_contacts(self) -> np.ndarray:
        counts = np.zeros(len(self.arms), dtype=np.int64)
        for body_a, body_b in self.world.contact_pairs():
            a, b = self._body_to_agent.get(body_a), self._body_to_agent.get(body_b)
            if a is not None and b is not None and a != b:
                counts[a] += 1
                counts[b] += 1
        return counts

    def _slot_errors(self, i: int) -> np.ndarray:
        """Agent i's slot edge errors in its own frame: (deg,) or (deg, m)."""
        errors = self._edge_errors[self._slot_edges[i]]
        if self.formation.kind == "distance":
            return errors
        rotation = self.arms[i].base_rotation[:self.dim, :self.dim]
        return (self._slot_signs[i][:, None] * errors) @ rotation

    def _observations(self) -> dict[str, np.ndarray]:
        m, w, size = self.dim, self.formation.error_width, self._slot_size
        observations = {}
        for i, agent in enumerate(self.agents):
            rotation = self.arms[i].base_rotation[:m, :m]  # world <- base; row-vector @ R maps world -> base
            edges, signs = self._slot_edges[i], self._slot_signs[i]
            degree = len(edges)
            slots = np.zeros((self.graph.max_degree, size))
            slots[:degree, 0] = 1.0
            slots[:degree, 1:1 + m] = (signs[:, None] * self._z[edges]) @ rotation
            if self.formation.kind == "distance":
                slots[:degree, 1 + m] = self.formation.desired[edges]
            else:
                slots[:degree, 1 + m:1 + m + w] = (signs[:, None] * self.formation.desired_vectors[edges]) @ rotation
            slots[:degree, 1 + m + w:] = self._slot_errors(i).reshape(degree, w)
            space = self._observation_spaces[agent]
            observation = np.concatenate([slots.ravel(), self._q_observed[i], self._dq[i]])
            observations[agent] = np.clip(observation, space.low, space.high).astype(np.float32)
        return observations

    def _rewards(self, normalized: list[np.ndarray]) -> dict[str, float]:
        weights = self.scenario.reward
        per_edge = np.linalg.norm(self._edge_errors.reshape(self.graph.n_edges, -1), axis=1)
        rewards = np.array([
            -(weights.formation * float(per_edge[self._slot_edges[i]].mean())
              + weights.velocity * float(self._dq[i] @ self._dq[i])
              + weights.torque * float(normalized[i] @ normalized[i]))
            for i in range(len(self.arms))
        ])
        if weights.team:
            rewards[:] = rewards.mean()
        return {agent: float(rewards[i]) for i, agent in enumerate(self.agents)}

    def _infos(self, saturation: list[np.ndarray], contacts: np.ndarray, fault: str,
               torques: list[np.ndarray]) -> dict[str, dict[str, Any]]:
        formation_error = self.formation.formation_error(self._z)
        sim_time = self._step_count * self.scenario.control_dt
        infos = {}
        for i, agent in enumerate(self.agents):
            margin = float(np.linalg.svd(self._jacobians[i][:self.dim], compute_uv=False).min())
            infos[agent] = {
                "formation_error": formation_error,
                "edge_errors": self._slot_errors(i).copy(),
                "singularity_margin": margin,
                "torque_saturation": float(np.mean(saturation[i])),
                "applied_torque": torques[i].copy(),
                "clipped_actions": int(self._clipped_actions[i]),
                "contacts": int(contacts[i]),
                "physics_fault": fault,
                "sim_time": sim_time,
            }
        return infos

    def _camera(self) -> tuple[np.ndarray, float, float, float]:
        bases = np.asarray([arm.base_position for arm in self.arms])
        target = bases.mean(axis=0)
        if self.dim == 3:
            target = target + np.array([0.0, 0.0, -0.5 * max(self._reaches)])
        radius = max(float(np.linalg.norm(b - target)) + r for b, r in zip(bases, self._reaches))
        distance = 1.15 * radius / math.tan(math.radians(25.0))
        if self.dim == 2:
            return target, distance, 0.0, -89.9  # top view of the formation plane
        return target, distance, 45.0, -30.0
