"""The action check: actions of any array type (numpy, lists, torch tensors, objects with ``__array__``) are
converted, or refused in one line naming the agent, before any copy moves."""

from __future__ import annotations

import numpy as np
import pytest

import ee_formation_env


class ArrayLike:
    """A jax-like array: numpy sees it only through ``__array__``."""

    def __init__(self, values, fail: bool = False):
        self.values, self.fail = np.asarray(values), fail

    def __array__(self, dtype=None, copy=None):
        if self.fail:
            raise RuntimeError("the device buffer was deleted")
        return self.values if dtype is None else self.values.astype(dtype)


def _step_with(env, convert):
    env.reset(seed=0)
    actions = {agent: convert(np.full(env.action_space(agent).shape, 0.25 * (i + 1), np.float32))
               for i, agent in enumerate(env.agents)}
    return env.step(actions)[0]


def test_torch_tensors_that_require_grad_lists_and_array_likes_step_as_numpy_arrays(make_env):
    torch = pytest.importorskip("torch")
    env = make_env("planar_square")
    expected = _step_with(env, lambda a: a)
    for convert in (lambda a: torch.tensor(a, requires_grad=True), torch.from_numpy, lambda a: a.tolist(),
                    ArrayLike):
        observations = _step_with(env, convert)
        for agent in env.possible_agents:
            assert np.array_equal(observations[agent], expected[agent])


def test_a_torch_batch_that_requires_grad_steps_the_batched_env(closer):
    torch = pytest.importorskip("torch")
    batched = closer(ee_formation_env.vector_env("planar_square", num_envs=2, episode_seconds=0.5))
    actions = np.linspace(-0.5, 0.5, 16).reshape(2, 8)
    batched.reset(seed=0)
    expected = batched.step_arrays(actions).observations
    batched.reset(seed=0)
    assert np.array_equal(batched.step_arrays(torch.tensor(actions, requires_grad=True)).observations, expected)
    batched.reset(seed=0)
    observations = batched.step({agent: torch.tensor(actions[:, 2 * i:2 * i + 2], requires_grad=True)
                                 for i, agent in enumerate(batched.possible_agents)})[0]
    assert np.array_equal(np.concatenate([observations[agent] for agent in batched.possible_agents], axis=1),
                          expected)


def test_an_action_that_cannot_be_converted_is_refused_naming_the_agent_before_anything_moves(make_env):
    torch = pytest.importorskip("torch")
    env = make_env("planar_square")
    env.reset(seed=0)
    state = env.state()
    good = {agent: np.zeros(2) for agent in env.agents}
    for bad in (ArrayLike([0.0, 0.0], fail=True), torch.zeros(2, dtype=torch.complex64, requires_grad=True),
                torch.tensor([0.0, float("nan")], requires_grad=True)):
        with pytest.raises(ValueError, match=r"^actions\['arm_2'\]: expected (a numeric array|finite values)"):
            env.step({**good, "arm_2": bad})
    assert np.array_equal(env.state(), state)
