"""The paper's controllers: convergence, the printed law's stall, gravity and model mismatch."""

from __future__ import annotations

import numpy as np
import pytest

import baselines
import ee_formation_env
from baselines.gains import PAPER_GAINS, default_gains
from baselines.metrics import run_episode
from ee_formation_env.scenario import _square, builtin_scenario

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
    """FACTS.md: far from the target the printed law collapses a_hat to its spurious equilibrium 0."""
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
