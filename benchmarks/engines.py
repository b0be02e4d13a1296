"""PyBullet against MuJoCo, one run, one core: the raw floor (physics steps/s of a scenario's arms under constant
torques, contacts on, through the engine seam, ``frame_skip`` steps per call as the env makes them) and the
parallel env's steps/s, on each engine, with the MuJoCo / PyBullet ratios (``docs/physics.md``, "Engines").

    python -m benchmarks.engines            # planar_square and spatial_tetrahedron
    python -m benchmarks.engines --quick    # a smoke run (few steps)

Each figure is the best of ``--repeats`` timings, the engines taking turns so that a load change on the
machine hits both.
"""

from __future__ import annotations

import argparse
import time
from typing import Sequence

import numpy as np

import ee_formation_env
from ee_formation_env.scenario import load_scenario

ENGINES = ("pybullet", "mujoco")


def time_floor(scenario: str, engine: str, physics_steps: int) -> float:
    """Seconds for ``physics_steps`` physics steps of the scenario's arms (reset with seed 0) under constant
    torques (a fifth of each joint's limit), ``frame_skip`` steps per :meth:`step_torques` call."""
    with ee_formation_env.parallel_env(scenario, engine=engine) as env:
        env.reset(seed=0)
        torques = 0.2 * np.concatenate(env.torque_limits)
        frame_skip = env.scenario.frame_skip
        world = env.world
        start = time.perf_counter()
        for _ in range(physics_steps // frame_skip):
            world.step_torques(torques, frame_skip)
        return time.perf_counter() - start


def time_env(scenario: str, engine: str, env_steps: int) -> float:
    """Seconds for ``env_steps`` steps of the parallel env under constant actions (0.2), reset when an episode
    ends (the resets are timed too)."""
    with ee_formation_env.parallel_env(scenario, engine=engine) as env:
        env.reset(seed=0)
        actions = {agent: np.full(env.action_space(agent).shape, 0.2, dtype=np.float32) for agent in env.agents}
        start = time.perf_counter()
        for _ in range(env_steps):
            _, _, terminations, truncations, _ = env.step(actions)
            if any(terminations.values()) or any(truncations.values()):
                env.reset()
        return time.perf_counter() - start


def measure(scenarios: Sequence[str], physics_steps: int, env_steps: int, repeats: int) -> list[dict]:
    """One row per scenario: physics steps/s (floor) and env steps/s on each engine, best of ``repeats``."""
    rows = []
    for scenario in scenarios:
        frame_skip = load_scenario(scenario).frame_skip
        floor = {engine: [] for engine in ENGINES}
        env = {engine: [] for engine in ENGINES}
        for _ in range(repeats):
            for engine in ENGINES:
                floor[engine].append(time_floor(scenario, engine, physics_steps))
                env[engine].append(time_env(scenario, engine, env_steps))
        row = {"scenario": scenario, "frame_skip": frame_skip}
        for engine in ENGINES:
            row[f"floor_{engine}"] = physics_steps // frame_skip * frame_skip / min(floor[engine])
            row[f"env_{engine}"] = env_steps / min(env[engine])
        rows.append(row)
    return rows


def table(rows: Sequence[dict]) -> str:
    lines = ["| scenario | floor PyBullet (physics steps/s) | floor MuJoCo | ratio | env PyBullet (env steps/s) "
             "| env MuJoCo | ratio |", "|---|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        lines.append(f"| {row['scenario']} | {row['floor_pybullet']:,.0f} | {row['floor_mujoco']:,.0f} | "
                     f"{row['floor_mujoco'] / row['floor_pybullet']:.2f}x | {row['env_pybullet']:,.0f} | "
                     f"{row['env_mujoco']:,.0f} | {row['env_mujoco'] / row['env_pybullet']:.2f}x |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.engines", description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenarios", nargs="+", default=["planar_square", "spatial_tetrahedron"])
    parser.add_argument("--physics-steps", type=int, default=20_000, help="physics steps per floor timing")
    parser.add_argument("--env-steps", type=int, default=2_000, help="env steps per env timing")
    parser.add_argument("--repeats", type=int, default=3, help="timings per figure; the best is kept")
    parser.add_argument("--quick", action="store_true", help="a smoke run: 500 physics steps, 50 env steps, once")
    args = parser.parse_args(argv)
    if args.quick:
        args.physics_steps, args.env_steps, args.repeats = 500, 50, 1
    print(table(measure(args.scenarios, args.physics_steps, args.env_steps, args.repeats)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
