"""The paper's controllers: convergence, the printed law's stall, gravity and model mismatch."""

from __future__ import annotations

import numpy as np
import pytest

from ee_formation_env import baselines
import ee_formation_env
from ee_formation_env.baselines.reference.controllers import ControllerBatch, Gains
from ee_formation_env.baselines.reference.team import PolicyTeam
from ee_formation_env.baselines.reference.gains import PAPER_GAINS, default_gains
from ee_formation_env.baselines.metrics import run_episode
from ee_formation_env.builtin import builtin_scenario
from ee_formation_env.generators import square_vertices as _square

PAPER_2D_LIFTED = dict(frame_skip=1, torque_limits=1e7, max_joint_velocity=1000.0)


def _run(scenario, policy, seconds, seed=0, policy_kwargs=None, **overrides):
    overrides.setdefault("initial_q_noise", 0.0)
    with ee_formation_env.parallel_env(scenario, episode_seconds=seconds, **overrides) as env:
        policies = baselines.make_policies(policy, env, **(policy_kwargs or {}))
        metrics = run_episode(env, policies, seed=seed)
        estimates = [getattr(p, "a_hat", None) for p in policies.values()]
        return metrics, env.edge_errors(), env.joint_velocities(), estimates


@pytest.mark.parametrize("policy", ["gradient", "approx_jacobian", "adaptive_jacobian"])
def test_each_law_converges_on_planar_square_under_torque_limits(policy):
    metrics, edge_errors, velocities, _ = _run("planar_square", policy, 10.0)
    assert metrics.physics_fault == ""
    assert np.max(np.abs(edge_errors)) < 1e-4
    assert max(np.max(np.abs(dq)) for dq in velocities) < 1e-3
    assert metrics.peak_torque <= 50.0 + 1e-9  # the default torque limits hold


def test_printed_law_with_paper_gains_converges_on_3m_square():
    """Paper gains, torque limits lifted, a_hat(0) = [2, 2], the law exactly as printed."""
    metrics, edge_errors, velocities, _ = _run(
        "planar_square", "adaptive_jacobian", 5.0, **PAPER_2D_LIFTED,
        policy_kwargs=dict(gains=PAPER_GAINS[2], a_hat0=[2.0, 2.0], projection=False))
    assert metrics.physics_fault == ""
    assert np.max(np.abs(edge_errors)) < 1e-4
    assert max(np.max(np.abs(dq)) for dq in velocities) < 1e-3


def test_printed_law_stalls_on_4m_square_and_projection_fixes_it():
    """Far from the target the printed law collapses a_hat to its spurious equilibrium 0 (docs/physics.md)."""
    # planar_square's own tuned gains on the 4.0 m square (a shape override alone would derive new ones)
    kwargs = dict(shape=_square(4.0), controller_gains=builtin_scenario("planar_square")["controller_gains"])
    printed, printed_errors, _, printed_estimates = _run(
        "planar_square", "adaptive_jacobian", 15.0, **kwargs,
        policy_kwargs=dict(a_hat0=[2.0, 2.0], projection=False))
    assert not printed.success
    assert np.max(np.abs(printed_errors)) > 1.0
    assert max(np.max(np.abs(a)) for a in printed_estimates) < 0.1  # a_hat collapsed to ~0

    projected, projected_errors, _, projected_estimates = _run(
        "planar_square", "adaptive_jacobian", 15.0, **kwargs, policy_kwargs=dict(a_hat0=[2.0, 2.0]))
    assert projected.success
    assert np.max(np.abs(projected_errors)) < 1e-4
    assert min(np.min(a) for a in projected_estimates) >= 0.75 - 1e-12  # inside the default box [0.5, 2] x nominal 1.5


def test_printed_law_with_paper_gains_stalls_on_4m_square():
    """At 5 kHz (fine enough to follow the fast a_hat collapse) the paper's gains stall too."""
    metrics, edge_errors, _, estimates = _run(
        "planar_square", "adaptive_jacobian", 0.5, shape=_square(4.0), frame_skip=1, physics_hz=5000.0,
        torque_limits=1e7, max_joint_velocity=1000.0,
        policy_kwargs=dict(gains=PAPER_GAINS[2], a_hat0=[2.0, 2.0], projection=False))
    assert metrics.physics_fault == ""
    assert np.max(np.abs(edge_errors)) > 1.0
    assert max(np.max(np.abs(a)) for a in estimates) < 0.05


def test_adaptive_law_holds_the_tetrahedron_against_gravity():
    metrics, edge_errors, velocities, _ = _run("spatial_tetrahedron", "adaptive_jacobian", 15.0)
    assert metrics.physics_fault == ""
    assert np.max(np.abs(edge_errors)) < 1e-4
    assert max(np.max(np.abs(dq)) for dq in velocities) < 1e-3


def test_mismatch_leaves_gradient_error_that_the_robust_laws_remove():
    """Paper Sec. IV: with +-20 % kinematic and dynamic mismatch, law-I with the nominal G keeps a
    steady-state error; the internal model (law-II) and the adaptive Jacobian (law-III) remove it."""
    mismatch = {"length": 0.2, "mass": 0.2, "seed": 0}
    gradient, gradient_errors, _, _ = _run("spatial_tetrahedron", "gradient", 20.0, model_mismatch=mismatch)
    assert np.max(np.abs(gradient_errors)) > 1e-3
    for policy in ("approx_jacobian", "adaptive_jacobian"):
        robust, robust_errors, _, _ = _run("spatial_tetrahedron", policy, 20.0, model_mismatch=mismatch)
        assert np.max(np.abs(robust_errors)) < 1e-4, policy


def test_controllers_reset_clears_internal_state():
    with ee_formation_env.parallel_env("spatial_tetrahedron", episode_seconds=0.2) as env:
        policy = baselines.make_policy("adaptive_jacobian", env, "arm_0")
        observations, _ = env.reset(seed=0)
        first = policy(observations["arm_0"])
        for _ in range(5):
            policy(observations["arm_0"])
        assert np.any(policy.eta != 0)
        policy.reset()
        assert np.all(policy.eta == 0)
        np.testing.assert_array_equal(policy.a_hat, env.nominal_models[0].nominal_params)
        np.testing.assert_array_equal(policy(observations["arm_0"]), first)


def test_make_policy_rejects_bad_input():
    with ee_formation_env.parallel_env("planar_square") as env:
        with pytest.raises(ValueError, match="unknown policy"):
            baselines.make_policy("pid", env, "arm_0")
        with pytest.raises(ValueError, match="agent"):
            baselines.make_policy("gradient", env, "arm_9")
        with pytest.raises(ValueError, match="gains.kd"):
            baselines.make_policy("gradient", env, "arm_0", gains={"kd": -1.0})
        with pytest.raises(ValueError, match="gains.kp"):
            baselines.make_policy("gradient", env, "arm_0", gains={"kp": [1.0, 2.0, 3.0]})
        with pytest.raises(ValueError, match="unknown key"):
            baselines.make_policy("gradient", env, "arm_0", gains={"k_p": 1.0})
        with pytest.raises(ValueError, match="a_hat0"):
            baselines.make_policy("adaptive_jacobian", env, "arm_0", a_hat0=[1.0])
        with pytest.raises(ValueError, match="options"):
            baselines.make_policy("gradient", env, "arm_0", projection=False)


def test_action_is_the_law_divided_by_the_torque_limits():
    """gradient on a planar arm: -K_P J^T e_hat - K_D dq (no gravity on z-axis joints), by hand."""
    with ee_formation_env.parallel_env("planar_square", initial_q_noise=0.0) as env:
        observations, _ = env.reset(seed=0)
        observations, *_ = env.step({a: np.full(2, 0.3) for a in env.agents})  # non-zero dq
        policy = baselines.make_policy("gradient", env, "arm_0")
        parts = env.observation_layout("arm_0").split(observations["arm_0"])
        q, dq = parts.q, parts.dq
        l1 = l2 = 1.5
        jacobian = np.array([[-l1 * np.sin(q[0]) - l2 * np.sin(q[0] + q[1]), -l2 * np.sin(q[0] + q[1])],
                             [l1 * np.cos(q[0]) + l2 * np.cos(q[0] + q[1]), l2 * np.cos(q[0] + q[1])]])
        e_hat = 2.0 * (parts.edge_errors[:, 0] * parts.mask) @ parts.relative_positions
        gains = default_gains(env.task, 0)  # planar_square's own tuned gains
        expected = (-gains.kp * jacobian.T @ e_hat - gains.kd * dq) / 50.0
        np.testing.assert_allclose(policy(observations["arm_0"]), expected, rtol=1e-5, atol=1e-6)


def test_saturated_springs_bound_the_force_and_keep_the_law_near_the_target():
    """Finite spring_force: far away each edge error is clipped at F / (2 K_P d); near the target the
    law is the printed one; the result is the same at both ends of an edge (one potential)."""
    with ee_formation_env.parallel_env("planar_square", initial_q_noise=0.0) as env:
        observations, _ = env.reset(seed=0)
        gains = Gains(kp=2.0, kd=20.0, spring_force=4.0)
        saturated = baselines.make_policy("gradient", env, "arm_0", gains=gains)
        printed = baselines.make_policy("gradient", env, "arm_0", gains=Gains(kp=2.0, kd=20.0))
        parts = env.observation_layout("arm_0").split(observations["arm_0"])
        errors = parts.edge_errors[:, 0] * parts.mask
        lengths = parts.desired[:, 0]
        level = 4.0 / (2.0 * 2.0 * np.where(lengths > 0, lengths, 1.0))
        expected = 2.0 * np.clip(errors, -level, level) @ parts.relative_positions
        np.testing.assert_allclose(saturated.gradient(parts)[:2], expected, rtol=1e-12)
        assert np.any(np.abs(errors) > level)  # the start is far enough for the clip to act
        small = parts.edge_errors * 1e-6  # near the target: no clipping, the printed gradient
        np.testing.assert_array_equal(saturated.saturated_errors(small, parts.desired), small)
        assert np.linalg.norm(saturated.gradient(parts)) < np.linalg.norm(printed.gradient(parts))


def test_gains_reject_a_per_joint_formation_gain_with_saturation():
    with ee_formation_env.parallel_env("planar_square") as env:
        with pytest.raises(ValueError, match="gains.kp"):
            baselines.make_policy("gradient", env, "arm_0", gains={"kp": [1.0, 2.0], "spring_force": 3.0})
        with pytest.raises(ValueError, match="gains.spring_force"):
            baselines.make_policy("gradient", env, "arm_0", gains={"spring_force": -1.0})


def test_parameter_bounds_are_validated_and_the_boundary_time_reported():
    with ee_formation_env.parallel_env("planar_square", initial_q_noise=0.0, episode_seconds=2.0) as env:
        for bad, field in ((1.0, "parameter_bounds"), ((2.0, 1.0), "parameter_bounds"),
                           (([1.0, 2.0, 3.0], 4.0), "parameter_bounds.lower"), ((0.5, "x"), "parameter_bounds.upper")):
            with pytest.raises(ValueError, match=field):
                baselines.make_policy("adaptive_jacobian", env, "arm_0", parameter_bounds=bad)
        with pytest.raises(ValueError, match="a_hat0"):  # the initial estimate must lie in the known set
            baselines.make_policy("adaptive_jacobian", env, "arm_0", a_hat0=[2.7, 0.3], parameter_bounds=(1.0, 3.0))
        default = baselines.make_policy("adaptive_jacobian", env, "arm_0")
        np.testing.assert_allclose(default.param_low, [0.75, 0.75])  # [0.5, 2] x nominal 1.5 m
        np.testing.assert_allclose(default.param_high, [3.0, 3.0])
        # A tight box around a poor guess: the estimate ends on its boundary and the fraction says so.
        policies = baselines.make_policies("adaptive_jacobian", env, a_hat0=[2.7, 0.3],
                                           parameter_bounds=([2.6, 0.25], [2.8, 0.35]))
        run_episode(env, policies, seed=0)
        fractions = [p.boundary_fraction for p in policies.values()]
        assert all(0.0 < f <= 1.0 for f in fractions)
        # A slow adaptation (Gamma = 1e-3) from the truth never reaches a wide box's boundary.
        free = baselines.make_policies("adaptive_jacobian", env, a_hat0=[1.5, 1.5], parameter_bounds=(0.5, 5.0),
                                       gains={"adaptation_gain": 1e-3})
        run_episode(env, free, seed=0)
        assert all(p.boundary_fraction == 0.0 for p in free.values())


def test_anti_windup_keeps_the_internal_model_within_the_torque_limits():
    """Law-II under torque limits: the printed internal model integrates torque never applied."""
    limits = [[2.0] * 7] * 4
    peaks = {}
    for anti_windup in (False, True):
        with ee_formation_env.parallel_env("spatial_tetrahedron", torque_limits=limits, episode_seconds=1.0,
                                           initial_q_noise=0.0) as env:
            policies = baselines.make_policies("approx_jacobian", env, gains={"kp": 120.0, "kd": 2.0, "ki": 1.0},
                                               anti_windup=anti_windup)
            peak = [0.0]
            run_episode(env, policies, seed=0, on_step=lambda _: peak.__setitem__(0, max(peak[0], max(
                float(np.max(np.abs(p.eta) / 2.0)) for p in policies.values()))))
            peaks[anti_windup] = peak[0]
    assert peaks[True] <= 1.0 + 1e-9  # |K_I eta| <= limit with K_I = 1
    assert peaks[False] > peaks[True]


KUKA = {"urdf": "kuka_iiwa/model.urdf", "ee_link": "lbr_iiwa_link_7", "initial_q": [0.0, 0.5, 0.0, -1.2, 0.0, 0.8, 0.0]}
PANDA = {"urdf": "franka_panda/panda.urdf", "ee_link": "panda_hand", "initial_q": [0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.8]}
MIXED_TEAM = {  # two KUKA iiwa and one Franka Panda
    "arms": [dict(KUKA, base_position=[0.0, 0.0, 0.0]), dict(PANDA, base_position=[1.0, 0.0, 0.0]),
             dict(KUKA, base_position=[0.5, 0.9, 0.0])],
    "edges": [[0, 1], [1, 2], [0, 2]], "shape": [[0.4, 0.2, 0.6], [0.9, 0.2, 0.6], [0.65, 0.6, 0.6]],
    "formation": "displacement", "dim": 3, "arm_collisions": False,
}


@pytest.mark.parametrize("policy", ["gradient", "approx_jacobian", "adaptive_jacobian"])
@pytest.mark.parametrize("scenario", ["planar_square", "spatial_tetrahedron", "planar_square_transport",
                                      "spatial_tetrahedron_rotate"])
def test_a_batch_of_controllers_acts_as_each_controller_alone(make_env, policy, scenario):
    """Batched evaluation (PolicyTeam, ControllerBatch) gives every agent bit for bit the action and internal
    state it gets alone, over steps that move the internal states, with gains that differ per agent (the
    manoeuvres' reference holds too: the motion starts within the episode, agent 0 has no hold)."""
    squeezed = {"manoeuvre": {"start": 0.05, "duration": 0.3}} if scenario.endswith(("transport", "rotate")) else {}
    env = make_env(scenario, episode_seconds=0.2, **squeezed)
    gains = [default_gains(env.task, i).with_updates(kd=5.0 + i, ki=0.5 * i, rate_gain=0.01 * i,
                                                     reference_stiffness=50.0 * i)
             for i in range(env.task.n_agents)]  # agent 0 without gradient-rate damping, the others with it
    alone = {a: baselines.make_policy(policy, env, a, gains=g) for a, g in zip(env.possible_agents, gains)}
    batched = {a: baselines.make_policy(policy, env, a, gains=g) for a, g in zip(env.possible_agents, gains)}
    team = PolicyTeam(batched)
    observations, _ = env.reset(seed=3)
    team.reset()
    while env.agents:
        expected = {agent: alone[agent](observations[agent]) for agent in env.agents}
        actions = team(observations)
        for agent in env.agents:
            assert actions[agent].tobytes() == expected[agent].tobytes()
            for state in ("eta", "a_hat", "boundary_steps", "_previous_e_hat", "reference_anchor",
                          "reference_turn", "reference_rate", "reference_moving"):
                assert np.array_equal(getattr(batched[agent], state, 0), getattr(alone[agent], state, 0))
        observations, *_ = env.step(actions)


def test_a_team_batches_like_robots_and_calls_other_policies_one_by_one(make_env):
    env = make_env(MIXED_TEAM, episode_seconds=0.1)
    team = PolicyTeam(baselines.make_policies("adaptive_jacobian", env))
    assert sorted(len(batch.members) for _, batch in team._batches) == [1, 2]  # the two KUKAs, the Panda
    twins = baselines.make_policies("adaptive_jacobian", env)
    observations, _ = env.reset(seed=0)
    actions = team(observations)
    for agent in env.possible_agents:
        assert actions[agent].tobytes() == twins[agent](observations[agent]).tobytes()
    mixed = dict(twins, arm_1=baselines.make_policy("zero", env, "arm_1"))
    assert not np.any(PolicyTeam(mixed)(observations)["arm_1"])


def test_a_team_acts_on_a_stack_as_on_a_dict(make_env):
    """act_on_stack (rows in the order the policies were given) gives what __call__ gives, a policy outside
    any batch (zero) included; a stack of the wrong height is a ValueError."""
    env = make_env("planar_square", episode_seconds=0.1)
    policies = baselines.make_policies("adaptive_jacobian", env)
    twins = baselines.make_policies("adaptive_jacobian", env)
    team = PolicyTeam(dict(policies, arm_2=baselines.make_policy("zero", env, "arm_2")))
    twin_team = PolicyTeam(dict(twins, arm_2=baselines.make_policy("zero", env, "arm_2")))
    observations, _ = env.reset(seed=1)
    for _ in range(3):  # the internal states move alike
        stacked = team.act_on_stack(np.stack([observations[agent] for agent in env.possible_agents]))
        expected = twin_team(observations)
        assert stacked.dtype == np.float32 and stacked.shape == (4, 2)
        for row, agent in zip(stacked, env.possible_agents):
            assert row.tobytes() == expected[agent].tobytes()
        assert not np.any(stacked[2])
        observations, *_ = env.step(dict(zip(env.possible_agents, stacked)))
    with pytest.raises(ValueError, match="observations: expected a stack of 4 rows"):
        team.act_on_stack(np.stack([observations["arm_0"]]))


def test_a_batch_rejects_controllers_it_cannot_stack(make_env):
    env = make_env("planar_square")
    gradient = baselines.make_policy("gradient", env, "arm_0")
    adaptive = baselines.make_policy("adaptive_jacobian", env, "arm_1")
    with pytest.raises(ValueError, match="one law"):
        ControllerBatch([gradient, adaptive])
    with pytest.raises(ValueError, match="same options"):
        ControllerBatch([adaptive, baselines.make_policy("adaptive_jacobian", env, "arm_2", projection=False)])
    with pytest.raises(ValueError, match="at least one"):
        ControllerBatch([])


def test_gradient_rate_damping_adds_the_backward_difference_of_e_hat():
    """rate_gain K_R: the spring acts on e_hat + K_R (e_hat - e_hat_prev) / dt; the first step after a
    reset, and K_R = 0, give the printed law; bad values are rejected."""
    with ee_formation_env.parallel_env("planar_square", initial_q_noise=0.0) as env:
        observations, _ = env.reset(seed=0)
        dt = env.scenario.control_dt
        plain = baselines.make_policy("gradient", env, "arm_0", gains=Gains(kp=2.0, kd=20.0))
        rated = baselines.make_policy("gradient", env, "arm_0", gains=Gains(kp=2.0, kd=20.0, rate_gain=0.015))
        first = observations["arm_0"]
        np.testing.assert_array_equal(rated(first), plain(first))  # no previous e_hat yet
        actions = {agent: np.full(env.action_space(agent).shape, 0.5, np.float32) for agent in env.agents}
        observations, *_ = env.step(actions)
        second = observations["arm_0"]
        layout = env.observation_layout("arm_0")
        e_prev, e_now = plain.gradient(layout.split(first)), plain.gradient(layout.split(second))
        jacobian = env.nominal_models[0].jacobian(layout.split(second).q)
        expected = plain(second) - 2.0 * (jacobian.T @ (0.015 / dt * (e_now - e_prev))) / env.task.torque_limits[0]
        np.testing.assert_allclose(rated(second), expected, rtol=1e-5, atol=1e-6)
        rated.reset()
        np.testing.assert_array_equal(rated(second), plain(second))
        for policy in ("approx_jacobian", "adaptive_jacobian"):  # the same term, and reset, in law-II/III
            law = baselines.make_policy(policy, env, "arm_0", gains=Gains(kp=2.0, kd=20.0, rate_gain=0.015))
            law(first)
            law.reset()
            assert law._previous_e_hat is None
        for bad in (-1.0, float("nan"), True):
            with pytest.raises(ValueError, match="gains.rate_gain"):
                baselines.make_policy("gradient", env, "arm_0", gains={"rate_gain": bad})
