"""Random scenarios: do the reference policies work out of the box on a scenario nobody tuned them for?

    python -m studies.random_scenarios                      # 10 planar + 6 spatial scenarios, ~6 min
    python -m studies.random_scenarios --planar 20 --spatial 0 --seed 1 --json out.json
    python -m studies.random_scenarios --distribution planar_random --json out.json   # its 50-seed test set

A seeded generator writes scenarios the way a new user would (plain scenario dicts, default physics and
default gains), then every reference policy (``gradient``, ``approx_jacobian``, ``adaptive_jacobian``)
runs each of them once from its ``initial_q`` (no reset noise). Printed per family and policy: the success
rate, the mean and worst settling time of the successes, physics faults and arm contacts.

- **planar** (:func:`ee_formation_env.generators.planar_scenario`): 3 to 6 ``planar_2link`` arms with bases on a ring of radius
  4-6 m (random ring offset, a random base yaw each), random initial q with the elbow away from its
  singularities (|q2| in [0.4, pi - 0.4] rad), each target vertex inside its own arm's reach (0.8 m to
  the reach less 0.4 m from its base; the reach, 3 m, is the sum of the link lengths read from the arm's
  kinematic model, :func:`ee_formation_env.generators.planar_link_lengths`), a minimally rigid
  trilateration graph. 20 s episodes.
- **spatial** (:func:`ee_formation_env.generators.spatial_scenario`): 3 or 4 arms, each one of ``kuka_iiwa`` (``pybullet_data``
  ``kuka_iiwa/model.urdf``, end-effector ``lbr_iiwa_link_7``), ``franka_panda`` (``franka_panda/panda.urdf``,
  ``panda_hand``) and the built-in ``pera_arm``, mixed at random (heterogeneous teams), bases on a ring of
  radius 0.45-0.65 m with random yaw; the hanging PERA-like arm is mounted 1 m up so that every arm reaches
  the shared region. Initial and target end-effector positions are those of random joint configurations
  (inside the joint limits, away from singularities) that put the end-effector in a shared region above the
  ring's centre, so every target vertex is reachable by its own arm; both sets of poses are resampled until
  every arm is 3 cm clear of the others (a draw that cannot be is redrawn, seeded). Complete graph (rigid in
  3D for 3 or 4 agents), gravity on, 5 ms control steps (as the built-in spatial scenarios). 30 s episodes.

``--distribution NAME`` runs a built-in scenario distribution (``planar_random``, ``spatial_random``) on its
test set instead: each policy on the draw of every reset seed of ``ee_formation_env.scenario_sets.TEST_SEEDS``
(the episode ``reset(seed=s)`` gives, start noise included), with the gains of each draw. Targets: 95 % for
``planar_random``, 100 % for ``spatial_random``.

A failed run is classified from its final state and its last seconds (:attr:`RunRecord.failure_kind`):
a physics fault; arms still touching each other at the end (jammed); an arm at a singularity; the paper's gradient e_hat small while edges are off, either
with the error on a plateau (at or near an undesired equilibrium of the distance formation, or a saddle
the flow leaves only slowly) or still falling (converging slowly along a weak mode: an ill-conditioned
shape, or an arm near its workspace boundary that can barely move its end-effector the way the error
needs); or still converging (a transient, e_hat not small).

Every run is rolled by :func:`ee_formation_env.baselines.metrics.run_episode`, and **success** and the
**settling time** are its (:func:`ee_formation_env.baselines.metrics.settle`): the formation error (RMS
over edges of ``|e_k|``) below :func:`ee_formation_env.baselines.metrics.formation_tolerance` (the edges'
accuracy ``ee_formation_env.reward.DEFAULT_POSITION_TOLERANCE``, 1 cm) from the settling time to the end,
held at least 1 s, with no physics fault. The largest edge-length error (m) is recorded along the way
for the failure classification and the table. Targets (checked and printed): planar >= 90 % of the
scenarios for every formation law, spatial 100 %. Results and their history: see docs/results.md.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

import ee_formation_env
from ee_formation_env.env import FormationEnv
from ee_formation_env.formation import rigidity_matrix

if __package__ in (None, ""):  # run as a script: python studies/random_scenarios.py
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from ee_formation_env.baselines import REFERENCE_CONTROLLERS, make_policies  # noqa: E402
from ee_formation_env.baselines.metrics import Step, run_episode  # noqa: E402
from ee_formation_env.scenario_sets import DISTRIBUTIONS, RANDOM_FAMILIES, TEST_SEEDS  # noqa: E402
from studies._common import max_edge_length_error  # noqa: E402

# The families' generators live with the scenario sets (one home for generation), not in this study.
planar_scenario, spatial_scenario = RANDOM_FAMILIES["planar"], RANDOM_FAMILIES["spatial"]

POLICIES = tuple(REFERENCE_CONTROLLERS)  # the paper's laws I, II and III
TARGETS = {"planar": 0.9, "spatial": 1.0,  # required success rate per family and policy
           "planar_random": 0.95, "spatial_random": 1.0}  # and per distribution, on its test set
SINGULAR_MARGIN = 0.02  # m: a final smallest Jacobian singular value below this counts as singular
EQUILIBRIUM_RATIO = 0.05  # a final gradient ratio below this: e_hat small for the edge errors
TREND_SECONDS = 5.0  # s: the error trend is measured over the last this many seconds
PLATEAU_DROP = 0.1  # a max edge error that fell by less than this fraction over them is on a plateau

@dataclass
class RunRecord:
    """One (scenario, policy) episode."""

    family: str
    scenario: str
    n_agents: int
    robots: str
    policy: str
    success: bool  # run_episode's (ee_formation_env.baselines.metrics.settle)
    settling_time: float  # s, run_episode's; nan if the formation error never stays within tolerance to the end
    final_max_edge_error: float  # m, largest |edge length - target| at the end
    physics_fault: str
    contact_steps: int
    min_singularity_margin: float  # m, over the episode
    final_singularity_margin: float  # m, smallest Jacobian singular value at the end
    final_gradient_ratio: float  # max_i |e_hat_i| / (2 max_k |e_k| max_k |z_k|) at the end (0: an equilibrium)
    final_max_joint_speed: float  # rad/s at the end
    wall_s: float
    final_error_trend: float = math.nan  # relative change of the max edge error over the last TREND_SECONDS
    final_rigidity_ratio: float = math.nan  # sigma_min / sigma_max of the rigidity matrix at the end
    final_contact: bool = False  # arms touching each other at the last step

    @property
    def failure_kind(self) -> str:
        """Why a failed run failed, from its final state ("" for a success)."""
        if self.success:
            return ""
        if self.physics_fault:
            return "physics fault"
        if self.final_contact:
            return "arms jammed against each other (in contact at the end)"
        if self.final_singularity_margin < SINGULAR_MARGIN:
            return "an arm at a singularity (workspace boundary or folded)"
        if self.final_gradient_ratio < EQUILIBRIUM_RATIO:
            if not self.final_error_trend < -PLATEAU_DROP:
                return ("at or near an undesired equilibrium of the distance formation (e_hat ~ 0, e != 0, the "
                        "error on a plateau)")
            return ("converging slowly along a weak mode (e_hat small for the edge errors, the error still "
                    "falling)")
        return "still converging at the horizon"


def gradient_ratio(env: FormationEnv) -> float:
    """``max_i |e_hat_i| / (2 max_k |e_k| max_k |z_k|)`` with the paper's (unsaturated) e_hat: near 0 when the
    formation sits at an equilibrium of its gradient flow with nonzero edge errors."""
    positions = env.end_effector_positions()[:, :env.dim]
    z = env.graph.edge_vectors(positions)
    errors = np.einsum("kd,kd->k", z, z) - env.formation.desired**2
    e_hat = 2.0 * env.graph.incidence @ (errors[:, None] * z)  # (N, dim): sum over incident edges, signed
    scale = 2.0 * np.max(np.abs(errors)) * np.max(np.linalg.norm(z, axis=1))
    return float(np.max(np.linalg.norm(e_hat, axis=1)) / max(scale, 1e-300))


def rigidity_ratio(env: FormationEnv) -> float:
    """``sigma_min / sigma_max`` of the rigidity matrix at the current end-effector positions (its
    ``n_edges``-th singular value: 0 where the realization is degenerate, small for an ill-conditioned one)."""
    rigidity = rigidity_matrix(env.graph, env.end_effector_positions()[:, :env.dim])
    values = np.linalg.svd(rigidity, compute_uv=False)
    return float(values[min(rigidity.shape) - 1] / max(values[0], 1e-300))


def run_one(scenario: Any, family: str, policy: str, seed: int = 0, **policy_kwargs: Any) -> RunRecord:
    """Roll ``policy`` on ``scenario`` once (reset ``seed``) with :func:`run_episode`; success and settling are
    its, the final state and the largest edge-length error along the way feed the failure classification."""
    env = ee_formation_env.parallel_env(scenario)
    try:
        policies = make_policies(policy, env, **policy_kwargs)
        lengths: list[float] = []  # largest edge-length error (m): after the reset, then after each step
        last: list[Step] = []

        def watch(env: FormationEnv, step: Step) -> None:
            lengths.append(max_edge_length_error(env))
            last[:] = [step]

        start = time.perf_counter()
        metrics = run_episode(env, policies, seed=seed, on_reset=lambda env: lengths.append(max_edge_length_error(env)),
                              on_transition=watch)
        wall = time.perf_counter() - start
        dt = env.scenario.control_dt
        series = np.asarray(lengths)
        infos = last[0].infos
        robots = ",".join(arm.robot or Path(arm.urdf).parent.name for arm in env.scenario.arms)
        final_margin = min(info["singularity_margin"] for info in infos.values())
        speed = max(float(np.max(np.abs(dq))) for dq in env.joint_velocities())
        back = min(len(series) - 1, int(round(TREND_SECONDS / dt)))
        trend = float(series[-1] / series[-1 - back] - 1.0) if back > 0 and series[-1 - back] > 0 else math.nan
        name = env.scenario.name + (f"@{seed}" if env.scenario.distribution.active else "")
        return RunRecord(family, name, env.scenario.n_agents, robots, policy, metrics.success,
                         metrics.settling_time, float(series[-1]), metrics.physics_fault, metrics.contact_steps,
                         metrics.min_singularity_margin, float(final_margin), gradient_ratio(env), speed, wall, trend,
                         rigidity_ratio(env), any(info["contacts"] > 0 for info in infos.values()))
    finally:
        env.close()


def summarize(records: Sequence[RunRecord]) -> list[dict[str, Any]]:
    """One row per (family, policy): success rate, settling times, faults, contacts."""
    rows = []
    for family in TARGETS:
        for policy in POLICIES:
            selected = [r for r in records if r.family == family and r.policy == policy]
            if not selected:
                continue
            settled = [r.settling_time for r in selected if r.success]
            rows.append({
                "family": family, "policy": policy, "scenarios": len(selected),
                "success_rate": float(np.mean([r.success for r in selected])),
                "mean_settling_s": float(np.mean(settled)) if settled else math.nan,
                "max_settling_s": float(np.max(settled)) if settled else math.nan,
                "physics_faults": sum(bool(r.physics_fault) for r in selected),
                "runs_with_contacts": sum(r.contact_steps > 0 for r in selected),
                "target": TARGETS[family],
                "target_met": float(np.mean([r.success for r in selected])) >= TARGETS[family],
            })
    return rows


def format_rows(rows: Sequence[dict[str, Any]]) -> str:
    """The summary as a markdown table."""
    lines = ["| family | policy | scenarios | success | mean settle s | max settle s | faults | runs with contacts "
             "| target | met |", "|---|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for row in rows:
        def seconds(value: float) -> str:
            return "n/a" if math.isnan(value) else f"{value:.2f}"
        met = "yes" if row["target_met"] else "NO"
        lines.append(f"| {row['family']} | {row['policy']} | {row['scenarios']} | {row['success_rate']:.0%} "
                     f"| {seconds(row['mean_settling_s'])} | {seconds(row['max_settling_s'])} "
                     f"| {row['physics_faults']} | {row['runs_with_contacts']} | >= {row['target']:.0%} | {met} |")
    return "\n".join(lines)


def format_failures(records: Sequence[RunRecord]) -> str:
    """One line per failed run, for the explanation of failures."""
    lines = []
    for r in records:
        if not r.success:
            lines.append(f"- {r.scenario} ({r.n_agents} arms: {r.robots}) {r.policy}: {r.failure_kind}; final max edge "
                         f"error {r.final_max_edge_error:.3g} m, final smallest singular value "
                         f"{r.final_singularity_margin:.3g} m, gradient ratio {r.final_gradient_ratio:.2g}, "
                         f"error change over the last {TREND_SECONDS:g} s {r.final_error_trend:+.0%}, rigidity "
                         f"sigma_min / sigma_max {r.final_rigidity_ratio:.2g}, "
                         f"joint speed {r.final_max_joint_speed:.2g} rad/s, contact steps {r.contact_steps}"
                         + (f", FAULT: {r.physics_fault}" if r.physics_fault else ""))
    return "\n".join(lines) if lines else "(none)"


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Command-line entry: generate, run, print the table; return the results."""
    parser = argparse.ArgumentParser(prog="python -m studies.random_scenarios", description=__doc__.split("\n\n")[0])
    parser.add_argument("--planar", type=int, default=10, help="number of planar scenarios (default 10)")
    parser.add_argument("--spatial", type=int, default=6, help="number of spatial scenarios (default 6)")
    parser.add_argument("--seed", type=int, default=0, help="first scenario seed (seeds seed .. seed + n - 1)")
    parser.add_argument("--policy", action="append", choices=POLICIES, help="only this policy (repeatable)")
    parser.add_argument("--distribution", choices=DISTRIBUTIONS, default=None,
                        help="run this scenario distribution's test set instead of the random families")
    parser.add_argument("--seeds", type=int, default=len(TEST_SEEDS),
                        help=f"--distribution: the first this many test seeds (default all {len(TEST_SEEDS)})")
    parser.add_argument("--json", type=Path, default=None, help="write every run and the summary here")
    args = parser.parse_args(argv)
    if args.planar < 0 or args.spatial < 0:
        raise ValueError("--planar/--spatial: expected counts >= 0")
    if not 1 <= args.seeds <= len(TEST_SEEDS):
        raise ValueError(f"--seeds: expected 1 to {len(TEST_SEEDS)}, got {args.seeds}")
    policies = args.policy or list(POLICIES)
    if args.distribution is not None:
        runs = [(args.distribution, args.distribution, seed) for seed in TEST_SEEDS[:args.seeds]]
    else:
        runs = ([("planar", planar_scenario(args.seed + k), 0) for k in range(args.planar)]
                + [("spatial", spatial_scenario(args.seed + k), 0) for k in range(args.spatial)])
    records = []
    for family, scenario, seed in runs:
        for policy in policies:
            record = run_one(scenario, family, policy, seed)
            records.append(record)
            print(f"{record.scenario} {record.policy}: success={record.success} settle={record.settling_time:.2f} s "
                  f"err={record.final_max_edge_error:.2e} m {record.physics_fault} ({record.wall_s:.1f} s)", flush=True)
    rows = summarize(records)
    print(format_rows(rows))
    print("\nFailed runs:\n" + format_failures(records))
    results = {"rows": rows, "runs": [{**asdict(r), "failure_kind": r.failure_kind} for r in records]}
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=2) + "\n", encoding="utf-8")
        print(f"wrote {args.json.resolve()}", flush=True)
    return results


if __name__ == "__main__":
    main()
