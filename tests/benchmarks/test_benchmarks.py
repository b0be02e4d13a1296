"""Smoke test of ``python -m benchmarks.run --quick``: every section runs and lands in the JSON.

No timing is asserted here: speed targets are checked by the benchmark itself (its ``targets`` table),
never by the test suite, whose machines vary.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

import ee_formation_env
from ee_formation_env.formation import required_rigidity_rank

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))  # benchmarks/ is a top-level folder of the repository, not an installed package

from benchmarks.run import ARM_COUNTS, SECTIONS  # noqa: E402
from ee_formation_env.generators import planar_ring, spatial_ring, trilateration_edges  # noqa: E402


def test_quick_benchmark_writes_every_section(tmp_path: Path) -> None:
    path = tmp_path / "bench.json"
    run = subprocess.run([sys.executable, "-m", "benchmarks.run", "--quick", "--json", str(path)], cwd=REPO,
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "| target |" in run.stdout and "x raw floor" in run.stdout  # the markdown tables

    results = json.loads(path.read_text())
    assert results["quick"] is True and results["sections"] == list(SECTIONS)
    rows = results["rows"]
    for section in SECTIONS:
        assert any(row["section"] == section for row in rows), section
    for row in rows:
        if row.get("skipped"):
            continue
        if row["section"] == "reset":
            assert row["reset_ms"] > 0
            continue
        if row["section"] == "sb3_training":  # train.py's default run, updates included
            assert row["mode"] == "residual"
            assert row["agent_steps_per_s"] == pytest.approx(row["agent_steps"] / min(row["seconds"]), rel=1e-12)
            continue
        for key in ("physics_steps_per_s", "env_steps_per_s", "real_time_factor", "ratio_to_raw"):
            assert math.isfinite(row[key]) and row[key] > 0, (row["case"], key)
    raw = [row for row in rows if row["section"] == "raw_floor" and "stepSimulation" in row["case"]]
    assert {row["scenario"] for row in raw} == {"planar_square", "spatial_tetrahedron"}
    # Every other timed row: its physics rate from its own best repeat, and ratio_to_raw = that rate over the
    # raw floor of the same bodies measured in the same run (the scaling rows carry their own floor).
    raw_rate = {row["scenario"]: row["physics_steps_per_s"] for row in raw}
    timed = [row for row in rows if not row.get("skipped") and row["section"] not in ("reset", "sb3_training")
             and row not in raw]
    assert {row["section"] for row in timed} >= {"raw_floor", "env_step", "closed_loop", "scaling"}
    for row in timed:
        assert row["best_seconds"] == pytest.approx(min(row["seconds"]), abs=1e-6), row["case"]
        assert row["physics_steps_per_s"] == pytest.approx(
            row["env_steps"] * row["frame_skip"] / row["best_seconds"], rel=1e-12), row["case"]
        floor = (row["raw_physics_steps_per_s"] if row["section"] in ("scaling", "vector", "torchrl")
                 else raw_rate[row["scenario"]])
        assert row["ratio_to_raw"] == pytest.approx(row["physics_steps_per_s"] / floor, rel=1e-12), row["case"]
    env_steps = {(row["scenario"], row["frame_skip"]) for row in rows if row["section"] == "env_step"}
    assert env_steps == {("planar_square", 1), ("planar_square", 10), ("spatial_tetrahedron", 1),
                         ("spatial_tetrahedron", 5)}
    scaling = [row for row in rows if row["section"] == "scaling"]
    assert sorted((row["dof"], row["n_arms"]) for row in scaling) == sorted(
        (dof, n) for dof in (2, 7) for n in ARM_COUNTS)
    assert set(results["scaling_fits"]) == {row["family"] for row in scaling}
    # The batched env at K = 1 and 4 (--quick), each against the faster raw floor of the same K formations in
    # the two layouts measured beside it, with memory per formation in each layout.
    vector = [row for row in rows if row["section"] == "vector"]
    assert {(row["scenario"], row["num_envs"], row["layout"]) for row in vector} == {
        (scenario, k, layout) for scenario in ("planar_square", "spatial_tetrahedron") for k in (1, 4)
        for layout in ("vector_env", "clients", "clients_reads", "clients_free", "clients_substeps",
                       "clients_substeps_reads", "one_client")}
    for row in vector:
        floors = (row["floor_clients_physics_steps_per_s"], row["floor_one_client_physics_steps_per_s"],
                  row["floor_clients_substeps_physics_steps_per_s"])
        assert row["raw_physics_steps_per_s"] == max(floors) and row["rss_mb_per_formation"] > 0, row["case"]
        assert row["floor_clients_reads_physics_steps_per_s"] > 0, row["case"]
    assert "| batched env |" in run.stdout
    # TorchRL collection (skipped without the torchrl extra): the PettingZooWrapper (K = 1) and the native
    # batched env at K = 4 (--quick), each beside the raw floor of the same K formations.
    torchrl_rows = [row for row in rows if row["section"] == "torchrl" and not row.get("skipped")]
    if torchrl_rows:
        assert {(row["num_envs"], row["batched"], row["layout"]) for row in torchrl_rows} == {
            (1, False, "floor"), (1, False, "collector"), (4, True, "floor"), (4, True, "collector"),
            (4, True, "vector_env")}
    assert {target["target"] for target in results["targets"]} >= {
        "env.step frame_skip 1 / raw floor, planar_square", "env.step frame_skip 1 / raw floor, spatial_tetrahedron",
        "closed loop planar_square: wall s per 30 s simulated", "reset, 4 arms (planar_square)"}
    assert all(isinstance(target["met"], bool) for target in results["targets"])


@pytest.mark.parametrize("builder, dim", [(planar_ring, 2), (spatial_ring, 3)])
@pytest.mark.parametrize("n_agents", [2, 3, 5, 16])
def test_ring_scenarios_are_valid_and_minimally_rigid(builder, dim, n_agents) -> None:
    data = builder(n_agents)
    assert data["edges"] == trilateration_edges(n_agents, dim)
    assert len(data["edges"]) == required_rigidity_rank(n_agents, dim)  # minimal: one edge per constraint
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # "rigid but not minimally rigid" would be a warning
        env = ee_formation_env.parallel_env(data)
    try:
        _, infos = env.reset(seed=0)
        assert env.scenario.dim == dim and len(env.possible_agents) == n_agents
        assert min(info["singularity_margin"] for info in infos.values()) > env.scenario.singularity_threshold
    finally:
        env.close()
