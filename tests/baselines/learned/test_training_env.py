"""The batched training env: copy k is one single-copy training env (the PettingZoo view) reset with its seed, bit
for bit."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ee_formation_env.baselines.learned.options import TrainingOptions
from ee_formation_env.baselines.learned.training_env import BatchedTrainingEnv, ParallelTrainingEnv

# Physically scaled learned actions (its URDF efforts are far above its links' needs): action_scale.py.
KUKA_TEAM = str(Path(__file__).parents[3] / "studies" / "scenarios" / "kuka_team.yaml")

# (mode, settings) of the training envs compared: both modes, gated and plain residuals, features and shaping.
CASES = {
    "residual": TrainingOptions(mode="residual", residual_scale=0.1, residual_gate=False),
    "residual-gated": TrainingOptions(mode="residual", residual_gate=True, residual_scale=0.3, correction_penalty=0.8),
    "torque-shaped": TrainingOptions(mode="torque", hold_penalty=0.5, obs_features="log-error"),
    "residual-shaped": TrainingOptions(mode="residual", hold_penalty=1.0, obs_features="log-error"),
    "residual-invariant": TrainingOptions(mode="residual", residual_gate=True, obs_features="invariant"),
}


def _single(scenario: str, overrides: dict, options: TrainingOptions) -> Any:
    return ParallelTrainingEnv(scenario, overrides, options)


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("scenario, steps", [("planar_square", 40), ("spatial_tetrahedron", 12), (KUKA_TEAM, 12)])
def test_copies_are_single_training_envs_through_autoresets(closer, case, scenario, steps):
    if case == "residual-invariant" and scenario == "spatial_tetrahedron":
        pytest.skip("the PERA arm's first joint does not turn about its base z axis (no invariant features)")
    # Short episodes: every copy ends and restarts (its references reset) within the steps compared.
    overrides = {"episode_seconds": 0.15 if scenario == "planar_square" else 0.05}
    count, seeds = 3, [5, 11, 2]
    batched = closer(BatchedTrainingEnv(scenario, overrides, CASES[case], num_envs=count))
    singles = [closer(_single(scenario, overrides, CASES[case])) for _ in range(count)]
    agents = batched.possible_agents
    N, n = len(agents), batched.action_space(agents[0]).shape[0]
    result = batched.reset_arrays(seed=seeds)
    size = batched.observation_space(agents[0]).shape[0]
    for k, single in enumerate(singles):
        observations, _ = single.reset(seed=seeds[k])
        assert result.observations[k].tobytes() == np.concatenate([observations[a] for a in agents]).tobytes()
    rng = np.random.default_rng(0)
    ends = 0
    for _ in range(steps):
        actions = rng.uniform(-1.3, 1.3, (count * N, n)).astype(np.float32)
        result = batched.step_arrays(actions)
        for k, single in enumerate(singles):
            observations, rewards, terminations, truncations, _ = single.step(
                {agent: actions[k * N + i] for i, agent in enumerate(agents)})
            final = result.infos["final_observation"][k].reshape(N, size)
            for i, agent in enumerate(agents):
                assert final[i].tobytes() == observations[agent].tobytes(), (k, agent)
                assert result.rewards[k, i] == rewards[agent], (k, agent)
            assert result.terminations[k] == terminations[agents[0]]
            assert result.truncations[k] == truncations[agents[0]]
            if not single.agents:  # SAME_STEP autoreset: the batched copy already started its next episode
                ends += 1
                observations, _ = single.reset()
            assert result.observations[k].tobytes() == np.concatenate([observations[a] for a in agents]).tobytes()
    assert ends >= count


def test_spaces_are_the_single_training_envs(closer):
    batched = closer(BatchedTrainingEnv("planar_square", options=CASES["torque-shaped"], num_envs=2))
    single = closer(_single("planar_square", {}, CASES["torque-shaped"]))
    for agent in single.possible_agents:
        assert batched.observation_space(agent) == single.observation_space(agent)
        assert batched.action_space(agent) == single.action_space(agent)
    result = batched.reset_arrays(seed=0)
    assert result.observations.shape == (2, 4 * single.observation_space("arm_0").shape[0])
    assert result.observations.dtype == np.float32


@pytest.mark.parametrize("settings, message", [
    (dict(mode="imitation"), r"mode: expected one of \['residual', 'torque', 'velocity', 'position'\]"),
    (dict(obs_features="squared"), "obs_features: expected one of"),
    (dict(mode="residual", residual_scale=2.0), r"residual_scale: expected a value in \(0, 1\]"),
    (dict(mode="residual", reference="zero"), "reference: expected a model-based controller"),
    (dict(hold_penalty=-0.1), r"hold_penalty: expected a value in \[0, 1\]"),
])
def test_bad_settings_name_the_field_before_any_client_starts(settings, message, monkeypatch):
    import ee_formation_env

    monkeypatch.setattr(ee_formation_env, "vector_env", lambda *a, **k: pytest.fail("a client was built"))
    with pytest.raises(ValueError, match=message):
        BatchedTrainingEnv("planar_square", options=TrainingOptions(**settings), num_envs=2)


@pytest.mark.parametrize("bad, match", [
    (np.full((8, 2), np.nan), r"actions: expected finite values"),
    (np.zeros((8, 3)), r"actions: expected shape"),
    (np.array([["a", "b"]] * 8), r"actions: expected a numeric array"),
])
def test_bad_residuals_raise_before_any_copy_or_controller_moves(closer, bad, match):
    batched = closer(BatchedTrainingEnv("planar_square", options=TrainingOptions(mode="residual", residual_gate=True),
                                        num_envs=2))
    before = batched.reset_arrays(seed=0)
    positions = batched.env.joint_positions().copy()
    with pytest.raises(ValueError, match=match):
        batched.step_arrays(bad)
    assert all(np.all(policy.eta == 0) for policy in batched.action_rows.references)  # nothing adapted
    assert np.array_equal(batched.env.joint_positions(), positions)  # nothing moved
    after = batched.step_arrays(np.zeros((8, 2), np.float32))  # still usable, from the same start
    assert after.infos["sim_time"].tolist() == pytest.approx([batched.scenario.control_dt] * 2)
    assert before.observations.shape == after.observations.shape


def test_step_before_reset_is_refused(closer):
    batched = closer(BatchedTrainingEnv("planar_square", options=TrainingOptions(mode="residual"), num_envs=2))
    with pytest.raises(RuntimeError, match="call reset"):
        batched.step_arrays(np.zeros((8, 2)))
