"""Learning curves with intervals: held-out success and settling time against agent steps, per method and task,
over training seeds, from the checkpoints of the scoreboard's runs.

    python -m studies.learning_curves --board results/scoreboard --scenario spatial_tetrahedron \\
        --methods residual-ppo-gradient torque-ppo --figure docs/figures/learning_curves_spatial_tetrahedron.png

Every SB3 PPO run of the board (``BOARD/runs/<scenario>/<method>/seed-<k>/``, finished) keeps four checkpoints
of its training and its final model; each of them acts on the held-out episodes the board evaluates (seeds
10,000 + j, the scenario's own episodes, the run's own env settings) through
:meth:`~ee_formation_env.baselines.learned.policy.SavedRun.policy_source`. A point of a curve is the k-th
checkpoint of every seed (at the same agent steps when the budget is in steps; their mean when a wall-clock limit
ended some runs first): the mean over (seed, episode) of the episode's success and of its settling time (the
episode length when it did not settle), with the 95 % interval of the board's stratified bootstrap
(:func:`studies.bootstrap.aggregate`). The reference laws' values on the same episodes are drawn as lines. The
JSON (``--json``) holds every point.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

METRICS = (("success", "held-out success", "%"), ("settling_time_or_limit", "settling time or episode length", "s"))


def finished_runs(board: Path, scenario: str, method: str) -> list[Path]:
    """The method's finished run folders on ``scenario`` (a ``model/`` folder in each), by seed."""
    folder = Path(board) / "runs" / scenario / method
    runs = [path for path in folder.glob("seed-*") if (path / "model" / "state.json").is_file()]
    return sorted(runs, key=lambda path: int(path.name.split("-")[1]))


def _episode_values(metrics: Any, episode_seconds: float) -> dict[str, float]:
    from studies.scoreboard_rows import episode_values

    return episode_values(metrics.as_dict(), episode_seconds)


def run_points(run_dir: Path, seeds: Sequence[int]) -> list[dict[str, Any]]:
    """Each checkpoint's and the final model's (agent steps, per-episode values) of one run, in training order."""
    from ee_formation_env.baselines.learned.checkpoint import checkpoints, read_json
    from ee_formation_env.baselines.learned.policy import MODEL_FOLDER, SavedRun
    from ee_formation_env.baselines.metrics import run_episodes
    from ee_formation_env.scenario import load_scenario

    run = SavedRun.load(run_dir, "--board")
    scenario = load_scenario(run.scenario)
    points = []
    folders = [*checkpoints(run_dir), run_dir / MODEL_FOLDER]
    for folder in folders:
        steps = int(read_json(folder / "state.json", "state.json")["agent_steps"])
        if points and steps <= points[-1]["agent_steps"]:  # the final model is the last checkpoint, once
            continue
        episodes = run_episodes(run.scenario, run.policy_source(folder), seeds, overrides=run.env_overrides())
        points.append({"agent_steps": steps, "checkpoint": folder.name,
                       "episodes": [_episode_values(e, scenario.episode_seconds) for e in episodes]})
    return points


def method_curve(runs: Sequence[Path], seeds: Sequence[int]) -> list[dict[str, Any]]:
    """The curve of one method: per checkpoint index, the mean agent steps and each metric's aggregate over the
    runs (:func:`studies.bootstrap.aggregate`); as many points as the run with the fewest checkpoints."""
    from studies.bootstrap import aggregate

    per_run = [run_points(run, seeds) for run in runs]
    points = []
    for index in range(min(len(points) for points in per_run)):
        row = {"agent_steps": float(np.mean([points[index]["agent_steps"] for points in per_run])),
               "agent_steps_per_seed": [points[index]["agent_steps"] for points in per_run]}
        for key, _, _ in METRICS:
            row[key] = aggregate([[e[key] for e in points[index]["episodes"]] for points in per_run])
        points.append(row)
    return points


def reference_values(scenario: str, seeds: Sequence[int]) -> dict[str, dict[str, float]]:
    """Each reference law's mean of every metric on the same held-out episodes."""
    from ee_formation_env.baselines import MODEL_BASED_POLICIES
    from ee_formation_env.baselines.metrics import run_policies
    from ee_formation_env.scenario import load_scenario

    length = load_scenario(scenario).episode_seconds
    runs = run_policies(scenario, {name: name for name in MODEL_BASED_POLICIES}, seeds)
    return {name: {key: float(np.mean([_episode_values(e, length)[key] for e in episodes])) for key, _, _ in METRICS}
            for name, episodes in runs.items()}


def plot(curves: dict[str, list[dict[str, Any]]], references: dict[str, dict[str, float]], scenario: str,
         figure: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from studies._common import save_figure

    fig, axes = plt.subplots(1, len(METRICS), figsize=(6 * len(METRICS), 4))
    for axis, (key, title, unit) in zip(axes, METRICS):
        scale = 100.0 if unit == "%" else 1.0
        for method, points in curves.items():
            steps = np.array([p["agent_steps"] for p in points]) / 1e6
            mean = np.array([p[key]["mean"] for p in points]) * scale
            low = np.array([p[key]["ci_low"] for p in points]) * scale
            high = np.array([p[key]["ci_high"] for p in points]) * scale
            line, = axis.plot(steps, mean, marker="o", label=f"{method} ({len(points[0][key]['per_seed'])} seeds)")
            axis.fill_between(steps, low, high, color=line.get_color(), alpha=0.2)
        for (name, values), color in zip(references.items(), plt.cm.Dark2.colors):
            axis.axhline(values[key] * scale, linestyle="--", linewidth=1, color=color, label=name)
        axis.set(title=f"{scenario}: {title}", xlabel="agent steps (millions)", ylabel=f"{title} ({unit})")
        if unit == "%":
            axis.set_ylim(-3, 103)
    axes[0].legend(fontsize=7)
    figure.parent.mkdir(parents=True, exist_ok=True)
    return save_figure(fig, figure)


def main(argv: Sequence[str] | None = None) -> int:
    from ee_formation_env.builtin import BUILTIN_SCENARIOS
    from ee_formation_env.scenario_sets import HELD_OUT_SEED_OFFSET

    parser = argparse.ArgumentParser(prog="python -m studies.learning_curves", description=__doc__.split("\n\n")[0])
    parser.add_argument("--board", type=Path, required=True, help="a scoreboard folder (its runs/)")
    parser.add_argument("--scenario", required=True, help="built-in scenario")
    parser.add_argument("--methods", nargs="+", required=True, help="the board's learned SB3 methods")
    parser.add_argument("--episodes", type=int, default=10, help=f"held-out episodes (seeds {HELD_OUT_SEED_OFFSET}+)")
    parser.add_argument("--figure", type=Path, required=True, help="the figure to write (PNG)")
    parser.add_argument("--json", type=Path, default=None, help="also write every point as JSON here")
    args = parser.parse_args(argv)
    if args.scenario not in BUILTIN_SCENARIOS:
        parser.error(f"--scenario: unknown {args.scenario!r}; available: {sorted(BUILTIN_SCENARIOS)}")
    if args.episodes < 1:
        parser.error("--episodes: expected an integer >= 1")
    runs = {method: finished_runs(args.board, args.scenario, method) for method in args.methods}
    missing = [method for method, found in runs.items() if not found]
    if missing:
        parser.error(f"--methods: no finished run of {missing} under {args.board / 'runs' / args.scenario}")
    seeds = [HELD_OUT_SEED_OFFSET + k for k in range(args.episodes)]
    curves = {}
    for method, found in runs.items():
        print(f"{method}: {len(found)} runs", file=sys.stderr, flush=True)
        curves[method] = method_curve(found, seeds)
    references = reference_values(args.scenario, seeds)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"scenario": args.scenario, "seeds": seeds, "curves": curves,
                                         "references": references}, indent=1), encoding="utf-8")
    print(f"wrote {plot(curves, references, args.scenario, args.figure)}")
    for method, points in curves.items():
        for point in points:
            print(f"{method} at {point['agent_steps']:,.0f} agent steps: success {point['success']['mean']:.0%} "
                  f"[{point['success']['ci_low']:.0%}, {point['success']['ci_high']:.0%}], settle "
                  f"{point['settling_time_or_limit']['mean']:.2f} s [{point['settling_time_or_limit']['ci_low']:.2f}, "
                  f"{point['settling_time_or_limit']['ci_high']:.2f}]")
    return 0


if __name__ == "__main__":
    sys.exit(main())
