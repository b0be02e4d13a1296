"""One definition of success and settling: ``metrics.settle``, used by ``run_episode`` and by every study."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import ee_formation_env
from ee_formation_env.baselines import make_policies
from ee_formation_env.baselines.metrics import DEFAULT_HOLD_SECONDS, formation_tolerance, run_episode, settle
from ee_formation_env.reward import DEFAULT_POSITION_TOLERANCE
from studies import random_scenarios, robustness
from studies._common import LAWS

STUDIES = Path(__file__).resolve().parents[2] / "studies"


def _same(a: float, b: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or a == b


def test_settle_is_the_documented_rule():
    dt = 0.1
    # Below the tolerance (1.0) from sample 3 on: settling index 3, time 0.3 s, held 0.7 s.
    errors = [5.0, 2.0, 1.0, 0.5, 0.4, 0.3, 0.2, 0.1, 0.1, 0.1]
    assert settle(errors, 1.0, dt, hold_seconds=0.5) == (True, pytest.approx(0.3))
    assert settle(errors, 1.0, dt, hold_seconds=0.8) == (False, pytest.approx(0.3))  # settled, not held long enough
    assert settle(errors[:3], 1.0, dt, hold_seconds=0.0)[0] is False  # the last sample is not below: never settled
    assert math.isnan(settle(errors[:3], 1.0, dt)[1])
    success, time = settle(errors, 1.0, dt, hold_seconds=0.0, faulted=True)
    assert success is False and math.isnan(time)
    assert settle([0.5, math.nan, 0.5], 1.0, dt, hold_seconds=0.0) == (True, pytest.approx(0.2))  # NaN is not below
    assert settle([0.1] * 20, 1.0, dt) == (True, 0.0)  # in formation from the first step, held 2 s >= 1 s
    assert DEFAULT_HOLD_SECONDS == 1.0


def test_the_tolerance_is_the_rewards_one_centimetre():
    assert DEFAULT_POSITION_TOLERANCE == 0.01  # m
    with ee_formation_env.parallel_env("planar_square") as env:
        lengths = np.linalg.norm(env.formation.desired_vectors, axis=1)
        # Distance formation: e_k ~ 2 d_k delta, so the threshold is 2 delta rms(d_k) (m^2).
        assert formation_tolerance(env) == pytest.approx(2 * 0.01 * np.sqrt(np.mean(lengths**2)))


def test_run_episode_scores_with_settle():
    with ee_formation_env.parallel_env("planar_square", episode_seconds=6.0, initial_q_noise=0.0) as env:
        metrics = run_episode(env, make_policies("gradient", env), seed=0, record=True)
        errors = metrics.trajectory["formation_error"][1:]  # after each step (sample 0 is the reset)
        assert (metrics.success, metrics.settling_time) == settle(errors, formation_tolerance(env),
                                                                  env.scenario.control_dt, DEFAULT_HOLD_SECONDS,
                                                                  faulted=bool(metrics.physics_fault))
        assert metrics.success  # the rule is exercised on a success, not only on NaNs


def test_on_transition_sees_each_step_and_can_stop_early():
    seen = []

    def watch(env, step):
        seen.append((step.index, set(step.actions), set(step.infos)))
        return step.index == 7

    with ee_formation_env.parallel_env("planar_square", episode_seconds=2.0) as env:
        metrics = run_episode(env, make_policies("zero", env), seed=0, on_transition=watch)
        agents = set(env.possible_agents)
        assert [index for index, _, _ in seen] == list(range(1, 8))
        assert all(actions == infos == agents for _, actions, infos in seen)
        assert metrics.sim_time == pytest.approx(7 * env.scenario.control_dt)


def test_random_scenarios_give_run_episodes_success_and_settling():
    scenario = random_scenarios.planar_scenario(9)
    record = random_scenarios.run_one(scenario, "planar", "gradient")
    with ee_formation_env.parallel_env(scenario) as env:
        metrics = run_episode(env, make_policies("gradient", env), seed=0)
    assert record.success == metrics.success and record.success  # this scenario settles within its horizon
    assert _same(record.settling_time, metrics.settling_time)
    assert record.contact_steps == metrics.contact_steps
    assert record.min_singularity_margin == metrics.min_singularity_margin


def test_robustness_spatial_runs_give_run_episodes_success_and_settling():
    row = robustness.spatial_run("law-I", 2.0, {"length": 0.2, "mass": 0.0, "seed": 0})
    with ee_formation_env.parallel_env("spatial_tetrahedron", episode_seconds=2.0, initial_q_noise=0.0,
                                       model_mismatch={"length": 0.2, "mass": 0.0, "seed": 0}) as env:
        metrics = run_episode(env, make_policies(LAWS["law-I"], env), seed=0)
    assert row["success"] == metrics.success
    assert _same(row["settling_time"], metrics.settling_time)
    assert row["fault"] == metrics.physics_fault


@pytest.mark.parametrize("name", ["random_scenarios", "robustness", "reproduce"])
def test_no_study_scores_or_loops_episodes_itself(name):
    """Scoring and the loop live in metrics; figure copying and the link length in their one home."""
    source = (STUDIES / f"{name}.py").read_text(encoding="utf-8")
    for marker in ("EDGE_TOLERANCE", "settle_index", "while env.agents", "env.step(", "shutil.copy", "= 1.5"):
        assert marker not in source, (name, marker)
