"""The batched sections of the benchmark: the batched env against the raw floor of K formations in both layouts,
its memory per formation, and the native batched TorchRL env (``docs/performance.md``, "Batched env")."""

from __future__ import annotations

import json
import os
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pybullet

import ee_formation_env

from benchmarks.timing import Budget, _row, interleaved, time_zero_torques


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


def time_floor_clients(venv: Any, steps: int, lockstep: int | None = None, reads: bool = False,
                       substeps: bool = False) -> float:
    """Raw floor, one client per formation: every copy of ``venv`` (reset) steps its own client ``steps``
    physics steps, zero torques re-sent before each; no env logic. ``lockstep = frame_skip``: the clients take
    turns, ``frame_skip`` physics steps each (what any env that steps all copies per call must do); None:
    each client runs all its steps in one go (free-running, cache-warm: a bound no lockstep env reaches).
    ``reads`` (lockstep only): after each turn, the reads every env step needs and PyBullet cannot batch, one
    ``getJointStates`` per arm and one ``getContactPoints`` per client, results unused: the floor of an env
    that computes nothing from what it reads. ``substeps`` (lockstep only): each turn sends the torques once and
    makes its ``frame_skip`` physics steps in one ``stepSimulation`` call (PyBullet's ``numSubSteps``, as the env
    steps: :meth:`~ee_formation_env.world.PhysicsWorld.step_with_torques`), the same physics in fewer calls."""
    venv.reset(seed=0)
    set_motors, step, torque_control = pybullet.setJointMotorControlArray, pybullet.stepSimulation, pybullet.TORQUE_CONTROL
    joint_states, contact_points = pybullet.getJointStates, pybullet.getContactPoints
    copies = range(venv.num_envs)
    clients = [(venv.world(k).client, _torque_commands([venv.arm_set(k)])) for k in copies]
    chunk = lockstep or steps
    read = reads and lockstep is not None
    if substeps:
        if lockstep is None:
            raise ValueError("substeps: the floor with substeps steps in lockstep")
        worlds = [(venv.world(k), client, commands) for k, (client, commands) in zip(copies, clients)]
        start = time.perf_counter()
        for _ in range(steps // chunk):
            for world, client, commands in worlds:
                world.step_with_torques(commands, chunk)
                if read:
                    for body, joints, _ in commands:
                        joint_states(body, joints, physicsClientId=client)
                    contact_points(physicsClientId=client)
        return time.perf_counter() - start
    start = time.perf_counter()
    for _ in range(steps // chunk):
        for client, commands in clients:
            for _ in range(chunk):
                for body, joints, forces in commands:
                    set_motors(body, joints, torque_control, forces=forces, physicsClientId=client)
                step(physicsClientId=client)
            if read:
                for body, joints, _ in commands:
                    joint_states(body, joints, physicsClientId=client)
                contact_points(physicsClientId=client)
    return time.perf_counter() - start


_MEMORY_PROBE = """
import json, sys, warnings
sys.path.insert(0, {repo!r})
from benchmarks.batched import resident_mb, OneClientFormations
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
            for config, arm in zip(scenario.arms, self._venv.arm_set(0).arms):
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
        return time_zero_torques(self.world.client, self.arms, steps)

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
                    "clients_reads": lambda: time_floor_clients(venv, physics, lockstep=fs, reads=True),
                    "clients_free": lambda: time_floor_clients(venv, physics),
                    "clients_substeps": lambda: time_floor_clients(venv, physics, lockstep=fs, substeps=True),
                    "clients_substeps_reads": lambda: time_floor_clients(venv, physics, lockstep=fs, reads=True,
                                                                         substeps=True),
                    "one_client": lambda: one_client.time(physics),
                    "vector": lambda: time_vector_steps(venv, env_steps),
                }, max(1, min(budget.repeats, 3)))
            finally:
                venv.close()
                one_client.close()
            floors = {key: count * physics / min(times[key]) for key in (
                "clients", "clients_reads", "clients_free", "clients_substeps", "clients_substeps_reads", "one_client")}
            # the row's floor: the fastest way to make these physics steps (the env's own way, substeps, included)
            floor_layout = max(("clients", "one_client", "clients_substeps"), key=floors.get)
            floor = floors[floor_layout]
            common = dict(scenario=name, n_arms=scenario.n_agents, num_envs=count, raw_physics_steps_per_s=floor,
                          floor_layout=floor_layout, floor_clients_physics_steps_per_s=floors["clients"],
                          floor_clients_free_physics_steps_per_s=floors["clients_free"],
                          floor_clients_reads_physics_steps_per_s=floors["clients_reads"],
                          floor_one_client_physics_steps_per_s=floors["one_client"],
                          floor_clients_substeps_physics_steps_per_s=floors["clients_substeps"],
                          floor_clients_substeps_reads_physics_steps_per_s=floors["clients_substeps_reads"])
            for key, what in (("clients", f"raw floor, {count} clients in lockstep ({fs} physics steps each per turn)"),
                              ("clients_reads", f"raw floor and the per-step reads, {count} clients in lockstep"),
                              ("clients_free", f"raw floor, {count} clients, each run through (free-running)"),
                              ("clients_substeps", f"raw floor, {count} clients in lockstep, one stepSimulation of "
                                                   f"{fs} substeps per turn"),
                              ("clients_substeps_reads", f"raw floor with substeps and the per-step reads, {count} "
                                                         "clients in lockstep"),
                              ("one_client", f"raw floor, one client holding {count} formations")):
                rss = memory["one_client" if key == "one_client" else "clients"][count]  # same bodies
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


