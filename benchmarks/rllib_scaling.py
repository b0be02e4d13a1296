"""RLlib PPO throughput against the number of env runners: ``python -m benchmarks.rllib_scaling``.

Builds ``train.py --backend rllib``'s PPO (``rllib_backend.ppo_config``, the run's preset) with 0, 1, 2, ...
env runners, the same ``n_envs`` copies split among them, runs a few training iterations each (after one
untimed) and prints, per layout, the agent steps per second of training (sampling and PPO updates, what a run
gets, timed by wall clock), per env runner, and the ratio to one env runner. Needs the ``distributed`` extra;
every layout runs in a fresh local Ray instance, one after the other, so compare ratios within one invocation.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any, Sequence


def measure(scenario: str, runners: int, n_envs: int, iterations: int, warmup: int = 1) -> dict[str, Any]:
    """Agent steps per second of ``iterations`` PPO iterations (after ``warmup`` ones) with ``runners`` env
    runners sharing ``n_envs`` copies of ``scenario``'s training env."""
    import ray
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv
    from ray.tune.registry import register_env

    from ee_formation_env.baselines.learned.config import TrainConfig
    from ee_formation_env.baselines.learned.rllib_backend import env_runner_copies, ppo_config
    from ee_formation_env.baselines.learned.training_env import env_factory

    args = TrainConfig.from_args(["--backend", "rllib", "--scenario", scenario, "--n-envs", str(n_envs),
                                  "--n-workers", str(runners), "--no-progress"])
    factory = env_factory(args)
    probe = factory()
    agents = len(probe.possible_agents)
    probe.close()
    ray.init(address="local", include_dashboard=False, log_to_driver=False)
    try:
        register_env("ee_formation", lambda _config: ParallelPettingZooEnv(factory()))
        algorithm = ppo_config(args, agents).build_algo()
        for _ in range(warmup):
            algorithm.train()
        env_steps, started = 0, time.perf_counter()
        for _ in range(iterations):
            result = algorithm.train()
            env_steps += int(result["env_runners"]["num_env_steps_sampled"])
        seconds = time.perf_counter() - started
        algorithm.stop()
    finally:
        ray.shutdown()
    _, copies = env_runner_copies(args)
    return {"scenario": scenario, "env_runners": runners, "copies_per_runner": copies, "agents": agents,
            "agent_steps": env_steps * agents, "seconds": seconds,
            "training_agent_steps_per_s": env_steps * agents / seconds}


def table(rows: Sequence[dict[str, Any]]) -> str:
    one = next((r for r in rows if r["env_runners"] == 1), rows[0])
    lines = ["| scenario | env runners | copies per runner | training agent steps/s | per env runner | x 1 runner |",
             "|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        rate = r["training_agent_steps_per_s"]
        per_runner = f"{rate / r['env_runners']:,.0f}" if r["env_runners"] else "(driver)"
        lines.append(f"| {r['scenario']} | {r['env_runners']} | {r['copies_per_runner']} | {rate:,.0f} | {per_runner} | "
                     f"{rate / one['training_agent_steps_per_s']:.2f} |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.rllib_scaling", description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="planar_square", help="built-in scenario (default planar_square)")
    parser.add_argument("--runners", nargs="+", type=int, default=[0, 1, 2], help="env runner counts (default 0 1 2)")
    parser.add_argument("--n-envs", type=int, default=32, help="copies in all, split among the runners (default 32)")
    parser.add_argument("--iterations", type=int, default=5, help="timed PPO iterations per layout (default 5)")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = parser.parse_args(argv)
    if any(r < 0 for r in args.runners) or args.iterations < 1:
        parser.error("--runners: expected integers >= 0; --iterations: expected an integer >= 1")
    rows = [measure(args.scenario, runners, args.n_envs, args.iterations) for runners in args.runners]
    print(table(rows))
    if args.json is not None:
        args.json.write_text(json.dumps({"rows": rows}, indent=1), encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
