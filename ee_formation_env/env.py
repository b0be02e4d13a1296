"""The PettingZoo parallel environment: N torque-controlled arms whose end-effectors hold a formation.

It is the batched env (:mod:`ee_formation_env.vector`) at K = 1 without autoreset, dict in and dict out."""

from __future__ import annotations

import os
from typing import Any, Mapping

import gymnasium
import numpy as np
from pettingzoo import ParallelEnv

from ee_formation_env.formation import Formation, FormationGraph
from ee_formation_env.kinematics import SerialChain
from ee_formation_env.measurement import PHYSICS_FAULTS
from ee_formation_env.observation import ObservationLayout, observation_table
from ee_formation_env.robot import Arm, ArmSet
from ee_formation_env.scenario import Scenario
from ee_formation_env.task import FormationTask
from ee_formation_env.vector import AutoresetMode, VectorFormationEnv
from ee_formation_env.world import Engine

__all__ = ["FormationEnv", "PHYSICS_FAULTS"]


class FormationEnv(ParallelEnv):
    """End-effector formation control of N robot arms (Wu et al., "Distributed formation control for
    manipulator end-effectors"), one agent per arm, simulated by PyBullet in torque-control mode.

    Build it with :func:`ee_formation_env.parallel_env` (``scenario`` = a built-in name, a YAML/JSON path
    or a dict; ``**overrides`` replace top-level scenario keys). Agents are ``arm_0 .. arm_{N-1}``.

    **Action** of agent ``i``: ``Box(-1, 1, (n_i,), float32)``, joint torques divided by the per-joint
    torque limits (N m). Values outside [-1, 1] are clipped; the clipping is reported in ``info``.
    The torque is held for ``frame_skip`` physics steps (one PyBullet call with that many substeps).

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

    **Implementation**: this env is the batched env (:class:`~ee_formation_env.vector.VectorFormationEnv`,
    attribute :attr:`batch`) at K = 1 with autoreset disabled, seen through per-agent dicts: the action check,
    the step, the reset, the measurement, the observations, rewards and infos are the batched env's, row 0.
    Its parts: :class:`~ee_formation_env.task.FormationTask` (everything derived from the scenario),
    :class:`~ee_formation_env.engines.base.Engine` (the physics world: PyBullet's, or MuJoCo's with the scenario
    key ``engine``), :class:`~ee_formation_env.robot.ArmSet`
    (the arms, their torques and joint states), :class:`~ee_formation_env.observation.ObservationBuilder`
    (layouts, spaces, observations), :class:`~ee_formation_env.measurement.Measurement` (what a state read found).

    Arguments of :func:`ee_formation_env.parallel_env` (and of this class):

    ================= ======================================================================================
    argument          meaning
    ================= ======================================================================================
    ``scenario``      a built-in name, a YAML/JSON path, a dict or a :class:`~ee_formation_env.scenario.Scenario`
    ``render_mode``   None, ``"human"`` (the PyBullet GUI) or ``"rgb_array"`` (frames from :meth:`render`)
    ``render_width``  pixels of ``rgb_array`` frames, 16 to 4096 (default 480)
    ``render_height`` pixels of ``rgb_array`` frames, 16 to 4096 (default 360)
    ``real_time``     ``human`` mode: :meth:`render` waits so that the GUI plays at simulated speed
    ``max_cycles``    (:func:`~ee_formation_env.parallel_env` only) truncate episodes after this many env steps
    ``**overrides``   top-level scenario keys replaced (``docs/scenarios.md``)
    ================= ======================================================================================
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
        """Arguments: the class docstring's table."""
        for name in ("num_envs", "autoreset_mode"):  # the batched env's own arguments are not scenario keys
            if name in overrides:
                raise ValueError(f"{name}: not an argument of the parallel env (one copy, no autoreset); use "
                                 "ee_formation_env.vector_env")
        self.batch = VectorFormationEnv(scenario, num_envs=1, autoreset_mode=AutoresetMode.DISABLED,
                                        render_mode=render_mode, render_width=render_width,
                                        render_height=render_height, real_time=real_time, **overrides)
        self.render_width, self.render_height = int(render_width), int(render_height)  # checked by the batched env
        self.scenario = self.batch.scenario
        self.possible_agents = self.batch.possible_agents
        self.observation_spaces = dict(self.batch.observation_spaces)  # PettingZoo's dict attributes
        self.action_spaces = dict(self.batch.action_spaces)
        self.state_space = self.batch.state_space
        self._observation_slices = self.batch.observation_slices
        self._joint_slices = self.batch.joint_slices

    # ------------------------------------------------------------------------------------------ the task
    @property
    def agents(self) -> list[str]:
        """The live agents: every agent during an episode, none before the first reset, after the episode's
        end or after :meth:`close`."""
        return list(self.possible_agents) if self.batch.is_running(0) else []

    @property
    def task(self) -> FormationTask:
        """The current task (on a scenario distribution, this episode's draw)."""
        return self.batch.tasks[0]

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
    def world(self) -> Engine:
        """The physics world (the scenario's engine; PyBullet by default)."""
        return self.batch.world(0)

    @property
    def arm_set(self) -> ArmSet:
        return self.batch.arm_set(0)

    @property
    def arms(self) -> list[Arm]:
        """The simulated arms, in agent order."""
        return self.arm_set.arms

    @property
    def np_random(self) -> np.random.Generator:
        """The episode generator (initial joint noise, scenario draws, sensor noise); ``reset(seed=s)`` re-seeds it."""
        return self.batch.np_randoms[0]

    @np_random.setter
    def np_random(self, generator: np.random.Generator) -> None:
        self.batch.np_randoms[0] = generator

    @property
    def render_mode(self) -> str | None:
        return self.batch.render_mode

    @property
    def step_count(self) -> int:
        """Env steps since the last reset."""
        return self.batch.step_count(0)

    # ------------------------------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        return self.batch.observation_space(agent)

    def action_space(self, agent: str) -> gymnasium.spaces.Box:
        return self.batch.action_space(agent)

    def observation_layout(self, agent: str) -> ObservationLayout:
        """How ``agent``'s observation vector is laid out (see the class docstring)."""
        return self.batch.observation_layout(agent)

    # ------------------------------------------------------------------------------------------ API
    def reset(self, seed: int | None = None, options: dict | None = None):
        """Restore the world saved at construction, then randomize the initial joint positions.

        ``seed`` re-seeds the env's generator: the same seed gives bit-identical episodes whatever ran
        before. Initial joint positions are the scenario's plus uniform noise of half-width
        ``initial_q_noise`` (rad), clipped to the joint limits; velocities are zero.
        """
        result = self.batch.reset_arrays(seed=seed, options=options)
        return self.agent_observations(result.observations), self.agent_infos()

    def step(self, actions: Mapping[str, np.ndarray]):
        """Apply one action per live agent for ``frame_skip`` physics steps."""
        batch = self.batch
        if not batch.is_running(0):
            if not batch.connected:
                raise RuntimeError("step: the environment is closed")
            raise RuntimeError("step: call reset() first (the episode has ended or never started)")
        check = batch.actions_check
        normalized = check.agent_dict(actions, None)
        result = batch.step_checked(normalized, check.clip(normalized), info_arrays=False)
        agents = self.possible_agents
        ended, truncated = result.terminations.item(), result.truncations.item()
        return (self.agent_observations(result.observations), dict(zip(agents, result.rewards.tolist()[0])),
                dict.fromkeys(agents, ended), dict.fromkeys(agents, truncated), self.agent_infos())

    def check_action(self, agent: str, action: Any) -> None:
        """Check one agent's action as :meth:`step` does (a numeric array of its action space's shape, finite);
        ``ValueError`` naming the agent otherwise. Changes nothing (the AEC form checks each action with it
        when it is given, before buffering it)."""
        self.batch.actions_check.agent_action(agent, action)

    @property
    def physics_fault_reason(self) -> str:
        """Why the last step ended the episode ("" if it did not): the arm and the fault, in words."""
        return self.batch.fault_reason(0)

    def end_effector_positions(self) -> np.ndarray:
        """World-frame end-effector positions (N, 3), m, at the last reset/step."""
        return self.batch.end_effector_positions()[0]

    def reference_centroid(self) -> np.ndarray:
        """The manoeuvre's reference centroid c*(t) (dim,), world, m, at the last reset/step: until the motion's
        start t0 the end-effectors' current centroid, then that of t0 moved along the path (without a
        manoeuvre, the centroid at reset: a reference at rest)."""
        return self.batch.reference_centroid()[0]

    def centroid_tracking_error(self) -> float:
        """|c - c*| (m): the end-effectors' centroid against :meth:`reference_centroid`."""
        return float(self.batch.centroid_tracking_error()[0])

    def orientation_tracking_error(self) -> float:
        """The formation's orientation error (rad) against the manoeuvre's turn theta*(t): the best-fit
        rotation's angle (:mod:`ee_formation_env.manoeuvre`); 0 before the motion starts."""
        return float(self.batch.orientation_tracking_error()[0])

    def edge_errors(self) -> np.ndarray:
        """Every edge's error e_k (world frame for displacement formations), at the last reset/step."""
        return self.batch.edge_errors()[0]

    def joint_positions(self) -> list[np.ndarray]:
        """Each arm's joint positions (rad, unwrapped) at the last reset/step."""
        q = self.batch.joint_positions()[0]
        return [q[joints] for joints in self._joint_slices]

    def joint_velocities(self) -> list[np.ndarray]:
        """Each arm's joint velocities (rad/s) at the last reset/step."""
        dq = self.batch.joint_velocities()[0]
        return [dq[joints] for joints in self._joint_slices]

    def state(self) -> np.ndarray:
        """Global state for centralized critics: all end-effector positions (world, m), all q, all dq."""
        return self.batch.state()[0]

    def render(self) -> np.ndarray | None:
        """``rgb_array``: an RGB frame (render_height, render_width, 3) uint8 of every arm, the current
        formation's edges in red and the target formation (placed at the best fit) as a light blue ghost.
        ``human``: the PyBullet GUI with the same camera and lines; returns None. Without a display, a
        ``human`` env simulates headless (warning once) and this does nothing. See ``rendering.py``."""
        return self.batch.render()

    def close(self) -> None:
        """Disconnect the physics client; safe to call more than once."""
        if "batch" in self.__dict__:
            self.batch.close()

    def __enter__(self) -> "FormationEnv":
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.close()

    def __del__(self) -> None:
        self.close()  # PhysicsWorld.close stays safe at interpreter exit

    # Copies (pickle, deepcopy, subprocess workers) rebuild the env from its scenario in a new world.
    def __getstate__(self) -> dict[str, Any]:
        renderer = self.batch.renderer
        return {"scenario": self.scenario, "render_mode": self.render_mode, "render_width": self.render_width,
                "render_height": self.render_height, "real_time": bool(renderer and renderer.real_time)}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state.pop("scenario"), **state)

    # ------------------------------------------------------------------------------------------ dict out
    def agent_observations(self, matrix: np.ndarray) -> dict[str, np.ndarray]:
        """agent -> its observation: views of the one copy's row of the batched observations (1, O)."""
        row = matrix[0]
        return {agent: row[part] for agent, part in zip(self.possible_agents, self._observation_slices)}

    def agent_infos(self) -> dict[str, dict[str, Any]]:
        """agent -> its info dict at the last reset/step: the one copy's row of the batched env's infos, less
        ``physics_fault_reason`` (:meth:`~ee_formation_env.vector.VectorFormationEnv.copy_infos`)."""
        return self.batch.copy_infos(0)


FormationEnv.__doc__ = FormationEnv.__doc__.replace(
    "{observation_table}", "\n".join("    " + line for line in observation_table().splitlines()))
