"""Metrics tables never hide a fault: faults of one kind count together, with an example reason."""

from __future__ import annotations

import pytest

from ee_formation_env.baselines.metrics import fault_kind, fault_kinds, fault_notes


def test_fault_kind_masks_numbers_but_keeps_the_arm():
    assert (fault_kind("arm_12: joint speed 50.9 rad/s exceeds max_joint_velocity 50.0 rad/s")
            == "arm_12: joint speed # rad/s exceeds max_joint_velocity # rad/s")
    assert fault_kind("arm_0: joint speed at least 1e+03 rad/s") == "arm_0: joint speed at least # rad/s"


def test_fault_kinds_group_and_rank():
    reasons = {"arm_0: joint speed 50.1 rad/s exceeds max_joint_velocity 50.0 rad/s": 1,
               "arm_0: joint speed 50.9 rad/s exceeds max_joint_velocity 50.0 rad/s": 2,
               "arm_1: non-finite joint state": 1}
    assert fault_kinds(reasons) == [("arm_0: joint speed 50.9 rad/s exceeds max_joint_velocity 50.0 rad/s", 3),
                                    ("arm_1: non-finite joint state", 1)]


def test_fault_notes_name_every_faulted_policy_only():
    rows = {"gradient": {"episodes": 10, "physics_faults": 0, "physics_fault_reasons": {}},
            "random": {"episodes": 10, "physics_faults": 3,
                       "physics_fault_reasons": {"arm_2: joint speed 51.0 rad/s exceeds max_joint_velocity 50.0 rad/s": 3}}}
    (note,) = fault_notes(rows)
    assert note == ("- random: 3 of 10 episodes ended in a physics fault: arm_2: joint speed 51.0 rad/s exceeds "
                    "max_joint_velocity 50.0 rad/s (3x)")


def test_run_episode_refuses_a_wrapper_whose_step_it_would_bypass():
    import ee_formation_env
    from ee_formation_env.baselines import make_policies
    from ee_formation_env.baselines.metrics import run_episode
    from pettingzoo.utils.wrappers import BaseParallelWrapper

    env = ee_formation_env.parallel_env("planar_square", episode_seconds=0.05)
    try:
        with pytest.raises(TypeError, match=r"^env: expected the parallel env"):
            run_episode(BaseParallelWrapper(env), make_policies("zero", env), seed=0)
    finally:
        env.close()


# ------------------------------------------------------------------------------------------ precision metrics
import math  # noqa: E402

import numpy as np  # noqa: E402

import ee_formation_env  # noqa: E402
from ee_formation_env.baselines import make_policies  # noqa: E402
from ee_formation_env.baselines.metrics import (PRECISION_TOLERANCE, edge_length_errors, run_episode,  # noqa: E402
                                                run_episodes, summarize)


def test_edge_length_errors_are_metres_of_edge_length():
    with ee_formation_env.parallel_env("planar_square") as distance, \
            ee_formation_env.parallel_env("planar_square_displacement") as displacement:
        d = np.linalg.norm(distance.task.formation.desired_vectors, axis=1)
        # every edge 2 mm long: e = (d + 0.002)^2 - d^2
        assert np.allclose(edge_length_errors(distance.task, (d + 0.002) ** 2 - d**2), 0.002, atol=1e-12)
        assert np.allclose(edge_length_errors(distance.task, (d - 0.003) ** 2 - d**2), 0.003, atol=1e-12)
        z_error = np.zeros((len(d), 2))
        z_error[:, 0], z_error[:, 1] = 0.003, 0.004
        assert np.allclose(edge_length_errors(displacement.task, z_error), 0.005)


def test_a_law_reaches_the_1mm_band_after_the_1cm_band_and_holds_it():
    (metrics,) = run_episodes("planar_square", "gradient", [70_000], overrides={"episode_seconds": 5.0})
    assert metrics.success and metrics.success_1mm
    assert metrics.settling_time < metrics.settling_time_1mm < 5.0 - 1.0
    assert metrics.steady_worst_edge_error < PRECISION_TOLERANCE
    assert 0 < metrics.steady_rms_edge_error <= metrics.steady_worst_edge_error
    assert math.isfinite(metrics.torque_rate) and metrics.torque_rate > 0
    summary = summarize([metrics])
    assert summary["success_rate_1mm"] == 1.0 and summary["settling_time_1mm"] == metrics.settling_time_1mm


def test_a_policy_parked_off_the_shape_is_no_1mm_success_and_its_steady_error_says_how_far():
    (metrics,) = run_episodes("planar_square", "zero", [70_000], overrides={"episode_seconds": 2.0})
    assert not metrics.success_1mm and math.isnan(metrics.settling_time_1mm)
    assert metrics.steady_worst_edge_error > 0.1 and metrics.torque_rate == 0.0


def test_the_one_episode_loop_and_the_batched_one_agree_on_the_precision_metrics():
    with ee_formation_env.parallel_env("spatial_tetrahedron", episode_seconds=3.0) as env:
        alone = run_episode(env, make_policies("adaptive_jacobian", env), seed=70_001)
    (batched,) = run_episodes("spatial_tetrahedron", "adaptive_jacobian", [70_001], overrides={"episode_seconds": 3.0})
    for name in ("success_1mm", "settling_time_1mm", "steady_rms_edge_error", "steady_worst_edge_error",
                 "torque_rate"):
        assert getattr(alone, name) == getattr(batched, name) or (
            math.isnan(getattr(alone, name)) and math.isnan(getattr(batched, name))), name


def test_stopping_on_the_precision_hold_ends_each_episode_one_hold_after_its_band_and_changes_nothing_before():
    seeds = [70_002, 70_003]
    full = run_episodes("planar_square", "gradient", seeds, overrides={"episode_seconds": 6.0})
    stopped = run_episodes("planar_square", "gradient", seeds, overrides={"episode_seconds": 6.0},
                           stop_on_precision_hold=True)
    for a, b in zip(full, stopped):
        assert b.success_1mm and b.settling_time_1mm == a.settling_time_1mm and b.settling_time == a.settling_time
        assert b.sim_time == pytest.approx(a.settling_time_1mm + 1.0, abs=0.011) and b.sim_time < a.sim_time
        assert b.control_energy < a.control_energy
