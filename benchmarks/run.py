"""Speed benchmarks: raw PyBullet floor, ``env.step``, closed loop, SB3 rollouts, scaling and reset cost.

    python -m benchmarks.run                  # full run (a few minutes), table + results/benchmarks.json
    python -m benchmarks.run --quick          # a smoke run (seconds), same sections, few steps
    python -m benchmarks.run --json out.json

Every figure comes from this one process and one run (the SB3 section's worker processes are started by
it), so the ratios between rows are meaningful even on a loaded machine; absolute rates are not. Each
measurement is repeated (``--repeats``) with the cases of one scenario interleaved round by round, and the
fastest repeat is reported (the one least disturbed by other processes); every repeat is in the JSON.

Sections:

- ``raw_floor``: the env's own bodies, torques set with ``setJointMotorControlArray`` and
  ``stepSimulation`` only; and, for reference, a naive per-arm ``getJointStates`` + ``getLinkState`` +
  ``setJointMotorControlArray`` loop;
- ``env_step``: ``env.step`` with zero actions at ``frame_skip`` 1 and at the scenario's default;
- ``closed_loop``: ``env.step`` plus the ``adaptive_jacobian`` controller on every agent;
- ``sb3_rollout``: ``PPO.collect_rollouts`` through :class:`~ee_formation_env.integrations.sb3.SharedPolicyVecEnv`
  with 2 worker processes (and in-process, for comparison);
- ``sb3_training``: ``model.learn`` of ``train.py``'s default configuration (the same model, envs and PPO
  settings, built by ``ee_formation_env.baselines.learned.sb3_backend.build_sb3_model``): training throughput in agent steps/s, updates included;
- ``scaling``: 2, 4, 8 and 16 arms on a minimally rigid graph (:mod:`ee_formation_env.generators`), 2-DOF planar
  and 7-DOF spatial arms: raw floor, ``env.step`` at ``frame_skip`` 1, and reset cost;
- ``reset``: ``env.reset`` (state restore, no URDF reload) of the built-in scenarios;
- ``vector``: the batched env (``ee_formation_env.vector_env``) at K = 1, 4, 16, 64 copies, zero actions at the
  scenario's frame_skip, against the raw floor of the same K formations in both physics layouts (K clients,
  each stepping its formation; one client holding all K, placed 10 m apart), and resident memory per formation;
- ``torchrl`` (skipped without the ``torchrl`` extra): frames (env steps) per second collected by TorchRL's
  ``SyncDataCollector`` with a random policy on ``planar_square``: through ``make_torchrl_env`` without
  ``num_envs`` (the ``PettingZooWrapper``, one env) and natively batched at K = 32, 64, against the raw floor
  of the same K formations (K clients in lockstep, :func:`time_floor_clients`) and the batched env alone
  (``step_arrays``, random actions).

Figures: physics steps/s, env steps/s, the ratio to the raw floor of the same bodies (physics steps/s
over raw physics steps/s) and the real-time factor (simulated seconds per wall-clock second).
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import platform
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import pybullet

import ee_formation_env
from ee_formation_env.env import FormationEnv

if __package__ in (None, ""):  # run as a script: python benchmarks/run.py
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from ee_formation_env.generators import planar_ring, spatial_ring  # noqa: E402

SECTIONS = ("raw_floor", "env_step", "closed_loop", "sb3_rollout", "sb3_training", "scaling", "reset", "vector",
            "torchrl")
VECTOR_COUNTS = (1, 4, 16, 64)  # copies K of the batched env (--quick: 1 and 4)
TORCHRL_COUNTS = (32, 64)  # copies K of the native batched TorchRL env (--quick: 4)
ARM_COUNTS = (2, 4, 8, 16)
# train.py runs whose training throughput is measured: each mode's default run first (its target applies to
# it). The others: every env in worker processes, every env in-process, the first layout (8 envs x 128 steps),
# and torque mode with the same samples per update as 32 envs x 32 steps (its update cost is the same).
TRAINING_CASES = ((), ("--n-workers", "2", "--in-process-envs", "0"), ("--n-workers", "0"),
                  ("--n-envs", "8", "--n-steps", "128", "--n-workers", "0"), ("--mode", "torque"),
                  ("--mode", "torque", "--n-envs", "32", "--n-steps", "32"))
DEFAULT_JSON = "results/benchmarks.json"


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


def time_raw_floor(env: FormationEnv, steps: int) -> float:
    """Seconds for ``steps`` physics steps of the env's bodies: zero torques set, ``stepSimulation``."""
    env.reset(seed=0)
    client = env.world.client
    arms = [(arm.body, arm.joint_indices, [0.0] * arm.n_joints) for arm in env.arms]
    set_motors, step, torque_control = pybullet.setJointMotorControlArray, pybullet.stepSimulation, pybullet.TORQUE_CONTROL
    start = time.perf_counter()
    for _ in range(steps):
        for body, joints, forces in arms:
            set_motors(body, joints, torque_control, forces=forces, physicsClientId=client)
        step(physicsClientId=client)
    return time.perf_counter() - start


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


def bench_scenario(name: str, budget: Budget) -> list[dict[str, Any]]:
    """Sections (a) and (b) for one built-in scenario: raw floor, naive loop, env.step at two frame skips."""
    env1 = _make_env(name, frame_skip=1)
    env_default = _make_env(name)
    hz, fs = env1.scenario.physics_hz, env_default.scenario.frame_skip
    # Every case covers the same simulated span from the same reset state, so the physics is the same.
    steps, default_steps = budget.physics_steps, budget.physics_steps // fs
    try:
        times = interleaved({
            "raw": lambda: time_raw_floor(env1, steps),
            "naive": lambda: time_naive_loop(env1, steps),
            "fs1": lambda: time_env_steps(env1, steps),
            "default": lambda: time_env_steps(env_default, default_steps),
        }, budget.repeats)
    finally:
        env1.close()
        env_default.close()
    raw_rate = steps / min(times["raw"])
    n = env1.scenario.n_agents
    return [
        _row("raw_floor", f"{name}: setJointMotorControlArray + stepSimulation", times["raw"], steps, 1, hz,
             raw_rate, scenario=name, n_arms=n),
        _row("raw_floor", f"{name}: naive per-arm query loop", times["naive"], steps, 1, hz, raw_rate,
             scenario=name, n_arms=n),
        _row("env_step", f"{name}: env.step, zero action, frame_skip 1", times["fs1"], steps, 1, hz,
             raw_rate, scenario=name, n_arms=n),
        _row("env_step", f"{name}: env.step, zero action, frame_skip {fs}", times["default"], default_steps,
             fs, hz, raw_rate, scenario=name, n_arms=n),
    ]


def bench_closed_loop(name: str, seconds: float, budget: Budget, raw_rate: float) -> list[dict[str, Any]]:
    """Section (c): env plus ``adaptive_jacobian`` on every agent, ``seconds`` of simulated time; the team
    evaluated in batches (as ``run_episode`` does) and agent by agent."""
    from ee_formation_env import baselines

    env = _make_env(name)
    try:
        policies = baselines.make_policies("adaptive_jacobian", env)
        steps = max(1, int(round(seconds / env.scenario.control_dt)))
        times = interleaved({"team": lambda: time_closed_loop(env, policies, steps),
                             "agents": lambda: time_closed_loop(env, policies, steps, batched=False)},
                            max(1, min(budget.repeats, 3)))
        scenario = env.scenario
    finally:
        env.close()
    rows = []
    for key, how in (("team", "one team call per step"), ("agents", "one call per agent")):
        row = _row("closed_loop", f"{name}: env + adaptive_jacobian, {how} ({seconds:g} s simulated)", times[key],
                   steps, scenario.frame_skip, scenario.physics_hz, raw_rate, scenario=name,
                   n_arms=scenario.n_agents, simulated_seconds=seconds, batched=key == "team")
        row["wall_seconds_per_30s_simulated"] = 30.0 / row["real_time_factor"]
        rows.append(row)
    return rows


def bench_sb3(name: str, budget: Budget, raw_rate: float, n_envs: int = 2) -> list[dict[str, Any]]:
    """Section (d): ``PPO.collect_rollouts`` through SharedPolicyVecEnv, 2 worker processes and in-process."""
    try:
        import torch
        from stable_baselines3 import PPO

        from ee_formation_env.integrations.sb3 import SharedPolicyVecEnv
    except ImportError as error:  # the optional "train" extra
        return [{"section": "sb3_rollout", "case": f"{name}: skipped ({error})", "skipped": True}]
    torch.set_num_threads(1)
    rows = []
    for workers in (2, 0):
        # As train.py: no per-step infos cross the pipes.
        venv = SharedPolicyVecEnv(functools.partial(ee_formation_env.vector_env, name), n_envs, n_workers=workers,
                                  info_keys=())
        try:
            model = PPO("MlpPolicy", venv, n_steps=budget.sb3_steps, batch_size=budget.sb3_steps, device="cpu",
                        seed=0, verbose=0)
            _, callback = model._setup_learn(budget.sb3_steps * venv.num_envs, None)
            callback.on_training_start(locals(), globals())

            def collect() -> float:
                start = time.perf_counter()
                model.collect_rollouts(venv, callback, model.rollout_buffer, n_rollout_steps=budget.sb3_steps)
                return time.perf_counter() - start

            times = interleaved({"collect": collect}, max(1, min(budget.repeats, 3)))["collect"]
            scenario, slots = venv.scenario, venv.num_envs
        finally:
            venv.close()
        where = f"{workers} worker processes" if workers else "in-process"
        # One VecEnv step advances every env by one env step: count env steps over all envs.
        rows.append(_row("sb3_rollout", f"{name}: PPO.collect_rollouts, {n_envs} envs ({slots} agent slots), {where}",
                         times, budget.sb3_steps * n_envs, scenario.frame_skip, scenario.physics_hz, raw_rate,
                         scenario=name, n_envs=n_envs, n_workers=workers, slots=slots,
                         samples_per_s=budget.sb3_steps * slots / min(times)))
    return rows


def bench_training(budget: Budget, extra_args: Sequence[str] = ()) -> list[dict[str, Any]]:
    """Section ``sb3_training``: agent steps/s of ``train.py``'s default run (``extra_args`` change it),
    PPO updates included, and the split of each update's wall time into the rollout (``collect_rollouts``)
    and the PPO update (``train``); the first update (model warm-up) is not timed."""
    try:
        from stable_baselines3.common.utils import configure_logger  # noqa: F401 (the "train" extra)

        from ee_formation_env.baselines.learned.config import TrainConfig
        from ee_formation_env.baselines.learned.sb3_backend import build_sb3_model
    except ImportError as error:
        return [{"section": "sb3_training", "case": f"skipped ({error})", "skipped": True}]
    args = TrainConfig.from_args(["--no-progress", *extra_args])
    model = build_sb3_model(args, None)
    spent = {"collect_rollouts": 0.0, "train": 0.0}

    def timed(name: str, method: Callable[..., Any]) -> Callable[..., Any]:
        def call(*call_args: Any, **call_kwargs: Any) -> Any:
            start = time.perf_counter()
            try:
                return method(*call_args, **call_kwargs)
            finally:
                spent[name] += time.perf_counter() - start
        return call

    try:
        per_update = model.n_steps * model.get_env().num_envs
        model.learn(total_timesteps=per_update)  # warm-up: first rollout, first update
        model.collect_rollouts = timed("collect_rollouts", model.collect_rollouts)
        model.train = timed("train", model.train)
        splits: list[tuple[float, float]] = []

        def learn() -> float:
            before = dict(spent)
            start = time.perf_counter()
            model.learn(total_timesteps=budget.training_updates * per_update, reset_num_timesteps=False)
            seconds = time.perf_counter() - start
            splits.append(((spent["collect_rollouts"] - before["collect_rollouts"]) / budget.training_updates,
                           (spent["train"] - before["train"]) / budget.training_updates))
            return seconds

        times = interleaved({"learn": learn}, max(1, min(budget.repeats, 3)))["learn"]
    finally:
        model.get_env().close()
    agent_steps = budget.training_updates * per_update
    fastest = int(np.argmin(times))
    description = " ".join(extra_args) or "defaults"
    layout = (f"{args.n_envs} envs in-process" if not args.n_workers else
              f"{args.n_envs} envs: {args.in_process_envs} in-process, the others in {args.n_workers} worker "
              f"process{'es' if args.n_workers > 1 else ''}")
    return [{"section": "sb3_training", "case": f"train.py ({description}): {args.mode} mode, {layout}",
             "scenario": args.scenario, "mode": args.mode, "n_envs": args.n_envs, "n_workers": args.n_workers,
             "in_process_envs": args.in_process_envs, "extra_args": list(extra_args),
             "agent_steps": agent_steps, "seconds": times, "agent_steps_per_s": agent_steps / min(times),
             "rollout_ms_per_update": 1000 * splits[fastest][0], "update_ms_per_update": 1000 * splits[fastest][1],
             "agent_steps_per_update": per_update}]


def bench_scaling(budget: Budget, counts: Sequence[int]) -> list[dict[str, Any]]:
    """Section (e): raw floor, env.step at frame_skip 1 and reset cost versus the number of arms and DOF."""
    rows = []
    for family, builder in (("planar 2-DOF", planar_ring), ("spatial 7-DOF", spatial_ring)):
        steps = budget.physics_steps // 2
        for n in counts:
            env = _make_env(builder(n), frame_skip=1)
            try:
                times = interleaved({
                    "raw": lambda: time_raw_floor(env, steps),
                    "fs1": lambda: time_env_steps(env, steps),
                }, budget.scaling_repeats)
                reset_seconds = time_resets(env, budget.resets // 2 or 1)
                hz, dof = env.scenario.physics_hz, env.nominal_models[0].n_joints
            finally:
                env.close()
            raw_rate = steps / min(times["raw"])
            row = _row("scaling", f"{family}, {n} arms: env.step, frame_skip 1", times["fs1"], steps,
                       1, hz, raw_rate, family=family, n_arms=n, dof=dof, raw_physics_steps_per_s=raw_rate,
                       raw_seconds=[round(s, 6) for s in times["raw"]], reset_ms=1e3 * reset_seconds)
            row["us_per_env_step_per_arm"] = row["us_per_env_step"] / n
            rows.append(row)
    return rows


def bench_resets(names: Sequence[str], budget: Budget) -> list[dict[str, Any]]:
    """Reset cost of built-in scenarios."""
    rows = []
    for name in names:
        env = _make_env(name)
        try:
            seconds = min(time_resets(env, budget.resets) for _ in range(max(1, min(budget.repeats, 3))))
            rows.append({"section": "reset", "case": f"{name}: env.reset", "scenario": name,
                         "n_arms": env.scenario.n_agents, "reset_ms": 1e3 * seconds})
        finally:
            env.close()
    return rows


# ---------------------------------------------------------------------------------------------- vector
def resident_mb() -> float:
    """This process's resident memory, MB (Linux ``/proc``; 0 where unavailable)."""
    try:
        with open("/proc/self/statm", encoding="ascii") as statm:
            return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6
    except (OSError, ValueError, IndexError):
        return 0.0


def _torque_commands(arm_sets: Sequence[Any]) -> list[tuple[int, list[int], list[float]]]:
    return [(arm.body, arm.joint_indices, [0.0] * arm.n_joints) for arm_set in arm_sets for arm in arm_set.arms]


def time_floor_clients(venv: Any, steps: int, lockstep: int | None = None) -> float:
    """Raw floor, one client per formation: every copy of ``venv`` (reset) steps its own client ``steps``
    physics steps, zero torques re-sent before each; no env logic. ``lockstep = frame_skip``: the clients take
    turns, ``frame_skip`` physics steps each (what any env that steps all copies per call must do); None:
    each client runs all its steps in one go (free-running, cache-warm: a bound no lockstep env reaches)."""
    venv.reset(seed=0)
    set_motors, step, torque_control = pybullet.setJointMotorControlArray, pybullet.stepSimulation, pybullet.TORQUE_CONTROL
    clients = [(world.client, _torque_commands([arm_set])) for world, arm_set in zip(venv._worlds, venv._arm_sets)]
    chunk = lockstep or steps
    start = time.perf_counter()
    for _ in range(steps // chunk):
        for client, commands in clients:
            for _ in range(chunk):
                for body, joints, forces in commands:
                    set_motors(body, joints, torque_control, forces=forces, physicsClientId=client)
                step(physicsClientId=client)
    return time.perf_counter() - start


_MEMORY_PROBE = """
import json, sys, warnings
sys.path.insert(0, {repo!r})
from benchmarks.run import resident_mb, OneClientFormations
import ee_formation_env
name, layout, counts = {name!r}, {layout!r}, {counts!r}
probe = ee_formation_env.vector_env(name, num_envs=1)
kept, built, rss = [], 0, {{}}
base = resident_mb()
for count in counts:  # cumulative: memory is measured as it grows, never after a free
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if layout == "clients":
            kept.append(ee_formation_env.vector_env(name, num_envs=count - built))
        elif kept:
            kept[0].add(count - built)
        else:
            kept.append(OneClientFormations(probe, count))
    built = count
    rss[count] = resident_mb() - base
print(json.dumps(rss))
"""


def memory_growth(name: str, layout: str, counts: Sequence[int]) -> dict[int, float]:
    """Resident MB of ``counts`` formations (cumulative, in a fresh process) in one layout: ``clients`` (the
    batched env's copies, one client each) or ``one_client`` (all formations in one client)."""
    import subprocess

    repo = str(Path(__file__).resolve().parent.parent)
    code = _MEMORY_PROBE.format(repo=repo, name=name, layout=layout, counts=list(counts))
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=repo, timeout=600)
    if run.returncode != 0:
        raise RuntimeError(f"memory probe failed: {run.stderr[-2000:]}")
    return {int(k): v for k, v in json.loads(run.stdout.strip().splitlines()[-1]).items()}


class OneClientFormations:
    """The raw floor's other layout: K formations of one scenario in one PyBullet client, each formation's
    bases shifted by ``spacing`` m along x (far enough apart that no pair between formations overlaps in the
    broadphase, so they never collide: no filter table is needed), loaded as the env loads its arms."""

    def __init__(self, venv: Any, count: int, spacing: float = 10.0):
        import dataclasses

        from ee_formation_env.robot import Arm
        from ee_formation_env.world import PhysicsWorld

        self._venv, self._spacing, self._replace, self._arm = venv, spacing, dataclasses.replace, Arm
        self.world = PhysicsWorld(venv.scenario.physics_hz, venv.scenario.gravity)
        self.arms: list[Any] = []
        self.count = 0
        self.add(count)

    def add(self, count: int) -> None:
        """Load ``count`` more formations (at their initial configurations) and save the world."""
        scenario, task = self._venv.scenario, self._venv.task
        for k in range(self.count, self.count + count):
            for config, arm in zip(scenario.arms, self._venv._arm_sets[0].arms):
                shifted = self._replace(config, base_position=(config.base_position[0] + k * self._spacing,
                                                               *config.base_position[1:]))
                loaded = self._arm(self.world, shifted, arm.model, scenario.joint_damping, scenario.arm_collisions)
                self.arms.append(loaded)
        self.count += count
        q0 = list(task.initial_q)
        for i, arm in enumerate(self.arms):
            arm.reset_state(q0[i % len(q0)])
        self.world.save_snapshot()

    def time(self, steps: int) -> float:
        self.world.restore_snapshot()
        client = self.world.client
        commands = [(arm.body, arm.joint_indices, [0.0] * arm.n_joints) for arm in self.arms]
        set_motors, step, torque_control = pybullet.setJointMotorControlArray, pybullet.stepSimulation, pybullet.TORQUE_CONTROL
        start = time.perf_counter()
        for _ in range(steps):
            for body, joints, forces in commands:
                set_motors(body, joints, torque_control, forces=forces, physicsClientId=client)
            step(physicsClientId=client)
        return time.perf_counter() - start

    def close(self) -> None:
        self.world.close()


def time_vector_steps(venv: Any, steps: int) -> float:
    """Seconds for ``steps`` calls of the batched env's ``step`` with zero actions (dict API; autoreset)."""
    actions = {agent: np.zeros(venv.batched_action_space(agent).shape, dtype=np.float32) for agent in venv.possible_agents}
    venv.reset(seed=0)
    start = time.perf_counter()
    for _ in range(steps):
        venv.step(actions)
    return time.perf_counter() - start


def bench_vector(budget: Budget, counts: Sequence[int]) -> list[dict[str, Any]]:
    """Section ``vector``: formation physics steps/s of ``vector_env`` at K copies against the raw floor of the
    same K formations in both layouts (K clients stepped in lockstep at frame_skip; one client holding all K):
    the faster is the row's floor. Also the free-running K-client floor (reference) and resident memory per
    formation in each layout (measured as it grows, in a fresh process)."""
    rows = []
    for name in ("planar_square", "spatial_tetrahedron"):
        memory = {layout: memory_growth(name, layout, counts) for layout in ("clients", "one_client")}
        for count in counts:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                venv = ee_formation_env.vector_env(name, num_envs=count)
            one_client = OneClientFormations(venv, count)
            scenario = venv.scenario
            fs, hz = scenario.frame_skip, scenario.physics_hz
            env_steps = max(1, budget.vector_physics_steps // (count * fs))  # per copy
            physics = env_steps * fs  # per copy
            try:
                times = interleaved({
                    "clients": lambda: time_floor_clients(venv, physics, lockstep=fs),
                    "clients_free": lambda: time_floor_clients(venv, physics),
                    "one_client": lambda: one_client.time(physics),
                    "vector": lambda: time_vector_steps(venv, env_steps),
                }, max(1, min(budget.repeats, 3)))
            finally:
                venv.close()
                one_client.close()
            floors = {key: count * physics / min(times[key]) for key in ("clients", "clients_free", "one_client")}
            floor_layout = max(("clients", "one_client"), key=floors.get)
            floor = floors[floor_layout]
            common = dict(scenario=name, n_arms=scenario.n_agents, num_envs=count, raw_physics_steps_per_s=floor,
                          floor_layout=floor_layout, floor_clients_physics_steps_per_s=floors["clients"],
                          floor_clients_free_physics_steps_per_s=floors["clients_free"],
                          floor_one_client_physics_steps_per_s=floors["one_client"])
            for key, what in (("clients", f"raw floor, {count} clients in lockstep ({fs} physics steps each per turn)"),
                              ("clients_free", f"raw floor, {count} clients, each run through (free-running)"),
                              ("one_client", f"raw floor, one client holding {count} formations")):
                rss = memory["one_client" if key == "one_client" else "clients"][count]
                rows.append(_row("vector", f"{name}, K={count}: {what}", times[key], count * physics, 1, hz, floor,
                                 layout=key, rss_mb=rss, rss_mb_per_formation=rss / count, **common))
            rss = memory["clients"][count]
            rows.append(_row("vector", f"{name}, K={count}: vector_env step (dict API, zero actions, frame_skip {fs})",
                             times["vector"], count * env_steps, fs, hz, floor, layout="vector_env", rss_mb=rss,
                             rss_mb_per_formation=rss / count, **common))
    return rows


def time_collector(env: Any, frames_per_batch: int, batches: int) -> float:
    """Seconds for ``batches`` batches of ``frames_per_batch`` frames from a ``SyncDataCollector`` over ``env``
    with a random policy (after one warm-up batch, not timed)."""
    from torchrl.collectors import SyncDataCollector

    with warnings.catch_warnings():  # torchrl 0.11 renames it Collector (SyncDataCollector stays until 0.13)
        warnings.simplefilter("ignore", DeprecationWarning)
        # total_frames -1 (endless): a collector that reaches its total closes the env, which is timed again
        collector = SyncDataCollector(env, None, frames_per_batch=frames_per_batch, total_frames=-1, device="cpu")
    try:
        iterator = iter(collector)
        next(iterator)
        start = time.perf_counter()
        for _ in range(batches):
            next(iterator)
        return time.perf_counter() - start
    finally:
        collector.shutdown(close_env=False)


def time_step_arrays(venv: Any, steps: int, seed: int = 0) -> float:
    """Seconds for ``steps`` calls of the batched env's ``step_arrays`` with uniform random actions (autoreset)."""
    actions = np.random.default_rng(seed).uniform(-1.0, 1.0, (steps, venv.num_envs, venv.n_joints)).astype(np.float32)
    venv.reset(seed=0)
    start = time.perf_counter()
    for row in actions:
        venv.step_arrays(row)
    return time.perf_counter() - start


def bench_torchrl(budget: Budget, counts: Sequence[int], name: str = "planar_square") -> list[dict[str, Any]]:
    """Section ``torchrl``: ``SyncDataCollector`` frames/s, one env (the ``PettingZooWrapper``) and natively
    batched at K copies, against the raw floor of the same K formations (K clients in lockstep)."""
    try:
        import torch

        from ee_formation_env.integrations.torchrl import make_torchrl_env
    except ImportError as error:  # the optional "torchrl" extra
        return [{"section": "torchrl", "case": f"{name}: skipped ({error})", "skipped": True}]
    torch.set_num_threads(1)
    rows = []
    for count in (None, *counts):
        copies = count or 1
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            env = make_torchrl_env(name, num_envs=count, seed=0)
            floor_env = env.vector_env if count else ee_formation_env.vector_env(name, num_envs=1)
        scenario = floor_env.scenario
        fs, hz = scenario.frame_skip, scenario.physics_hz
        steps = max(2, budget.vector_physics_steps // (copies * fs) // 4)  # env steps per copy per batch
        batches = 4 if budget.repeats > 1 else 1
        cases = {"floor": lambda: time_floor_clients(floor_env, steps * batches * fs, lockstep=fs),
                 "collector": lambda: time_collector(env, copies * steps, batches)}
        if count:  # the batched env alone (array API, random actions): what the TorchRL layer adds on top
            cases["vector"] = lambda: time_step_arrays(floor_env, steps * batches)
        try:
            times = interleaved(cases, max(1, min(budget.repeats, 3)))
        finally:
            env.close()
            floor_env.close()
        floor = copies * steps * batches * fs / min(times["floor"])
        what = (f"SyncDataCollector, random policy, native batched env K={count}" if count else
                "SyncDataCollector, random policy, PettingZooWrapper (one env)")
        common = dict(scenario=name, num_envs=copies, batched=bool(count), raw_physics_steps_per_s=floor,
                      frames_per_batch=copies * steps)
        rows.append(_row("torchrl", f"{name}, K={copies}: raw floor, {copies} clients in lockstep", times["floor"],
                         copies * steps * batches * fs, 1, hz, floor, layout="floor", **common))
        rows.append(_row("torchrl", f"{name}, K={copies}: {what}", times["collector"], copies * steps * batches, fs,
                         hz, floor, layout="collector", **common))
        if count:
            rows.append(_row("torchrl", f"{name}, K={copies}: vector_env.step_arrays alone, random actions",
                             times["vector"], copies * steps * batches, fs, hz, floor, layout="vector_env", **common))
    return rows


# ---------------------------------------------------------------------------------------------- report
def linear_fit(counts: Sequence[int], values: Sequence[float]) -> dict[str, float]:
    """Least-squares ``value = intercept + slope * n`` and its largest relative residual."""
    n, v = np.asarray(counts, dtype=float), np.asarray(values, dtype=float)
    slope, intercept = np.polyfit(n, v, 1)
    residual = np.max(np.abs(intercept + slope * n - v) / v)
    return {"intercept_us": float(intercept), "slope_us_per_arm": float(slope), "max_relative_residual": float(residual)}


def evaluate_targets(results: dict[str, Any]) -> list[dict[str, Any]]:
    """The speed targets (``docs/performance.md``), each with the measured value and whether it is met."""
    def find(section: str, scenario: str, frame_skip: int | None = None) -> dict[str, Any] | None:
        return next((r for r in results["rows"] if r["section"] == section and r.get("scenario") == scenario
                     and frame_skip in (None, r.get("frame_skip"))), None)

    targets = []

    def add(name: str, value: float | None, limit: float, at_least: bool, unit: str = "") -> None:
        met = value is not None and (value >= limit if at_least else value <= limit)
        targets.append({"target": name, "value": value, "limit": limit, "at_least": at_least, "unit": unit,
                        "met": bool(met)})

    for scenario, limit in (("planar_square", 0.35), ("spatial_tetrahedron", 0.6)):
        row = find("env_step", scenario, frame_skip=1)
        add(f"env.step frame_skip 1 / raw floor, {scenario}", row and row["ratio_to_raw"], limit, True, "x")
    loop = find("closed_loop", "planar_square")
    add("closed loop planar_square: wall s per 30 s simulated", loop and loop["wall_seconds_per_30s_simulated"],
        2.0, False, "s")
    for scenario in ("planar_square", "spatial_tetrahedron"):
        reset = find("reset", scenario)
        add(f"reset, 4 arms ({scenario})", reset and reset["reset_ms"], 5.0, False, "ms")
    for mode, limit in (("residual", 15000.0), ("torque", 10000.0)):
        # The first row of each mode: train.py's defaults for it.
        training = next((r for r in results["rows"] if r["section"] == "sb3_training" and r.get("mode") == mode
                         and r.get("extra_args") in ([], ["--mode", mode])), None)
        add(f"train.py {mode} mode (defaults): agent steps/s, updates included",
            training and training["agent_steps_per_s"], limit, True, "")
    for family, fit in results.get("scaling_fits", {}).items():
        add(f"scaling {family}: per-arm env.step cost, {max(ARM_COUNTS)} arms / 4 arms", fit["per_arm_cost_ratio"],
            1.25, False, "x")
    for scenario in ("planar_square", "spatial_tetrahedron"):
        batched = [r for r in results["rows"] if r["section"] == "vector" and r.get("layout") == "vector_env"
                   and r["scenario"] == scenario and r["num_envs"] >= 16]
        if batched:
            add(f"vector_env / faster raw floor, K >= 16 (lowest), {scenario}",
                min(r["ratio_to_raw"] for r in batched), 0.8, True, "x")
    collected = [r for r in results["rows"] if r["section"] == "torchrl" and r.get("layout") == "collector"
                 and r.get("batched") and r["num_envs"] >= 32]
    if collected:
        add("TorchRL SyncDataCollector, native batched env K >= 32 / raw floor (best), planar_square",
            max(r["ratio_to_raw"] for r in collected), 0.6, True, "x")
    return targets


def _fmt(value: Any, spec: str) -> str:
    return "-" if value is None or (isinstance(value, float) and not math.isfinite(value)) else format(value, spec)


def format_tables(results: dict[str, Any]) -> str:
    lines = ["| section | case | physics steps/s | env steps/s | x raw floor | real-time factor | us/env step |",
             "|---|---|---:|---:|---:|---:|---:|"]
    for r in results["rows"]:
        if r["section"] in ("reset", "sb3_training", "vector") or r.get("skipped"):
            continue
        lines.append(f"| {r['section']} | {r['case']} | {_fmt(r['physics_steps_per_s'], ',.0f')} | "
                     f"{_fmt(r['env_steps_per_s'], ',.0f')} | {_fmt(r['ratio_to_raw'], '.2f')} | "
                     f"{_fmt(r['real_time_factor'], '.1f')} | {_fmt(r['us_per_env_step'], ',.1f')} |")
    scaling = [r for r in results["rows"] if r["section"] == "scaling"]
    if scaling:
        lines += ["", "| arms | DOF | raw physics steps/s | env.step (fs 1) steps/s | x raw floor | us/step | us/step/arm | reset ms |",
                  "|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for r in scaling:
            lines.append(f"| {r['n_arms']} | {r['dof']} | {r['raw_physics_steps_per_s']:,.0f} | "
                         f"{r['env_steps_per_s']:,.0f} | {r['ratio_to_raw']:.2f} | {r['us_per_env_step']:,.1f} | "
                         f"{r['us_per_env_step_per_arm']:,.1f} | {r['reset_ms']:.2f} |")
        for family, fit in results.get("scaling_fits", {}).items():
            lines.append(f"\n{family}: env.step ~ {fit['intercept_us']:.0f} us + {fit['slope_us_per_arm']:.1f} us per arm "
                         f"(largest deviation from the line {fit['max_relative_residual']:.0%})")
    training = [r for r in results["rows"] if r["section"] == "sb3_training" and not r.get("skipped")]
    if training:
        lines += ["", "| training throughput | agent steps/s | rollout ms per update | PPO update ms per update |",
                  "|---|---:|---:|---:|"]
        lines += [f"| {r['case']} | {r['agent_steps_per_s']:,.0f} | {_fmt(r.get('rollout_ms_per_update'), ',.0f')} | "
                  f"{_fmt(r.get('update_ms_per_update'), ',.0f')} |" for r in training]
    batched = [r for r in results["rows"] if r["section"] == "vector" and r.get("layout") == "vector_env"]
    if batched:
        lines += ["", "| batched env | K | physics steps/s | floor, K clients (lockstep) | floor, one client | "
                  "x faster floor | floor, K clients (free-running) | MB per formation (K clients) | "
                  "MB per formation (one client) |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
        one_client = {(r["scenario"], r["num_envs"]): r for r in results["rows"]
                      if r["section"] == "vector" and r.get("layout") == "one_client"}
        for r in batched:
            other = one_client.get((r["scenario"], r["num_envs"]), {})
            lines.append(f"| {r['scenario']} | {r['num_envs']} | {r['physics_steps_per_s']:,.0f} | "
                         f"{r['floor_clients_physics_steps_per_s']:,.0f} | {r['floor_one_client_physics_steps_per_s']:,.0f} | "
                         f"{r['ratio_to_raw']:.2f} | {r['floor_clients_free_physics_steps_per_s']:,.0f} | "
                         f"{r['rss_mb_per_formation']:.1f} | "
                         f"{_fmt(other.get('rss_mb_per_formation'), '.1f')} |")
    resets = [r for r in results["rows"] if r["section"] == "reset"]
    if resets:
        lines += ["", "| reset | arms | ms |", "|---|---:|---:|"]
        lines += [f"| {r['scenario']} | {r['n_arms']} | {r['reset_ms']:.2f} |" for r in resets]
    lines += ["", "| target | measured | limit | met |", "|---|---:|---:|---|"]
    if results["quick"]:
        lines.insert(len(lines) - 2, "--quick: few steps and one repeat; a smoke run, not a measurement\n")
    for t in results["targets"]:
        sign = ">=" if t["at_least"] else "<="
        lines.append(f"| {t['target']} | {_fmt(t['value'], '.3g')} {t['unit']} | {sign} {t['limit']:g} {t['unit']} | "
                     f"{'yes' if t['met'] else 'NO'} |")
    return "\n".join(lines)


def run(quick: bool = False, sections: Sequence[str] = SECTIONS, progress: Callable[[str], None] = print
        ) -> dict[str, Any]:
    """Run the selected sections; return the results dict (rows, fits, targets, machine info)."""
    budget = QUICK if quick else FULL
    started = time.time()
    results: dict[str, Any] = {
        "quick": quick, "sections": list(sections),
        "machine": {"python": platform.python_version(), "numpy": np.__version__, "platform": platform.platform(),
                    "cpu_count": os.cpu_count(), "load_average_start": list(os.getloadavg())},
        "budget": budget.__dict__, "rows": [],
    }
    raw_rates: dict[str, float] = {}
    if {"raw_floor", "env_step", "closed_loop", "sb3_rollout"} & set(sections):
        for name in ("planar_square", "spatial_tetrahedron"):
            progress(f"raw floor and env.step: {name}")
            rows = bench_scenario(name, budget)
            raw_rates[name] = rows[0]["physics_steps_per_s"]
            results["rows"] += [r for r in rows if r["section"] in sections]
    if "closed_loop" in sections:
        for name, seconds in (("planar_square", budget.closed_loop_seconds),
                              ("spatial_tetrahedron", budget.closed_loop_seconds_spatial)):
            progress(f"closed loop: {name}")
            results["rows"] += bench_closed_loop(name, seconds, budget, raw_rates[name])
    if "sb3_rollout" in sections:
        progress("SB3 rollouts: planar_square")
        results["rows"] += bench_sb3("planar_square", budget, raw_rates["planar_square"])
    if "sb3_training" in sections:
        for extra_args in TRAINING_CASES[:1] if quick else TRAINING_CASES:  # --quick: the default run only
            progress(f"SB3 training throughput: train.py {' '.join(extra_args) or '(defaults)'}")
            results["rows"] += bench_training(budget, extra_args)
    if "scaling" in sections:
        counts = ARM_COUNTS
        progress(f"scaling: {list(counts)} arms, 2 and 7 DOF")
        scaling = bench_scaling(budget, counts)
        results["rows"] += scaling
        fits = {}
        for family in dict.fromkeys(r["family"] for r in scaling):
            rows = [r for r in scaling if r["family"] == family]
            fit = linear_fit([r["n_arms"] for r in rows], [r["us_per_env_step"] for r in rows])
            per_arm = {r["n_arms"]: r["us_per_env_step_per_arm"] for r in rows}
            fit["per_arm_cost_ratio"] = per_arm[max(counts)] / per_arm[4]
            fits[family] = fit
        results["scaling_fits"] = fits
    if "reset" in sections:
        progress("reset")
        results["rows"] += bench_resets(("planar_square", "spatial_tetrahedron"), budget)
    if "vector" in sections:
        counts = VECTOR_COUNTS[:2] if quick else VECTOR_COUNTS
        progress(f"vector: vector_env at K = {list(counts)} against the raw floor of both layouts")
        results["rows"] += bench_vector(budget, counts)
    if "torchrl" in sections:
        counts = (4,) if quick else TORCHRL_COUNTS
        progress(f"torchrl: SyncDataCollector, one env and K = {list(counts)} natively batched")
        results["rows"] += bench_torchrl(budget, counts)
    results["targets"] = evaluate_targets(results)
    results["machine"]["load_average_end"] = list(os.getloadavg())
    results["wall_seconds"] = time.time() - started
    return results


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.run", description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="few steps, one repeat: a smoke test, not a measurement")
    parser.add_argument("--json", default=DEFAULT_JSON, metavar="PATH", help=f"write the results here ({DEFAULT_JSON})")
    parser.add_argument("--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS), metavar="SECTION",
                        help=f"run only these sections, of {list(SECTIONS)}")
    args = parser.parse_args(argv)
    results = run(quick=args.quick, sections=args.sections, progress=lambda text: print(text, file=sys.stderr, flush=True))
    print(format_tables(results))
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(results, indent=2) + "\n", encoding="utf-8")
    print(f"\nwrote {path} ({results['wall_seconds']:.0f} s, load average {results['machine']['load_average_start'][0]:.2f} "
          f"at start on {results['machine']['cpu_count']} CPUs)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
