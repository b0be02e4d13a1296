"""The benchmark's timers and budgets: each case timed from the same reset state, cases interleaved round by round
(``docs/performance.md``, "Method")."""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np
import pybullet

import ee_formation_env
from ee_formation_env.env import FormationEnv


@dataclass(frozen=True)
class Budget:
    """How many steps each measurement takes, and how often it is repeated."""

    physics_steps: int  # simulated span of one raw-floor / env.step run, in physics steps (same for both)
    closed_loop_seconds: float  # simulated seconds of closed loop per repeat (planar_square)
    closed_loop_seconds_spatial: float
    sb3_steps: int  # n_steps of the PPO rollout (per slot)
    training_updates: int  # PPO updates of train.py's default run timed per repeat
    resets: int
    repeats: int
    scaling_repeats: int


    vector_physics_steps: int = 64 * 600  # formation physics steps per vector-section run (all K copies together)


FULL = Budget(physics_steps=10_000, closed_loop_seconds=30.0,
              closed_loop_seconds_spatial=10.0, sb3_steps=512, training_updates=4, resets=200, repeats=5, scaling_repeats=3)
QUICK = Budget(physics_steps=200, closed_loop_seconds=0.5,
               closed_loop_seconds_spatial=0.2, sb3_steps=16, training_updates=1, resets=5, repeats=1, scaling_repeats=1,
               vector_physics_steps=4 * 40)


# ---------------------------------------------------------------------------------------------- timers
def _zero_actions(env: FormationEnv) -> dict[str, np.ndarray]:
    return {agent: np.zeros(env.action_space(agent).shape, dtype=np.float32) for agent in env.possible_agents}


def time_zero_torques(client: int, arms: Sequence[Any], steps: int) -> float:
    """Seconds for ``steps`` physics steps of one client's ``arms``: zero torques set, ``stepSimulation``."""
    commands = [(arm.body, arm.joint_indices, [0.0] * arm.n_joints) for arm in arms]
    set_motors, step, torque_control = pybullet.setJointMotorControlArray, pybullet.stepSimulation, pybullet.TORQUE_CONTROL
    start = time.perf_counter()
    for _ in range(steps):
        for body, joints, forces in commands:
            set_motors(body, joints, torque_control, forces=forces, physicsClientId=client)
        step(physicsClientId=client)
    return time.perf_counter() - start


def time_raw_floor(env: FormationEnv, steps: int) -> float:
    """Seconds for ``steps`` physics steps of the env's bodies: zero torques set, ``stepSimulation``."""
    env.reset(seed=0)
    return time_zero_torques(env.world.client, env.arms, steps)


def _ee_link_index(body: int, name: str, client: int) -> int:
    for j in range(pybullet.getNumJoints(body, physicsClientId=client)):
        if pybullet.getJointInfo(body, j, physicsClientId=client)[12].decode() == name:
            return j
    raise ValueError(f"link {name!r} not found")


def time_naive_loop(env: FormationEnv, steps: int) -> float:
    """Seconds for ``steps`` physics steps with a naive per-arm query loop: joint states, end-effector link
    state and torques, one PyBullet call each per arm and step (a reference point: ``docs/physics.md``, "Raw
    PyBullet speed")."""
    env.reset(seed=0)
    client = env.world.client
    arms = [(arm.body, arm.joint_indices, _ee_link_index(arm.body, arm.config.ee_link, client), [0.0] * arm.n_joints)
            for arm in env.arms]
    start = time.perf_counter()
    for _ in range(steps):
        for body, joints, link, forces in arms:
            pybullet.getJointStates(body, joints, physicsClientId=client)
            pybullet.getLinkState(body, link, computeForwardKinematics=1, physicsClientId=client)
            pybullet.setJointMotorControlArray(body, joints, pybullet.TORQUE_CONTROL, forces=forces,
                                               physicsClientId=client)
        pybullet.stepSimulation(physicsClientId=client)
    return time.perf_counter() - start


def time_env_steps(env: FormationEnv, steps: int, seed: int = 0) -> float:
    """Seconds for ``steps`` calls of ``env.step`` with zero actions (episodes that end are reset)."""
    actions = _zero_actions(env)
    env.reset(seed=seed)
    start = time.perf_counter()
    for _ in range(steps):
        env.step(actions)
        if not env.agents:
            env.reset()
    return time.perf_counter() - start


def time_closed_loop(env: FormationEnv, policies: dict[str, Any], steps: int, seed: int = 0,
                     batched: bool = True) -> float:
    """Seconds for ``steps`` env steps with one controller per agent acting on its observation: evaluated as
    one :class:`ee_formation_env.baselines.reference.controllers.PolicyTeam` (``batched``, as ``run_episode`` does) or agent by agent."""
    from ee_formation_env.baselines.reference.team import PolicyTeam

    team = PolicyTeam(policies)
    act = team if batched else (lambda observations: {a: policies[a](observations[a]) for a in env.agents})
    observations, _ = env.reset(seed=seed)
    team.reset()
    start = time.perf_counter()
    for _ in range(steps):
        observations, _, _, _, _ = env.step(act(observations))
        if not env.agents:
            observations, _ = env.reset()
            team.reset()
    return time.perf_counter() - start


def time_resets(env: FormationEnv, count: int) -> float:
    """Mean seconds of one ``env.reset`` (after a few steps, so that there is state to restore)."""
    actions = _zero_actions(env)
    total = 0.0
    for k in range(count):
        env.reset(seed=k)
        env.step(actions)
        start = time.perf_counter()
        env.reset(seed=k + 1)
        total += time.perf_counter() - start
    return total / count


def interleaved(cases: dict[str, Callable[[], float]], repeats: int) -> dict[str, list[float]]:
    """Run every case once per round, ``repeats`` rounds; the seconds of each run per case."""
    times: dict[str, list[float]] = {name: [] for name in cases}
    for _ in range(repeats):
        for name, case in cases.items():
            times[name].append(case())
    return times


# ---------------------------------------------------------------------------------------------- rows
def _row(section: str, case: str, seconds: Sequence[float], env_steps: int, frame_skip: int, physics_hz: float,
         raw_rate: float | None, **extra: Any) -> dict[str, Any]:
    """One result row from the repeat times of a run of ``env_steps`` env steps (best repeat)."""
    best = min(seconds)
    physics_rate = env_steps * frame_skip / best
    return {
        "section": section, "case": case, "env_steps": env_steps, "frame_skip": frame_skip,
        "seconds": [round(s, 6) for s in seconds], "best_seconds": best,
        "spread": (max(seconds) - best) / best,
        "env_steps_per_s": env_steps / best, "physics_steps_per_s": physics_rate,
        "ratio_to_raw": physics_rate / raw_rate if raw_rate else None,
        "real_time_factor": physics_rate / physics_hz,
        "us_per_env_step": 1e6 * best / env_steps,
        **extra,
    }


def _make_env(scenario: Any, **overrides: Any) -> FormationEnv:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ee_formation_env.parallel_env(scenario, **overrides)


