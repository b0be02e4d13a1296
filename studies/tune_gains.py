"""Tune the reference laws' gains: a seeded Optuna search per (built-in scenario, law), written as data.

    python -m studies.tune_gains                                   # every built-in, every law (hours)
    python -m studies.tune_gains --scenario planar_square --law gradient --trials 60

Each trial is a point of :data:`~ee_formation_env.baselines.reference.tuned.SEARCH_SPACE` (the gains the law
reads, relative to its defaults), scored on ``--episodes`` tuning starts (``TUNING_SEEDS``; a distribution's
training draws ``DISTRIBUTION_TUNING_SEEDS``; never an evaluation seed) by the episode loop of
:mod:`ee_formation_env.baselines.metrics`, each episode stopped once every edge has held the 1 mm band for 1 s
(a manoeuvre's runs to :data:`MANOEUVRE_SETTLE_SECONDS` after its motion: the band must hold through it). The objective (:func:`objective_value`,
lower is better) is the mean time to the 1 mm band, under constraints each worth a full horizon when broken:
every episode a success at 1 cm and at 1 mm, no physics fault, no contact step, energy at most
:data:`ENERGY_RATIO` times the default gains' on the same starts, saturation no higher than theirs (in seconds
at the limit per joint: the episodes stop at the hold, so a clipped share alone would grow with speed).
The sampler is Optuna's TPE, seeded; the default gains are the first trial (the search starts from them).

Laws that coincide on a task are tuned once: where gravity loads no joint, law II with K_I = 0 is law I
(``approx_jacobian`` gets ``gradient``'s point, recorded as such).

Writes ``baselines/reference/tuned/<scenario>.json`` (the library's data, stamped: scenario digest, seeds,
trials, sampler seed, objective, the default's and the best's figures) and, for the lab, every trial and the
best-so-far curve under ``studies/results/tuning/`` (``<scenario>.csv``, ``<scenario>.png``).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ee_formation_env.baselines import REFERENCE_CONTROLLERS, make_policies
from ee_formation_env.baselines.metrics import EpisodeMetrics, run_episodes
from ee_formation_env.baselines.reference.gains import arm_gain_limits, arm_inputs
from ee_formation_env.baselines.reference.tuned import (DISTRIBUTION_TUNING_SEEDS, SEARCH_SPACE, TUNED_SCHEMA,
                                                        TUNING_SEEDS, gains_from_point, law_parameters,
                                                        read_tuned_file, scenario_digest, tuned_path)
from ee_formation_env.builtin import BUILTIN_SCENARIOS, builtin_scenario
from ee_formation_env.scenario import load_scenario
from ee_formation_env.task import build_task

ENERGY_RATIO = 1.5  # a tuned set may spend at most this multiple of the default gains' energy
DEFAULT_TRIALS = 60
DEFAULT_EPISODES = 6  # tuning starts per trial
MANOEUVRE_EPISODES = 2  # a manoeuvre's episodes run through its motion (30 s): fewer starts per trial
HORIZON_SECONDS = 12.0  # s: a trial's episodes end here at the latest (a manoeuvre's: see below)
MANOEUVRE_SETTLE_SECONDS = 5.0  # s: a manoeuvre's tuning episodes end this long after its motion
RESULTS = Path(__file__).resolve().parent / "results" / "tuning"


def gravity_loads_joints(scenario: Any) -> bool:
    """Whether gravity loads any joint of the scenario's arms (then laws II and III read K_I)."""
    task = build_task(load_scenario(scenario))
    return any(arm_gain_limits(arm, task.scenario.control_dt, samples=20).gravity_loads_joints
               for arm in arm_inputs(task))


def default_point(law: str, gravity: bool, scenario: Any) -> dict[str, Any]:
    """The search-space point of the default gains (the first trial): scales 1, the default's saturation and
    rate damping, its K_I."""
    data = load_scenario(scenario)
    carried = data.controller_gains
    point: dict[str, Any] = {"kp_scale": 1.0, "kd_scale": 1.0, "saturated": carried is None, "spring_scale": 1.0,
                             "rate_steps": 0.0 if carried is not None else 1.5}
    names = law_parameters(law, gravity)
    if "ki" in names:
        task = build_task(data)
        from ee_formation_env.baselines.reference.gains import default_gains

        point["ki"] = float(np.clip(np.max(default_gains(task, 0).ki), *SEARCH_SPACE["ki"][:2]))
    if "alpha_scale" in names:
        point.update(alpha_scale=1.0, adaptation_scale=1.0)
    return point


def tuning_seeds(scenario: str, episodes: int) -> list[int]:
    data = load_scenario(scenario)
    seeds = DISTRIBUTION_TUNING_SEEDS if data.distribution.active else TUNING_SEEDS
    return list(seeds[:episodes])


def episode_settings(scenario: str) -> tuple[dict[str, Any], bool]:
    """(scenario overrides, stop on the precision hold) of a trial's episodes."""
    data = load_scenario(scenario)
    manoeuvre = data.manoeuvre is not None and data.manoeuvre.active
    if manoeuvre:  # the motion and MANOEUVRE_SETTLE_SECONDS after it: the band must hold through it
        motion_end = data.manoeuvre.start + data.manoeuvre.duration
        return {"episode_seconds": min(data.episode_seconds, motion_end + MANOEUVRE_SETTLE_SECONDS)}, False
    return {"episode_seconds": min(data.episode_seconds, HORIZON_SECONDS)}, True


def evaluate_point(scenario: str, law: str, point: dict[str, Any] | None, seeds: Sequence[int]
                   ) -> list[EpisodeMetrics]:
    """The tuning episodes of ``law`` at ``point`` (None: its default gains) on ``seeds``."""
    overrides, stop = episode_settings(scenario)

    def policies(copy_env: Any) -> dict[str, Any]:
        if point is None:
            return make_policies(law, copy_env)
        team = make_policies(law, copy_env)
        for index, controller in enumerate(team.values()):
            source = (lambda env=copy_env, i=index: gains_from_point(env.task, i, point))
            controller.set_gains(source())
            if copy_env.scenario.distribution.active:
                controller.gains_source = source
        return team

    return run_episodes(scenario, policies, seeds, overrides=overrides, stop_on_precision_hold=stop)


def figures(episodes: Sequence[EpisodeMetrics]) -> dict[str, float]:
    """What a trial is judged on, over its episodes."""
    return {
        "success": float(np.mean([e.success for e in episodes])),
        "success_1mm": float(np.mean([e.success_1mm for e in episodes])),
        "settling_time_1mm": float(np.mean([e.settling_time_1mm if e.success_1mm else math.nan for e in episodes])),
        "settling_time": float(np.mean([e.settling_time if e.success else math.nan for e in episodes])),
        "steady_worst_edge_error": float(max(e.steady_worst_edge_error for e in episodes)),
        "energy": float(np.mean([e.control_energy for e in episodes])),
        # s per joint at the limit: the clipped share times the episode's length (episodes stop at the hold,
        # so a share alone would grow with speed)
        "saturated_seconds": float(np.mean([e.saturation_fraction * e.sim_time for e in episodes])),
        "contact_steps": float(sum(e.contact_steps for e in episodes)),
        "faults": float(sum(bool(e.physics_fault) for e in episodes)),
    }


def objective_value(episodes: Sequence[EpisodeMetrics], default: dict[str, float], horizon: float) -> float:
    """Lower is better: the mean time to the 1 mm band (an episode that never holds it counts ``horizon`` plus
    its final worst edge error in cm, capped at 10), plus ``horizon`` for each broken constraint (module
    docstring), scaled by how far it is broken."""
    times = [e.settling_time_1mm if e.success_1mm else horizon + min(e.steady_worst_edge_error / 1e-2, 10.0)
             for e in episodes]
    value = float(np.mean(times))
    mine = figures(episodes)
    value += horizon * (1.0 - mine["success"])
    value += horizon * (mine["faults"] > 0) + horizon * (mine["contact_steps"] > 0)
    if mine["energy"] > ENERGY_RATIO * default["energy"]:
        value += horizon * (1.0 + mine["energy"] / (ENERGY_RATIO * default["energy"]) - 1.0)
    if mine["saturated_seconds"] > default["saturated_seconds"] + 1e-9:
        value += horizon * (1.0 + (mine["saturated_seconds"] - default["saturated_seconds"]))
    return value


def feasible(episodes: Sequence[EpisodeMetrics], default: dict[str, float]) -> bool:
    mine = figures(episodes)
    return (mine["success"] == 1.0 and mine["success_1mm"] == 1.0 and mine["faults"] == 0
            and mine["contact_steps"] == 0 and mine["energy"] <= ENERGY_RATIO * default["energy"]
            and mine["saturated_seconds"] <= default["saturated_seconds"] + 1e-9)


def suggest(trial: Any, law: str, gravity: bool) -> dict[str, Any]:
    point: dict[str, Any] = {}
    for name in law_parameters(law, gravity):
        if name == "saturated":
            point[name] = trial.suggest_categorical(name, [True, False])
            continue
        low, high, log = SEARCH_SPACE[name]
        point[name] = trial.suggest_float(name, low, high, log=log)
    return point


def tune(scenario: str, law: str, trials: int, episodes: int, sampler_seed: int,
         progress: Any = print) -> dict[str, Any]:
    """One law's search on one scenario: its record for the tuned file, and every trial."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    gravity = gravity_loads_joints(scenario)
    seeds = tuning_seeds(scenario, episodes)
    overrides, stop = episode_settings(scenario)
    horizon = overrides["episode_seconds"]
    started = time.process_time()
    default_episodes = evaluate_point(scenario, law, None, seeds)
    default = figures(default_episodes)
    history: list[dict[str, Any]] = []

    def objective(trial: Any) -> float:
        point = suggest(trial, law, gravity)
        episodes_run = evaluate_point(scenario, law, point, seeds)
        value = objective_value(episodes_run, default, horizon)
        history.append({"trial": trial.number, "value": value, "feasible": feasible(episodes_run, default),
                        "point": point, **figures(episodes_run)})
        return value

    sampler = optuna.samplers.TPESampler(seed=sampler_seed, n_startup_trials=10)
    study = optuna.create_study(direction="minimize", sampler=sampler)
    study.enqueue_trial(default_point(law, gravity, scenario))
    for number in range(trials):
        study.optimize(objective, n_trials=1)
        if (number + 1) % 10 == 0:
            best = min(history, key=lambda h: h["value"])
            progress(f"  {scenario} / {law}: {number + 1} trials, best {best['value']:.3f} "
                     f"(1 mm in {best['settling_time_1mm']:.2f} s, feasible {best['feasible']})")
    best = min(history, key=lambda h: h["value"])
    cpu_seconds = time.process_time() - started
    record = {
        "point": best["point"] if best["feasible"] else history[0]["point"],
        "improved": bool(best["feasible"] and best["value"] < history[0]["value"]),
        "trials": trials, "sampler": f"optuna TPESampler(seed={sampler_seed}, n_startup_trials=10)",
        "optuna": optuna.__version__, "tuning_seeds": [seeds[0], seeds[-1]], "episodes_per_trial": len(seeds),
        "horizon_seconds": horizon, "stopped_on_precision_hold": stop, "cpu_seconds": round(cpu_seconds, 1),
        "default": default, "best": {k: v for k, v in best.items() if k not in ("point",)},
    }
    return {"record": record, "history": history, "gravity": gravity}


def write_tuned(scenario: str, laws: dict[str, dict[str, Any]]) -> Path:
    """Merge ``laws`` (law -> record) into the scenario's tuned file (the other laws' entries stay)."""
    path = tuned_path(scenario)
    digest = scenario_digest(builtin_scenario(scenario))
    existing: dict[str, Any] = {}
    if path.is_file():
        data = read_tuned_file(path)
        if data["scenario_digest"] == digest:
            existing = data["laws"]
    data = {"schema": TUNED_SCHEMA, "scenario": scenario, "scenario_digest": digest,
            "laws": {**existing, **laws}}
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_suffix(".json.partial")
    temporary.write_text(json.dumps(data, indent=1, default=float) + "\n", encoding="utf-8")
    temporary.replace(path)
    read_tuned_file(path)  # what was written reads back
    return path


def write_history(scenario: str, law: str, history: list[dict[str, Any]]) -> Path:
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{scenario}-{law}.csv"
    keys = ["trial", "value", "feasible", "settling_time_1mm", "settling_time", "success", "success_1mm",
            "steady_worst_edge_error", "energy", "saturated_seconds", "contact_steps", "faults", "point"]
    with path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(keys)
        for row in history:
            writer.writerow([json.dumps(row[k], sort_keys=True) if k == "point" else row[k] for k in keys])
    return path


def read_histories(scenario: str) -> dict[str, list[dict[str, Any]]]:
    """Each law's tuning history of ``scenario`` as :func:`write_history` saved it (the laws tuned so far)."""
    histories = {}
    for law in REFERENCE_CONTROLLERS:
        path = RESULTS / f"{scenario}-{law}.csv"
        if path.is_file():
            with path.open(newline="", encoding="utf-8") as handle:
                histories[law] = [{"value": float(row["value"])} for row in csv.DictReader(handle)]
    return histories


def best_so_far_figure(scenario: str, histories: dict[str, list[dict[str, Any]]]) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(6, 3.6))
    for law, history in histories.items():
        values = np.minimum.accumulate([h["value"] for h in history])
        axis.plot(np.arange(1, len(values) + 1), values, label=law)
    axis.set(title=f"{scenario}: best objective so far", xlabel="trial (1: the default gains)",
             ylabel="objective (s to the 1 mm band)", yscale="log")
    axis.legend(fontsize=8)
    figure.tight_layout()
    path = RESULTS / f"{scenario}.png"
    figure.savefig(path, dpi=100)
    plt.close(figure)
    return path


def unseen_check(scenario: str, laws: Sequence[str], episodes: int = 50) -> list[dict[str, Any]]:
    """Each law at its defaults and at its tuned gains on ``episodes`` of the unseen-check seeds
    (``UNSEEN_CHECK_SEEDS``: never tuned or evaluated on), full episodes: one summary row each."""
    from ee_formation_env.baselines.metrics import summarize
    from ee_formation_env.baselines.reference.tuned import UNSEEN_CHECK_SEEDS

    rows = []
    for law in laws:
        for gains in ("default", "tuned"):
            metrics = run_episodes(scenario, law, list(UNSEEN_CHECK_SEEDS[:episodes]),
                                   policy_kwargs={} if gains == "default" else {"gains": "tuned"})
            summary = summarize(metrics)
            rows.append({"scenario": scenario, "law": law, "gains": gains, "episodes": len(metrics),
                         "settling_time_max": float(np.nanmax([m.settling_time for m in metrics])),
                         **{key: summary[key] for key in ("success_rate", "success_rate_1mm", "settling_time",
                                                         "settling_time_1mm", "steady_worst_edge_error_max",
                                                         "control_energy", "contact_steps", "physics_faults")}})
    return rows


def unseen_table(rows: Sequence[dict[str, Any]]) -> str:
    lines = ["| scenario | law | gains | success | 1 mm | settle 1 cm (s), mean / max | to 1 mm (s) | worst edge (m) "
             "| energy | contacts |", "|---|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['scenario']} | {r['law']} | {r['gains']} | {r['success_rate']:.0%} | "
                     f"{r['success_rate_1mm']:.0%} | {r['settling_time']:.2f} / {r['settling_time_max']:.2f} | "
                     f"{r['settling_time_1mm']:.2f} | {r['steady_worst_edge_error_max']:.1e} | "
                     f"{r['control_energy']:,.0f} | {r['contact_steps']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m studies.tune_gains", description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", action="append", choices=BUILTIN_SCENARIOS,
                        help="a built-in scenario (repeatable; default: every built-in)")
    parser.add_argument("--law", action="append", choices=list(REFERENCE_CONTROLLERS),
                        help="a law (repeatable; default: all three)")
    parser.add_argument("--trials", type=int, default=DEFAULT_TRIALS, help="trials per law and scenario (60)")
    parser.add_argument("--episodes", type=int, default=None,
                        help=f"tuning starts per trial ({DEFAULT_EPISODES}; a manoeuvre's {MANOEUVRE_EPISODES})")
    parser.add_argument("--sampler-seed", type=int, default=0, help="the TPE sampler's seed (0)")
    parser.add_argument("--check-unseen", action="store_true",
                        help="tune nothing: run each law at its defaults and its tuned gains on the 50 unseen-check "
                             "seeds (full episodes) and print the table")
    args = parser.parse_args(argv)
    if args.check_unseen:
        rows = [row for scenario in args.scenario or BUILTIN_SCENARIOS
                for row in unseen_check(scenario, args.law or list(REFERENCE_CONTROLLERS))]
        RESULTS.mkdir(parents=True, exist_ok=True)
        (RESULTS / "unseen_check.json").write_text(json.dumps(rows, indent=1, default=float), encoding="utf-8")
        print(unseen_table(rows))
        return 0
    if args.trials < 1:
        parser.error("--trials: expected at least 1")
    if args.episodes is not None and not 1 <= args.episodes <= len(TUNING_SEEDS):
        parser.error(f"--episodes: expected 1 to {len(TUNING_SEEDS)}")
    for scenario in args.scenario or BUILTIN_SCENARIOS:
        laws = args.law or list(REFERENCE_CONTROLLERS)
        data = load_scenario(scenario)
        manoeuvre = data.manoeuvre is not None and data.manoeuvre.active
        episodes = args.episodes or (MANOEUVRE_EPISODES if manoeuvre else DEFAULT_EPISODES)
        gravity = gravity_loads_joints(scenario)
        records: dict[str, dict[str, Any]] = {}
        tuned_laws: list[str] = []
        for law in laws:
            if law == "approx_jacobian" and not gravity:
                continue  # law II with K_I = 0 is law I here: tuned once, as gradient
            print(f"tuning {scenario} / {law}: {args.trials} trials x {episodes} episodes", flush=True)
            result = tune(scenario, law, args.trials, episodes, args.sampler_seed)
            records[law] = result["record"]
            write_history(scenario, law, result["history"])
            print(f"wrote {write_tuned(scenario, {law: result['record']})}", flush=True)  # each law kept once tuned
            tuned_laws.append(law)
        if "approx_jacobian" in laws and not gravity:
            source = records.get("gradient")
            if source is None:
                try:
                    source = read_tuned_file(tuned_path(scenario))["laws"]["gradient"]
                except (ValueError, KeyError):
                    source = None
            if source is not None:
                same = {**source, "same_as": "gradient", "why": "no joint carries gravity: law II with K_I = 0 is law I"}
                print(f"wrote {write_tuned(scenario, {'approx_jacobian': same})}", flush=True)
        if tuned_laws:
            best_so_far_figure(scenario, read_histories(scenario))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
