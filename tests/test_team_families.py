"""The team-size families: every N gives a valid distribution whose test draws validate, refusals name the field."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ee_formation_env.env import FormationEnv
from ee_formation_env.formation import required_rigidity_rank, rigidity_matrix
from ee_formation_env.team_families import (TEAM_FAMILIES, ring_chord_edges, ring_growth, team_scenario,
                                             team_test_draws)

CASES = [(family, n) for family, (low, high) in TEAM_FAMILIES.items() for n in range(low, high + 1)]


@pytest.mark.parametrize("family, n_agents", CASES)
def test_every_team_size_draws_valid_test_problems(family, n_agents):
    draws = team_test_draws(family, n_agents, seeds=(10_000, 10_001))
    dim = 2 if family == "planar_team" else 3
    assert sorted(draws) == [10_000, 10_001]
    for scenario in draws.values():
        assert scenario.n_agents == n_agents and not scenario.distribution.active
        complete = [[i, j] for i in range(n_agents) for j in range(i + 1, n_agents)]
        expected = ring_chord_edges(n_agents) if family == "planar_team" else complete
        assert [list(edge) for edge in scenario.edges] == expected
        with FormationEnv(scenario) as env:  # the fixed draw passes the env's checks on its own
            rank = np.linalg.matrix_rank(rigidity_matrix(env.task.graph, np.asarray(scenario.shape)))
            assert rank == required_rigidity_rank(n_agents, dim)


@pytest.mark.parametrize("family", sorted(TEAM_FAMILIES))
def test_the_test_draws_are_fixed_by_their_seeds(family):
    first = team_test_draws(family, 5, seeds=(10_003,))[10_003]
    again = team_test_draws(family, 5, seeds=(10_003,))[10_003]
    np.testing.assert_array_equal(np.asarray(first.shape), np.asarray(again.shape))


def test_the_ring_chord_graph_joins_first_and_second_neighbours():
    assert ring_chord_edges(3) == [[0, 1], [0, 2], [1, 2]]
    assert len(ring_chord_edges(4)) == 6  # complete
    assert ring_chord_edges(8) == sorted([sorted([i, (i + k) % 8]) for i in range(8) for k in (1, 2)])
    assert len(ring_chord_edges(8)) == 16


def test_the_ring_keeps_the_neighbour_spacing_of_four_arms():
    for n_agents in range(3, 9):
        radius = 4.0 * ring_growth(n_agents)
        assert 2 * radius * math.sin(math.pi / n_agents) == pytest.approx(2 * 4.0 * math.sin(math.pi / 4))
    with FormationEnv(team_scenario("planar_team", 8)) as env:
        env.reset(seed=10_000)
        bases = env.task.base_positions[:, :2]
        spacing = np.linalg.norm(bases - np.roll(bases, 1, axis=0), axis=1)
        assert spacing.min() > 5.0  # m: neighbouring arms (3 m reach each) stay apart


@pytest.mark.parametrize("family, n_agents, field", [("planar_team", 2, "n_agents"), ("planar_team", 9, "n_agents"),
                                                     ("spatial_team", 7, "n_agents"), ("spatial_team", 4.0, "n_agents"),
                                                     ("planar", 4, "family")])
def test_an_unknown_family_or_size_is_refused_naming_the_field(family, n_agents, field):
    with pytest.raises(ValueError, match=f"^{field}: "):
        team_scenario(family, n_agents)
