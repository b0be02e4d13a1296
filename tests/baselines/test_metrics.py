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
