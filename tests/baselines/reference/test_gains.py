"""Default gains and the rule that derives stable gains for any robot."""

from __future__ import annotations

import numpy as np
import pytest

from ee_formation_env import baselines
import ee_formation_env
from ee_formation_env.baselines.reference.dynamics import nominal_dynamics
from ee_formation_env.baselines.reference.gains import INTERNAL_MODEL_GAIN, default_gains, derive_gains
from ee_formation_env.baselines.metrics import run_episode
from ee_formation_env.scenario import BUILTIN_SCENARIOS, load_scenario
from ee_formation_env.task import build_task

KUKA_TRIANGLE = {
    "name": "kuka_triangle",
    "arms": [
        {"urdf": "kuka_iiwa/model.urdf", "ee_link": "lbr_iiwa_link_7", "base_position": [0, 0, 0],
         "initial_q": [0, 0.6, 0, -1.2, 0, 0.8, 0]},
        {"urdf": "kuka_iiwa/model.urdf", "ee_link": "lbr_iiwa_link_7", "base_position": [0, 1.0, 0],
         "initial_q": [0, 0.6, 0, -1.2, 0, 0.8, 0]},
        {"urdf": "kuka_iiwa/model.urdf", "ee_link": "lbr_iiwa_link_7", "base_position": [0.9, 0.5, 0],
         "initial_q": [2.9, 0.6, 0, -1.2, 0, 0.8, 0]},
    ],
    "edges": [[0, 1], [1, 2], [2, 0]],
    "shape": [[0.5, 0.2, 0.6], [0.5, 0.8, 0.6], [0.3, 0.5, 0.7]],
    "formation": "distance", "dim": 3, "episode_seconds": 15.0, "torque_limits": 50.0,
}


def test_every_builtin_scenario_has_tuned_defaults():
    for name in BUILTIN_SCENARIOS:
        scenario = load_scenario(name)
        # A distribution's draws differ in layout and shape: each derives its own gains (test_distribution.py).
        assert (scenario.controller_gains is None) == scenario.distribution.active, name


def test_tuned_gains_apply_only_to_the_physics_they_were_tuned_for():
    tuned = load_scenario("planar_square").controller_gains
    # A gain-neutral override keeps them; an override of the physics (torque limits, rates) drops them.
    assert load_scenario("planar_square", episode_seconds=5.0, initial_q_noise=0.0).controller_gains == tuned
    assert load_scenario("planar_square", frame_skip=10).controller_gains == tuned  # the same value: no change
    for override in ({"torque_limits": 1.0}, {"frame_skip": 1}, {"physics_hz": 500.0}):
        scenario = load_scenario("planar_square", **override)
        assert scenario.controller_gains is None, override
        gains, derived = default_gains(build_task(scenario), 0), derive_gains(build_task(scenario), 0)
        np.testing.assert_array_equal(gains.kp, derived.kp)
        np.testing.assert_array_equal(gains.kd, derived.kd)
        assert not np.allclose(gains.kp, tuned.kp)
    # Explicit gains with the override are kept.
    explicit = {"kp": 1.0, "kd": 2.0, "ki": 0.0, "alpha": 0.1}
    assert load_scenario("planar_square", torque_limits=1.0, controller_gains=explicit).controller_gains.kp == 1.0


def test_derived_gains_need_no_env():
    gains = derive_gains(build_task(load_scenario(KUKA_TRIANGLE)), 1)
    assert np.all(np.asarray(gains.kp) > 0) and np.all(np.asarray(gains.kd) > 0)


def test_derived_damping_respects_the_explicit_step_rule():
    with ee_formation_env.parallel_env(KUKA_TRIANGLE) as env:
        gains = derive_gains(env.task, 0)
        chain = env.nominal_models[0]
        dynamics = nominal_dynamics(env.scenario.arms[0].urdf, chain.joint_names)
        dt = env.scenario.control_dt
        for q in chain.sample_configurations(50, np.random.default_rng(1)):
            radius = np.max(np.abs(np.linalg.eigvals(dt * np.linalg.inv(dynamics.mass_matrix(q)) * gains.kd)))
            assert radius <= 1.0 + 1e-9
        assert np.all(np.asarray(gains.kd) > 0)
        assert gains.ki == INTERNAL_MODEL_GAIN  # gravity loads the kuka's joints


@pytest.mark.parametrize("policy", ["gradient", "adaptive_jacobian"])
def test_derived_gains_converge_on_a_robot_without_tuned_defaults(policy):
    with ee_formation_env.parallel_env(KUKA_TRIANGLE, initial_q_noise=0.0) as env:
        assert env.scenario.controller_gains is None  # so make_policy uses derive_gains
        metrics = run_episode(env, baselines.make_policies(policy, env), seed=0)
        assert metrics.physics_fault == ""
        assert metrics.success, metrics.final_formation_error


def test_derived_formation_gain_is_one_scalar_within_the_step_rule():
    """K_P and the spring force are shared by every arm (one potential), and the stiffness they add keeps
    dt^2 rho(H^-1 K_q) <= KAPPA at sampled configurations (rule 3 of ee_formation_env.baselines.reference.gains)."""
    from ee_formation_env.baselines.reference.gains import KAPPA, arm_inputs, formation_gains, formation_stiffness

    task = build_task(load_scenario(KUKA_TRIANGLE))
    incident = [[n.edge for n in neighbors] for neighbors in task.graph.neighbors]
    gains = formation_gains(arm_inputs(task), task.scenario.control_dt, task.formation.kind, incident,
                            formation_stiffness(task))
    assert len({float(g.kp) for g in gains}) == 1 and np.ndim(gains[0].kp) == 0
    assert float(derive_gains(task, 0).kp) == float(gains[0].kp)
    # Each edge's spring force is the same at both of its ends.
    for k in range(task.graph.n_edges):
        forces = {gains[i].spring_force[incident[i].index(k)] for i in range(len(gains)) if k in incident[i]}
        assert len(forces) == 1 and 0 < forces.pop() < np.inf
    chain = task.models[0]
    dynamics = nominal_dynamics(task.scenario.arms[0].urdf, chain.joint_names)
    stiffness = formation_stiffness(task)
    dt = task.scenario.control_dt
    for q in chain.sample_configurations(50, np.random.default_rng(2)):
        jacobian = chain.jacobian(q)
        k_q = gains[0].kp * stiffness * jacobian.T @ jacobian
        radius = np.max(np.abs(np.linalg.eigvals(dt**2 * np.linalg.solve(dynamics.mass_matrix(q), k_q))))
        assert radius <= KAPPA * 1.05  # sampled: a little above the rule's own samples is possible


def test_formation_gains_reject_bad_input():
    from ee_formation_env.baselines.reference.gains import arm_inputs, formation_gains

    task = build_task(load_scenario(KUKA_TRIANGLE))
    incident = [[0, 2], [0, 1], [1, 2]]
    with pytest.raises(ValueError, match="control_dt"):
        formation_gains(arm_inputs(task), 0.0, "distance", incident, 1.0)
    with pytest.raises(ValueError, match="formation_kind"):
        formation_gains(arm_inputs(task), 0.01, "bearing", incident, 1.0)
    with pytest.raises(ValueError, match="incident_edges"):
        formation_gains(arm_inputs(task), 0.01, "distance", [[0, 2]], 1.0)
    with pytest.raises(ValueError, match="formation_stiffness"):
        formation_gains(arm_inputs(task), 0.01, "distance", incident, 0.0)


def test_rate_term_keeps_every_sampled_mode_stable_at_low_damping():
    """Rules 1, 3 and 5: with K_R = 1.5 dt every mode with kappa <= 0.75 and beta in [0, 1] decays
    (control held over the step); without it beta = 0.1 is unstable at kappa = 0.5, the rule's bound."""
    from ee_formation_env.baselines.reference.gains import BETA, KAPPA, mode_decay

    kappas, betas = np.linspace(1e-4, 0.75, 60), np.linspace(0.0, 1.0, 11)
    assert max(mode_decay(k, b) for k in kappas for b in betas) < 1.0
    assert mode_decay(KAPPA, BETA, rate_steps=0.0) > 1.0
    assert mode_decay(KAPPA, BETA) < 0.85


def test_derived_damping_is_low_without_gravity_and_the_rate_gain_is_set():
    from ee_formation_env.baselines.reference.gains import BETA, RATE_STEPS

    scenario = load_scenario("planar_square", torque_limits=50.0, frame_skip=10, initial_q_noise=0.0,
                             physics_hz=1000.0, episode_seconds=1.0, controller_gains=None)
    with ee_formation_env.parallel_env(scenario) as env:
        gains = derive_gains(env.task, 0)
        chain = env.nominal_models[0]
        dynamics = nominal_dynamics(env.scenario.arms[0].urdf, chain.joint_names)
        dt = env.scenario.control_dt
        radius = max(np.max(np.abs(np.linalg.eigvals(dt * np.linalg.inv(dynamics.mass_matrix(q)) * gains.kd)))
                     for q in chain.sample_configurations(50, np.random.default_rng(1)))
        assert 0.5 * BETA < radius <= BETA * 1.05
        assert gains.ki == 0.0 and gains.rate_gain == pytest.approx(RATE_STEPS * dt)
