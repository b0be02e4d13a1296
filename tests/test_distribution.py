"""Scenario distributions: each reset draws a validated problem for the same team; the seed fixes the draw, the
spaces never change, the physics is where the task says, batched copies draw as single envs, the reference
controllers take each draw's gains, and bad or infeasible distributions are refused naming the field."""

from __future__ import annotations

import numpy as np
import pybullet
import pytest

from ee_formation_env import load_scenario
from ee_formation_env.baselines import make_policies
from ee_formation_env.baselines.learned.training_env import EVAL_SEED_OFFSET
from ee_formation_env.baselines.metrics import run_episode, run_episodes
from ee_formation_env.baselines.reference.gains import default_gains
from ee_formation_env.scenario_sets import DISTRIBUTIONS, TEST_SEEDS, TRAIN_SEEDS, held_out_draws

SHORT = {"episode_seconds": 0.1}


def _layout(env):
    scenario = env.task.scenario
    return [arm.base_position for arm in scenario.arms], [arm.base_rpy for arm in scenario.arms], scenario.shape


def test_the_reset_seed_fixes_the_draw_and_the_spaces_never_change(make_env):
    env = make_env("planar_random", **SHORT)
    spaces = {agent: env.observation_space(agent) for agent in env.possible_agents}
    layouts = {}
    for seed in (3, 4, 3):
        observations, _ = env.reset(seed=seed)
        layouts.setdefault(seed, []).append(_layout(env))
        for agent, observation in observations.items():
            assert env.observation_space(agent) == spaces[agent]
            assert spaces[agent].contains(observation)
    assert layouts[3][0] == layouts[3][1]
    assert layouts[3][0] != layouts[4][0]
    other = make_env("planar_random", **SHORT)
    other.reset(seed=4)
    assert _layout(other) == layouts[4][0]


@pytest.mark.parametrize("name", ["planar_random", "spatial_random"])
def test_the_simulated_arms_stand_where_the_draw_puts_them(make_env, name):
    env = make_env(name, **SHORT)
    for seed in (0, 1):
        env.reset(seed=seed)
        task = env.task
        client = env.world.client
        for i, arm in enumerate(env.arms):
            # PyBullet's own end-effector position: the draw's bases really moved the bodies.
            link = [pybullet.getJointInfo(arm.body, j, physicsClientId=client)[12].decode()
                    for j in range(pybullet.getNumJoints(arm.body, physicsClientId=client))].index(
                task.scenario.arms[i].ee_link)
            world = np.array(pybullet.getLinkState(arm.body, link, computeForwardKinematics=True,
                                                   physicsClientId=client)[4])
            assert np.allclose(env.end_effector_positions()[i], world, atol=1e-9)
            assert np.allclose(task.base_positions[i], task.scenario.arms[i].base_position)


def test_each_draw_keeps_the_distribution_margins_and_starts_clear(make_env):
    env = make_env("planar_random", **SHORT)
    config = env.scenario.distribution
    radii = []
    for seed in range(12):
        _, infos = env.reset(seed=seed)
        shape = np.asarray(env.task.scenario.shape)
        gaps = np.linalg.norm(shape[:, None] - shape[None], axis=-1)[np.triu_indices(len(shape), 1)]
        assert gaps.min() >= config.vertex_spacing
        reach = np.linalg.norm(shape - env.task.base_positions[:, :2], axis=1)
        assert np.all(reach <= np.asarray(env.task.reaches) - config.reach_margin)
        assert all(info["contacts"] == 0 for info in infos.values())
        radius = np.linalg.norm(env.task.base_positions[:, :2], axis=1)
        assert np.allclose(radius, radius[0]) and config.ring_radius[0] <= radius[0] <= config.ring_radius[1]
        radii.append(radius[0])
        for i, (model, q0) in enumerate(zip(env.task.models, env.task.initial_q)):
            assert np.linalg.svd(model.jacobian(q0)[:2], compute_uv=False).min() >= config.singularity_margin
    assert np.ptp(radii) > 0.3  # the ring radius really varies


def test_batched_copies_draw_as_single_envs_through_autoresets(lockstep):
    def same_draw(batched, singles, k):
        task = batched.tasks[k]
        assert _layout(singles[k]) == ([a.base_position for a in task.scenario.arms],
                                       [a.base_rpy for a in task.scenario.arms], task.scenario.shape)

    assert lockstep("planar_random", SHORT, check=same_draw) >= 4  # 10-step episodes: each copy draws again


def test_reference_controllers_take_each_draws_gains(make_env):
    env = make_env("planar_random", **SHORT)
    policies = make_policies("gradient", env)  # built before any reset: the construction draw's gains
    for seed in (1, 2):
        env.reset(seed=seed)
        for policy in policies.values():
            policy.reset()
        for i, agent in enumerate(env.possible_agents):
            assert policies[agent].gains == default_gains(env.task, i)
    assert default_gains(env.task, 0) != make_policies("gradient", make_env("planar_random", **SHORT))["arm_0"].gains


def test_batched_evaluation_equals_the_single_episode_loop(make_env):
    seeds = [10_000, 10_001]
    batched = run_episodes("planar_random", "gradient", seeds, overrides={"episode_seconds": 2.0})
    env = make_env("planar_random", episode_seconds=2.0)
    single = [run_episode(env, make_policies("gradient", env), seed) for seed in seeds]
    assert [m.as_dict() for m in batched] == [m.as_dict() for m in single]


def test_the_test_sets_are_fixed_and_never_training_seeds():
    assert set(DISTRIBUTIONS) == {"planar_random", "spatial_random"}
    assert len(TEST_SEEDS) >= 50 and min(TEST_SEEDS) >= EVAL_SEED_OFFSET
    assert max(TRAIN_SEEDS) < EVAL_SEED_OFFSET and not set(TRAIN_SEEDS) & set(TEST_SEEDS)
    first = held_out_draws("planar_random")
    assert len(first) == len(TEST_SEEDS)
    again = held_out_draws("planar_random")
    assert first[TEST_SEEDS[0]].to_dict() == again[TEST_SEEDS[0]].to_dict()
    assert not first[TEST_SEEDS[0]].distribution.active  # each entry is the fixed scenario of that draw


def test_a_distribution_round_trips_through_plain_data():
    scenario = load_scenario("planar_random")
    again = load_scenario(scenario.to_dict())
    assert again.distribution == scenario.distribution and again.distribution.active


def test_an_infeasible_distribution_is_refused_at_construction(make_env):
    with pytest.raises(ValueError, match=r"distribution: no valid draw of 'planar_random' in 5 tries.*out of reach"):
        make_env("planar_random", distribution={"shape_scale": [40.0, 50.0], "max_tries": 5})


@pytest.mark.parametrize("distribution, message", [
    ({"ring_radius": [4.0, 3.0]}, r"distribution\.ring_radius: expected finite numbers with low <= high"),
    ({"ring_radius": -1.0}, r"distribution\.ring_radius: expected values > 0"),
    ({"base_yaw": "wide"}, r"distribution\.base_yaw: expected a number or \[low, high\]"),
    ({"shape": "star"}, r"distribution\.shape: expected one of"),
    ({"graph": "random"}, r"distribution\.graph: expected one of"),
    ({"initial_q": "zeros"}, r"distribution\.initial_q: expected one of"),
    ({"max_tries": 0}, r"distribution\.max_tries: expected an integer"),
    ({"region_radius": 0.0}, r"distribution\.region_radius: expected a finite number > 0"),
    ({"reach_margin": -0.1}, r"distribution\.reach_margin: expected a finite number >= 0"),
    ({"spacing": 1.0}, r"distribution: unknown key\(s\) \['spacing'\]"),
    ([1, 2], r"distribution: expected a dict"),
])
def test_bad_distributions_name_their_field(distribution, message):
    data = load_scenario("planar_square").to_dict()
    data["distribution"] = distribution
    with pytest.raises(ValueError, match=message):
        load_scenario(data)


def test_a_distribution_with_sensing_is_refused():
    with pytest.raises(ValueError, match="distribution: a scenario distribution cannot be combined with sensing"):
        load_scenario("planar_random", sensing={"noise": 0.01})


def test_an_infeasible_distribution_is_refused_without_one_placement_search(monkeypatch):
    """Bases 100 m apart cannot hold a shape of a few metres: the pair-distance bound refuses each draw at once,
    so the tries do not run the placement search (a fraction of a second each) at all."""
    import ee_formation_env.validation as validation
    from ee_formation_env.generators import sample_task

    MAX_TRIES = 300

    searches = []
    monkeypatch.setattr(validation, "_candidate_rotations", lambda *args: searches.append(args) or [])
    scenario = load_scenario("planar_random", distribution={"ring_radius": 50.0, "max_tries": MAX_TRIES})
    with pytest.raises(ValueError, match=rf"^distribution: no valid draw of 'planar_random' in {MAX_TRIES} tries"
                                         r".*out of reach"):
        sample_task(scenario, np.random.default_rng(0), deadline_seconds=None)
    assert searches == []


def test_the_first_draw_stops_at_its_deadline_naming_the_distribution_and_the_tries_made():
    from ee_formation_env.generators import sample_task

    scenario = load_scenario("planar_random", distribution={"vertex_spacing": 100.0, "max_tries": 10_000})
    with pytest.raises(ValueError, match=r"^distribution: no valid draw of 'planar_random' within 0 s \(1 of "
                                         r"max_tries 10000 tries\); last rejection: .*vertex"):
        sample_task(scenario, np.random.default_rng(0), deadline_seconds=0.0)
