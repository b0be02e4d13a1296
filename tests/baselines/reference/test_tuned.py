"""Tuned gains (baselines/reference/tuned.py): named, disjoint seeds; the search point of the defaults is the
defaults; every tuned file verified before use; opt-in only."""

from __future__ import annotations

import json

import numpy as np
import pytest

import ee_formation_env
from ee_formation_env.baselines import make_policies
from ee_formation_env.baselines.learned.training_env import EVAL_SEED_OFFSET
from ee_formation_env.baselines.reference import tuned
from ee_formation_env.baselines.reference.gains import default_gains
from ee_formation_env.builtin import builtin_scenario
from ee_formation_env.scenario_sets import HELD_OUT_SEED_OFFSET, TEST_SEEDS, TRAIN_SEEDS
from studies.scoreboard_methods import DEFAULT_EPISODES
from conftest import write_tuned_file
from studies.tune_gains import default_point, gravity_loads_joints


def test_tuning_evaluation_and_unseen_check_seeds_never_meet():
    board_eval = set(range(EVAL_SEED_OFFSET, EVAL_SEED_OFFSET + max(DEFAULT_EPISODES, len(TEST_SEEDS))))
    named = {"tuning": set(tuned.TUNING_SEEDS), "distribution tuning": set(tuned.DISTRIBUTION_TUNING_SEEDS),
             "unseen check": set(tuned.UNSEEN_CHECK_SEEDS), "board evaluation": board_eval | set(TEST_SEEDS),
             "distribution train set": set(TRAIN_SEEDS)}
    for a, seeds_a in named.items():
        for b, seeds_b in named.items():
            if a < b:
                assert not seeds_a & seeds_b, f"{a} and {b} seeds meet"
    # a distribution's tuning draws are training draws: below the held-out offset
    assert max(tuned.DISTRIBUTION_TUNING_SEEDS) < HELD_OUT_SEED_OFFSET
    assert len(tuned.TUNING_SEEDS) == 100 and len(tuned.UNSEEN_CHECK_SEEDS) == 50


@pytest.mark.parametrize("scenario, law", [("planar_square", "gradient"), ("spatial_tetrahedron", "adaptive_jacobian"),
                                           ("planar_random", "approx_jacobian")])
def test_the_point_of_the_default_gains_gives_the_default_gains(scenario, law):
    """The tuner's first trial is the law at its defaults, exactly."""
    point = default_point(law, gravity_loads_joints(scenario), scenario)
    with ee_formation_env.parallel_env(scenario) as env:
        env.reset(seed=5000)
        for index in range(env.task.n_agents):
            mine, theirs = tuned.gains_from_point(env.task, index, point), default_gains(env.task, index)
            for name in ("kp", "kd", "ki", "alpha", "adaptation_gain", "rate_gain", "spring_force"):
                if name == "ki" and law == "gradient":
                    continue  # law I reads no K_I
                assert np.allclose(np.asarray(getattr(mine, name), dtype=float),
                                   np.asarray(getattr(theirs, name), dtype=float), rtol=1e-12), name


def _write(folder, scenario="planar_square", **changes):
    point = {"kp_scale": 2.0, "kd_scale": 0.5, "saturated": True, "spring_scale": 3.0, "rate_steps": 1.0}
    laws = changes.pop("laws", {"gradient": {"point": point}})
    return write_tuned_file(folder, scenario, laws, **changes)


def test_tuned_gains_are_the_files_point_on_the_env_and_opt_in(tmp_path, monkeypatch):
    monkeypatch.setattr(tuned, "TUNED_DIR", tmp_path)
    _write(tmp_path)
    with ee_formation_env.parallel_env("planar_square") as env:
        default = make_policies("gradient", env)
        policies = make_policies("gradient", env, gains="tuned")
        for index, (agent, policy) in enumerate(policies.items()):
            expected = tuned.gains_from_point(env.task, index, tuned.load_tuned("planar_square", "gradient").point)
            assert policy.gains == expected.validated(env.task.models[index].n_joints)
            assert policy.gains.kp == 2.0 * default[agent].gains.kp and policy.gains.rate_gain > 0
            assert np.all(np.isfinite(policy.gains.spring_force))


@pytest.mark.parametrize("changes, field", [
    ({"schema": 99}, "schema"),
    ({"scenario_digest": "0" * 64}, "scenario_digest"),
    ({"laws": {"gradient": {"point": {"kp_scale": 2.0}}}}, "laws.gradient.point"),
    ({"laws": {"gradient": {"point": {"kp_scale": 1e6, "kd_scale": 1.0, "saturated": True, "spring_scale": 1.0,
                                       "rate_steps": 0.0}}}}, "laws.gradient.point.kp_scale"),
    ({"laws": {"gradient": {"point": {"kp_scale": 1.0, "kd_scale": 1.0, "saturated": "yes", "spring_scale": 1.0,
                                       "rate_steps": 0.0}}}}, "laws.gradient.point.saturated"),
    ({"laws": {"pid": {"point": {}}}}, "laws.pid"),
])
def test_a_bad_or_stale_tuned_file_is_refused_naming_the_file_and_field(tmp_path, monkeypatch, changes, field):
    monkeypatch.setattr(tuned, "TUNED_DIR", tmp_path)
    path = _write(tmp_path, **changes)
    with ee_formation_env.parallel_env("planar_square") as env:
        with pytest.raises(ValueError, match=f"{path}: {field}"):
            make_policies("gradient", env, gains="tuned")


def test_tuned_gains_are_refused_where_they_were_not_tuned(tmp_path, monkeypatch):
    monkeypatch.setattr(tuned, "TUNED_DIR", tmp_path)
    _write(tmp_path)
    with ee_formation_env.parallel_env("planar_square", torque_limits=40.0) as env:  # other physics
        with pytest.raises(ValueError, match="with its own physics"):
            make_policies("gradient", env, gains="tuned")
    with ee_formation_env.parallel_env("planar_square", episode_seconds=3.0, initial_q_noise=0.2) as env:
        make_policies("gradient", env, gains="tuned")  # gain-neutral changes keep them
        with pytest.raises(ValueError, match="no tuned gains for 'adaptive_jacobian'"):
            make_policies("adaptive_jacobian", env, gains="tuned")
        with pytest.raises(ValueError, match="'tuned'"):
            make_policies("gradient", env, gains="best")
    data = builtin_scenario("planar_square")
    data["name"] = "my_square"
    with ee_formation_env.parallel_env(data) as env:
        with pytest.raises(ValueError, match="built-in scenarios only"):
            make_policies("gradient", env, gains="tuned")
    with ee_formation_env.parallel_env("planar_square_rotated") as env:
        with pytest.raises(ValueError, match="no tuned gains for 'planar_square_rotated'"):
            make_policies("gradient", env, gains="tuned")


def test_every_committed_tuned_file_reads_and_matches_its_builtin():
    files = sorted(tuned.TUNED_DIR.glob("*.json"))
    for path in files:
        data = tuned.read_tuned_file(path)
        assert data["scenario"] == path.stem
        for law in data["laws"]:
            tuned.load_tuned(path.stem, law)
