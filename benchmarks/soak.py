"""Soak benchmark (not a test): a long closed-loop run with memory sampled along the way.

    python -m benchmarks.soak                      # 1e6 physics steps on planar_square, ~2 min
    python -m benchmarks.soak --physics-steps 200000 --scenario spatial_tetrahedron --json results/soak.json

Runs ``adaptive_jacobian`` on every agent, resetting at each episode end, and prints resident memory, open
file descriptors and connected PyBullet clients every ``--samples``-th of the run: flat columns mean no leak.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import pybullet

from ee_formation_env import baselines
import ee_formation_env


def resident_memory_mb() -> float:
    with open("/proc/self/statm") as handle:
        return int(handle.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def connected_clients() -> int:
    return sum(bool(pybullet.getConnectionInfo(i)["isConnected"]) for i in range(64))


def soak(scenario: str, physics_steps: int, samples: int, seed: int = 0) -> list[dict[str, float]]:
    """Run the closed loop for ``physics_steps`` and return the samples taken along the way."""
    rows = []
    with ee_formation_env.parallel_env(scenario) as env:
        policies = baselines.make_policies("adaptive_jacobian", env)
        env_steps = physics_steps // env.scenario.frame_skip
        every = max(env_steps // samples, 1)
        observations, _ = env.reset(seed=seed)
        for policy in policies.values():
            policy.reset()
        episodes, started = 0, time.perf_counter()
        for step in range(1, env_steps + 1):
            observations, _, _, _, infos = env.step({a: policies[a](observations[a]) for a in env.agents})
            if not env.agents:
                episodes += 1
                observations, _ = env.reset(seed=seed + episodes)
                for policy in policies.values():
                    policy.reset()
            if step % every == 0 or step == env_steps:
                rows.append({"physics_steps": step * env.scenario.frame_skip, "episodes": episodes,
                             "wall_s": time.perf_counter() - started, "rss_mb": resident_memory_mb(),
                             "open_fds": len(os.listdir("/proc/self/fd")), "pybullet_clients": connected_clients()})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="planar_square")
    parser.add_argument("--physics-steps", type=int, default=1_000_000)
    parser.add_argument("--samples", type=int, default=10)
    parser.add_argument("--json", default=None, help="also write the samples as JSON")
    args = parser.parse_args()
    rows = soak(args.scenario, args.physics_steps, args.samples)
    print(f"soak: {args.scenario}, {args.physics_steps} physics steps, adaptive_jacobian on every agent")
    print("| physics steps | episodes | wall s | RSS MB | open fds | PyBullet clients |")
    print("|---|---|---|---|---|---|")
    for row in rows:
        print(f"| {row['physics_steps']} | {row['episodes']} | {row['wall_s']:.1f} | {row['rss_mb']:.1f} | "
              f"{row['open_fds']} | {row['pybullet_clients']} |")
    growth = rows[-1]["rss_mb"] - rows[0]["rss_mb"]
    print(f"RSS growth from the first to the last sample: {growth:+.1f} MB")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"scenario": args.scenario, "samples": rows}, indent=2))


if __name__ == "__main__":
    main()
