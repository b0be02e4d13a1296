"""Evaluate reference policies on seeded episodes and print a metrics table.

    python -m baselines.evaluate --scenario planar_square --policy adaptive_jacobian --episodes 10 --seed 0
    python -m baselines.evaluate --scenario spatial_tetrahedron --policy all --json results.json

Episode ``k`` uses reset seed ``seed + k``, so every policy sees the same initial states. Metrics are
defined in :mod:`baselines.metrics` (the same module ``train.py`` uses).
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any, Sequence

import ee_formation_env
from baselines import POLICIES, make_policies
from baselines.metrics import DEFAULT_POSITION_TOLERANCE, format_table, run_episode, summarize


def evaluate_policy(scenario: Any, policy: str, episodes: int, seed: int,
                    position_tolerance: float = DEFAULT_POSITION_TOLERANCE, overrides: dict | None = None,
                    policy_kwargs: dict | None = None) -> dict[str, Any]:
    """Summary (see :func:`baselines.metrics.summarize`) of ``policy`` over seeded episodes."""
    with ee_formation_env.parallel_env(scenario, **(overrides or {})) as env:
        policies = make_policies(policy, env, **(policy_kwargs or {}))
        results = [run_episode(env, policies, seed=seed + k, position_tolerance=position_tolerance)
                   for k in range(episodes)]
    summary = summarize(results)
    summary["per_episode"] = [r.as_dict() for r in results]
    return summary


def _overrides(pairs: Sequence[str]) -> dict[str, Any]:
    overrides = {}
    for pair in pairs:
        key, separator, value = pair.partition("=")
        if not separator:
            raise ValueError(f"--set: expected KEY=VALUE (VALUE in JSON), got {pair!r}")
        try:
            overrides[key] = json.loads(value)
        except json.JSONDecodeError:
            overrides[key] = value
    return overrides


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m baselines.evaluate", description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="planar_square", help="built-in name or YAML/JSON file")
    parser.add_argument("--policy", default="all", help=f"one of {list(POLICIES)} or 'all'")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tolerance", type=float, default=DEFAULT_POSITION_TOLERANCE,
                        help="edge-length accuracy (m) that counts as success")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                        help="scenario overrides, VALUE in JSON, e.g. --set torque_limits=1e6 frame_skip=1")
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error("--episodes: expected an integer >= 1")
    names = list(POLICIES) if args.policy == "all" else [args.policy]
    for name in names:
        if name not in POLICIES:
            parser.error(f"--policy: unknown policy {name!r}; available: {list(POLICIES)} or 'all'")
    try:
        overrides = _overrides(args.set)
        results = {name: evaluate_policy(args.scenario, name, args.episodes, args.seed, args.tolerance, overrides)
                   for name in names}
    except ValueError as error:
        parser.error(str(error))
    print(f"scenario {args.scenario}, {args.episodes} episodes from seed {args.seed}, tolerance {args.tolerance} m")
    print(format_table(results))
    if args.json:
        with open(args.json, "w", encoding="utf-8") as handle:
            json.dump({"scenario": args.scenario, "episodes": args.episodes, "seed": args.seed,
                       "overrides": overrides, "results": results}, handle, indent=2, default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
