"""Reproduce the paper's simulations (Sec. VI, Figs. 4-7 in 2D and 9-12 in 3D) and the stall study.

    python -m studies.reproduce [--out results/reproduction] [--figures-dir docs/figures]
                                  [--only planar|spatial|stall ...] [--quick]

Every run uses the adaptive-Jacobian law (Theorem 4.2, law-III) from the paper's initial joint positions
(``initial_q_noise = 0``, reset seed 0) and is rolled by :func:`ee_formation_env.baselines.metrics.run_episode`; the
controllers' kinematic estimates ``a_hat`` are logged through its ``on_step`` callback. Two presets:

- ``paper``: the paper's gains (:data:`ee_formation_env.baselines.reference.gains.PAPER_GAINS`), the printed law (no projection),
  1 ms control steps (``frame_skip = 1``) and torque limits lifted;
- ``project defaults``: the tuned gains the built-in scenarios carry (``controller_gains``), the projected law,
  the scenario's control rate and torque limits.

Studies: ``planar`` (3.0 m square, 30 s), ``spatial`` (0.4 m tetrahedron, 50 s) and ``stall`` (4.0 m
square: printed vs projected law under both presets). Each run writes a CSV of its time series; each
study writes PNG figures; ``summary.json`` holds one row per run, with the episode's metrics (success and
settling time as :func:`ee_formation_env.baselines.metrics.settle` defines them). Results and how they
compare with the paper: see docs/reproduction.md.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

import ee_formation_env
from ee_formation_env.baselines import make_policies
from ee_formation_env.baselines.reference.controllers import Gains
from ee_formation_env.baselines.extras import require
from ee_formation_env.baselines.reference.gains import PAPER_GAINS
from ee_formation_env.baselines.metrics import EpisodeMetrics, run_episode
from ee_formation_env.generators import square_vertices
from ee_formation_env.scenario import builtin_scenario
from studies._common import add_output_arguments, copy_figures, report_outputs, save_figure

try:
    import matplotlib
except ImportError:  # the "figures" extra is missing: main() says so in one line before creating anything
    matplotlib = None
else:
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

STUDIES = ("planar", "spatial", "stall")
PAPER, DEFAULTS = "paper", "project defaults"
QUICK_SECONDS = 2.0  # horizon cap of --quick
CSV_PERIOD = 0.01  # s between CSV rows (the figures use every step)
PLOT_POINTS = 4000  # at most this many samples per plotted line
LOG_POINTS = 800  # samples per line on a log time axis
JOINTS_DPI = 75  # the joint figures have 16 panels: a lower resolution keeps them under 200 kB

# The paper's 2D preset needs 1 ms steps and unbounded torque (peaks of ~1e5 N m).
_PLANAR_PAPER = {"frame_skip": 1, "torque_limits": 1e7, "max_joint_velocity": 1000.0}


@dataclass(frozen=True)
class RunSpec:
    """One episode: scenario, env overrides, gains (None = project defaults) and law variant."""

    name: str  # file stem
    study: str
    preset: str
    scenario: str
    seconds: float
    gains: Gains | None = None
    a_hat0: tuple[float, ...] | None = None  # None: the nominal URDF parameters
    projection: bool = True
    overrides: dict[str, Any] = field(default_factory=dict)
    note: str = ""

    @property
    def law(self) -> str:
        return "projected" if self.projection else "printed"


@dataclass
class RunResult:
    """What one run produced: the episode metrics (with trajectory), a_hat (T, N, p) and the geometry."""

    spec: RunSpec
    metrics: EpisodeMetrics
    gains: Gains  # as used by the controllers
    torque_limit: float  # N m, largest joint limit
    a_hat: np.ndarray
    param_names: tuple[str, ...]
    joint_counts: list[int]
    edges: list[tuple[int, int]]
    dim: int
    control_hz: float
    physics_hz: float
    wall_time: float
    base_yaws: tuple[float, ...] = ()  # rad, each arm's base yaw (world frame)

    @property
    def trajectory(self) -> dict[str, np.ndarray]:
        assert self.metrics.trajectory is not None
        return self.metrics.trajectory

    def summary(self) -> dict[str, Any]:
        """One row of the summary table (plain JSON types)."""
        traj = self.trajectory
        return {
            "run": self.spec.name, "study": self.spec.study, "preset": self.spec.preset, "law": self.spec.law,
            "physics_hz": self.physics_hz, "control_hz": self.control_hz,
            "horizon_s": self.spec.seconds, "sim_time_s": float(traj["t"][-1]),
            "final_max_abs_edge_error": float(np.max(np.abs(traj["edge_errors"][-1]))),
            "final_rms_edge_error": self.metrics.final_formation_error,
            "final_max_abs_dq": float(np.max(np.abs(traj["dq"][-1]))),
            "peak_torque": self.metrics.peak_torque, "torque_limit": self.torque_limit,
            "gains": {key: np.asarray(value).tolist() for key, value in asdict(self.gains).items()},
            "final_a_hat": {f"arm_{i}": a.tolist() for i, a in enumerate(self.a_hat[-1])},
            "physics_fault": self.metrics.physics_fault,
            "wall_time_s": self.wall_time,
            "note": self.spec.note,
            "metrics": self.metrics.as_dict(),
        }


def run_specs(studies: Sequence[str], quick: bool = False) -> list[RunSpec]:
    """The runs of the selected studies (``quick``: horizons capped at :data:`QUICK_SECONDS`)."""
    planar_paper = dict(gains=PAPER_GAINS[2], a_hat0=(2.0, 2.0), projection=False, overrides=_PLANAR_PAPER)
    # The 4.0 m square with planar_square's own tuned gains (a shape override alone would derive new ones).
    stall_shape = {"shape": square_vertices(4.0), "controller_gains": builtin_scenario("planar_square")["controller_gains"]}
    specs = {
        "planar": [
            RunSpec("planar_paper", "planar", PAPER, "planar_square", 30.0, **planar_paper),
            RunSpec("planar_defaults", "planar", DEFAULTS, "planar_square", 30.0, a_hat0=(2.0, 2.0)),
        ],
        "spatial": [
            RunSpec("spatial_paper", "spatial", PAPER, "spatial_tetrahedron", 50.0, gains=PAPER_GAINS[3],
                    projection=False, overrides={"frame_skip": 1, "torque_limits": 1e4}),
            RunSpec("spatial_defaults", "spatial", DEFAULTS, "spatial_tetrahedron", 50.0),
        ],
        "stall": [
            RunSpec("stall_defaults_printed", "stall", DEFAULTS, "planar_square", 30.0, a_hat0=(2.0, 2.0),
                    projection=False, overrides=stall_shape),
            RunSpec("stall_defaults_projected", "stall", DEFAULTS, "planar_square", 30.0, a_hat0=(2.0, 2.0),
                    overrides=stall_shape),
            RunSpec("stall_paper_printed_1khz", "stall", PAPER, "planar_square", 30.0,
                    **{**planar_paper, "overrides": {**_PLANAR_PAPER, **stall_shape}},
                    note="expected to end early with a physics fault (joint speed runaway)"),
            RunSpec("stall_paper_printed_5khz", "stall", PAPER, "planar_square", 2.0,
                    **{**planar_paper, "overrides": {**_PLANAR_PAPER, **stall_shape, "physics_hz": 5000.0}},
                    note="5 kHz physics and control, 2 s horizon (30 s at 5 kHz is slow)"),
            RunSpec("stall_paper_projected_1khz", "stall", PAPER, "planar_square", 30.0,
                    **{**planar_paper, "projection": True, "overrides": {**_PLANAR_PAPER, **stall_shape}}),
        ],
    }
    selected = [spec for study in STUDIES if study in studies for spec in specs[study]]
    if quick:
        selected = [replace(spec, seconds=min(spec.seconds, QUICK_SECONDS)) for spec in selected]
    return selected


def run(spec: RunSpec) -> RunResult:
    """Roll one episode of ``spec`` from the paper's initial q (seed 0), logging every agent's a_hat."""
    env = ee_formation_env.parallel_env(spec.scenario, initial_q_noise=0.0, episode_seconds=spec.seconds,
                                        **spec.overrides)
    try:
        policies = make_policies("adaptive_jacobian", env, gains=spec.gains, a_hat0=spec.a_hat0,
                                 projection=spec.projection)
        agents = env.possible_agents
        estimates = [np.stack([policies[agent].a_hat0 for agent in agents])]  # t = 0

        def log_estimates(_: Any) -> None:
            estimates.append(np.stack([policies[agent].a_hat for agent in agents]))

        start = time.perf_counter()
        metrics = run_episode(env, policies, seed=0, record=True, on_step=log_estimates)
        wall = time.perf_counter() - start
        return RunResult(spec, metrics, policies[agents[0]].gains, float(np.max(env.torque_limits[0])),
                         np.asarray(estimates), env.nominal_models[0].param_names,
                         [model.n_joints for model in env.nominal_models], list(env.scenario.edges), env.dim,
                         env.scenario.control_hz, env.scenario.physics_hz, wall,
                         tuple(float(arm.base_rpy[2]) for arm in env.scenario.arms))
    finally:
        env.close()


def write_csv(result: RunResult, path: Path) -> None:
    """Time series at :data:`CSV_PERIOD` (plus the last sample): t, e_k, a_hat, q, dq, end-effector positions."""
    traj = result.trajectory
    n_agents = len(result.joint_counts)
    joints = [(i, j) for i, count in enumerate(result.joint_counts) for j in range(count)]
    columns = (["t"] + [f"e{k}_{t}_{h}" for k, (t, h) in enumerate(result.edges)]
               + [f"a_hat{i}_{p}" for i in range(n_agents) for p in result.param_names]
               + [f"q{i}_{j}" for i, j in joints] + [f"dq{i}_{j}" for i, j in joints]
               + [f"ee{i}_{c}" for i in range(n_agents) for c in "xyz"])
    data = np.column_stack([traj["t"], traj["edge_errors"].reshape(len(traj["t"]), -1),
                            result.a_hat.reshape(len(traj["t"]), -1), traj["q"], traj["dq"],
                            traj["ee"].reshape(len(traj["t"]), -1)])
    stride = max(1, int(round(CSV_PERIOD * result.control_hz)))
    rows = np.unique(np.append(np.arange(0, len(data), stride), len(data) - 1))
    np.savetxt(path, data[rows], delimiter=",", header=",".join(columns), comments="", fmt="%.10g")


# ------------------------------------------------------------------------------------------------ figures
def _every(n: int) -> slice:
    return slice(None, None, max(1, math.ceil(n / PLOT_POINTS)))


def _title(result: RunResult) -> str:
    spec, gains = result.spec, result.gains
    text = (f"{spec.preset}: {spec.law} law, {result.control_hz:g} Hz control"
            + (f" / {result.physics_hz:g} Hz physics" if result.physics_hz != result.control_hz else ""))
    text += (f"\nK_P={gains.kp:g}, K_D={gains.kd:g}, K_I={gains.ki:g}, alpha={gains.alpha:g}, "
             f"torque limit {result.torque_limit:g} N m")
    if result.metrics.physics_fault:
        text += f"\nFAULT at t={result.trajectory['t'][-1]:.3f} s"
    return text


def _plot_trajectories(ax: Any, result: RunResult) -> None:
    ee = result.trajectory["ee"][:, :, :result.dim]
    every = _every(len(ee))
    for i in range(ee.shape[1]):
        path = ee[every, i].T
        line, = ax.plot(*path, lw=1, label=f"arm_{i}")
        ax.plot(*ee[0, i][:, None], "x", color=line.get_color(), ms=8)
        ax.plot(*ee[-1, i][:, None], "o", color=line.get_color(), mfc="none", ms=8)
    for tail, head in result.edges:
        ax.plot(*np.stack([ee[-1, tail], ee[-1, head]]).T, "k-", lw=1.5)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    if result.dim == 3:
        ax.set_zlabel("z (m)")
    else:
        ax.set_aspect("equal", adjustable="datalim")


# The paper's figure numbers (order of the figures in its LaTeX source).
PAPER_FIGURES = {"planar": {"trajectories": 4, "edge_errors": 5, "estimates": 6, "joints": 7},
                 "spatial": {"trajectories": 9, "edge_errors": 10, "estimates": 11, "joints": 12}}


def _log_time(t: np.ndarray, every: slice) -> np.ndarray:
    """Indices of samples with t > 0, log-spaced in time (for a log time axis, where the 0.1-2 s
    transients stay visible; :data:`LOG_POINTS` per line keeps the PNGs small)."""
    positive = np.arange(len(t))[every]
    positive = positive[t[positive] > 0]
    if len(positive) <= LOG_POINTS:
        return positive
    wanted = np.geomspace(t[positive[0]], t[positive[-1]], LOG_POINTS)
    return np.unique(positive[np.clip(np.searchsorted(t[positive], wanted), 0, len(positive) - 1)])


def study_figures(results: Sequence[RunResult], out: Path) -> list[Path]:
    """The paper-style figures of a two-preset study, presets side by side (one column each).

    Time axes are logarithmic: the transients take 0.1-2 s of 30-50 s runs. Joint plots are small
    multiples, one row per arm, one labelled line per joint.
    """
    study = results[0].spec.study
    label = {"planar": "2D planar square", "spatial": "3D tetrahedron"}[study]
    numbers = PAPER_FIGURES[study]
    paths = []
    cols = len(results)

    fig = plt.figure(figsize=(5 * cols, 4.9))
    for c, result in enumerate(results):
        ax = fig.add_subplot(1, cols, c + 1, projection="3d" if result.dim == 3 else None)
        _plot_trajectories(ax, result)
        title = _title(result)
        if result.dim == 3:
            title += "\nbase yaws (deg): " + ", ".join(f"{math.degrees(y):.0f}" for y in result.base_yaws)
        ax.set_title(title, fontsize=9)
        ax.legend(fontsize=7)
    fig.suptitle(f"{label}: end-effector trajectories (x start, o end; final formation edges in black) "
                 f"- paper Fig. {numbers['trajectories']}")
    paths.append(save_figure(fig, out / f"{study}_trajectories.png"))

    fig, axes = plt.subplots(2, cols, figsize=(5.5 * cols, 6.5), sharex="col", squeeze=False)
    for c, result in enumerate(results):
        t, errors = result.trajectory["t"], result.trajectory["edge_errors"]
        rows = _log_time(t, _every(len(t)))
        for k, (tail, head) in enumerate(result.edges):
            axes[0, c].plot(t[rows], errors[rows, k], lw=1, label=f"e{k} ({tail}-{head})")
            axes[1, c].loglog(t[rows], np.abs(errors[rows, k]) + 1e-16, lw=1)
        axes[0, c].set_xscale("log")
        axes[0, c].set_title(_title(result), fontsize=9)
        axes[0, c].set_ylabel("e_k = |z_k|^2 - d_k^2 (m^2)")
        axes[1, c].set_ylabel("|e_k| (m^2, log)")
        axes[1, c].set_xlabel("t (s, log)")
        axes[0, c].legend(fontsize=7, ncol=2)
    fig.suptitle(f"{label}: inner distance errors - paper Fig. {numbers['edge_errors']}")
    paths.append(save_figure(fig, out / f"{study}_edge_errors.png"))

    n_agents = results[0].a_hat.shape[1]
    fig, axes = plt.subplots(n_agents, cols, figsize=(5.5 * cols, 2.0 * n_agents + 1), sharex="col", squeeze=False)
    for c, result in enumerate(results):
        t = result.trajectory["t"]
        rows = _log_time(t, _every(len(t)))
        for i in range(n_agents):
            for p, name in enumerate(result.param_names):
                axes[i, c].plot(t[rows], result.a_hat[rows, i, p], lw=1, label=name)
            axes[i, c].set_xscale("log")
            axes[i, c].set_ylabel(f"arm_{i} a_hat (m)")
        axes[0, c].set_title(_title(result), fontsize=9)
        axes[0, c].legend(fontsize=7, ncol=2)
        axes[-1, c].set_xlabel("t (s, log)")
    fig.suptitle(f"{label}: kinematic parameter estimates - paper Fig. {numbers['estimates']}")
    paths.append(save_figure(fig, out / f"{study}_estimates.png"))

    fig, axes = plt.subplots(n_agents, 2 * cols, figsize=(3.7 * 2 * cols, 1.9 * n_agents + 1.2), sharex="col",
                             squeeze=False)
    for c, result in enumerate(results):
        t = result.trajectory["t"]
        rows = _log_time(t, _every(len(t)))
        start = np.cumsum([0] + result.joint_counts)
        for i in range(n_agents):
            joints = range(start[i], start[i + 1])
            for column, key, unit in ((2 * c, "q", "rad"), (2 * c + 1, "dq", "rad/s")):
                ax = axes[i, column]
                for j, index in enumerate(joints):
                    ax.plot(t[rows], result.trajectory[key][rows, index], lw=0.9, label=f"joint {j + 1}")
                ax.set_xscale("log")
                ax.set_ylabel(f"arm_{i} {key} ({unit})", fontsize=8)
                if i == 0:
                    ax.set_title(f"{result.spec.preset}: {key}", fontsize=9)
                    ax.legend(fontsize=6, ncol=2 if len(joints) > 4 else 1)
        axes[-1, 2 * c].set_xlabel("t (s, log)")
        axes[-1, 2 * c + 1].set_xlabel("t (s, log)")
    fig.suptitle(f"{label}: joint positions and velocities, one row per arm - paper Fig. {numbers['joints']}")
    paths.append(save_figure(fig, out / f"{study}_joints.png", dpi=JOINTS_DPI))
    return paths


def stall_figure(results: Sequence[RunResult], out: Path) -> list[Path]:
    """a_hat(t) and max |e_k|(t), printed vs projected, one column per preset (log time axis)."""
    presets = [preset for preset in (DEFAULTS, PAPER) if any(r.spec.preset == preset for r in results)]
    fig, axes = plt.subplots(2, len(presets), figsize=(6.5 * len(presets), 7.5), squeeze=False)
    for c, preset in enumerate(presets):
        for n, result in enumerate(r for r in results if r.spec.preset == preset):
            t = result.trajectory["t"]
            every = _every(len(t))
            color = f"C{n}"
            label = (f"{result.spec.law}, {result.control_hz:g} Hz control / {result.physics_hz:g} Hz physics, "
                     f"{t[-1]:g} s") + (
                " (FAULT)" if result.metrics.physics_fault else "")
            estimates = result.a_hat.reshape(len(t), -1)
            for p in range(estimates.shape[1]):
                axes[0, c].plot(t[every][1:], estimates[every, p][1:], color=color, lw=0.8,
                                label=label if p == 0 else None)
            error = np.max(np.abs(result.trajectory["edge_errors"]), axis=1)
            axes[1, c].loglog(t[every][1:], error[every][1:] + 1e-16, color=color, lw=1.2, label=label)
        first = next(r for r in results if r.spec.preset == preset)
        axes[0, c].set_title(f"{preset}: K_P={first.gains.kp:g}, K_D={first.gains.kd:g}, "
                             f"alpha={first.gains.alpha:g}, torque limit {first.torque_limit:g} N m", fontsize=9)
        axes[0, c].set_xscale("log")
        axes[0, c].set_ylabel("a_hat, all arms and components (m)")
        axes[1, c].set_ylabel("max_k |e_k| (m^2)")
        axes[1, c].set_xlabel("t (s, log)")
        axes[0, c].legend(fontsize=7)
        axes[1, c].legend(fontsize=7)
    fig.suptitle("Stall study, 4.0 m square, a_hat(0) = [2, 2]: printed vs projected adaptive law")
    return [save_figure(fig, out / "stall_study.png")]


# ---------------------------------------------------------------------------------------------- reporting
def format_summary(rows: Sequence[dict[str, Any]]) -> str:
    """A markdown table of the per-run summary rows."""
    header = ("| run | preset | law | physics / control Hz | sim s | final max abs(e_k) m^2 | final RMS e m^2 | final max abs(dq) rad/s"
              " | peak torque N m | final a_hat (arm_0) | a_hat range (all arms) | physics fault | wall s |")
    lines = [header, "|" + "---|" * header.count(" | ") + "---|"]
    for row in rows:
        a_hat = np.array(list(row["final_a_hat"].values()))
        fault = row["physics_fault"] or "-"
        lines.append(
            f"| {row['run']} | {row['preset']} | {row['law']} | {row['physics_hz']:g} / {row['control_hz']:g} "
            f"| {row['sim_time_s']:.3f} | {row['final_max_abs_edge_error']:.3g} | {row['final_rms_edge_error']:.3g} | {row['final_max_abs_dq']:.3g} "
            f"| {row['peak_torque']:.3g} | [{', '.join(f'{v:.3g}' for v in a_hat[0])}] "
            f"| {a_hat.min():.3g} .. {a_hat.max():.3g} | {fault} | {row['wall_time_s']:.1f} |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> list[dict[str, Any]]:
    """Command-line entry: run the selected studies, write CSVs, PNGs and summary.json; return the rows."""
    parser = argparse.ArgumentParser(prog="python -m studies.reproduce", description=__doc__.split("\n\n")[0])
    add_output_arguments(parser, STUDIES, "results/reproduction")
    parser.add_argument("--quick", action="store_true", help=f"cap every horizon at {QUICK_SECONDS:g} s (tests)")
    args = parser.parse_args(argv)
    studies = args.only or list(STUDIES)
    require(["matplotlib"], "figures", "python -m studies.reproduce")
    args.out.mkdir(parents=True, exist_ok=True)

    results: list[RunResult] = []
    for spec in run_specs(studies, args.quick):
        print(f"running {spec.name} ({spec.seconds:g} s) ...", flush=True)
        result = run(spec)
        write_csv(result, args.out / f"{spec.name}.csv")
        print(f"  done in {result.wall_time:.1f} s; fault: {result.metrics.physics_fault or 'none'}", flush=True)
        results.append(result)

    figures: list[Path] = []
    for study in ("planar", "spatial"):
        selected = [r for r in results if r.spec.study == study]
        if selected:
            figures += study_figures(selected, args.out)
    stall = [r for r in results if r.spec.study == "stall"]
    if stall:
        figures += stall_figure(stall, args.out)
    copies = copy_figures(figures, args.figures_dir)

    rows = [result.summary() for result in results]
    (args.out / "summary.json").write_text(json.dumps(rows, indent=2) + "\n", encoding="utf-8")
    print(format_summary(rows))
    report_outputs(args.out, copies)
    return rows


if __name__ == "__main__":
    main()
