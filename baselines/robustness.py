"""Robustness of the three laws to kinematic model mismatch, the printed law-III's stall map, anti-windup.

    python -m baselines.robustness [--out results/robustness] [--figures-dir docs/figures] [--quick]
                                   [--only mismatch|separating|stall|windup ...]

Studies (all on the built-in planar square: four ``planar_2link`` arms, 3.0 m square, the project's
tuned gains K_P 5, K_D 20, alpha 0.02, 50 N m limits, 100 Hz control; see REPRODUCTION.md):

- ``mismatch``: the simulated ("true") arms differ from the nominal URDF the controllers know, by one of
  four kinds of size s, per arm, seeded: ``uniform`` (both link lengths scaled by 1 + s or 1 - s, one sign
  per arm), ``lengths`` (each length by its own factor 1 + s u, u uniform in [-1, 1]), ``offsets`` (each
  joint origin moved by s * 1.5 m in a random in-plane direction: along the link, a modelled parameter,
  and across it, an unmodelled one), ``zero_component`` (the tool frame moved sideways by s * 1.5 m: a
  component that is zero in the nominal model, so no estimate a_hat can represent it). Law-I uses the
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

Outputs: ``robustness.json`` (every run) and PNG figures in ``--out`` (also copied to ``--figures-dir``).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
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
from baselines import _CONTROLLERS, agent_model  # noqa: E402
from baselines.controllers import Gains  # noqa: E402
from baselines.dynamics import nominal_dynamics  # noqa: E402
from baselines.metrics import run_episode  # noqa: E402
from ee_formation_env.formation import rigidity_matrix  # noqa: E402
from ee_formation_env.kinematics import chain_model  # noqa: E402
from ee_formation_env.scenario import ROBOTS, _square, load_scenario  # noqa: E402

STUDIES = ("mismatch", "separating", "stall", "windup")
KINDS = ("uniform", "lengths", "offsets", "zero_component")
SIZES = (0.1, 0.3, 0.5)
SEEDS = (0, 1, 2)
LAWS = {"law-I": "gradient", "law-II": "approx_jacobian", "law-III": "adaptive_jacobian"}
PLANAR_GAINS = Gains(kp=5.0, kd=20.0, ki=0.0, alpha=0.02)  # the built-in planar square's tuned gains
LINK = 1.5  # m, both links of the nominal planar_2link
DPI = 100


# ------------------------------------------------------------------------------------------ true robots
def perturbed_planar_urdf(kind: str, size: float, rng: np.random.Generator, directory: str) -> str:
    """A copy of ``planar_2link.urdf`` with the mismatch ``kind`` of ``size`` (module docstring); its path."""
    source = Path(ROBOTS["planar_2link"].urdf)
    tree = ElementTree.parse(source)
    joints = {joint.get("name"): joint.find("origin") for joint in tree.getroot().iter("joint")}
    origins = {name: np.array([float(v) for v in joints[name].get("xyz").split()]) for name in ("joint_2", "ee_joint")}
    if kind == "uniform":
        factor = 1.0 + size * rng.choice([-1.0, 1.0])
        origins = {name: xyz * factor for name, xyz in origins.items()}
    elif kind == "lengths":
        origins = {name: xyz * (1.0 + size * rng.uniform(-1.0, 1.0)) for name, xyz in origins.items()}
    elif kind == "offsets":
        for name in origins:
            angle = rng.uniform(-math.pi, math.pi)
            origins[name] = origins[name] + size * LINK * np.array([math.cos(angle), math.sin(angle), 0.0])
    elif kind == "zero_component":
        origins["ee_joint"] = origins["ee_joint"] + np.array([0.0, size * LINK * rng.choice([-1.0, 1.0]), 0.0])
    else:
        raise ValueError(f"kind: expected one of {KINDS}, got {kind!r}")
    for name, xyz in origins.items():
        joints[name].set("xyz", " ".join(repr(float(v)) for v in xyz))
    # Absolute mesh paths so the copy loads from the temporary directory.
    for mesh in tree.getroot().iter("mesh"):
        if mesh.get("filename") and not Path(mesh.get("filename")).is_absolute():
            mesh.set("filename", str(source.parent / mesh.get("filename")))
    path = Path(tempfile.mkstemp(suffix=".urdf", dir=directory)[1])
    tree.write(path)
    return str(path)


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
    delta_star = lambda_4 / (4.0 * lambda_jhat * lambda_3)
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
            policies[agent] = _CONTROLLERS[LAWS[law]](model, gains, None if a_hat0 is None else np.asarray(a_hat0, float),
                                                      **options)
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
                        print(f"mismatch {kind} s={size} seed={seed} {law}: final max|e| {row['final_max_abs_e']:.3g} m^2, "
                              f"delta {row['delta']:.3g}, delta* {row['delta_star']:.3g}", flush=True)
    return rows
