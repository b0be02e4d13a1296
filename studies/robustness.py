"""Robustness of the three laws to model mismatch (planar, and 3D under gravity), law-III's stall map, anti-windup.

    python -m studies.robustness [--out results/robustness] [--figures-dir docs/figures] [--quick]
                                   [--only mismatch|separating|stall|windup|spatial ...]

Studies (the first three on the built-in planar square: four ``planar_2link`` arms, 3.0 m square, the
project's tuned gains K_P 5, K_D 20, alpha 0.02, 50 N m limits, 100 Hz control):

- ``mismatch``: the simulated ("true") arms differ from the nominal URDF the controllers know, by one of
  four kinds of size s, per arm, seeded: ``uniform`` (both link lengths scaled by 1 + s or 1 - s, one sign
  per arm), ``lengths`` (each length by its own factor 1 + s u, u uniform in [-1, 1]), ``offsets`` (each
  joint origin moved by s times its link's length, 1.5 m, in a random in-plane direction: along the link, a
  modelled parameter, and across it, an unmodelled one), ``zero_component`` (the tool frame moved sideways
  by s times the tool link's length: a component that is zero in the nominal model, so no estimate a_hat
  can represent it). The link lengths are read from the nominal kinematic model
  (:func:`ee_formation_env.generators.planar_link_lengths`). Law-I uses the
  nominal parameters, law-II keeps them fixed, law-III adapts them (projected onto the default box).
  For each run the paper's Proposition 4.1 quantities are computed along the trajectory:
  ``delta = max_t |J(q, a_hat) - J_true(q)|`` and ``delta* = lambda_4 / (4 lambda_Jhat lambda_3)``, with
  ``lambda_3 = lambda_max(R R^T)`` at the desired shape (R the rigidity matrix ``D_z^T B^T``),
  ``lambda_Jhat = max_t |J(q, a_hat)|`` and ``lambda_4 = min_t lambda_min(R J(q, a_hat) J^T(q, a_hat) R^T)``
  (block-diagonal J over the arms). Prop. 4.1 guarantees law-II only for ``delta < delta*``.
- ``separating``: no mismatch in the arms, but a poor initial estimate a_hat(0) = [2.7, 0.3] (true
  [1.5, 1.5]): law-II keeps it, law-III adapts it (projected onto ``parameter_bounds`` [0.25, 3] and, the
  printed law, unprojected). 3 reset seeds (initial q noise 0.05 rad).
- ``stall``: the printed law-III (no projection) from a_hat(0) = [2, 2], over square side, alpha and K_P:
  final max |e_k| after 10 s.
- ``windup``: law-II on the built-in spatial tetrahedron (gravity, K_I = 1) with torque limits halved,
  with and without the anti-windup option of the internal model.
- ``spatial``: the built-in spatial tetrahedron (four PERA-like 7-DOF arms hanging from their bases,
  gravity, its tuned gains K_P 120, K_D 2, K_I 1, alpha 0.01, 200 Hz control) with the env's
  ``model_mismatch`` (:mod:`ee_formation_env.mismatch`): every joint-origin translation of each simulated
  arm scaled by its own factor in ``[1 - s, 1 + s]`` (``length``), every link mass and inertia by one in
  ``[1 - s, 1 + s]`` (``mass``), or both (``both``), s = 0.2, 0.5, 0.9, three mismatch seeds each, plus
  the unperturbed arms; the controllers keep the nominal model (law-I its nominal gravity torque too).
  Recorded per run: final max |edge length - target| (m), success, settling time and physics faults.

Every episode is rolled by :func:`ee_formation_env.baselines.metrics.run_episode`; success and settling
time are its (:func:`ee_formation_env.baselines.metrics.settle`: the formation error below
:func:`ee_formation_env.baselines.metrics.formation_tolerance`, edges within 1 cm in the RMS sense, from
the settling time to the end, held at least 1 s, no physics fault). Outputs: ``robustness.json`` (every
run) and PNG figures in ``--out`` (also copied to ``--figures-dir``). Results: see docs/results.md.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
import xml.etree.ElementTree as ElementTree
from dataclasses import replace
from pathlib import Path
from typing import Any, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import ee_formation_env  # noqa: E402
from ee_formation_env.baselines import agent_model, make_controller, make_policies  # noqa: E402
from ee_formation_env.baselines.reference.controllers import Gains  # noqa: E402
from ee_formation_env.baselines.reference.dynamics import nominal_dynamics  # noqa: E402
from ee_formation_env.baselines.metrics import run_episode  # noqa: E402
from ee_formation_env.formation import rigidity_matrix  # noqa: E402
from ee_formation_env.kinematics import chain_model  # noqa: E402
from ee_formation_env.generators import planar_link_lengths, square_vertices  # noqa: E402
from ee_formation_env.mismatch import write_urdf_copy  # noqa: E402
from ee_formation_env.reward import DEFAULT_POSITION_TOLERANCE  # noqa: E402
from ee_formation_env.scenario import ROBOTS, builtin_scenario, load_scenario  # noqa: E402
from studies._common import (LAWS, add_output_arguments, copy_figures, max_edge_length_error,  # noqa: E402
                             report_outputs, save_figure)

STUDIES = ("mismatch", "separating", "stall", "windup", "spatial")
KINDS = ("uniform", "lengths", "offsets", "zero_component")
SIZES = (0.1, 0.3, 0.5)
SEEDS = (0, 1, 2)
SPATIAL_KINDS = ("length", "mass", "both")
SPATIAL_SIZES = (0.2, 0.5, 0.9)
PLANAR_GAINS = Gains(**builtin_scenario("planar_square")["controller_gains"])  # its tuned gains (K_P 5, K_D 20)


# ------------------------------------------------------------------------------------------ true robots
def perturbed_planar_urdf(kind: str, size: float, rng: np.random.Generator, directory: str) -> str:
    """A copy of ``planar_2link.urdf`` with the mismatch ``kind`` of ``size`` (module docstring); its path."""
    source = Path(ROBOTS["planar_2link"].urdf)
    tree = ElementTree.parse(source)
    joints = {joint.get("name"): joint.find("origin") for joint in tree.getroot().iter("joint")}
    origins = {name: np.array([float(v) for v in joints[name].get("xyz").split()]) for name in ("joint_2", "ee_joint")}
    links = dict(zip(("joint_2", "ee_joint"), planar_link_lengths()))  # m, the link each joint origin ends
    if kind == "uniform":
        factor = 1.0 + size * rng.choice([-1.0, 1.0])
        origins = {name: xyz * factor for name, xyz in origins.items()}
    elif kind == "lengths":
        origins = {name: xyz * (1.0 + size * rng.uniform(-1.0, 1.0)) for name, xyz in origins.items()}
    elif kind == "offsets":
        for name in origins:
            angle = rng.uniform(-math.pi, math.pi)
            origins[name] = origins[name] + size * links[name] * np.array([math.cos(angle), math.sin(angle), 0.0])
    elif kind == "zero_component":
        origins["ee_joint"] = origins["ee_joint"] + np.array([0.0, size * links["ee_joint"] * rng.choice([-1.0, 1.0]),
                                                              0.0])
    else:
        raise ValueError(f"kind: expected one of {KINDS}, got {kind!r}")
    for name, xyz in origins.items():
        joints[name].set("xyz", " ".join(repr(float(v)) for v in xyz))
    return write_urdf_copy(tree, source, directory)


# ------------------------------------------------------------------------------------- Prop. 4.1 numbers
def proposition_bounds(env: Any, q_series: np.ndarray, a_hat_series: np.ndarray, true_chains: Sequence[Any],
                       nominal_chain: Any) -> dict[str, float]:
    """delta, delta*, lambda_3, lambda_4, lambda_Jhat of Prop. 4.1 along a trajectory (module docstring).

    ``q_series`` (T, N n) joint positions; ``a_hat_series`` (T, N, p) estimates (constant for law-I/II).
    """
    dim, n = env.dim, nominal_chain.n_joints
    shape = np.asarray(env.scenario.shape)[:, :dim]
    rigidity = rigidity_matrix(env.graph, shape)  # (|E|, N dim), rows 2 z_k^T ... up to the factor convention
    lambda_3 = float(np.max(np.linalg.eigvalsh(rigidity @ rigidity.T)))
    delta, lambda_jhat, lambda_4 = 0.0, 0.0, math.inf
    stride = max(1, len(q_series) // 200)
    for q_all, a_hats in zip(q_series[::stride], a_hat_series[::stride]):
        blocks = []
        for i, chain in enumerate(true_chains):
            q = q_all[i * n:(i + 1) * n]
            estimate = nominal_chain.jacobian(q, a_hats[i])[:dim]
            truth = chain.jacobian(q)[:dim]
            delta = max(delta, float(np.linalg.norm(estimate - truth, 2)))
            lambda_jhat = max(lambda_jhat, float(np.linalg.norm(estimate, 2)))
            # Rotate into the world frame: R is built from world-frame edge vectors.
            rotation = env.task.base_rotations[i][:dim, :dim]
            blocks.append(rotation @ estimate)
        jacobian = np.zeros((len(blocks) * dim, len(blocks) * n))
        for i, block in enumerate(blocks):
            jacobian[i * dim:(i + 1) * dim, i * n:(i + 1) * n] = block
        product = rigidity @ jacobian
        lambda_4 = min(lambda_4, float(np.min(np.linalg.eigvalsh(product @ product.T))))
    delta_star = max(lambda_4, 0.0) / (4.0 * lambda_jhat * lambda_3)  # lambda_4 ~ -1e-19 when a_hat collapsed
    return {"delta": delta, "delta_star": delta_star, "lambda_3": lambda_3, "lambda_4": lambda_4,
            "lambda_jhat": lambda_jhat}


# ----------------------------------------------------------------------------------------------- running
def run_planar(scenario: dict[str, Any] | str, law: str, seconds: float, gains: Gains, seed: int = 0,
               a_hat0: Sequence[float] | None = None, nominal_urdf: str | None = None,
               **options: Any) -> dict[str, Any]:
    """One episode: controllers built on the *nominal* planar_2link model whatever the simulated arms are."""
    env = ee_formation_env.parallel_env(scenario, episode_seconds=seconds)
    try:
        nominal_urdf = nominal_urdf or str(ROBOTS["planar_2link"].urdf)
        nominal_chain = chain_model(nominal_urdf, "ee_link")
        policies = {}
        for agent in env.possible_agents:
            model = replace(agent_model(env, agent), chain=nominal_chain,
                            dynamics=nominal_dynamics(nominal_urdf, nominal_chain.joint_names))
            estimate = None if a_hat0 is None else np.asarray(a_hat0, dtype=np.float64)
            policies[agent] = make_controller(LAWS[law], model, gains, estimate, **options)
        estimates = [np.stack([getattr(p, "a_hat", p.a_hat0) for p in policies.values()])]

        def log(_: Any) -> None:
            estimates.append(np.stack([getattr(p, "a_hat", p.a_hat0) for p in policies.values()]))

        start = time.perf_counter()
        metrics = run_episode(env, policies, seed=seed, record=True, on_step=log)
        trajectory = metrics.trajectory
        estimates_array = np.asarray(estimates)
        bounds = proposition_bounds(env, trajectory["q"], estimates_array, env.nominal_models, nominal_chain)
        errors = np.max(np.abs(trajectory["edge_errors"]), axis=1)
        return {
            "law": law, "seed": seed, "final_max_abs_e": float(errors[-1]), "t": trajectory["t"].tolist(),
            "max_abs_e": errors.tolist(), "fault": metrics.physics_fault, "settling_time": metrics.settling_time,
            "final_a_hat": estimates_array[-1].tolist(),
            "boundary_fraction": float(np.mean([getattr(p, "boundary_fraction", 0.0) for p in policies.values()])),
            "wall_s": time.perf_counter() - start, **bounds,
        }
    finally:
        env.close()


def mismatch_study(seconds: float) -> list[dict[str, Any]]:
    """Every kind x size x seed x law (module docstring)."""
    rows = []
    with tempfile.TemporaryDirectory() as directory:
        for kind in KINDS:
            for size in SIZES:
                for seed in SEEDS:
                    rng = np.random.default_rng([KINDS.index(kind), int(round(size * 100)), seed])
                    scenario = load_scenario("planar_square").to_dict()
                    scenario.pop("controller_gains", None)
                    for arm in scenario["arms"]:
                        arm.pop("robot", None)
                        arm["urdf"] = perturbed_planar_urdf(kind, size, rng, directory)
                        arm["ee_link"] = "ee_link"
                    scenario["initial_q_noise"] = 0.0
                    for law in LAWS:
                        row = run_planar(scenario, law, seconds, PLANAR_GAINS)
                        row.update(kind=kind, size=size, mismatch_seed=seed)
                        rows.append(row)
                        print(f"mismatch {kind} s={size} seed={seed} {law}: final max|e| "
                              f"{row['final_max_abs_e']:.3g} m^2, delta {row['delta']:.3g}, "
                              f"delta* {row['delta_star']:.3g}", flush=True)
    return rows


def separating_study(seconds: float) -> list[dict[str, Any]]:
    """a_hat(0) = [2.7, 0.3] against the true [1.5, 1.5]: law-II, projected and printed law-III, 3 seeds."""
    rows = []
    variants = [("law-II", {}), ("law-III", {"parameter_bounds": (0.25, 3.0)}), ("law-III", {"projection": False})]
    for seed in SEEDS:
        for law, options in variants:
            row = run_planar({"name": "planar_square", **_planar_square_data()}, law, seconds, PLANAR_GAINS,
                             seed=seed, a_hat0=(2.7, 0.3), **options)
            row["variant"] = law + (" printed" if options.get("projection") is False else
                                    " projected" if law == "law-III" else "")
            rows.append(row)
            print(f"separating seed={seed} {row['variant']}: final max|e| {row['final_max_abs_e']:.3g} m^2, "
                  f"boundary fraction {row['boundary_fraction']:.2f}, delta {row['delta']:.3g}, "
                  f"delta* {row['delta_star']:.3g}", flush=True)
    return rows


def _planar_square_data() -> dict[str, Any]:
    """The built-in planar square's data with reset noise (the separating study's seeds draw it)."""
    data = load_scenario("planar_square").to_dict()
    data.pop("name", None)
    return data


def stall_study(seconds: float, sides: Sequence[float], alphas: Sequence[float],
                gains_kp: Sequence[float]) -> list[dict[str, Any]]:
    """Printed law-III from a_hat(0) = [2, 2]: final max |e_k| over side x alpha x K_P."""
    rows = []
    for kp in gains_kp:
        for side in sides:
            for alpha in alphas:
                scenario = {**_planar_square_data(), "shape": square_vertices(side), "initial_q_noise": 0.0}
                scenario.pop("controller_gains", None)
                row = run_planar(scenario, "law-III", seconds, replace(PLANAR_GAINS, kp=kp, alpha=alpha),
                                 a_hat0=(2.0, 2.0), projection=False)
                row.update(side=side, alpha=alpha, kp=kp)
                for key in ("t", "max_abs_e"):
                    row.pop(key)
                rows.append(row)
                print(f"stall K_P={kp:g} side={side:g} alpha={alpha:g}: final max|e| {row['final_max_abs_e']:.3g} m^2, "
                      f"min a_hat {np.min(row['final_a_hat']):.3g}", flush=True)
    return rows


def windup_study(seconds: float) -> list[dict[str, Any]]:
    """Law-II on the spatial tetrahedron with halved torque limits, internal model with and without anti-windup."""
    rows = []
    with ee_formation_env.parallel_env("spatial_tetrahedron") as env:
        limits = [(np.asarray(limit) * 0.5).tolist() for limit in env.task.torque_limits]
    gains = Gains(**builtin_scenario("spatial_tetrahedron")["controller_gains"])
    for anti_windup in (False, True):
        env = ee_formation_env.parallel_env("spatial_tetrahedron", torque_limits=limits, episode_seconds=seconds,
                                            initial_q_noise=0.0)
        try:
            policies = {agent: make_controller("approx_jacobian", agent_model(env, agent), gains, anti_windup=anti_windup)
                        for agent in env.possible_agents}
            integral = []

            def log(_: Any) -> None:
                integral.append(max(float(np.max(np.abs(np.asarray(p.gains.ki, dtype=np.float64) * p.eta)
                                                 / p.agent.torque_limits))
                                    for p in policies.values()))

            metrics = run_episode(env, policies, seed=0, record=True, on_step=log)
            errors = np.max(np.abs(metrics.trajectory["edge_errors"]), axis=1)
            rows.append({"anti_windup": anti_windup, "t": metrics.trajectory["t"][1:].tolist(),
                         "max_abs_e": errors[1:].tolist(), "integral_over_limit": integral,
                         "final_max_abs_e": float(errors[-1]), "settling_time": metrics.settling_time,
                         "saturation_fraction": metrics.saturation_fraction, "fault": metrics.physics_fault})
            print(f"windup anti_windup={anti_windup}: final max|e| {errors[-1]:.3g} m^2, "
                  f"settle {metrics.settling_time:.2f} s, peak |K_I eta|/limit {max(integral):.2f}, saturated {metrics.saturation_fraction:.1%}", flush=True)
        finally:
            env.close()
    return rows


def spatial_run(law: str, seconds: float, mismatch: dict[str, Any] | None) -> dict[str, Any]:
    """One spatial-tetrahedron episode of ``law`` with ``model_mismatch`` ``mismatch`` (None: exact arms)."""
    overrides: dict[str, Any] = {"episode_seconds": seconds, "initial_q_noise": 0.0}
    if mismatch:
        overrides["model_mismatch"] = mismatch
    env = ee_formation_env.parallel_env("spatial_tetrahedron", **overrides)
    try:
        policies = make_policies(LAWS[law], env)  # the scenario's tuned gains; nominal models
        lengths: list[float] = []  # largest edge-length error (m): after the reset, then after each step

        def log(env: Any) -> None:
            lengths.append(max_edge_length_error(env))

        start = time.perf_counter()
        metrics = run_episode(env, policies, seed=0, on_reset=log, on_step=log)
        series = np.asarray(lengths)
        dt = env.scenario.control_dt
        return {"law": law, "final_max_length_error": float(series[-1]), "success": metrics.success,
                "settling_time": metrics.settling_time, "fault": metrics.physics_fault,
                "t": (np.arange(len(series)) * dt).tolist(), "max_length_error": series.tolist(),
                "wall_s": time.perf_counter() - start}
    finally:
        env.close()


def spatial_study(seconds: float, sizes: Sequence[float] = SPATIAL_SIZES,
                  seeds: Sequence[int] = SEEDS) -> list[dict[str, Any]]:
    """Every law on the spatial tetrahedron: exact arms, then kind x size x seed of model mismatch."""
    cases: list[tuple[str, float, int, dict[str, Any] | None]] = [("none", 0.0, 0, None)]
    for kind in SPATIAL_KINDS:
        for size in sizes:
            for seed in seeds:
                mismatch = {"length": size if kind in ("length", "both") else 0.0,
                            "mass": size if kind in ("mass", "both") else 0.0, "seed": seed}
                cases.append((kind, size, seed, mismatch))
    rows = []
    for kind, size, seed, mismatch in cases:
        for law in LAWS:
            row = spatial_run(law, seconds, mismatch)
            row.update(kind=kind, size=size, mismatch_seed=seed)
            rows.append(row)
            print(f"spatial {kind} s={size} seed={seed} {law}: final max|dl| {row['final_max_length_error']:.3g} m, "
                  f"settle {row['settling_time']:.2f} s {row['fault']} ({row['wall_s']:.1f} s)", flush=True)
    return rows


def spatial_table(rows: Sequence[dict[str, Any]]) -> str:
    """Markdown: per kind and size, per law: median (max) final max |dl| over seeds, successes, settling, faults."""
    lines = ["| mismatch | s | law-I: final max abs(dl) m, median (max) | law-II | law-III "
             "| in formation (I / II / III) | median settle s (I / II / III) | faults (I / II / III) |",
             "|---|---|---|---|---|---|---|---|"]
    keys = list(dict.fromkeys((r["kind"], r["size"]) for r in rows))
    for kind, size in keys:
        cells, wins, settles, faults = [], [], [], []
        for law in LAWS:
            selected = [r for r in rows if r["kind"] == kind and r["size"] == size and r["law"] == law]
            errors = np.array([r["final_max_length_error"] for r in selected])
            cells.append(f"{np.median(errors):.2g} ({errors.max():.2g})")
            wins.append(f"{sum(r['success'] for r in selected)}/{len(selected)}")
            settled = [r["settling_time"] for r in selected if r["success"]]
            settles.append(f"{np.median(settled):.1f}" if settled else "-")
            faults.append(str(sum(bool(r["fault"]) for r in selected)))
        lines.append(f"| {kind} | {size:g} | " + " | ".join(cells) + f" | {' / '.join(wins)} | "
                     f"{' / '.join(settles)} | {' / '.join(faults)} |")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------ figures
def mismatch_figure(rows: Sequence[dict[str, Any]], out: Path) -> Path:
    """Top: final max |e_k| vs size per kind (median and range over seeds) per law; bottom: delta vs delta*."""
    fig, axes = plt.subplots(2, len(KINDS), figsize=(4.2 * len(KINDS), 7.5), sharex=True, squeeze=False)
    for c, kind in enumerate(KINDS):
        for n, law in enumerate(LAWS):
            values = np.array([[r["final_max_abs_e"] for r in rows if r["kind"] == kind and r["size"] == size
                                and r["law"] == law] for size in SIZES]) + 1e-16
            offset = (n - 1) * 0.008
            axes[0, c].errorbar(np.array(SIZES) + offset, np.median(values, axis=1),
                                yerr=[np.median(values, axis=1) - values.min(axis=1),
                                      values.max(axis=1) - np.median(values, axis=1)],
                                marker="os^"[n], capsize=3, label=law)
        axes[0, c].set_yscale("log")
        axes[0, c].set_title(kind.replace("_", " "))
        axes[0, c].axhline(2 * 3.0 * DEFAULT_POSITION_TOLERANCE, color="grey", ls=":", lw=1)  # e ~ 2 d delta
        law2 = [r for r in rows if r["kind"] == kind and r["law"] == "law-II"]
        axes[1, c].plot([r["size"] for r in law2], [r["delta"] for r in law2], "o", label="delta (law-II)")
        axes[1, c].plot([r["size"] for r in law2], [r["delta_star"] for r in law2], "x", label="delta* (Prop. 4.1)")
        axes[1, c].set_yscale("log")
        axes[1, c].set_xlabel("mismatch size s")
    axes[0, 0].set_ylabel("final max |e_k| at the horizon (m^2, log)")
    axes[1, 0].set_ylabel("m (log)")
    axes[0, 0].legend(fontsize=8)
    axes[1, 0].legend(fontsize=8)
    fig.suptitle("Model mismatch (planar square, 3 seeds per point; dotted: 1 cm edge-length error)")
    return save_figure(fig, out / "robustness_mismatch.png")


def separating_figure(rows: Sequence[dict[str, Any]], out: Path) -> Path:
    """max |e_k|(t) for the three variants, each seed a line (log axes)."""
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for n, variant in enumerate(dict.fromkeys(r["variant"] for r in rows)):
        for k, row in enumerate(r for r in rows if r["variant"] == variant):
            ax.loglog(np.array(row["t"][1:]), np.array(row["max_abs_e"][1:]) + 1e-16, color=f"C{n}", lw=1,
                      label=variant if k == 0 else None)
    ax.set_xlabel("t (s, log)")
    ax.set_ylabel("max |e_k| (m^2, log)")
    ax.set_title("a_hat(0) = [2.7, 0.3], true [1.5, 1.5]: law-II vs law-III (3 seeds each)")
    ax.legend()
    return save_figure(fig, out / "robustness_separating.png")


def stall_figure(rows: Sequence[dict[str, Any]], out: Path) -> Path:
    """Heat maps of the printed law-III's final max |e_k| over side x alpha, one panel per K_P."""
    kps = sorted({r["kp"] for r in rows})
    sides = sorted({r["side"] for r in rows})
    alphas = sorted({r["alpha"] for r in rows})
    fig, axes = plt.subplots(1, len(kps), figsize=(max(7.0, 5.2 * len(kps)), 4.4), squeeze=False)
    for c, kp in enumerate(kps):
        grid = np.array([[next(r["final_max_abs_e"] for r in rows if r["kp"] == kp and r["side"] == side
                               and r["alpha"] == alpha) for side in sides] for alpha in alphas])
        image = axes[0, c].imshow(np.log10(grid + 1e-16), origin="lower", cmap="viridis", vmin=-15, vmax=2,
                                  aspect="auto")
        for a in range(len(alphas)):
            for s in range(len(sides)):
                axes[0, c].text(s, a, f"{grid[a, s]:.1g}", ha="center", va="center", fontsize=7,
                                color="white" if grid[a, s] < 1e-3 else "black")
        axes[0, c].set_xticks(range(len(sides)), [f"{s:g}" for s in sides])
        axes[0, c].set_yticks(range(len(alphas)), [f"{a:g}" for a in alphas])
        axes[0, c].set_xlabel("square side (m)")
        axes[0, c].set_ylabel("alpha")
        axes[0, c].set_title(f"K_P = {kp:g}")
        fig.colorbar(image, ax=axes[0, c], label="log10 final max |e_k| (m^2)")
    fig.suptitle("Printed law-III (no projection), a_hat(0) = [2, 2], 10 s: final max |e_k| (m^2)", fontsize=11)
    return save_figure(fig, out / "robustness_stall_map.png")


def windup_figure(rows: Sequence[dict[str, Any]], out: Path) -> Path:
    """max |e_k|(t) and max |K_I eta| / limit, with and without anti-windup."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for n, row in enumerate(rows):
        label = "anti-windup" if row["anti_windup"] else "printed internal model"
        axes[0].semilogy(row["t"], np.array(row["max_abs_e"]) + 1e-16, color=f"C{n}", label=label)
        axes[1].plot(row["t"], row["integral_over_limit"], color=f"C{n}", label=label)
    axes[0].set_ylabel("max |e_k| (m^2, log)")
    axes[1].set_ylabel("max_j |K_I eta_j| / torque limit_j")
    for ax in axes:
        ax.set_xlabel("t (s)")
        ax.legend()
    fig.suptitle("Law-II, spatial tetrahedron, torque limits halved (K_I = 1)")
    return save_figure(fig, out / "robustness_windup.png")


def spatial_figure(rows: Sequence[dict[str, Any]], out: Path) -> Path:
    """Final max |edge length error| vs mismatch size per kind (each seed a marker) per law, log scale."""
    fig, axes = plt.subplots(1, len(SPATIAL_KINDS), figsize=(4.4 * len(SPATIAL_KINDS), 4.2), sharey=True,
                             squeeze=False)
    for c, kind in enumerate(SPATIAL_KINDS):
        ax = axes[0, c]
        for n, law in enumerate(LAWS):
            selected = [r for r in rows if r["law"] == law and r["kind"] in ("none", kind)]
            sizes = np.array([r["size"] for r in selected]) + (n - 1) * 0.015
            values = np.array([r["final_max_length_error"] for r in selected]) + 1e-9
            faulted = np.array([bool(r["fault"]) for r in selected])
            ax.semilogy(sizes[~faulted], values[~faulted], "os^"[n], color=f"C{n}", label=law, alpha=0.8)
            if faulted.any():
                ax.semilogy(sizes[faulted], values[faulted], "x", color=f"C{n}", ms=9)
        ax.axhline(DEFAULT_POSITION_TOLERANCE, color="grey", ls=":", lw=1)
        ax.set_title(f"{kind} mismatch" + (" (x: fault)" if c == 0 else ""))
        ax.set_xlabel("mismatch size s (factors in [1 - s, 1 + s])")
    axes[0, 0].set_ylabel("final max |edge length - target| (m, log)")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("Spatial tetrahedron (PERA-like arms, gravity): model mismatch, 3 seeds per point; "
                 "dotted: 1 cm", fontsize=10)
    return save_figure(fig, out / "robustness_spatial.png")


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Command-line entry: run the selected studies, write robustness.json and the figures."""
    parser = argparse.ArgumentParser(prog="python -m studies.robustness", description=__doc__.split("\n\n")[0])
    add_output_arguments(parser, STUDIES, "results/robustness")
    parser.add_argument("--quick", action="store_true", help="1 s horizons, a 2 x 2 stall map, one spatial case per kind (tests)")
    args = parser.parse_args(argv)
    studies = args.only or list(STUDIES)
    args.out.mkdir(parents=True, exist_ok=True)
    seconds = 1.0 if args.quick else 15.0
    results: dict[str, Any] = {}
    figures = []
    if "mismatch" in studies:
        results["mismatch"] = mismatch_study(seconds)
        figures.append(mismatch_figure(results["mismatch"], args.out))
    if "separating" in studies:
        results["separating"] = separating_study(seconds)
        figures.append(separating_figure(results["separating"], args.out))
    if "stall" in studies:
        grid = ((3.0, 4.0), (0.02, 0.002), (5.0,)) if args.quick else \
            ((2.5, 3.0, 3.5, 4.0), (0.0002, 0.002, 0.02, 0.2), (5.0, 50.0))
        results["stall"] = stall_study(1.0 if args.quick else 10.0, *grid)
        figures.append(stall_figure(results["stall"], args.out))
    if "windup" in studies:
        results["windup"] = windup_study(1.0 if args.quick else 20.0)
        figures.append(windup_figure(results["windup"], args.out))
    if "spatial" in studies:
        results["spatial"] = spatial_study(1.0, sizes=(0.5,), seeds=(0,)) if args.quick else spatial_study(20.0)
        figures.append(spatial_figure(results["spatial"], args.out))
        print(spatial_table(results["spatial"]), flush=True)
    for rows in results.values():  # keep the JSON small: time series only where a figure needs them
        for row in rows:
            if "mismatch_seed" in row:
                row.pop("t", None)
                row.pop("max_abs_e", None)
                row.pop("max_length_error", None)
    (args.out / "robustness.json").write_text(json.dumps(results, indent=1) + "\n", encoding="utf-8")
    report_outputs(args.out, copy_figures(figures, args.figures_dir))
    return results


if __name__ == "__main__":
    main()
