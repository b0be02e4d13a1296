"""The random-scenario generator of ``python -m studies.random_scenarios``: valid scenarios, deterministic."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

import ee_formation_env
from ee_formation_env.formation import required_rigidity_rank

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))  # studies/ is a top-level folder of the repository, not an installed package

from ee_formation_env.baselines.metrics import formation_tolerance  # noqa: E402
from ee_formation_env.reward import DEFAULT_POSITION_TOLERANCE  # noqa: E402
from studies._common import max_edge_length_error  # noqa: E402
from studies.random_scenarios import planar_scenario, spatial_scenario  # noqa: E402


@pytest.mark.parametrize("seed", range(4))
def test_planar_scenarios_are_valid_and_match_the_recipe(seed):
    scenario = planar_scenario(seed)
    assert 3 <= len(scenario["arms"]) <= 6
    assert len(scenario["edges"]) == required_rigidity_rank(len(scenario["arms"]), 2)  # minimally rigid
    for arm, target in zip(scenario["arms"], scenario["shape"]):
        base = np.array(arm["base_position"][:2])
        assert 4.0 <= np.linalg.norm(base) <= 6.0
        assert 0.4 <= abs(arm["initial_q"][1]) <= math.pi - 0.4  # elbow away from its singularities
        assert 0.8 - 1e-9 <= np.linalg.norm(np.array(target) - base) <= 2.6 + 1e-9  # inside its own reach (3 m)
    with ee_formation_env.parallel_env(scenario) as env:  # the env's own validation accepts it
        _, infos = env.reset(seed=0)
        assert max_edge_length_error(env) > DEFAULT_POSITION_TOLERANCE  # not already in formation
        assert next(iter(infos.values()))["formation_error"] > formation_tolerance(env)  # nor by success's measure


@pytest.mark.parametrize("seed", range(2))
def test_spatial_scenarios_are_valid_and_start_without_contact(seed):
    scenario = spatial_scenario(seed)
    assert 3 <= len(scenario["arms"]) <= 4
    with ee_formation_env.parallel_env(scenario) as env:
        observations, _ = env.reset(seed=0)
        _, _, _, _, infos = env.step({agent: np.zeros(env.action_space(agent).shape, np.float32)
                                      for agent in env.agents})
        assert all(info["contacts"] == 0 for info in infos.values())
        assert not any(info["physics_fault"] for info in infos.values())


def test_generators_are_deterministic_and_seed_dependent():
    assert planar_scenario(3) == planar_scenario(3)
    assert spatial_scenario(1) == spatial_scenario(1)
    assert planar_scenario(3) != planar_scenario(4)
    assert spatial_scenario(1) != spatial_scenario(2)


def test_failure_kinds_tell_a_plateau_from_a_slow_weak_mode():
    from studies.random_scenarios import EQUILIBRIUM_RATIO, PLATEAU_DROP, SINGULAR_MARGIN, RunRecord

    def record(**changes):
        fields = dict(family="planar", scenario="s", n_agents=6, robots="r", policy="gradient", success=False,
                      settling_time=math.nan, final_max_edge_error=0.05, physics_fault="", contact_steps=0,
                      min_singularity_margin=0.1, final_singularity_margin=0.1, final_gradient_ratio=0.5,
                      final_max_joint_speed=0.0, wall_s=1.0, final_error_trend=-0.5, final_rigidity_ratio=0.01)
        fields.update(changes)
        return RunRecord(**fields).failure_kind

    assert record(success=True) == ""
    assert record(physics_fault="boom") == "physics fault"
    assert "singularity" in record(final_singularity_margin=0.5 * SINGULAR_MARGIN)
    assert "jammed" in record(final_contact=True, final_singularity_margin=0.5 * SINGULAR_MARGIN)
    assert record().startswith("still converging")
    small = 0.5 * EQUILIBRIUM_RATIO
    assert "undesired equilibrium" in record(final_gradient_ratio=small, final_error_trend=-0.5 * PLATEAU_DROP)
    assert "undesired equilibrium" in record(final_gradient_ratio=small, final_error_trend=0.2)
    assert "weak mode" in record(final_gradient_ratio=small, final_error_trend=-2 * PLATEAU_DROP)
