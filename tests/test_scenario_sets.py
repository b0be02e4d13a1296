"""Held-out scenario sets: every test scenario is a valid problem for the team of its training scenario."""

from __future__ import annotations

import numpy as np
import pytest

from ee_formation_env import parallel_env
from ee_formation_env.builtin import BUILTIN_SCENARIOS, builtin_scenario
from ee_formation_env.scenario_sets import TEST_SETS, held_out_scenarios


@pytest.mark.parametrize("train", sorted(TEST_SETS))
def test_test_scenarios_share_the_training_teams_spaces(closer, train):
    assert train in BUILTIN_SCENARIOS
    trained = closer(parallel_env(train))
    scenarios = held_out_scenarios(train)
    assert len(scenarios) == 4
    for name, scenario in scenarios.items():
        assert scenario["name"] == name
        env = closer(parallel_env(scenario))  # validated: reachable, rigid, away from singularities
        for agent in trained.possible_agents:
            assert env.observation_space(agent) == trained.observation_space(agent), (name, agent)
            assert env.action_space(agent) == trained.action_space(agent), (name, agent)


def test_planar_square_test_shapes_are_the_stated_sizes():
    scenarios = held_out_scenarios("planar_square")
    for name, (width, height) in {"planar_square_3.5m": (3.5, 3.5), "planar_square_4.0m": (4.0, 4.0),
                                  "planar_square_rect_2.5x3.5m": (2.5, 3.5)}.items():
        shape = np.array(scenarios[name]["shape"])
        assert np.allclose(shape.max(axis=0) - shape.min(axis=0), [width, height]), name
        assert np.allclose(shape.mean(axis=0), [3.0, 3.0]), name


def test_the_rotated_test_scenario_is_the_builtin_rotated_square():
    rotated = held_out_scenarios("planar_square")["planar_square_rotated"]
    assert rotated == builtin_scenario("planar_square_rotated") | {"name": "planar_square_rotated"}


def test_fresh_copies_each_call():
    first = held_out_scenarios("planar_square")
    first["planar_square_3.5m"]["shape"][0][0] = 99.0
    assert held_out_scenarios("planar_square")["planar_square_3.5m"]["shape"][0][0] != 99.0


def test_a_scenario_without_a_test_set_has_none_and_a_bad_name_type_is_refused():
    assert held_out_scenarios("spatial_tetrahedron") == {}
    with pytest.raises(TypeError, match="train: expected a built-in scenario name"):
        held_out_scenarios(["planar_square"])


def test_random_families_are_seeded_and_the_random_studys_own():
    from ee_formation_env.scenario_sets import RANDOM_FAMILIES
    from studies import random_scenarios

    assert random_scenarios.planar_scenario is RANDOM_FAMILIES["planar"]
    assert random_scenarios.spatial_scenario is RANDOM_FAMILIES["spatial"]
    assert RANDOM_FAMILIES["planar"](5) == RANDOM_FAMILIES["planar"](5) != RANDOM_FAMILIES["planar"](6)


def test_every_held_out_seed_starts_at_the_one_offset():
    """The env core defines the held-out seed offset; the learning wing's evaluation and the distributions'
    test sets start there, and no train draw reaches it."""
    from ee_formation_env.baselines.learned.training_env import EVAL_SEED_OFFSET
    from ee_formation_env.scenario_sets import HELD_OUT_SEED_OFFSET, TEST_SEEDS, TRAIN_SEEDS

    assert EVAL_SEED_OFFSET == HELD_OUT_SEED_OFFSET == TEST_SEEDS[0] == 10_000
    assert max(TRAIN_SEEDS) < HELD_OUT_SEED_OFFSET
