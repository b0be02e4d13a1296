"""Imperfect sensing: the three laws against each knob of the scenario's ``sensing`` (noise, delay, bias, yaw).

    python -m studies.sensing [--out results/sensing] [--figures-dir docs/figures] [--scenarios ...] [--quick]

For each scenario (default the planar square, distance and displacement), each law and each knob at each
level of :data:`LEVELS` (plus exact sensing), :data:`SEEDS` reset seeds of the scenario's 30 s episodes are
rolled by :func:`ee_formation_env.baselines.metrics.run_episode`, recording the end-effectors. Per run:
success and settling time (the metrics' definition, on the true formation error), the final largest edge
error (m: | |z_k| - d_k | for distance formations, |z_k - z*_k| for displacement ones), and over the last
:data:`RATE_WINDOW_SECONDS` of the episode the centroid's speed (m/s) and the formation's rotation rate
(rad/s: the angle of the best rotation taking the centred end-effector positions at the window's start to
those at its end, divided by its length). ``bias`` and ``yaw`` give every agent its own value: a bias of
that length in a seeded direction; yaws alternating in sign, +a, -a, ... (a common yaw is a consistent
rotation of every frame and moves nothing in a distance formation). Outputs: ``sensing.json`` and the
figure ``sensing_effects.png``. Results: docs/sensing.md.
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
from ee_formation_env.scenario import load_scenario
from ee_formation_env.scenario_sets import HELD_OUT_SEED_OFFSET
from studies._common import LAWS, copy_figures, report_outputs, save_figure

#: Each knob's levels: noise (m, standard deviation), delay (control steps), bias (m), yaw (rad).
LEVELS: dict[str, tuple[float, ...]] = {"noise": (0.002, 0.005, 0.01), "delay": (2, 5, 10),
                                        "bias": (0.005, 0.01, 0.02), "yaw": (0.05, 0.1, 0.2)}
SEEDS = tuple(HELD_OUT_SEED_OFFSET + k for k in range(3))
RATE_WINDOW_SECONDS = 10.0
DEFAULT_SCENARIOS = ("planar_square", "planar_square_displacement")
QUICK_EPISODE_SECONDS = 2.0


def sensing_of(knob: str, level: float, n_agents: int) -> dict[str, Any]:
    """The scenario's ``sensing`` for one knob at one level (module docstring)."""
    if knob == "none":
        return {}
    if knob == "yaw":
        return {"yaw": [level * (-1) ** i for i in range(n_agents)]}
    if knob == "delay":
        return {"delay": int(level)}
    return {knob: float(level)}


def rotation_angle(before: np.ndarray, after: np.ndarray, signed: bool = False) -> float:
    """The angle (rad) of the best rotation taking the centred points ``before`` (N, d) onto ``after``;
    ``signed`` (2D only): counter-clockwise positive."""
    a, b = before - before.mean(axis=0), after - after.mean(axis=0)
    u, _, vt = np.linalg.svd(a.T @ b)
    rotation = (u @ vt).T
    if np.linalg.det(rotation) < 0:  # a reflection: the nearest proper rotation
        u[:, -1] *= -1
        rotation = (u @ vt).T
    if rotation.shape == (2, 2):
        angle = float(np.arctan2(rotation[1, 0], rotation[0, 0]))
        return angle if signed else abs(angle)
    return float(np.arccos(np.clip((np.trace(rotation) - 1) / 2, -1.0, 1.0)))


def largest_edge_error(env: Any, ee: np.ndarray) -> float:
    """The largest edge error (m) of end-effector positions ``ee`` (N, 3) in ``env``'s formation."""
    z = env.graph.edge_vectors(ee[:, :env.dim])
    if env.scenario.formation == "distance":
        return float(np.max(np.abs(np.linalg.norm(z, axis=1) - env.formation.desired)))
    return float(np.max(np.linalg.norm(z - env.formation.desired_vectors, axis=1)))


def _env(scenario: str, knob: str, level: float, episode_seconds: float | None) -> Any:
    """The scenario's env with one knob at one level (and the episode length, if given)."""
    n_agents = load_scenario(scenario).n_agents  # the scenario alone: no second PyBullet world for a count
    extra = {} if episode_seconds is None else {"episode_seconds": episode_seconds}
    return parallel_env(scenario, sensing=sensing_of(knob, level, n_agents), **extra)


def run_one(scenario: str, law: str, knob: str, level: float, seed: int, episode_seconds: float | None = None
            ) -> dict[str, Any]:
    """One episode's record (module docstring)."""
    env = _env(scenario, knob, level, episode_seconds)
    started = time.time()
    try:
        metrics = run_episode(env, make_policies(LAWS[law], env), seed, record=True)
        ee, t = np.asarray(metrics.trajectory["ee"]), np.asarray(metrics.trajectory["t"])
        dim = env.dim
        window = t >= t[-1] - RATE_WINDOW_SECONDS
        first = int(np.argmax(window))
        span = max(float(t[-1] - t[first]), 1e-9)
        record = {"scenario": scenario, "law": law, "knob": knob, "level": level, "seed": seed,
                  "success": bool(metrics.success), "settling_time": float(metrics.settling_time),
                  "final_edge_error": largest_edge_error(env, ee[-1]),
                  "centroid_speed": float(np.linalg.norm(ee[-1, :, :dim].mean(0) - ee[first, :, :dim].mean(0)) / span),
                  "rotation_rate": rotation_angle(ee[first, :, :dim], ee[-1, :, :dim]) / span,
                  "physics_fault": metrics.physics_fault, "sim_time": float(metrics.sim_time),
                  "wall_s": time.time() - started}
    finally:
        env.close()
    return record


def summarize(records: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per (scenario, law, knob, level): success rate, faults, and the means over seeds."""
    keys = sorted({(r["scenario"], r["law"], r["knob"], r["level"]) for r in records},
                  key=lambda k: (k[0], k[1], list(LEVELS).index(k[2]) if k[2] in LEVELS else -1, k[3]))
    rows = []
    for scenario, law, knob, level in keys:
        runs = [r for r in records if (r["scenario"], r["law"], r["knob"], r["level"]) == (scenario, law, knob, level)]
        rows.append({"scenario": scenario, "law": law, "knob": knob, "level": level, "runs": len(runs),
                     "success": float(np.mean([r["success"] for r in runs])),
                     "faults": sum(bool(r["physics_fault"]) for r in runs),
                     **{name: float(np.mean([r[name] for r in runs]))
                        for name in ("final_edge_error", "centroid_speed", "rotation_rate")}})
    return rows


def format_rows(rows: Sequence[dict[str, Any]]) -> str:
    """The robustness table (markdown), one block per scenario."""
    lines = []
    for scenario in dict.fromkeys(r["scenario"] for r in rows):
        lines += ["", f"**{scenario}**", "",
                  "| knob | level | law | success | faults | final max edge err (m) | centroid speed (mm/s) "
                  "| rotation (mrad/s) |", "|---|---:|---|---:|---:|---:|---:|---:|"]
        for r in (r for r in rows if r["scenario"] == scenario):
            level = "-" if r["knob"] == "none" else f"{r['level']:g}"
            lines.append(f"| {r['knob']} | {level} | {r['law']} | {r['success']:.0%} | {r['faults']} | "
                         f"{r['final_edge_error']:.4f} | {1e3 * r['centroid_speed']:.2f} | "
                         f"{1e3 * r['rotation_rate']:.2f} |")
    return "\n".join(lines[1:])


def plot_effects(scenarios: Sequence[str], out: Path, episode_seconds: float | None = None) -> Path:
    """The known effects, law-I: per scenario, the largest edge error over time, and the formation's rotation
    (distance formations) or its centroid's travel (displacement formations), exact against biased sensing
    (the steady motion of mismatched measurements) and alternating yaw."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = (("none", 0.0, "exact"), ("bias", 0.01, "bias 1 cm"), ("yaw", 0.1, "yaw +-0.1 rad"))
    fig, axes = plt.subplots(2, len(scenarios), figsize=(5.5 * len(scenarios), 6.5), squeeze=False)
    for column, scenario in enumerate(scenarios):
        for knob, level, label in cases:
            env = _env(scenario, knob, level, episode_seconds)
            try:
                metrics = run_episode(env, make_policies(LAWS["law-I"], env), SEEDS[0], record=True)
                ee, t = np.asarray(metrics.trajectory["ee"]), np.asarray(metrics.trajectory["t"])
                errors = [largest_edge_error(env, frame) for frame in ee]
                planar = ee[:, :, :env.dim]
                distance = env.scenario.formation == "distance"
                if distance:
                    angles = [rotation_angle(planar[0], frame, signed=env.dim == 2) for frame in planar]
                    motion = np.degrees(np.unwrap(angles) if env.dim == 2 else angles)
                else:
                    motion = np.linalg.norm(planar.mean(axis=1) - planar[0].mean(axis=0), axis=1)
            finally:
                env.close()
            axes[0, column].semilogy(t, np.maximum(errors, 1e-6), label=label)
            axes[1, column].plot(t, motion, label=label)
        axes[0, column].axhline(0.01, color="grey", ls=":", lw=1)
        axes[0, column].set(title=f"{scenario}, law-I", ylabel="largest edge error (m)")
        axes[1, column].set(xlabel="t (s)", ylabel="formation rotation since t = 0 (deg)" if distance
                            else "centroid travel since t = 0 (m)")
        axes[0, column].legend(fontsize=8)
    return save_figure(fig, out / "sensing_effects.png")


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Command-line entry: run the grid, print the table, write the JSON and the figure."""
    parser = argparse.ArgumentParser(prog="python -m studies.sensing", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("results/sensing"), help="output folder")
    parser.add_argument("--figures-dir", type=Path, default=None, help="also copy the PNG here")
    parser.add_argument("--scenarios", nargs="+", default=list(DEFAULT_SCENARIOS), help="built-in scenarios")
    parser.add_argument("--quick", action="store_true", help=f"one level per knob (the largest), one seed and "
                        f"{QUICK_EPISODE_SECONDS:g} s episodes (a smoke run; never the documented table)")
    args = parser.parse_args(argv)
    from ee_formation_env.builtin import BUILTIN_SCENARIOS

    unknown = [s for s in args.scenarios if s not in BUILTIN_SCENARIOS]
    if unknown:
        parser.error(f"--scenarios: unknown {unknown}; available: {sorted(BUILTIN_SCENARIOS)}")
    levels = {knob: values[-1:] for knob, values in LEVELS.items()} if args.quick else LEVELS
    seeds = SEEDS[:1] if args.quick else SEEDS
    episode_seconds = QUICK_EPISODE_SECONDS if args.quick else None
    grid = [("none", 0.0)] + [(knob, level) for knob, values in levels.items() for level in values]
    records = []
    for scenario in args.scenarios:
        for law in LAWS:
            for knob, level in grid:
                for seed in seeds:
                    record = run_one(scenario, law, knob, level, seed, episode_seconds)
                    records.append(record)
                    print(f"{scenario} {law} {knob}={level:g} seed {seed}: success={record['success']} "
                          f"err={record['final_edge_error']:.4f} m rot={1e3 * record['rotation_rate']:.2f} mrad/s "
                          f"{record['physics_fault']} ({record['wall_s']:.1f} s)", flush=True)
    rows = summarize(records)
    print(format_rows(rows))
    args.out.mkdir(parents=True, exist_ok=True)
    results = {"levels": levels, "seeds": list(seeds), "episode_seconds": episode_seconds, "rows": rows,
               "runs": records}
    (args.out / "sensing.json").write_text(json.dumps(results, indent=1) + "\n", encoding="utf-8")
    figure = plot_effects(args.scenarios, args.out, episode_seconds)
    report_outputs(args.out, copy_figures([figure], args.figures_dir))
    return results


if __name__ == "__main__":
    main()
