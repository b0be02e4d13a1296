"""Team size: does one set policy trained on 4 planar arms serve teams of 3 to 8 arms, zero-shot?

    python -m studies.team_size                                   # 3 seeds x 10 min, N = 3..8, ~1 h on 2 cores
    python -m studies.team_size --max-train-seconds 300 --episodes 20 --out runs/team_size
    python -m studies.team_size --quick --out runs/team_size_quick      # the pipeline end to end in seconds

Rule: residual PPO on the ``gradient`` law with the permutation-invariant set network
(``--policy-network set``, :mod:`ee_formation_env.baselines.learned.set_network`) is trained on
``planar_random`` (4 arms) only, on ``--train-episode-seconds`` long episodes (8 s: longer than the laws take
to settle its draws), one run per training seed, each stopped after ``--max-train-seconds`` of wall
time. Each run is then evaluated unchanged at every team size N of ``--sizes`` on the fixed test draws of
``planar_team`` at N (:func:`ee_formation_env.team_families.team_test_draws`: reset seeds from
:data:`~ee_formation_env.scenario_sets.TEST_SEEDS`, disjoint from every training reset), beside the three
laws on the same draws; and on planar_random's own test set and the four planar_square held-out test
scenarios. Success and settling are :func:`ee_formation_env.baselines.metrics.settle`'s (the one episode loop
:func:`~ee_formation_env.baselines.metrics.run_policies`). The learned row pools the seeds' episodes.

Table per N: success with its 95 % Wilson interval, the settling time of the successes (mean and 95 % bootstrap
interval), its ratio to the best law's at that N (the law of highest success, then fastest), contact steps per
episode and faulted episodes. Figure: success vs N (``--figure``). Targets: zero-shot >= 90 % at every N,
settling <= 1.5 x the best law's at every N, >= 95 % on planar_random's test set. Docs: docs/training.md,
"Team-size transfer", with the measured tables.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

if __package__ in (None, ""):  # run as a script: python studies/team_size.py
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from ee_formation_env.baselines import REFERENCE_CONTROLLERS  # noqa: E402
from ee_formation_env.baselines.metrics import EpisodeMetrics, run_policies  # noqa: E402
from ee_formation_env.scenario_sets import HELD_OUT_SEED_OFFSET, TEST_SEEDS, held_out_scenarios  # noqa: E402
from ee_formation_env.team_families import TEAM_FAMILIES, team_scenario  # noqa: E402

from studies.bootstrap import stratified_bootstrap, wilson_interval  # noqa: E402
from studies.scoreboard_methods import METHODS  # noqa: E402

TRAIN_SCENARIO = "planar_random"  # 4 planar_2link arms
FAMILY = "planar_team"
DEFAULT_SEEDS = (0, 1, 2)
DEFAULT_SIZES = tuple(range(TEAM_FAMILIES[FAMILY][0], TEAM_FAMILIES[FAMILY][1] + 1))
DEFAULT_EPISODES = 20  # test draws per team size
DEFAULT_TRAIN_SECONDS = 600.0  # s of wall time per training seed
DEFAULT_TRAIN_EPISODE_SECONDS = 8.0  # s: planar_random's laws settle in about 3-4 s, beyond 3 s episodes
DEFAULT_TIMESTEPS = 3_000_000  # agent steps per seed, the budget if the wall-time limit is not reached first
SQUARE_EPISODES = 5  # reset seeds per planar_square test scenario
TARGET_SUCCESS = 0.90  # zero-shot, at every N
TARGET_SETTLING_RATIO = 1.5  # x the best law's, at every N
TARGET_TRAIN_SET = 0.95  # on planar_random's test set
# The scoreboard's set method (residual on gradient, set network); this study's own flags, after these, win.
TRAIN_FLAGS = ("--scenario", TRAIN_SCENARIO, "--recipe", "none", *METHODS["residual-ppo-set"].train_flags)
LEARNED = "learned (set)"


# ------------------------------------------------------------------------------------------ statistics
def mean_interval(values: Sequence[float]) -> tuple[float, float, float]:
    """Mean and 95 % percentile-bootstrap interval of ``values``, the episodes resampled (nan for none)."""
    values = np.asarray([v for v in values if np.isfinite(v)], dtype=np.float64)
    if not len(values):
        return math.nan, math.nan, math.nan
    low, high = stratified_bootstrap(values[:, None])["mean"]
    return float(values.mean()), low, high


def summary_row(episodes: Sequence[EpisodeMetrics]) -> dict[str, Any]:
    """One table row of a policy's episodes (module docstring)."""
    wins = sum(bool(e.success) for e in episodes)
    low, high = wilson_interval(wins, len(episodes))
    settle, settle_low, settle_high = mean_interval([e.settling_time for e in episodes if e.success])
    return {"episodes": len(episodes), "successes": wins, "success": wins / max(len(episodes), 1),
            "success_low": low, "success_high": high, "settle": settle, "settle_low": settle_low,
            "settle_high": settle_high, "contact_steps": float(np.mean([e.contact_steps for e in episodes])),
            "faults": sum(bool(e.physics_fault) for e in episodes)}


def best_law(rows: dict[str, dict[str, Any]]) -> str:
    """The law of highest success at one N, then of shortest mean settling."""
    laws = [name for name in REFERENCE_CONTROLLERS if name in rows]
    return min(laws, key=lambda name: (-rows[name]["success"], rows[name]["settle"]))


# ------------------------------------------------------------------------------------------ training
def check_transfer(sizes: Sequence[int]) -> None:
    """``ValueError`` naming the field, before any training or folder, if a team size is outside the family or
    its team is not the one a set policy trained on planar_random serves (:mod:`set_network`)."""
    from ee_formation_env.baselines.learned.set_network import set_description

    trained = set_description(TRAIN_SCENARIO, "none")["team"]
    for n in sizes:
        team = set_description(team_scenario(FAMILY, int(n)), "none")["team"]
        for field in trained:
            if team[field] != trained[field]:
                raise ValueError(f"sizes: {FAMILY} at N = {n} has {field} {team[field]!r}, the training team "
                                 f"{trained[field]!r}")


def train_runs(out: Path, seeds: Sequence[int], max_train_seconds: float, total_timesteps: int,
               quick: bool, train_episode_seconds: float | None = None) -> list[Path]:
    """One training run per seed in ``out/seed_<s>`` (a finished run is reused); the run folders.
    ``train_episode_seconds``: train.py's ``--train-episode-seconds`` (None: its residual default)."""
    from ee_formation_env.baselines.learned.config import TrainConfig
    from ee_formation_env.baselines.learned.run import train

    folders = []
    for seed in seeds:
        run_dir = out / f"seed_{seed}"
        if not (run_dir / "model" / "obs_normalizer.json").is_file():
            argv = [*TRAIN_FLAGS, "--seed", str(seed), "--total-timesteps", str(total_timesteps),
                    "--max-train-seconds", str(max_train_seconds), "--out", str(run_dir), "--overwrite",
                    "--eval-episodes", "1", "--eval-seconds", "1", "--eval-workers", "0", "--no-progress"]
            if train_episode_seconds is not None:
                argv += ["--train-episode-seconds", str(train_episode_seconds)]
            if quick:
                argv += ["--n-envs", "2", "--n-steps", "64", "--n-workers", "0"]
            train(TrainConfig.from_args(argv))
        folders.append(run_dir)
    return folders


# ------------------------------------------------------------------------------------------ evaluation
def evaluate_case(scenario: Any, runs: Sequence[Path], seeds: Sequence[int], episode_seconds: float | None
                  ) -> dict[str, Any]:
    """Every law and every run on ``scenario`` at the reset ``seeds``: ``{policy: row}`` with the learned
    runs pooled under :data:`LEARNED` and each run's success under ``per_seed``."""
    from ee_formation_env.baselines.learned.policy import SavedRun

    saved = [SavedRun.load(run) for run in runs]
    policies: dict[str, Any] = {name: name for name in REFERENCE_CONTROLLERS}
    for run, loaded in zip(runs, saved):
        policies[run.name] = loaded.policy_source()
    overrides = {} if episode_seconds is None else {"episode_seconds": episode_seconds}
    overrides.update(saved[0].env_overrides())  # the learned mode's action convention (residual: none)
    episodes = run_policies(scenario, policies, seeds, overrides=overrides)
    rows = {name: summary_row(episodes[name]) for name in REFERENCE_CONTROLLERS}
    pooled = [e for run in runs for e in episodes[run.name]]
    rows[LEARNED] = summary_row(pooled)
    rows[LEARNED]["per_seed"] = {run.name: summary_row(episodes[run.name])["success"] for run in runs}
    best = best_law(rows)
    rows[LEARNED]["best_law"] = best
    rows[LEARNED]["settle_ratio"] = rows[LEARNED]["settle"] / rows[best]["settle"]
    return rows


def evaluate(runs: Sequence[Path], sizes: Sequence[int], episodes: int, episode_seconds: float | None
             ) -> dict[str, Any]:
    """The study's measurements: per team size, on planar_random's test set, on planar_square's test scenarios."""
    seeds = TEST_SEEDS[:episodes]
    results: dict[str, Any] = {"sizes": {}, "episodes": episodes, "runs": [run.name for run in runs]}
    for n in sizes:
        results["sizes"][str(n)] = evaluate_case(team_scenario(FAMILY, int(n)), runs, seeds, episode_seconds)
        print(f"N = {n}: " + ", ".join(f"{name} {row['success']:.0%}" for name, row in
                                       results["sizes"][str(n)].items()), flush=True)
    results["planar_random"] = evaluate_case(TRAIN_SCENARIO, runs, seeds, episode_seconds)
    square_seeds = range(HELD_OUT_SEED_OFFSET, HELD_OUT_SEED_OFFSET + min(SQUARE_EPISODES, episodes))
    results["planar_square"] = {name: evaluate_case(scenario, runs, square_seeds, episode_seconds)
                                for name, scenario in held_out_scenarios("planar_square").items()}
    return results


# ------------------------------------------------------------------------------------------ outputs
def _rate(row: dict[str, Any]) -> str:
    return f"{row['success']:.0%} [{row['success_low']:.0%}, {row['success_high']:.0%}]"


def _settle(row: dict[str, Any]) -> str:
    if not np.isfinite(row["settle"]):
        return "n/a"
    return f"{row['settle']:.2f} [{row['settle_low']:.2f}, {row['settle_high']:.2f}]"


def case_table(title: str, rows: dict[str, Any]) -> list[str]:
    """Markdown lines of one case (a team size or a test scenario): a row per policy."""
    lines = [f"| {title} | policy | episodes | success [95 %] | settle s [95 %] | x best law | contacts (steps) "
             "| faults |", "|---|---|---:|---:|---:|---:|---:|---:|"]
    best = rows[LEARNED]["best_law"]
    for name, row in rows.items():
        ratio = row["settle"] / rows[best]["settle"] if np.isfinite(row["settle"]) else math.nan
        mark = " (best law)" if name == best else ""
        lines.append(f"| | {name}{mark} | {row['episodes']} | {_rate(row)} | {_settle(row)} | "
                     f"{ratio:.2f} | {row['contact_steps']:.1f} | {row['faults']} |")
    return lines


def targets(results: dict[str, Any]) -> list[str]:
    """Each target, met or missed, with its figure."""
    lines = []
    for n, rows in results["sizes"].items():
        learned = rows[LEARNED]
        success_met = learned["success"] >= TARGET_SUCCESS
        ratio = learned["settle_ratio"]
        ratio_met = bool(np.isfinite(ratio) and ratio <= TARGET_SETTLING_RATIO)
        lines.append(f"- N = {n}: success {learned['success']:.0%} (>= {TARGET_SUCCESS:.0%}: "
                     f"{'met' if success_met else '**missed**'}); settling {ratio:.2f} x {learned['best_law']} "
                     f"(<= {TARGET_SETTLING_RATIO}: {'met' if ratio_met else '**missed**'})")
    train_set = results["planar_random"][LEARNED]["success"]
    lines.append(f"- {TRAIN_SCENARIO} test set: {train_set:.0%} (>= {TARGET_TRAIN_SET:.0%}: "
                 f"{'met' if train_set >= TARGET_TRAIN_SET else '**missed**'})")
    return lines


def markdown(results: dict[str, Any]) -> str:
    """The study's tables and targets as Markdown."""
    lines = [f"Zero-shot on {FAMILY} ({results['episodes']} test draws per N; learned: runs "
             f"{', '.join(results['runs'])} pooled)", ""]
    for n, rows in results["sizes"].items():
        lines += case_table(f"N = {n}", rows) + [""]
    lines += [f"{TRAIN_SCENARIO} test set", ""] + case_table(TRAIN_SCENARIO, results["planar_random"]) + [""]
    lines += ["planar_square test scenarios", ""]
    for name, rows in results["planar_square"].items():
        lines += case_table(name, rows) + [""]
    lines += ["Targets", ""] + targets(results)
    return "\n".join(lines) + "\n"


def plot(results: dict[str, Any], path: Path) -> Path:
    """Success vs N with 95 % Wilson intervals: the pooled learned runs and each law."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from studies._common import save_figure

    sizes = [int(n) for n in results["sizes"]]
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    names = [LEARNED, *REFERENCE_CONTROLLERS]
    for k, name in enumerate(names):
        rows = [results["sizes"][str(n)][name] for n in sizes]
        rate = np.array([100 * row["success"] for row in rows])
        # clipped at 0: a Wilson bound equal to the rate can differ from it by a rounding error
        low = np.maximum(rate - np.array([100 * row["success_low"] for row in rows]), 0.0)
        high = np.maximum(np.array([100 * row["success_high"] for row in rows]) - rate, 0.0)
        ax.errorbar(np.array(sizes) + 0.08 * (k - 1.5), rate, yerr=[low, high], marker="o", capsize=3, label=name)
    ax.axhline(100 * TARGET_SUCCESS, color="grey", linestyle="--", linewidth=1, label="target 90 %")
    ax.axvline(4, color="grey", linestyle=":", linewidth=1)
    ax.set_xlabel("team size N (arms); trained at N = 4")
    ax.set_ylabel("success (%)")
    ax.set_ylim(0, 105)
    ax.set_xticks(sizes)
    ax.legend(loc="lower left", fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    return save_figure(fig, path)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m studies.team_size", description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("runs/team_size"), help="runs and results folder")
    parser.add_argument("--seeds", type=int, nargs="+", default=list(DEFAULT_SEEDS), help="training seeds")
    parser.add_argument("--sizes", type=int, nargs="+", default=None,
                        help=f"team sizes N (default {DEFAULT_SIZES[0]} to {DEFAULT_SIZES[-1]}; --quick: 3 and 8)")
    parser.add_argument("--episodes", type=int, default=DEFAULT_EPISODES, help="test draws per N (<= 50)")
    parser.add_argument("--max-train-seconds", type=float, default=DEFAULT_TRAIN_SECONDS,
                        help="wall time per training seed, s")
    parser.add_argument("--total-timesteps", type=int, default=DEFAULT_TIMESTEPS, help="agent steps per seed")
    parser.add_argument("--episode-seconds", type=float, default=None,
                        help="evaluation episode length, s (default: each scenario's)")
    parser.add_argument("--train-episode-seconds", type=float, default=DEFAULT_TRAIN_EPISODE_SECONDS,
                        help=f"training episode length, s (default {DEFAULT_TRAIN_EPISODE_SECONDS})")
    parser.add_argument("--figure", type=Path, default=None, help="the success-vs-N PNG (default OUT/team_size_success.png)")
    parser.add_argument("--quick", action="store_true",
                        help="a smoke run: one seed, N = 3 and 8, 1 draw of 1 s, 2,048 training steps")
    args = parser.parse_args(argv)
    if args.quick:
        args.seeds, args.sizes, args.episodes = args.seeds[:1], args.sizes or [3, 8], 1
        args.total_timesteps, args.episode_seconds = 2048, args.episode_seconds or 1.0
    args.sizes = args.sizes or list(DEFAULT_SIZES)
    if not 1 <= args.episodes <= len(TEST_SEEDS):
        parser.error(f"--episodes: expected 1 to {len(TEST_SEEDS)}, got {args.episodes}")
    try:
        check_transfer(args.sizes)
    except ValueError as error:
        parser.error(str(error))
    runs = train_runs(args.out, args.seeds, args.max_train_seconds, args.total_timesteps, args.quick,
                      args.train_episode_seconds)
    results = evaluate(runs, args.sizes, args.episodes, args.episode_seconds)
    (args.out / "team_size.json").write_text(json.dumps(results, indent=1, default=float) + "\n")
    text = markdown(results)
    (args.out / "team_size.md").write_text(text)
    plot(results, args.figure or args.out / "team_size_success.png")
    print(text, flush=True)
    return results


if __name__ == "__main__":
    main()
