"""Formation manoeuvres: the ``manoeuvre`` key's parsing and refusals, the reference signal, its block in each
agent's own frame, batched copies equal to single envs, and the reference laws' velocity feedforward."""

from __future__ import annotations

import math

import numpy as np
import pytest

import ee_formation_env
from ee_formation_env import load_scenario
from ee_formation_env.baselines import make_policies
from ee_formation_env.baselines.reference.controllers import ControllerBatch, turn_rotations
from ee_formation_env.baselines.reference.team import PolicyTeam
from ee_formation_env.baselines.reference.gains import HOLD_SHARE, default_gains, formation_stiffness
from ee_formation_env.manoeuvre import ManoeuvreConfig, ReferenceMotion, best_fit_angle, parse_manoeuvre, rotation_about
from ee_formation_env.task import build_task

MOVE = {"start": 0.3, "duration": 1.0, "translation": [0.2, -0.1], "rotation": 0.3}


def test_a_manoeuvre_parses_with_its_units_and_round_trips():
    scenario = load_scenario("spatial_tetrahedron", manoeuvre={"start": 1, "duration": 4.0, "translation": [0.1, 0, 0],
                                                               "rotation": -0.2, "axis": [0, 0, 2]})
    config = scenario.manoeuvre
    assert config == ManoeuvreConfig(start=1.0, duration=4.0, translation=(0.1, 0.0, 0.0), rotation=-0.2,
                                     axis=(0.0, 0.0, 1.0))
    assert config.active and config.peak_speed == pytest.approx(math.pi * 0.1 / 4.0)
    assert config.peak_angular_speed == pytest.approx(math.pi * 0.2 / 4.0)
    assert load_scenario(scenario.to_dict()) == scenario
    assert "manoeuvre" in ee_formation_env.scenario.GAIN_NEUTRAL_FIELDS
    assert scenario.controller_gains == load_scenario("spatial_tetrahedron").controller_gains
    # Overrides merge into the scenario's, and null drops it.
    merged = load_scenario("planar_square_transport", manoeuvre={"duration": 10.0})
    assert merged.manoeuvre.translation == (0.5, 0.0) and merged.manoeuvre.duration == 10.0
    assert not load_scenario("planar_square_transport", manoeuvre=None).manoeuvre.active


def test_a_shorter_episode_ends_during_the_motion():
    assert load_scenario("spatial_tetrahedron_rotate", episode_seconds=10.0).manoeuvre.active


def test_no_motion_is_no_manoeuvre():
    assert not load_scenario("planar_square").manoeuvre.active
    assert load_scenario("planar_square", manoeuvre={"start": 1.0, "duration": 2.0}).manoeuvre == ManoeuvreConfig()
    assert load_scenario("planar_square").to_dict()["manoeuvre"] is None


@pytest.mark.parametrize("manoeuvre, message", [
    ("east", "manoeuvre: expected a dict"),
    ({"speed": 1.0}, "manoeuvre: unknown key(s)"),
    ({"start": -1.0, "translation": [0.1, 0]}, "manoeuvre.start: expected a time >= 0 (s)"),
    ({"start": "soon"}, "manoeuvre.start: expected a time >= 0 (s)"),
    ({"duration": 0.0}, "manoeuvre.duration: expected a time > 0 (s)"),
    ({"duration": math.nan}, "manoeuvre.duration: expected a time > 0 (s)"),
    ({"duration": True}, "manoeuvre.duration: expected a time > 0 (s)"),
    ({"translation": [0.1, 0.0, 0.0]}, "manoeuvre.translation: expected 2 finite numbers (m)"),
    ({"translation": [0.1, math.inf]}, "manoeuvre.translation: expected 2 finite numbers (m)"),
    ({"translation": 0.5}, "manoeuvre.translation: expected 2 finite numbers (m)"),
    ({"translation": [True, 0.0]}, "manoeuvre.translation: expected 2 finite numbers (m)"),
    ({"rotation": math.inf}, "manoeuvre.rotation: expected an angle (rad)"),
    ({"rotation": 0.1, "axis": [0, 0, 1]}, "manoeuvre.axis: only for dim 3"),
])
def test_bad_manoeuvres_name_their_field(manoeuvre, message):
    with pytest.raises(ValueError) as raised:
        load_scenario("planar_square", manoeuvre=manoeuvre)
    assert message in str(raised.value)


@pytest.mark.parametrize("scenario, manoeuvre, message", [
    ("planar_square_displacement", {"rotation": 0.1}, "manoeuvre.rotation: a displacement formation's shape is "
                                                      "fixed in orientation"),
    ("spatial_tetrahedron", {"rotation": 0.1, "axis": [0, 0, 0]}, "manoeuvre.axis: expected a nonzero direction"),
    ("spatial_tetrahedron", {"rotation": 0.1, "axis": [0, 1]}, "manoeuvre.axis: expected 3 finite numbers"),
])
def test_rotation_refusals(scenario, manoeuvre, message):
    with pytest.raises(ValueError) as raised:
        load_scenario(scenario, manoeuvre=manoeuvre)
    assert message in str(raised.value)
    assert parse_manoeuvre({"translation": [0.1, 0.0]}, 2, "displacement", 0.01).active  # translating is fine


def test_an_inactive_manoeuvre_leaves_everything_bit_identical(open_loop):
    plain_env, plain = open_loop("planar_square")
    idle_env, idle = open_loop("planar_square", manoeuvre={"start": 0.1, "duration": 0.2})
    for agent in plain_env.possible_agents:
        assert plain_env.observation_space(agent) == idle_env.observation_space(agent)
        assert plain_env.observation_layout(agent) == idle_env.observation_layout(agent)
        assert plain_env.observation_layout(agent).reference_size == 0
    for (obs_a, rewards_a, infos_a), (obs_b, rewards_b, infos_b) in zip(plain, idle):
        assert rewards_a == rewards_b
        assert all(obs_a[a].tobytes() == obs_b[a].tobytes() for a in obs_a)
        for agent in infos_a:
            assert infos_a[agent].keys() == infos_b[agent].keys()
            assert all(np.array_equal(infos_a[agent][k], infos_b[agent][k]) for k in infos_a[agent])


def test_an_active_manoeuvre_changes_only_the_reference_block(open_loop):
    plain_env, plain = open_loop("planar_square", episode_seconds=1.5)
    env, moving = open_loop("planar_square", episode_seconds=1.5, manoeuvre=MOVE)
    for (obs_a, rewards_a, infos_a), (obs_b, rewards_b, _) in zip(plain, moving):
        assert rewards_a == rewards_b  # the reward stays the shape's
        for agent in obs_a:
            size = plain_env.observation_layout(agent).size
            assert obs_b[agent].shape == (size + 5,)
            assert obs_a[agent].tobytes() == obs_b[agent][:size].tobytes()
            assert env.observation_space(agent).contains(obs_b[agent])
    assert set(moving[-1][2]["arm_0"]) == set(plain[-1][2]["arm_0"])  # no new info keys


def test_the_reference_signal_is_the_out_and_back_profile():
    config = parse_manoeuvre({"start": 2.0, "duration": 4.0, "translation": [0.3, 0.0, -0.4], "rotation": 0.5,
                              "axis": [1.0, 0.0, 0.0]}, 3, "distance", 0.01)
    motion = ReferenceMotion(config, build_task(load_scenario("spatial_tetrahedron")))
    c0 = np.array([[0.25, 0.25, -0.5]])
    t = np.array([0.0, 1.9, 2.0, 3.0, 4.0, 5.0, 6.0, 6.5])
    centroid, velocity, theta, omega = motion.world(t, np.repeat(c0, len(t), axis=0))
    s = np.array([0.0, 0.0, 0.0, 0.5, 1.0, 0.5, 0.0, 0.0])
    np.testing.assert_allclose(centroid, c0 + s[:, None] * [0.3, 0.0, -0.4], atol=1e-15)
    np.testing.assert_allclose(theta, 0.5 * s, atol=1e-15)
    peak = math.pi / 4.0  # ds/dt at t0 + T / 4
    np.testing.assert_allclose(velocity[3], peak * np.array([0.3, 0.0, -0.4]))
    np.testing.assert_allclose(omega[3], [peak * 0.5, 0.0, 0.0])
    assert np.linalg.norm(velocity[3]) == pytest.approx(config.peak_speed)
    # The velocities are the derivatives of the positions and the angle (central differences).
    times = np.linspace(2.05, 5.95, 40)
    h = 1e-6
    ahead, behind = (motion.world(times + d, np.repeat(c0, 40, axis=0)) for d in (h, -h))
    now = motion.world(times, np.repeat(c0, 40, axis=0))
    np.testing.assert_allclose((ahead[0] - behind[0]) / (2 * h), now[1], atol=1e-8)
    np.testing.assert_allclose((ahead[2] - behind[2]) / (2 * h), now[3][:, 0], atol=1e-8)


def test_observations_carry_the_reference_in_each_base_frame(make_env):
    env = make_env("planar_square_rotated", episode_seconds=1.5, manoeuvre=MOVE)
    observations, _ = env.reset(seed=1)
    team = PolicyTeam(make_policies("gradient", env))
    team.reset()
    task, dt, seen = env.task, env.scenario.control_dt, 0
    previous = env.reference_centroid()
    while env.agents:
        observations, *_ = env.step(team(observations))
        reference = env.reference_centroid()
        t = env.step_count * dt
        s, rate = env.scenario.manoeuvre.profile(t)
        velocity, omega = rate * np.array(MOVE["translation"]), rate * MOVE["rotation"]
        if 0.3 < t < 1.3:
            # the world-frame velocity is the centroid's finite difference (one step, to first order)
            np.testing.assert_allclose((reference - previous) / dt, velocity, atol=5.0 * dt)  # |d2c*/dt2| < 5 m/s^2 here
        for i, agent in enumerate(env.possible_agents):
            parts = env.observation_layout(agent).split(observations[agent])
            rotation = task.base_rotations[i][:2, :2]  # base -> world
            np.testing.assert_allclose(parts.reference_centroid, rotation.T @ (reference - task.base_positions[i, :2]),
                                       atol=1e-6)
            np.testing.assert_allclose(parts.reference_velocity, rotation.T @ velocity, atol=1e-7)
            np.testing.assert_allclose(parts.reference_angular_velocity, [omega], atol=1e-7)
            seen += bool(np.any(parts.reference_velocity != 0))
        previous = reference
    assert seen > 100  # the motion was observed moving


def test_spatial_observations_rotate_the_angular_velocity_into_each_frame(make_env):
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    env = make_env("spatial_tetrahedron", episode_seconds=0.5, manoeuvre={"start": 0.0, "duration": 0.5,
                                                                          "rotation": 0.2, "axis": axis.tolist()})
    env.reset(seed=0)
    observations, *_ = env.step({a: np.zeros(7, np.float32) for a in env.agents})
    rate = env.scenario.manoeuvre.profile(env.scenario.control_dt)[1] * 0.2
    for i, agent in enumerate(env.possible_agents):
        parts = env.observation_layout(agent).split(observations[agent])
        np.testing.assert_allclose(parts.reference_angular_velocity, env.task.base_rotations[i].T @ (rate * axis),
                                   atol=1e-7)


def test_batched_copies_follow_the_reference_as_single_envs(lockstep):
    overrides = {"episode_seconds": 0.1, "manoeuvre": {"start": 0.02, "duration": 0.06, "translation": [0.3, 0.2],
                                                       "rotation": 0.4}}

    def same_tracking(batched, singles, k):
        assert batched.centroid_tracking_error()[k] == singles[k].centroid_tracking_error()
        assert batched.orientation_tracking_error()[k] == singles[k].orientation_tracking_error()
        assert batched.reference_centroid()[k].tobytes() == singles[k].reference_centroid().tobytes()

    assert lockstep("planar_square_rotated", overrides, check=same_tracking) >= 4  # 10-step episodes


def test_the_feedforward_is_exactly_zero_without_a_manoeuvre_and_before_the_motion(make_env):
    plain = make_env("planar_square", episode_seconds=0.3)
    moving = make_env("planar_square", episode_seconds=0.3, manoeuvre={"start": 0.2, "duration": 0.1,
                                                                       "translation": [0.2, 0.0]})
    for law in ("gradient", "approx_jacobian", "adaptive_jacobian"):
        teams = [PolicyTeam(make_policies(law, env)) for env in (plain, moving)]
        obs = [env.reset(seed=4)[0] for env in (plain, moving)]
        for team in teams:
            team.reset()
        for step in range(25):
            actions = [team(o) for team, o in zip(teams, obs)]
            same = all(actions[0][a].tobytes() == actions[1][a].tobytes() for a in actions[0])
            assert same == (step <= 20), (law, step)  # equal to the plain law until the reference moves
            obs = [env.step(a)[0] for env, a in zip((plain, moving), actions)]
    batch = ControllerBatch([make_policies("gradient", plain)["arm_0"]])
    parts = plain.observation_layout("arm_0").split(obs[0]["arm_0"][None])
    assert batch.damped_velocities(parts, batch.a_hat0) is parts.dq


@pytest.mark.parametrize("law", ["gradient", "adaptive_jacobian"])
def test_the_feedforward_carries_the_centroid_along_the_reference(make_env, law):
    """Against the same law without a manoeuvre (same seed): the centroid's extra travel is the reference's."""
    translation = np.array([0.3, 0.15])
    manoeuvre = {"start": 0.5, "duration": 3.0, "translation": translation.tolist()}
    travel = []
    for overrides in ({}, {"manoeuvre": manoeuvre}):
        env = make_env("planar_square", episode_seconds=3.5, **overrides)
        observations, _ = env.reset(seed=0)
        team = PolicyTeam(make_policies(law, env))
        team.reset()
        for _ in range(200):  # to t = 2 s
            observations, *_ = env.step(team(observations))
        travel.append(env.end_effector_positions()[:, :2].mean(axis=0))
    extra = travel[1] - travel[0]  # at t = 2 s: s = 1, the reference is at the far end of its path
    assert np.linalg.norm(extra - translation) < 0.02
    assert extra @ translation / (translation @ translation) > 0.9


def test_the_orientation_error_is_the_best_fit_turn():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(4, 3))
    turn = rotation_about(np.array([0.0, 0.6, 0.8]), np.array([0.3]), 3)[0]
    assert best_fit_angle(points, points @ turn.T + 5.0) == pytest.approx(0.3)
    flat = points[:, :2]
    assert best_fit_angle(flat, flat @ rotation_about(None, np.array([-0.2]), 2)[0].T) == pytest.approx(0.2)


def test_the_builtin_manoeuvres_stay_within_reach():
    """Every target vertex along the path (placed as the shape x*) stays within its arm's reach, with margin."""
    for name, steps in (("planar_square_transport", 21), ("spatial_tetrahedron_rotate", 21)):
        scenario = load_scenario(name)
        task = build_task(scenario)
        config, m = scenario.manoeuvre, scenario.dim
        assert config.active and scenario.controller_gains is not None
        assert config.start + config.duration < scenario.episode_seconds  # time to settle after the motion
        shape = np.asarray(scenario.shape)
        centre = shape.mean(axis=0)
        for s in np.linspace(0.0, 1.0, steps):
            turn = rotation_about(np.asarray(config.axis), np.array([s * config.rotation]), m)[0]
            translation = np.asarray(config.translation or (0.0,) * m)
            moved = centre + s * translation + (shape - centre) @ turn.T
            distances = np.linalg.norm(moved - task.base_positions[:, :m], axis=1)
            assert np.all(distances < 0.9 * np.asarray(task.reaches)), (name, s, distances)


def test_the_feedforward_turns_the_formation_with_the_reference(make_env):
    # The motion starts once the shape has formed (the orientation error's reference is the shape at t0).
    env = make_env("planar_square", episode_seconds=5.0, manoeuvre={"start": 2.0, "duration": 3.0, "rotation": 0.3})
    observations, _ = env.reset(seed=0)
    team = PolicyTeam(make_policies("gradient", env))
    team.reset()
    for _ in range(350):  # to t = 3.5 s: theta* = 0.3 rad
        observations, *_ = env.step(team(observations))
    assert env.orientation_tracking_error() < 0.03
    assert env.centroid_tracking_error() < 0.1  # the centroid's drift while the shape forms, not the turn


def test_the_reference_starts_from_the_centroid_at_the_motions_start(make_env):
    """Until t0 the reference centroid is the current one (the formation forms where its arms take it); from
    then on it is that centroid moved along the path."""
    manoeuvre = {"start": 0.3, "duration": 1.0, "translation": [0.2, -0.1]}
    env = make_env("planar_square", episode_seconds=1.5, manoeuvre=manoeuvre)
    observations, _ = env.reset(seed=2)
    team = PolicyTeam(make_policies("gradient", env))
    team.reset()
    dt = env.scenario.control_dt
    start = None
    for step in range(1, 100):
        observations, *_ = env.step(team(observations))
        centroid = env.end_effector_positions()[:, :2].mean(axis=0)
        t = step * dt
        if t <= 0.3 + 1e-12:
            np.testing.assert_array_equal(env.reference_centroid(), centroid)
            start = centroid
        else:
            s = (1 - math.cos(2 * math.pi * (t - 0.3) / 1.0)) / 2
            np.testing.assert_allclose(env.reference_centroid(), start + s * np.array([0.2, -0.1]), atol=1e-12)


def test_the_default_gains_hold_the_reference_on_an_active_manoeuvre_only():
    """Rule 6 of the gains: K_X = HOLD_SHARE K_P lambda_max(S) with an active manoeuvre, else 0."""
    for name, parent in (("planar_square_transport", "planar_square"), ("spatial_tetrahedron_rotate",
                                                                       "spatial_tetrahedron")):
        task = build_task(load_scenario(name))
        gains = default_gains(task, 0)
        assert gains.reference_stiffness == pytest.approx(HOLD_SHARE * gains.kp * formation_stiffness(task))
        assert gains.reference_stiffness > 0
        assert default_gains(build_task(load_scenario(parent)), 0).reference_stiffness == 0.0
        still = build_task(load_scenario(name, manoeuvre={"translation": [0.0] * task.dim, "rotation": 0.0}))
        assert default_gains(still, 0).reference_stiffness == 0.0
    with pytest.raises(ValueError, match="gains.reference_stiffness"):
        default_gains(task, 0).with_updates(reference_stiffness=-1.0).validated(7)


def test_turn_rotations_are_the_rotations_of_the_rotation_vectors():
    vectors = np.array([[0.1, -0.2, 0.3], [0.0, 0.0, 0.0]])
    angle = np.linalg.norm(vectors[0])
    expected = rotation_about(vectors[0] / angle, np.array([angle]), 3)[0]
    np.testing.assert_allclose(turn_rotations(vectors, 3)[0], expected, atol=1e-15)
    np.testing.assert_array_equal(turn_rotations(vectors, 3)[1], np.eye(3))
    np.testing.assert_allclose(turn_rotations(np.array([[0.4]]), 2)[0], rotation_about(None, np.array([0.4]), 2)[0])


@pytest.mark.parametrize("law, without_bound, with_bound", [("approx_jacobian", 0.2, 0.1), ("gradient", 0.03, 0.02)])
def test_the_reference_hold_turns_the_tetrahedron(make_env, law, without_bound, with_bound):
    """At the peak of a 0.5 rad turn (t = 3 s), law-II without the hold is left well behind the reference (its
    internal model holds the arms where gravity was); with the default hold it follows within 0.1 rad; law-I
    follows in both, closer with the hold."""
    errors = []
    for gains in ({"reference_stiffness": 0.0}, {}):
        env = make_env("spatial_tetrahedron_rotate", episode_seconds=3.0, manoeuvre={"start": 1.0, "duration": 4.0})
        observations, _ = env.reset(seed=0)
        team = PolicyTeam(make_policies(law, env, gains=gains))
        team.reset()
        while env.agents:
            observations, *_ = env.step(team(observations))
        errors.append(env.orientation_tracking_error())
    assert errors[0] > without_bound and errors[1] < with_bound and errors[1] < 0.5 * errors[0]


def test_a_manoeuvre_shorter_than_four_control_periods_is_refused_naming_duration():
    # planar_square steps at 100 Hz: 4 control periods are 0.04 s.
    for duration in (1e-300, 0.039):
        with pytest.raises(ValueError, match=r"^manoeuvre\.duration: expected at least 4 control periods \(0\.04 s"):
            load_scenario("planar_square_transport", manoeuvre={"duration": duration})
    assert load_scenario("planar_square_transport", manoeuvre={"duration": 0.04}).manoeuvre.duration == 0.04


def test_a_translation_no_end_effector_can_follow_is_refused_naming_translation_before_physics():
    # The planar arms reach 3 m: no end-effector moves farther than 6 m, across its workspace.
    with pytest.raises(ValueError, match=r"^manoeuvre\.translation: \|A\| = 100 m is beyond what the arms can "
                                         r"follow.*shortest reach 3\.000 m"):
        build_task(load_scenario("planar_square_transport", manoeuvre={"translation": [100.0, 0.0]}))
    build_task(load_scenario("planar_square_transport", manoeuvre={"translation": [5.9, 0.0]}))  # within


def test_the_tracking_term_rewards_each_end_effector_near_its_place_in_the_moving_reference(make_env):
    """reward.tracking: r_i gains tracking * closeness(|p_i - p*_i| / tracking_tolerance), p*_i the formation's
    shape placed as the end-effectors stood at the motion's start and carried along it (1 before it starts); the
    rest of the reward is unchanged."""
    manoeuvre = {"start": 0.3, "duration": 1.0, "translation": [0.2, -0.1], "rotation": 0.3}
    tracking = {"tracking": 0.5, "tracking_tolerance": 0.02}
    plain = make_env("planar_square", episode_seconds=1.5, manoeuvre=manoeuvre)
    tracked = make_env("planar_square", episode_seconds=1.5, manoeuvre=manoeuvre, reward=tracking)
    observations, _ = plain.reset(seed=2)
    tracked.reset(seed=2)
    team = PolicyTeam(make_policies("gradient", plain))
    team.reset()
    config = tracked.scenario.reward
    dt, start_points, seen_motion = plain.scenario.control_dt, None, False
    for step in range(1, 120):
        actions = team(observations)
        observations, rewards, *_ = plain.step(actions)
        _, tracked_rewards, *_ = tracked.step(actions)
        points = tracked.end_effector_positions()[:, :2]
        t = step * dt
        if t <= 0.3 + 1e-12:
            start_points = points.copy()
            expected = 0.0
        else:  # the shape placed as the start points stood, turned by theta*(t) about c*(t), carried by s(t) A
            s = (1 - math.cos(2 * math.pi * (t - 0.3) / 1.0)) / 2
            c0 = start_points.mean(axis=0)
            shape = np.asarray(tracked.scenario.shape) - np.mean(tracked.scenario.shape, axis=0)
            best, placed = np.inf, None
            for mirror in (1.0, -1.0):  # the best-fit rotation in the plane (closed form), with or without a mirror
                source, target = shape * [1.0, mirror], start_points - c0
                angle = math.atan2(np.sum(source[:, 0] * target[:, 1] - source[:, 1] * target[:, 0]),
                                   np.sum(source * target))
                c, w = math.cos(angle), math.sin(angle)
                candidate = source @ np.array([[c, -w], [w, c]]).T
                misfit = np.sum((candidate - target) ** 2)
                if misfit < best:
                    best, placed = misfit, candidate
            turn = rotation_about(np.array([0.0, 0.0, 1.0]), np.array([s * 0.3]), 2)[0]
            targets = c0 + s * np.array([0.2, -0.1]) + placed @ turn.T
            expected = np.linalg.norm(points - targets, axis=1) / 0.02
            seen_motion = seen_motion or float(np.max(expected)) > 1.0
        span = math.log10(config.error_ceiling / config.error_floor)
        closeness = np.clip(np.log10(config.error_ceiling / (expected + config.error_floor)) / span, 0.0, 1.0)
        for i, agent in enumerate(plain.possible_agents):
            assert tracked_rewards[agent] == pytest.approx(rewards[agent] + 0.5 * np.atleast_1d(closeness)[
                i if np.ndim(closeness) else 0], rel=1e-9, abs=1e-9)
    assert seen_motion  # the law lags the reference by more than a tolerance somewhere: the term is not constant


def test_the_tracking_term_is_refused_without_a_manoeuvre_and_checked():
    with pytest.raises(ValueError, match="reward.tracking: the tracking term needs a manoeuvre"):
        load_scenario("planar_square", reward={"tracking": 1.0})
    for bad, message in (({"tracking": -1.0}, "reward.tracking"), ({"tracking_tolerance": 0.0},
                                                                    "reward.tracking_tolerance")):
        with pytest.raises(ValueError, match=message):
            load_scenario("planar_square_transport", reward=bad)
    assert load_scenario("planar_square_transport", reward={"tracking": 1.0}).reward.tracking == 1.0


def test_the_batched_tracking_term_is_the_single_envs(lockstep):
    # 1 s episodes, 25 steps of 0.01 s: the motion runs from 0.1 s on, within the lockstep's steps
    manoeuvre = {"start": 0.1, "duration": 0.1, "rotation": 0.3}
    lockstep("planar_square", {"episode_seconds": 1.0, "manoeuvre": manoeuvre, "reward": {"tracking": 1.0}}, steps=40)


@pytest.mark.parametrize("mirror", [1.0, -1.0])
def test_the_tracking_targets_are_the_shape_placed_as_the_start_stood_then_turned(mirror):
    """3D: start points that are the shape turned, mirrored or not, and moved are their own targets at the start;
    halfway through the out-and-back turn every target has turned by the full rotation about c*."""
    task = build_task(load_scenario("spatial_tetrahedron_rotate"))
    motion = ReferenceMotion(task.scenario.manoeuvre, task)
    shape = np.asarray(task.scenario.shape)
    turn = rotation_about(np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]), np.array([1.1]), 3)[0]
    start = (shape - shape.mean(axis=0)) * [1.0, 1.0, mirror] @ turn.T + [0.1, 0.2, -0.4]
    at_start = motion.agent_targets(np.array([task.scenario.manoeuvre.start]), start[None])[0]
    np.testing.assert_allclose(at_start, start, atol=1e-12)
    config = task.scenario.manoeuvre
    halfway = motion.agent_targets(np.array([config.start + config.duration / 2]), start[None])[0]
    about_z = rotation_about(np.array([0.0, 0.0, 1.0]), np.array([config.rotation]), 3)[0]
    centre = start.mean(axis=0)
    np.testing.assert_allclose(halfway, centre + (start - centre) @ about_z.T, atol=1e-12)
    ratios = motion.tracking_ratios(np.array([config.start + 1.0]), start[None], np.pad(start, ((0, 0), (0, 0)))[None],
                                    0.02)
    assert ratios.shape == (1, 4) and (ratios > 0).all()  # one second in, the still start is off its targets


@pytest.mark.parametrize("changes, message", [
    ({"rotation": 1e308}, r"^manoeuvre\.rotation: expected at most half a turn \(pi rad\) per control period at the "
                          r"peak turn rate pi \|r\| / T, i\.e\. \|r\| <= T / control_dt = 4000 rad, got 1e\+308 rad$"),
    ({"rotation": 10**400}, r"^manoeuvre\.rotation: expected an angle \(rad\), got"),
    ({"translation": [1e308, 1e308, 0.0]}, r"^manoeuvre\.translation: expected a peak speed pi \|A\| / T of at most "
                                           r"1000 m/s, got \|A\| = 1\.41421e\+308 m over T = 20 s$"),
    ({"translation": [6400.0, 0.0, 0.0]}, r"^manoeuvre\.translation: expected a peak speed"),
    ({"start": 1e308}, r"^manoeuvre\.start: expected a time >= 0 \(s\), at most 1e\+06 \(the longest episode\), got 1e\+308$"),
    ({"duration": 1e308}, r"^manoeuvre\.duration: expected a time > 0 \(s\), at most 1e\+06 \(the longest episode\), got 1e\+308$"),
])
def test_manoeuvre_numbers_that_would_overflow_the_reference_are_refused_naming_the_key(changes, message):
    with pytest.raises(ValueError, match=message):
        load_scenario("spatial_tetrahedron_rotate", manoeuvre=changes)


def test_the_bounds_leave_the_fastest_allowed_reference_finite(make_env):
    # planar_square steps at 100 Hz: over T = 0.04 s (4 periods) the turn may be 4 rad, the translation 12.7 m.
    env = make_env("planar_square", episode_seconds=0.1, manoeuvre={"start": 0.0, "duration": 0.04, "rotation": 4.0})
    observations, _ = env.reset(seed=0)
    while env.agents:
        observations, *_ = env.step({agent: np.zeros(2) for agent in env.agents})
        assert all(np.isfinite(observation).all() for observation in observations.values())
    with pytest.raises(ValueError, match=r"^manoeuvre\.rotation: expected at most half a turn"):
        load_scenario("planar_square", manoeuvre={"start": 0.0, "duration": 0.04, "rotation": 4.01})
    assert load_scenario("planar_square", manoeuvre={"duration": 0.04, "translation": [12.7, 0.0]}).manoeuvre.active
