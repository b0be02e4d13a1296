"""Formation manoeuvres: the three laws with their feedforward on the transport and rotation built-ins.

    python -m studies.manoeuvres [--out results/manoeuvres] [--figures-dir docs/figures] [--quick]
                                 [--learned results/scoreboard]

For each task of :data:`TASKS`, each law, each feedforward of :data:`FEEDFORWARDS` (the default gains' reference
hold, and the velocity feedforward alone) and each of :data:`SEEDS`, one episode of the built-in is rolled by
:func:`ee_formation_env.baselines.metrics.run_episode`, recording after every step the largest edge error
(m: ``| |z_k| - d_k |`` for distance formations, ``|z_k - z*_k|`` for displacement ones), the centroid
tracking error ``|c - c*|`` (m) and the orientation tracking error (rad, :mod:`ee_formation_env.manoeuvre`).
Per run: the shape's settling time (s, the metrics' definition), the largest edge error from the later of it
and the motion's start t0 to the episode's end (m; target every edge within :data:`EDGE_TARGET`), over the motion [t0, t0 + T] the largest and RMS centroid error (m;
target :data:`CENTROID_TARGET`) and the largest *motion* error ``|(c - c*)(t) - (c - c*)(t0)|`` (m: the
part the feedforward answers for, without the centroid's drift while the shape forms before t0), the
residual of that after the motion (at the episode's end), the largest orientation error (rad), faults and
contact steps, and the farthest an end-effector got from its base over its reach. Outputs:
``manoeuvres.json`` and the figure ``manoeuvre_tracking.png``. Results: docs/manoeuvres.md.

``--learned BOARD``: also every trained run of the scoreboard's folder ``BOARD`` on these tasks (its
``runs/<task>/<method>/seed-<s>`` of the methods of :data:`LEARNED`), each on the same seeds, as rows named
after the method (worst case over training and evaluation seeds). Their reward is the shape's, so their tracking
is what they inherit from (or lose of) their reference law, except ``position-ppo-tracking``'s, trained with
the reward's tracking term. The BenchMARL ones need the ``torchrl`` extra.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ee_formation_env import parallel_env
from ee_formation_env.baselines import make_policies
from ee_formation_env.baselines.metrics import run_episode
from ee_formation_env.scenario_sets import HELD_OUT_SEED_OFFSET
from studies._common import LAWS, copy_figures, report_outputs, save_figure
from studies.sensing import largest_edge_error

TASKS = ("planar_square_transport", "spatial_tetrahedron_rotate")
SEEDS = tuple(HELD_OUT_SEED_OFFSET + k for k in range(3))
EDGE_TARGET = 0.01  # m: every edge within 1 cm after the shape settles
CENTROID_TARGET = 0.02  # m: centroid within 2 cm of the reference over the motion
#: The laws' manoeuvre feedforward (baselines.reference.controllers): ``hold``, the default gains (the velocity
#: feedforward and the reference hold of gains rule 6); ``velocity``, the velocity feedforward alone (K_X = 0).
FEEDFORWARDS: dict[str, dict[str, float] | None] = {"hold": None, "velocity": {"reference_stiffness": 0.0}}
QUICK = {"episode_seconds": 2.0, "manoeuvre": {"start": 0.5, "duration": 1.0}}  # a smoke run's squeezed motion


#: The scoreboard's learned methods this study evaluates (``--learned``; loaded by studies.scoreboard_methods.trained_policies).
LEARNED = ("residual-ppo", "mappo-residual", "position-ppo", "position-ppo-tracking")


def learned_runs(board: Path, tasks: Sequence[str] = TASKS) -> list[tuple[str, str, int, Path]]:
    """(task, method, training seed, run folder) of every complete run under ``board``'s ``runs/``."""
    found = []
    for task in tasks:
        for method in LEARNED:
            for run_dir in sorted((board / "runs" / task / method).glob("seed-*")):
                complete = (run_dir / "comparison.json").is_file() or (run_dir / "evaluation.json").is_file()
                if complete:
                    found.append((task, method, int(run_dir.name.split("-")[1]), run_dir))
    return found


def _env(task: str, quick: bool) -> Any:
    return parallel_env(task, **(QUICK if quick else {}))


def run_one(task: str, law: str, seed: int, quick: bool = False, keep_series: bool = False,
            feedforward: str = "hold", run: tuple[int, Path] | None = None) -> dict[str, Any]:
    """One episode's record (module docstring); ``keep_series`` adds the per-step series (for the figure).
    ``law``: one of :data:`LAWS`, or with ``run`` = (training seed, run folder) a method of :data:`LEARNED`."""
    env = _env(task, quick)
    series: dict[str, list] = {key: [] for key in ("t", "edge", "centroid_error", "orientation_error",
                                                    "centroid", "reference", "reach")}
    reaches = np.asarray(env.task.reaches)
    bases = env.task.base_positions[:, :env.dim]

    def sample(env: Any) -> None:
        ee = env.end_effector_positions()
        series["t"].append(env.step_count * env.scenario.control_dt)
        series["edge"].append(largest_edge_error(env, ee))
        series["centroid_error"].append(env.centroid_tracking_error())
        series["orientation_error"].append(env.orientation_tracking_error())
        series["centroid"].append(ee[:, :env.dim].mean(axis=0))
        series["reference"].append(env.reference_centroid())
        series["reach"].append(float(np.max(np.linalg.norm(ee[:, :env.dim] - bases, axis=1) / reaches)))

    started = time.time()
    try:
        if run is None:
            policies = make_policies(LAWS[law], env, gains=FEEDFORWARDS[feedforward])
        else:
            from studies.scoreboard_methods import METHODS, trained_policies

            policies = trained_policies(METHODS[law], run[1], env)(env)
        metrics = run_episode(env, policies, seed, on_reset=sample, on_step=sample)
        config = env.scenario.manoeuvre
    finally:
        env.close()
    t = np.asarray(series["t"])
    edge, centroid_error = np.asarray(series["edge"]), np.asarray(series["centroid_error"])
    offsets = np.asarray(series["centroid"]) - np.asarray(series["reference"])  # c - c*, m
    motion = (t >= config.start) & (t <= config.start + config.duration)
    at_start = offsets[int(np.argmax(motion))]
    motion_error = np.linalg.norm(offsets - at_start, axis=1)
    settling = float(metrics.settling_time)
    # Held from the later of the shape's settling and the motion's start: the edges while the formation moves.
    after = t >= max(settling, config.start) if np.isfinite(settling) else np.zeros(len(t), dtype=bool)
    record = {"task": task, "law": law, "feedforward": feedforward, "seed": seed,
              **({} if run is None else {"training_seed": run[0]}), "success": bool(metrics.success), "settling_time": settling,
              "max_edge_error_after_settling": float(edge[after].max()) if after.any() else float("nan"),
              "max_centroid_error": float(centroid_error[motion].max()),
              "rms_centroid_error": float(np.sqrt(np.mean(centroid_error[motion] ** 2))),
              "centroid_error_at_start": float(np.linalg.norm(at_start)),
              "max_motion_error": float(motion_error[motion].max()),
              "final_motion_error": float(motion_error[-1]),
              "max_orientation_error": float(np.max(series["orientation_error"])),
              "final_orientation_error": float(series["orientation_error"][-1]),
              "max_reach_fraction": float(np.max(series["reach"])),
              "min_singularity_margin": float(metrics.min_singularity_margin),
              "contact_steps": int(metrics.contact_steps), "physics_fault": metrics.physics_fault,
              "peak_speed": config.peak_speed, "peak_angular_speed": config.peak_angular_speed,
              "sim_time": float(metrics.sim_time), "wall_s": time.time() - started}
    if keep_series:
        record["series"] = {key: np.asarray(value).tolist() for key, value in series.items()}
    return record


SUMMED = ("settling_time", "max_edge_error_after_settling", "max_centroid_error", "rms_centroid_error",
          "centroid_error_at_start", "max_motion_error", "final_motion_error", "max_orientation_error",
          "final_orientation_error", "max_reach_fraction")


def summarize(records: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per (task, law, feedforward): faults and contacts summed, the worst case over seeds of every error."""
    rows = []
    for task, law, feedforward in dict.fromkeys((r["task"], r["law"], r["feedforward"]) for r in records):
        runs = [r for r in records if (r["task"], r["law"], r["feedforward"]) == (task, law, feedforward)]
        row = {"task": task, "law": law, "feedforward": feedforward, "runs": len(runs), "success": float(np.mean([r["success"] for r in runs])),
               "faults": sum(bool(r["physics_fault"]) for r in runs),
               "contact_steps": sum(r["contact_steps"] for r in runs)}
        row.update({name: float(np.max([r[name] for r in runs])) for name in SUMMED})
        row["edge_target_met"] = bool(row["max_edge_error_after_settling"] <= EDGE_TARGET)
        row["centroid_target_met"] = bool(row["max_centroid_error"] <= CENTROID_TARGET)
        rows.append(row)
    return rows


def format_rows(rows: Sequence[dict[str, Any]]) -> str:
    """The table (markdown): worst case over the seeds."""
    lines = ["| task | law | feedforward | success | faults / contacts | settling (s) | max edge err after (mm) | "
             "max / RMS centroid err (mm) | at motion start (mm) | max / final motion err (mm) | "
             "max / final orientation err (mrad) | reach used |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['task']} | {r['law']} | {r['feedforward']} | {r['success']:.0%} | {r['faults']} / {r['contact_steps']} | "
                     f"{r['settling_time']:.2f} | {1e3 * r['max_edge_error_after_settling']:.2f} | "
                     f"{1e3 * r['max_centroid_error']:.1f} / {1e3 * r['rms_centroid_error']:.1f} | "
                     f"{1e3 * r['centroid_error_at_start']:.1f} | "
                     f"{1e3 * r['max_motion_error']:.1f} / {1e3 * r['final_motion_error']:.1f} | "
                     f"{1e3 * r['max_orientation_error']:.1f} / {1e3 * r['final_orientation_error']:.1f} | "
                     f"{r['max_reach_fraction']:.0%} |")
    return "\n".join(lines)


def plot_tracking(records: Sequence[dict[str, Any]], out: Path) -> Path:
    """Per task (columns): the reference and actual centroid paths, the largest edge error and the tracking
    errors over time, one line per law (first seed, the default ``hold`` feedforward)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    records = [r for r in records if r["feedforward"] == "hold" and r["law"] in LAWS]
    tasks = list(dict.fromkeys(r["task"] for r in records if "series" in r))
    fig, axes = plt.subplots(3, len(tasks), figsize=(6.0 * len(tasks), 10.0), squeeze=False)
    for column, task in enumerate(tasks):
        runs = [r for r in records if r["task"] == task and "series" in r]
        for k, run in enumerate(runs):
            s = run["series"]
            t, centroid, reference = np.asarray(s["t"]), np.asarray(s["centroid"]), np.asarray(s["reference"])
            if k == 0:
                axes[0, column].plot(reference[:, 0], reference[:, 1], "k--", lw=2, label="reference c*")
            axes[0, column].plot(centroid[:, 0], centroid[:, 1], lw=1, label=f"{run['law']} centroid")
            axes[1, column].semilogy(t, np.maximum(s["edge"], 1e-6), lw=1, label=run["law"])
            axes[2, column].plot(t, 1e3 * np.asarray(s["centroid_error"]), lw=1, label=f"{run['law']} |c - c*|")
            if task.endswith("rotate"):
                axes[2, column].plot(t, 1e3 * np.asarray(s["orientation_error"]), lw=1, ls=":",
                                     label=f"{run['law']} orientation (mrad)")
        axes[0, column].set(title=task, xlabel="x (m)", ylabel="y (m)")
        axes[0, column].axis("equal")
        axes[1, column].axhline(EDGE_TARGET, color="grey", ls=":", lw=1)
        axes[1, column].set(ylabel="largest edge error (m)")
        axes[2, column].axhline(1e3 * CENTROID_TARGET, color="grey", ls=":", lw=1)
        axes[2, column].set(xlabel="t (s)", ylabel="tracking error (mm; mrad)")
        for row in range(3):
            axes[row, column].legend(fontsize=7)
    return save_figure(fig, out / "manoeuvre_tracking.png")


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Command-line entry: run every (task, law, seed), print the table, write the JSON and the figure."""
    parser = argparse.ArgumentParser(prog="python -m studies.manoeuvres", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("results/manoeuvres"), help="output folder")
    parser.add_argument("--figures-dir", type=Path, default=None, help="also copy the PNG here")
    parser.add_argument("--learned", type=Path, default=None, metavar="BOARD",
                        help="also evaluate the scoreboard's trained runs on these tasks found in BOARD (e.g. "
                             "results/scoreboard)")
    parser.add_argument("--quick", action="store_true", help=f"one seed, {QUICK['episode_seconds']:g} s episodes "
                        "with the motion squeezed into them (a smoke run; never the documented table)")
    args = parser.parse_args(argv)
    if args.learned is not None and not (args.learned / "runs").is_dir():
        parser.error(f"--learned: {args.learned} has no runs/ folder (a scoreboard's output folder)")
    seeds = SEEDS[:1] if args.quick else SEEDS
    records = []
    for task in TASKS:
        for law in LAWS:
            for feedforward in FEEDFORWARDS:
                for seed in seeds:
                    record = run_one(task, law, seed, args.quick, keep_series=seed == seeds[0], feedforward=feedforward)
                    records.append(record)
                    print(f"{task} {law} {feedforward} seed {seed}: edge after settling {record['max_edge_error_after_settling']:.4f} m, "
                          f"centroid max {record['max_centroid_error']:.4f} m, motion max {record['max_motion_error']:.4f} m, "
                          f"orientation max {record['max_orientation_error']:.4f} rad {record['physics_fault']} "
                          f"({record['wall_s']:.1f} s)", flush=True)
    for task, method, training_seed, run_dir in ([] if args.learned is None else learned_runs(args.learned)):
        for seed in seeds:
            record = run_one(task, method, seed, args.quick, run=(training_seed, run_dir))
            records.append(record)
            print(f"{task} {method} (training seed {training_seed}) seed {seed}: edge after settling "
                  f"{record['max_edge_error_after_settling']:.4f} m, centroid max {record['max_centroid_error']:.4f} m, "
                  f"orientation max {record['max_orientation_error']:.4f} rad {record['physics_fault']}", flush=True)
    rows = summarize(records)
    print(format_rows(rows))
    args.out.mkdir(parents=True, exist_ok=True)
    results = {"tasks": list(TASKS), "seeds": list(seeds), "quick": args.quick,
               "learned": None if args.learned is None else str(args.learned), "edge_target": EDGE_TARGET,
               "centroid_target": CENTROID_TARGET, "rows": rows,
               "runs": [{k: v for k, v in r.items() if k != "series"} for r in records]}
    (args.out / "manoeuvres.json").write_text(json.dumps(results, indent=1) + "\n", encoding="utf-8")
    figure = plot_tracking(records, args.out)
    report_outputs(args.out, copy_figures([figure], args.figures_dir))
    return results


if __name__ == "__main__":
    main()
