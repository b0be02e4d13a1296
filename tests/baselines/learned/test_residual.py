"""Residual mode: a zero correction is the reference, bit for bit; the regularization is on the correction."""

from __future__ import annotations

import numpy as np
import pytest

from ee_formation_env import baselines
from ee_formation_env.baselines.learned.options import TrainingOptions
from ee_formation_env.baselines.learned.policy import ComposedPolicy
from ee_formation_env.baselines.learned.residual import ResidualRows, error_gate, error_gates
from ee_formation_env.baselines.learned.training_env import ParallelTrainingEnv


def _residual_env(scenario, overrides=None, **options):
    """The residual training env of one copy, without features or shaping."""
    return ParallelTrainingEnv(scenario, overrides, TrainingOptions(mode="residual", obs_features="none",
                                                                    hold_penalty=0.0, **options))


class _Zero:
    def reset(self) -> None:
        pass

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        return np.zeros(2, dtype=np.float32)


@pytest.mark.parametrize("reference,gate", [("gradient", False), ("adaptive_jacobian", False), ("adaptive_jacobian", True)])
def test_zero_correction_reproduces_the_reference_bit_for_bit(make_env, closer, reference, gate):
    plain = make_env("planar_square", episode_seconds=0.3)
    residual = closer(_residual_env("planar_square", {"episode_seconds": 0.3}, reference=reference,
                                    residual_scale=0.3, residual_gate=gate))
    policies = baselines.make_policies(reference, plain)
    observations, _ = plain.reset(seed=4)
    residual_observations, _ = residual.reset(seed=4)
    steps = 0
    while plain.agents:
        observations, rewards, *_ = plain.step({a: policies[a](observations[a]) for a in plain.agents})
        residual_observations, residual_rewards, *_ = residual.step(
            {a: np.zeros(2, dtype=np.float32) for a in plain.possible_agents})
        for agent in plain.possible_agents:
            assert observations[agent].tobytes() == residual_observations[agent].tobytes()
            assert rewards[agent] == residual_rewards[agent]  # a zero correction costs nothing
        steps += 1
    assert steps == 30 and not residual.agents


def test_residual_policy_with_zero_correction_is_the_reference(make_env):
    env = make_env("planar_square")
    references = baselines.make_policies("adaptive_jacobian", env)
    twins = baselines.make_policies("adaptive_jacobian", env)
    observations, _ = env.reset(seed=1)
    for agent in env.possible_agents:
        rule = ResidualRows([twins[agent]], 0.5, 0.5, [None], [None])
        policy = ComposedPolicy(_Zero(), env.observation_layout(agent), "none", rule)
        policy.reset()
        references[agent].reset()
        expected = np.asarray(references[agent](observations[agent]), dtype=np.float64)  # the rule's float64
        assert policy(observations[agent]).tobytes() == expected.tobytes()


def test_correction_penalty_scales_the_reward_by_the_correction_only(make_env, closer):
    plain = make_env("planar_square", episode_seconds=0.1)
    residual = closer(_residual_env("planar_square", {"episode_seconds": 0.1}, residual_scale=0.1,
                                    correction_penalty=0.5, residual_gate=False))
    plain_policies = baselines.make_policies("adaptive_jacobian", plain)
    observations, _ = plain.reset(seed=0)
    residual.reset(seed=0)
    correction = np.array([1.0, -0.5], dtype=np.float32)
    reference_actions = {a: plain_policies[a](observations[a]) for a in plain.agents}
    _, plain_rewards, *_ = plain.step({a: reference_actions[a] + 0.1 * correction.astype(np.float64)
                                      for a in plain.agents})
    _, rewards, *_ = residual.step({a: correction for a in plain.possible_agents})
    for agent in plain.possible_agents:
        assert rewards[agent] == pytest.approx(plain_rewards[agent] * (1 - 0.5 * np.mean(correction.astype(np.float64) ** 2)), rel=1e-12)
    rule = ResidualRows([plain_policies["arm_0"]], 0.1, 1.0, [None], [None])
    _, factors = rule(observations["arm_0"][None], np.array([[3.0, -3.0]]))
    assert factors[0] == 0.0  # the correction is clipped: rewards stay >= 0
    with pytest.raises(ValueError, match="correction_penalty"):
        TrainingOptions(correction_penalty=1.5)


@pytest.mark.parametrize("scenario", ["planar_square", "planar_square_displacement"])
def test_error_gate_is_the_agents_error_in_tolerances_capped_at_one(make_env, scenario):
    env = make_env(scenario)
    observations, _ = env.reset(seed=0)
    layout = env.observation_layout("arm_0")
    assert error_gate(layout, observations["arm_0"]) == 1.0  # the start is ~40 tolerances away
    parts = layout.split(observations["arm_0"])
    real = parts.mask > 0.5
    scaled = observations["arm_0"].astype(np.float64).copy()
    slots = scaled[:layout.n_slots * layout.slot_size].reshape(layout.n_slots, layout.slot_size)
    errors = slots[:, 1 + layout.dim + layout.error_width:]
    if layout.error_width == 1:  # every edge at a quarter of its tolerance 2 d delta
        errors[real, 0] = 0.25 * 2.0 * parts.desired[real, 0] * 0.01
    else:
        errors[real] = 0.0
        errors[real, 0] = 0.25 * 0.01
    assert error_gate(layout, scaled) == pytest.approx(0.25)
    errors[:] = 0.0
    assert error_gate(layout, scaled) == 0.0  # at the goal the correction vanishes


@pytest.mark.parametrize("scenario", ["planar_square", "planar_square_displacement"])
def test_error_gates_of_a_stack_are_each_agents_gate(make_env, scenario):
    env = make_env(scenario)
    observations, _ = env.reset(seed=2)
    layout = env.observation_layout("arm_0")
    stack = np.stack([observations[agent] for agent in env.possible_agents]).astype(np.float64)
    slots = stack[:, :layout.n_slots * layout.slot_size].reshape(len(stack), layout.n_slots, layout.slot_size)
    slots[:, :, 1 + layout.dim + layout.error_width:] *= 1e-4 * np.arange(1, len(stack) + 1)[:, None, None]
    stack[:, :layout.n_slots * layout.slot_size] = slots.reshape(len(stack), -1)
    gates = error_gates(layout, stack)
    assert gates.shape == (len(stack),) and 0 < gates.min() < gates.max() < 1  # near the goal: gates below 1
    for row, gate in zip(stack, gates):
        assert gate == error_gate(layout, row)


@pytest.mark.parametrize("bad, match", [
    ({"arm_0": np.zeros(3)}, r"actions\['arm_0'\]: expected shape \(2,\)"),
    ({"arm_1": "left"}, r"actions\['arm_1'\]: expected a numeric array"),
    ({"arm_2": np.array([np.nan, 0.0])}, r"actions\['arm_2'\]: expected finite values"),
])
def test_bad_residuals_get_the_envs_error_before_anything_moves(closer, bad, match):
    residual = closer(_residual_env("planar_square", residual_scale=0.3, residual_gate=True))
    observations, _ = residual.reset(seed=0)
    positions = residual.batched.env.joint_positions().copy()
    actions = {agent: np.zeros(2, dtype=np.float32) for agent in residual.possible_agents}
    with pytest.raises(ValueError, match=match):
        residual.step({**actions, **bad})
    assert np.array_equal(residual.batched.env.joint_positions(), positions)  # nothing moved
    assert all(np.all(policy.eta == 0) for policy in residual.batched.action_rows.references)  # nothing adapted
    after, *_ = residual.step(actions)  # the wrapper is still usable
    assert set(after) == set(observations)


class _Constant:
    """A reference controller that always asks for zero torque, so that the applied action is the correction."""

    def reset(self) -> None:
        pass

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        return np.zeros(2)


@pytest.mark.parametrize("power", [1.0, 2.0, 3.0])
def test_the_gate_power_raises_the_error_gate_to_that_power(make_env, power):
    env = make_env("planar_square")
    observations, _ = env.reset(seed=0)
    env.step({agent: np.full(2, 0.3, dtype=np.float32) for agent in env.agents})  # somewhere off the goal
    observations = env.batch.step_arrays(np.zeros((1, 8))).observations.reshape(4, -1)  # (N, size)
    layout = env.observation_layout("arm_0")
    gates = error_gates(layout, observations)
    rule = ResidualRows([_Constant() for _ in range(4)], 0.3, 0.0, [layout] * 4, [None] * 4, gate_power=power)
    applied, _ = rule(observations, np.ones((4, 2)))
    np.testing.assert_allclose(applied, 0.3 * (gates ** power)[:, None] * np.ones((4, 2)), rtol=0, atol=1e-15)
    assert 0 < gates.min() and (power == 1.0 or np.all(gates ** power <= gates))


def test_rules_of_different_gate_powers_do_not_stack():
    one = ResidualRows([_Constant()], 0.3, 0.0, [None], [None], gate_power=1.0)
    two = ResidualRows([_Constant()], 0.3, 0.0, [None], [None], gate_power=2.0)
    assert ResidualRows.concatenate([two, two]).gate_power == 2.0 and two.split()[0].gate_power == 2.0
    with pytest.raises(ValueError, match="gate powers"):
        ResidualRows.concatenate([one, two])


@pytest.mark.parametrize("power, error", [(0.5, ValueError), (9.0, ValueError), (float("nan"), ValueError),
                                          ("2", TypeError), (True, TypeError)])
def test_a_gate_power_outside_one_to_eight_is_refused_naming_the_field(power, error):
    with pytest.raises(error, match="residual_gate_power"):
        TrainingOptions(residual_gate_power=power)
