"""The laws' tuned gains under the perturbations of the robustness and sensing studies, beside their defaults.

    python -m studies.tuned_perturbations [--out results/tuned_perturbations] [--scenario S] [--quick]

A tuned set is fast on the problem it was tuned on; this checks that it keeps its success where the defaults
are known to (or not to) hold. Each built-in with tuned gains of :data:`SCENARIOS` runs every tuned law and the
same law at its defaults, on the same seeds (:data:`SEEDS`, the sensing study's), episodes of the scenario's
length up to :data:`EPISODE_SECONDS`, under:

- the sensing study's knobs (``studies.sensing.LEVELS``: noise, delay, bias, yaw), each at its every level, on
  the planar squares (the sensing study's scenarios);
- the robustness study's model mismatch of the 7-DOF arms (``studies.robustness.SPATIAL_KINDS`` at
  ``SPATIAL_SIZES``; mismatch seed 0) on ``spatial_tetrahedron``.

Writes ``perturbations.json`` (one record per case) and a table; every case where the tuned set succeeds less
often than the defaults is listed after it (:func:`losses`): the docs report them.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ee_formation_env.baselines.metrics import run_episodes
from ee_formation_env.baselines.reference.tuned import load_tuned, read_tuned_file, tuned_path
from ee_formation_env.scenario import load_scenario
from studies.robustness import SPATIAL_KINDS, SPATIAL_SIZES
from studies.sensing import LEVELS, SEEDS, sensing_of

SCENARIOS = {"planar_square": "sensing", "planar_square_displacement": "sensing", "spatial_tetrahedron": "mismatch"}
QUICK_SECONDS = 2.0
EPISODE_SECONDS = 20.0  # s: every law settles within a few seconds here; the 50 s spatial episodes only hold


def perturbations(kind: str, n_agents: int) -> list[tuple[str, float, dict[str, Any]]]:
    """(knob, level, scenario overrides) of one family of perturbations (module docstring)."""
    if kind == "sensing":
        return [(knob, level, {"sensing": sensing_of(knob, level, n_agents)})
                for knob, levels in LEVELS.items() for level in levels]
    return [(mismatch, size, {"model_mismatch": {"length": size if mismatch in ("length", "both") else 0.0,
                                                 "mass": size if mismatch in ("mass", "both") else 0.0, "seed": 0}})
            for mismatch in SPATIAL_KINDS for size in SPATIAL_SIZES]


def tuned_laws(scenario: str) -> list[str]:
    if not tuned_path(scenario).is_file():
        return []
    return [law for law in read_tuned_file(tuned_path(scenario))["laws"]
            if load_tuned(scenario, law).record.get("improved")]


def run(quick: bool = False, scenarios: Sequence[str] | None = None) -> list[dict[str, Any]]:
    """Every case of ``scenarios`` (default: all of :data:`SCENARIOS`) for each law tuned there."""
    records = []
    for scenario in scenarios or SCENARIOS:
        kind = SCENARIOS[scenario]
        data = load_scenario(scenario)
        seconds = QUICK_SECONDS if quick else min(data.episode_seconds, EPISODE_SECONDS)
        cases = perturbations(kind, data.n_agents)[:1 if quick else None]
        for law in tuned_laws(scenario):
            for knob, level, overrides in cases:
                row = {"scenario": scenario, "law": law, "knob": knob, "level": level}
                for gains in ("default", "tuned"):
                    episodes = run_episodes(scenario, law, SEEDS[:1 if quick else None],
                                            overrides={"episode_seconds": seconds, **overrides},
                                            policy_kwargs={} if gains == "default" else {"gains": "tuned"})
                    row[gains] = {"success": float(np.mean([e.success for e in episodes])),
                                  "faults": sum(bool(e.physics_fault) for e in episodes),
                                  "steady_worst_edge_error": float(max(e.steady_worst_edge_error for e in episodes))}
                records.append(row)
                print(f"{scenario} / {law} / {knob} {level}: success default {row['default']['success']:.0%}, "
                      f"tuned {row['tuned']['success']:.0%}", flush=True)
    return records


def losses(records: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The cases where the tuned set succeeds less often than the defaults."""
    return [r for r in records if r["tuned"]["success"] < r["default"]["success"]]


def table(records: Sequence[dict[str, Any]]) -> str:
    lines = ["| scenario | law | perturbation | success, default | success, tuned | worst edge, default (m) | "
             "worst edge, tuned (m) |", "|---|---|---|---:|---:|---:|---:|"]
    for r in records:
        lines.append(f"| {r['scenario']} | {r['law']} | {r['knob']} {r['level']:g} | {r['default']['success']:.0%} | "
                     f"{r['tuned']['success']:.0%} | {r['default']['steady_worst_edge_error']:.1e} | "
                     f"{r['tuned']['steady_worst_edge_error']:.1e} |")
    lost = losses(records)
    lines += ["", f"The tuned set loses success in {len(lost)} of {len(records)} cases"
              + (": " + "; ".join(f"{r['scenario']} / {r['law']} / {r['knob']} {r['level']:g}" for r in lost)
                 if lost else ".")]
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(prog="python -m studies.tuned_perturbations", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("results/tuned_perturbations"), help="output folder")
    parser.add_argument("--quick", action="store_true", help="one case per family, one seed, 2 s episodes (tests)")
    parser.add_argument("--scenario", action="append", choices=list(SCENARIOS),
                        help="a scenario of the study (repeatable; default: all)")
    args = parser.parse_args(argv)
    records = run(args.quick, args.scenario)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "perturbations.json").write_text(json.dumps(records, indent=1), encoding="utf-8")
    (args.out / "perturbations.md").write_text(table(records), encoding="utf-8")
    print(table(records))
    return records


if __name__ == "__main__":
    main()
