"""Speed benchmarks: raw PyBullet floor, ``env.step``, closed loop, SB3 rollouts, scaling and reset cost.

    python -m benchmarks.run                  # full run (a few minutes), table + results/benchmarks.json
    python -m benchmarks.run --quick          # a smoke run (seconds), same sections, few steps
    python -m benchmarks.run --json out.json

Every figure comes from this one process and one run (the SB3 section's worker processes are started by
it), so the ratios between rows are meaningful even on a loaded machine; absolute rates are not. Each
measurement is repeated (``--repeats``) with the cases of one scenario interleaved round by round, and the
fastest repeat is reported (the one least disturbed by other processes); every repeat is in the JSON.

Sections:

- ``raw_floor``: the env's own bodies, torques set with ``setJointMotorControlArray`` and
  ``stepSimulation`` only; and, for reference, a naive per-arm ``getJointStates`` + ``getLinkState`` +
  ``setJointMotorControlArray`` loop;
- ``env_step``: ``env.step`` with zero actions at ``frame_skip`` 1 and at the scenario's default;
- ``closed_loop``: ``env.step`` plus the ``adaptive_jacobian`` controller on every agent;
- ``sb3_rollout``: ``PPO.collect_rollouts`` through :class:`~ee_formation_env.integrations.sb3.SharedPolicyVecEnv`
  with 2 worker processes (and in-process, for comparison);
- ``sb3_training``: ``model.learn`` of ``train.py``'s default configuration (the same model, envs and PPO
  settings, built by ``ee_formation_env.baselines.learned.sb3_backend.build_sb3_model``): training throughput in agent steps/s, updates included;
- ``scaling``: 2, 4, 8 and 16 arms on a minimally rigid graph (:mod:`ee_formation_env.generators`), 2-DOF planar
  and 7-DOF spatial arms: raw floor, ``env.step`` at ``frame_skip`` 1, and reset cost;
- ``reset``: ``env.reset`` (state restore, no URDF reload) of the built-in scenarios;
- ``vector``: the batched env (``ee_formation_env.vector_env``) at K = 1, 4, 16, 64 copies, zero actions at the
  scenario's frame_skip, against the raw floor of the same K formations in both physics layouts (K clients,
  each stepping its formation; one client holding all K, placed 10 m apart), and resident memory per formation;
- ``torchrl`` (skipped without the ``torchrl`` extra): frames (env steps) per second collected by TorchRL's
  ``SyncDataCollector`` with a random policy on ``planar_square``: through ``make_torchrl_env`` without
  ``num_envs`` (the ``PettingZooWrapper``, one env) and natively batched at K = 32, 64, against the raw floor
  of the same K formations (K clients in lockstep, :func:`time_floor_clients`) and the batched env alone
  (``step_arrays``, random actions).

Figures: physics steps/s, env steps/s, the ratio to the raw floor of the same bodies (physics steps/s
over raw physics steps/s) and the real-time factor (simulated seconds per wall-clock second).
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

import ee_formation_env

if __package__ in (None, ""):  # run as a script: python benchmarks/run.py
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from ee_formation_env.generators import planar_ring, spatial_ring  # noqa: E402

from benchmarks.batched import bench_torchrl, bench_vector  # noqa: E402
from benchmarks.timing import (FULL, QUICK, Budget, _make_env, _row, interleaved, time_closed_loop,  # noqa: E402
                               time_env_steps, time_naive_loop, time_raw_floor, time_resets)

SECTIONS = ("raw_floor", "env_step", "closed_loop", "sb3_rollout", "sb3_training", "scaling", "reset", "vector",
            "torchrl")
VECTOR_COUNTS = (1, 4, 16, 64)  # copies K of the batched env (--quick: 1 and 4)
TORCHRL_COUNTS = (32, 64)  # copies K of the native batched TorchRL env (--quick: 4)
ARM_COUNTS = (2, 4, 8, 16)
# train.py runs whose training throughput is measured: each mode's default run first (its target applies to
# it). The others: every env in worker processes, every env in-process, the first layout (8 envs x 128 steps),
# and torque mode with the same samples per update as 32 envs x 32 steps (its update cost is the same).
TRAINING_CASES = ((), ("--n-workers", "2", "--in-process-envs", "0"), ("--n-workers", "0"),
                  ("--n-envs", "8", "--n-steps", "128", "--n-workers", "0"), ("--mode", "torque"),
                  ("--mode", "torque", "--n-envs", "32", "--n-steps", "32"))
DEFAULT_JSON = "results/benchmarks.json"




def bench_scenario(name: str, budget: Budget) -> list[dict[str, Any]]:
    """Sections (a) and (b) for one built-in scenario: raw floor, naive loop, env.step at two frame skips."""
    env1 = _make_env(name, frame_skip=1)
    env_default = _make_env(name)
    hz, fs = env1.scenario.physics_hz, env_default.scenario.frame_skip
    # Every case covers the same simulated span from the same reset state, so the physics is the same.
    steps, default_steps = budget.physics_steps, budget.physics_steps // fs
    try:
        times = interleaved({
            "raw": lambda: time_raw_floor(env1, steps),
            "naive": lambda: time_naive_loop(env1, steps),
            "fs1": lambda: time_env_steps(env1, steps),
            "default": lambda: time_env_steps(env_default, default_steps),
        }, budget.repeats)
    finally:
        env1.close()
        env_default.close()
    raw_rate = steps / min(times["raw"])
    n = env1.scenario.n_agents
    return [
        _row("raw_floor", f"{name}: setJointMotorControlArray + stepSimulation", times["raw"], steps, 1, hz,
             raw_rate, scenario=name, n_arms=n),
        _row("raw_floor", f"{name}: naive per-arm query loop", times["naive"], steps, 1, hz, raw_rate,
             scenario=name, n_arms=n),
        _row("env_step", f"{name}: env.step, zero action, frame_skip 1", times["fs1"], steps, 1, hz,
             raw_rate, scenario=name, n_arms=n),
        _row("env_step", f"{name}: env.step, zero action, frame_skip {fs}", times["default"], default_steps,
             fs, hz, raw_rate, scenario=name, n_arms=n),
    ]


def bench_closed_loop(name: str, seconds: float, budget: Budget, raw_rate: float) -> list[dict[str, Any]]:
    """Section (c): env plus ``adaptive_jacobian`` on every agent, ``seconds`` of simulated time; the team
    evaluated in batches (as ``run_episode`` does) and agent by agent."""
    from ee_formation_env import baselines

    env = _make_env(name)
    try:
        policies = baselines.make_policies("adaptive_jacobian", env)
        steps = max(1, int(round(seconds / env.scenario.control_dt)))
        times = interleaved({"team": lambda: time_closed_loop(env, policies, steps),
                             "agents": lambda: time_closed_loop(env, policies, steps, batched=False)},
                            max(1, min(budget.repeats, 3)))
        scenario = env.scenario
    finally:
        env.close()
    rows = []
    for key, how in (("team", "one team call per step"), ("agents", "one call per agent")):
        row = _row("closed_loop", f"{name}: env + adaptive_jacobian, {how} ({seconds:g} s simulated)", times[key],
                   steps, scenario.frame_skip, scenario.physics_hz, raw_rate, scenario=name,
                   n_arms=scenario.n_agents, simulated_seconds=seconds, batched=key == "team")
        row["wall_seconds_per_30s_simulated"] = 30.0 / row["real_time_factor"]
        rows.append(row)
    return rows


def bench_sb3(name: str, budget: Budget, raw_rate: float, n_envs: int = 2) -> list[dict[str, Any]]:
    """Section (d): ``PPO.collect_rollouts`` through SharedPolicyVecEnv, 2 worker processes and in-process."""
    try:
        import torch
        from stable_baselines3 import PPO

        from ee_formation_env.integrations.sb3 import SharedPolicyVecEnv
    except ImportError as error:  # the optional "train" extra
        return [{"section": "sb3_rollout", "case": f"{name}: skipped ({error})", "skipped": True}]
    torch.set_num_threads(1)
    rows = []
    for workers in (2, 0):
        # As train.py: no per-step infos cross the pipes.
        venv = SharedPolicyVecEnv(functools.partial(ee_formation_env.vector_env, name), n_envs, n_workers=workers,
                                  info_keys=())
        try:
            model = PPO("MlpPolicy", venv, n_steps=budget.sb3_steps, batch_size=budget.sb3_steps, device="cpu",
                        seed=0, verbose=0)
            _, callback = model._setup_learn(budget.sb3_steps * venv.num_envs, None)
            callback.on_training_start(locals(), globals())

            def collect() -> float:
                start = time.perf_counter()
                model.collect_rollouts(venv, callback, model.rollout_buffer, n_rollout_steps=budget.sb3_steps)
                return time.perf_counter() - start

            times = interleaved({"collect": collect}, max(1, min(budget.repeats, 3)))["collect"]
            scenario, slots = venv.scenario, venv.num_envs
        finally:
            venv.close()
        where = f"{workers} worker processes" if workers else "in-process"
        # One VecEnv step advances every env by one env step: count env steps over all envs.
        rows.append(_row("sb3_rollout", f"{name}: PPO.collect_rollouts, {n_envs} envs ({slots} agent slots), {where}",
                         times, budget.sb3_steps * n_envs, scenario.frame_skip, scenario.physics_hz, raw_rate,
                         scenario=name, n_envs=n_envs, n_workers=workers, slots=slots,
                         samples_per_s=budget.sb3_steps * slots / min(times)))
    return rows


def bench_training(budget: Budget, extra_args: Sequence[str] = ()) -> list[dict[str, Any]]:
    """Section ``sb3_training``: agent steps/s of ``train.py``'s default run (``extra_args`` change it),
    PPO updates included, and the split of each update's wall time into the rollout (``collect_rollouts``)
    and the PPO update (``train``); the first update (model warm-up) is not timed."""
    try:
        from stable_baselines3.common.utils import configure_logger  # noqa: F401 (the "train" extra)

        from ee_formation_env.baselines.learned.config import TrainConfig
        from ee_formation_env.baselines.learned.sb3_backend import build_sb3_model
    except ImportError as error:
        return [{"section": "sb3_training", "case": f"skipped ({error})", "skipped": True}]
    args = TrainConfig.from_args(["--no-progress", *extra_args])
    model = build_sb3_model(args, None)
    spent = {"collect_rollouts": 0.0, "train": 0.0}

    def timed(name: str, method: Callable[..., Any]) -> Callable[..., Any]:
        def call(*call_args: Any, **call_kwargs: Any) -> Any:
            start = time.perf_counter()
            try:
                return method(*call_args, **call_kwargs)
            finally:
                spent[name] += time.perf_counter() - start
        return call

    try:
        per_update = model.n_steps * model.get_env().num_envs
        model.learn(total_timesteps=per_update)  # warm-up: first rollout, first update
        model.collect_rollouts = timed("collect_rollouts", model.collect_rollouts)
        model.train = timed("train", model.train)
        splits: list[tuple[float, float]] = []

        def learn() -> float:
            before = dict(spent)
            start = time.perf_counter()
            model.learn(total_timesteps=budget.training_updates * per_update, reset_num_timesteps=False)
            seconds = time.perf_counter() - start
            splits.append(((spent["collect_rollouts"] - before["collect_rollouts"]) / budget.training_updates,
                           (spent["train"] - before["train"]) / budget.training_updates))
            return seconds

        times = interleaved({"learn": learn}, max(1, min(budget.repeats, 3)))["learn"]
    finally:
        model.get_env().close()
    agent_steps = budget.training_updates * per_update
    fastest = int(np.argmin(times))
    description = " ".join(extra_args) or "defaults"
    layout = (f"{args.n_envs} envs in-process" if not args.n_workers else
              f"{args.n_envs} envs: {args.in_process_envs} in-process, the others in {args.n_workers} worker "
              f"process{'es' if args.n_workers > 1 else ''}")
    return [{"section": "sb3_training", "case": f"train.py ({description}): {args.options.mode} mode, {layout}",
             "scenario": args.scenario, "mode": args.options.mode, "n_envs": args.n_envs, "n_workers": args.n_workers,
             "in_process_envs": args.in_process_envs, "extra_args": list(extra_args),
             "agent_steps": agent_steps, "seconds": times, "agent_steps_per_s": agent_steps / min(times),
             "rollout_ms_per_update": 1000 * splits[fastest][0], "update_ms_per_update": 1000 * splits[fastest][1],
             "agent_steps_per_update": per_update}]


def bench_scaling(budget: Budget, counts: Sequence[int]) -> list[dict[str, Any]]:
    """Section (e): raw floor, env.step at frame_skip 1 and reset cost versus the number of arms and DOF."""
    rows = []
    for family, builder in (("planar 2-DOF", planar_ring), ("spatial 7-DOF", spatial_ring)):
        steps = budget.physics_steps // 2
        for n in counts:
            env = _make_env(builder(n), frame_skip=1)
            try:
                times = interleaved({
                    "raw": lambda: time_raw_floor(env, steps),
                    "fs1": lambda: time_env_steps(env, steps),
                }, budget.scaling_repeats)
                reset_seconds = time_resets(env, budget.resets // 2 or 1)
                hz, dof = env.scenario.physics_hz, env.nominal_models[0].n_joints
            finally:
                env.close()
            raw_rate = steps / min(times["raw"])
            row = _row("scaling", f"{family}, {n} arms: env.step, frame_skip 1", times["fs1"], steps,
                       1, hz, raw_rate, family=family, n_arms=n, dof=dof, raw_physics_steps_per_s=raw_rate,
                       raw_seconds=[round(s, 6) for s in times["raw"]], reset_ms=1e3 * reset_seconds)
            row["us_per_env_step_per_arm"] = row["us_per_env_step"] / n
            rows.append(row)
    return rows


def bench_resets(names: Sequence[str], budget: Budget) -> list[dict[str, Any]]:
    """Reset cost of built-in scenarios."""
    rows = []
    for name in names:
        env = _make_env(name)
        try:
            seconds = min(time_resets(env, budget.resets) for _ in range(max(1, min(budget.repeats, 3))))
            rows.append({"section": "reset", "case": f"{name}: env.reset", "scenario": name,
                         "n_arms": env.scenario.n_agents, "reset_ms": 1e3 * seconds})
        finally:
            env.close()
    return rows


# ---------------------------------------------------------------------------------------------- report
def linear_fit(counts: Sequence[int], values: Sequence[float]) -> dict[str, float]:
    """Least-squares ``value = intercept + slope * n`` and its largest relative residual."""
    n, v = np.asarray(counts, dtype=float), np.asarray(values, dtype=float)
    slope, intercept = np.polyfit(n, v, 1)
    residual = np.max(np.abs(intercept + slope * n - v) / v)
    return {"intercept_us": float(intercept), "slope_us_per_arm": float(slope), "max_relative_residual": float(residual)}


def evaluate_targets(results: dict[str, Any]) -> list[dict[str, Any]]:
    """The speed targets (``docs/performance.md``), each with the measured value and whether it is met."""
    def find(section: str, scenario: str, frame_skip: int | None = None) -> dict[str, Any] | None:
        return next((r for r in results["rows"] if r["section"] == section and r.get("scenario") == scenario
                     and frame_skip in (None, r.get("frame_skip"))), None)

    targets = []

    def add(name: str, value: float | None, limit: float, at_least: bool, unit: str = "") -> None:
        met = value is not None and (value >= limit if at_least else value <= limit)
        targets.append({"target": name, "value": value, "limit": limit, "at_least": at_least, "unit": unit,
                        "met": bool(met)})

    for scenario, limit in (("planar_square", 0.35), ("spatial_tetrahedron", 0.6)):
        row = find("env_step", scenario, frame_skip=1)
        add(f"env.step frame_skip 1 / raw floor, {scenario}", row and row["ratio_to_raw"], limit, True, "x")
    loop = find("closed_loop", "planar_square")
    add("closed loop planar_square: wall s per 30 s simulated", loop and loop["wall_seconds_per_30s_simulated"],
        2.0, False, "s")
    for scenario in ("planar_square", "spatial_tetrahedron"):
        reset = find("reset", scenario)
        add(f"reset, 4 arms ({scenario})", reset and reset["reset_ms"], 5.0, False, "ms")
    for mode, limit in (("residual", 15000.0), ("torque", 10000.0)):
        # The first row of each mode: train.py's defaults for it.
        training = next((r for r in results["rows"] if r["section"] == "sb3_training" and r.get("mode") == mode
                         and r.get("extra_args") in ([], ["--mode", mode])), None)
        add(f"train.py {mode} mode (defaults): agent steps/s, updates included",
            training and training["agent_steps_per_s"], limit, True, "")
    for family, fit in results.get("scaling_fits", {}).items():
        add(f"scaling {family}: per-arm env.step cost, {max(ARM_COUNTS)} arms / 4 arms", fit["per_arm_cost_ratio"],
            1.25, False, "x")
    for scenario in ("planar_square", "spatial_tetrahedron"):
        batched = [r for r in results["rows"] if r["section"] == "vector" and r.get("layout") == "vector_env"
                   and r["scenario"] == scenario and r["num_envs"] >= 16]
        if batched:
            add(f"vector_env / faster raw floor, K >= 16 (lowest), {scenario}",
                min(r["ratio_to_raw"] for r in batched), 0.8, True, "x")
            # the floor as the target was first set: torques re-sent before each single physics step
            add(f"vector_env / faster per-step raw floor, K >= 16 (lowest), {scenario}",
                min(r["physics_steps_per_s"] / max(r["floor_clients_physics_steps_per_s"],
                                                   r["floor_one_client_physics_steps_per_s"]) for r in batched),
                0.8, True, "x")
    collected = [r for r in results["rows"] if r["section"] == "torchrl" and r.get("layout") == "collector"
                 and r.get("batched") and r["num_envs"] >= 32]
    if collected:
        add("TorchRL SyncDataCollector, native batched env K >= 32 / raw floor (best), planar_square",
            max(r["ratio_to_raw"] for r in collected), 0.6, True, "x")
    return targets


def _fmt(value: Any, spec: str) -> str:
    return "-" if value is None or (isinstance(value, float) and not math.isfinite(value)) else format(value, spec)


def format_tables(results: dict[str, Any]) -> str:
    lines = ["| section | case | physics steps/s | env steps/s | x raw floor | real-time factor | us/env step |",
             "|---|---|---:|---:|---:|---:|---:|"]
    for r in results["rows"]:
        if r["section"] in ("reset", "sb3_training", "vector") or r.get("skipped"):
            continue
        lines.append(f"| {r['section']} | {r['case']} | {_fmt(r['physics_steps_per_s'], ',.0f')} | "
                     f"{_fmt(r['env_steps_per_s'], ',.0f')} | {_fmt(r['ratio_to_raw'], '.2f')} | "
                     f"{_fmt(r['real_time_factor'], '.1f')} | {_fmt(r['us_per_env_step'], ',.1f')} |")
    scaling = [r for r in results["rows"] if r["section"] == "scaling"]
    if scaling:
        lines += ["", "| arms | DOF | raw physics steps/s | env.step (fs 1) steps/s | x raw floor | us/step | us/step/arm | reset ms |",
                  "|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for r in scaling:
            lines.append(f"| {r['n_arms']} | {r['dof']} | {r['raw_physics_steps_per_s']:,.0f} | "
                         f"{r['env_steps_per_s']:,.0f} | {r['ratio_to_raw']:.2f} | {r['us_per_env_step']:,.1f} | "
                         f"{r['us_per_env_step_per_arm']:,.1f} | {r['reset_ms']:.2f} |")
        for family, fit in results.get("scaling_fits", {}).items():
            lines.append(f"\n{family}: env.step ~ {fit['intercept_us']:.0f} us + {fit['slope_us_per_arm']:.1f} us per arm "
                         f"(largest deviation from the line {fit['max_relative_residual']:.0%})")
    training = [r for r in results["rows"] if r["section"] == "sb3_training" and not r.get("skipped")]
    if training:
        lines += ["", "| training throughput | agent steps/s | rollout ms per update | PPO update ms per update |",
                  "|---|---:|---:|---:|"]
        lines += [f"| {r['case']} | {r['agent_steps_per_s']:,.0f} | {_fmt(r.get('rollout_ms_per_update'), ',.0f')} | "
                  f"{_fmt(r.get('update_ms_per_update'), ',.0f')} |" for r in training]
    batched = [r for r in results["rows"] if r["section"] == "vector" and r.get("layout") == "vector_env"]
    if batched:
        lines += ["", "| batched env | K | physics steps/s | floor, K clients (lockstep) | floor, one client | "
                  "floor, K clients (lockstep, substeps) | x faster floor | x faster per-step floor | "
                  "floor and reads, K clients (substeps) | its x faster floor | x floor and reads | "
                  "floor, K clients (free-running) | MB per formation (K clients) | MB per formation (one client) |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        one_client = {(r["scenario"], r["num_envs"]): r for r in results["rows"]
                      if r["section"] == "vector" and r.get("layout") == "one_client"}
        for r in batched:
            other = one_client.get((r["scenario"], r["num_envs"]), {})
            reads = r["floor_clients_substeps_reads_physics_steps_per_s"]
            per_step = max(r["floor_clients_physics_steps_per_s"], r["floor_one_client_physics_steps_per_s"])
            lines.append(f"| {r['scenario']} | {r['num_envs']} | {r['physics_steps_per_s']:,.0f} | "
                         f"{r['floor_clients_physics_steps_per_s']:,.0f} | {r['floor_one_client_physics_steps_per_s']:,.0f} | "
                         f"{r['floor_clients_substeps_physics_steps_per_s']:,.0f} | "
                         f"{r['ratio_to_raw']:.2f} | {r['physics_steps_per_s'] / per_step:.2f} | "
                         f"{reads:,.0f} | {reads / r['raw_physics_steps_per_s']:.2f} | "
                         f"{r['physics_steps_per_s'] / reads:.2f} | {r['floor_clients_free_physics_steps_per_s']:,.0f} | "
                         f"{r['rss_mb_per_formation']:.1f} | "
                         f"{_fmt(other.get('rss_mb_per_formation'), '.1f')} |")
    resets = [r for r in results["rows"] if r["section"] == "reset"]
    if resets:
        lines += ["", "| reset | arms | ms |", "|---|---:|---:|"]
        lines += [f"| {r['scenario']} | {r['n_arms']} | {r['reset_ms']:.2f} |" for r in resets]
    lines += ["", "| target | measured | limit | met |", "|---|---:|---:|---|"]
    if results["quick"]:
        lines.insert(len(lines) - 2, "--quick: few steps and one repeat; a smoke run, not a measurement\n")
    for t in results["targets"]:
        sign = ">=" if t["at_least"] else "<="
        lines.append(f"| {t['target']} | {_fmt(t['value'], '.3g')} {t['unit']} | {sign} {t['limit']:g} {t['unit']} | "
                     f"{'yes' if t['met'] else 'NO'} |")
    return "\n".join(lines)


def run(quick: bool = False, sections: Sequence[str] = SECTIONS, progress: Callable[[str], None] = print
        ) -> dict[str, Any]:
    """Run the selected sections; return the results dict (rows, fits, targets, machine info)."""
    budget = QUICK if quick else FULL
    started = time.time()
    results: dict[str, Any] = {
        "quick": quick, "sections": list(sections),
        "machine": {"python": platform.python_version(), "numpy": np.__version__, "platform": platform.platform(),
                    "cpu_count": os.cpu_count(), "load_average_start": list(os.getloadavg())},
        "budget": budget.__dict__, "rows": [],
    }
    raw_rates: dict[str, float] = {}
    if {"raw_floor", "env_step", "closed_loop", "sb3_rollout"} & set(sections):
        for name in ("planar_square", "spatial_tetrahedron"):
            progress(f"raw floor and env.step: {name}")
            rows = bench_scenario(name, budget)
            raw_rates[name] = rows[0]["physics_steps_per_s"]
            results["rows"] += [r for r in rows if r["section"] in sections]
    if "closed_loop" in sections:
        for name, seconds in (("planar_square", budget.closed_loop_seconds),
                              ("spatial_tetrahedron", budget.closed_loop_seconds_spatial)):
            progress(f"closed loop: {name}")
            results["rows"] += bench_closed_loop(name, seconds, budget, raw_rates[name])
    if "sb3_rollout" in sections:
        progress("SB3 rollouts: planar_square")
        results["rows"] += bench_sb3("planar_square", budget, raw_rates["planar_square"])
    if "sb3_training" in sections:
        for extra_args in TRAINING_CASES[:1] if quick else TRAINING_CASES:  # --quick: the default run only
            progress(f"SB3 training throughput: train.py {' '.join(extra_args) or '(defaults)'}")
            results["rows"] += bench_training(budget, extra_args)
    if "scaling" in sections:
        counts = ARM_COUNTS
        progress(f"scaling: {list(counts)} arms, 2 and 7 DOF")
        scaling = bench_scaling(budget, counts)
        results["rows"] += scaling
        fits = {}
        for family in dict.fromkeys(r["family"] for r in scaling):
            rows = [r for r in scaling if r["family"] == family]
            fit = linear_fit([r["n_arms"] for r in rows], [r["us_per_env_step"] for r in rows])
            per_arm = {r["n_arms"]: r["us_per_env_step_per_arm"] for r in rows}
            fit["per_arm_cost_ratio"] = per_arm[max(counts)] / per_arm[4]
            fits[family] = fit
        results["scaling_fits"] = fits
    if "reset" in sections:
        progress("reset")
        results["rows"] += bench_resets(("planar_square", "spatial_tetrahedron"), budget)
    if "vector" in sections:
        counts = VECTOR_COUNTS[:2] if quick else VECTOR_COUNTS
        progress(f"vector: vector_env at K = {list(counts)} against the raw floor of both layouts")
        results["rows"] += bench_vector(budget, counts)
    if "torchrl" in sections:
        counts = (4,) if quick else TORCHRL_COUNTS
        progress(f"torchrl: SyncDataCollector, one env and K = {list(counts)} natively batched")
        results["rows"] += bench_torchrl(budget, counts)
    results["targets"] = evaluate_targets(results)
    results["machine"]["load_average_end"] = list(os.getloadavg())
    results["wall_seconds"] = time.time() - started
    return results


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.run", description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="few steps, one repeat: a smoke test, not a measurement")
    parser.add_argument("--json", default=DEFAULT_JSON, metavar="PATH", help=f"write the results here ({DEFAULT_JSON})")
    parser.add_argument("--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS), metavar="SECTION",
                        help=f"run only these sections, of {list(SECTIONS)}")
    args = parser.parse_args(argv)
    results = run(quick=args.quick, sections=args.sections, progress=lambda text: print(text, file=sys.stderr, flush=True))
    print(format_tables(results))
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(results, indent=2) + "\n", encoding="utf-8")
    print(f"\nwrote {path} ({results['wall_seconds']:.0f} s, load average {results['machine']['load_average_start'][0]:.2f} "
          f"at start on {results['machine']['cpu_count']} CPUs)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
