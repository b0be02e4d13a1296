"""The RLlib backend: its PPO is the SB3 recipe's (one options owner), its module starts with the run's action
noise, its copies are split evenly among env runners, and a saved module is rebuilt with its own settings."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from ee_formation_env.baselines.learned.config import TrainConfig


def _config(*flags: str) -> TrainConfig:
    return TrainConfig.from_args(["--backend", "rllib", "--recipe", "none", "--no-progress", *flags])


def test_copies_that_do_not_split_evenly_among_env_runners_are_refused_naming_n_envs(tmp_path, capsys):
    from ee_formation_env.baselines.cli import train_command

    out = tmp_path / "run"
    with pytest.raises(SystemExit) as stopped:  # a parser error, before the run folder or Ray
        train_command(["--backend", "rllib", "--n-workers", "3", "--n-envs", "32", "--out", str(out)])
    assert stopped.value.code == 2
    assert "--n-envs: --backend rllib gives each of its --n-workers 3 env runners the same number of copies; " \
           "expected a multiple of 3, got 32" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("mode", ["residual", "torque"])
def test_rllib_ppo_takes_every_setting_from_the_run_as_sb3_does(mode):
    pytest.importorskip("ray.rllib")
    from ee_formation_env.baselines.learned.rllib_backend import ppo_config

    args = _config("--mode", mode, "--n-workers", "2")
    agents = 4
    config = ppo_config(args, agents)
    # One update learns from n_steps x n_envs x agents agent steps, in minibatches of min(1024, that), as SB3's.
    assert config.train_batch_size_per_learner * agents == args.n_steps * args.n_envs * agents
    assert config.minibatch_size == min(1024, args.n_steps * args.n_envs * agents)
    assert config.num_epochs == args.ppo.n_epochs and config.gamma == args.gamma
    assert (config.lambda_, config.clip_param, config.vf_loss_coeff, config.entropy_coeff) == (0.95, 0.2, 0.5, 0.0)
    assert config.grad_clip == 0.5 and config.grad_clip_by == "global_norm" and not config.use_kl_loss
    assert math.isinf(config.vf_clip_param)
    if args.ppo.learning_rate_decay:  # linear to 0 over the run, in env steps (every agent steps each env step)
        assert config.lr == [[0, args.ppo.learning_rate], [args.total_timesteps // agents, 0.0]]
    else:
        assert config.lr == args.ppo.learning_rate
    model = config.model_config
    assert list(model["fcnet_hiddens"]) == list(args.ppo.net_arch) and model["fcnet_activation"] == "tanh"
    assert model["free_log_std"] and not model["vf_share_layers"]
    assert config.num_env_runners == 2 and config.num_envs_per_env_runner == args.n_envs // 2
    assert config.rollout_fragment_length == args.n_steps
    assert config.seed == args.seed


def test_the_saved_module_starts_with_the_runs_action_noise_and_is_rebuilt_with_its_own_layers(tmp_path):
    pytest.importorskip("ray.rllib")
    from ee_formation_env.baselines.cli import train_command
    from ee_formation_env.baselines.learned.policy import rllib_predictor

    run_dir = tmp_path / "run"
    # One PPO iteration (16 env steps): a few Adam steps of 3e-4 move the log std by far less than 0.05.
    assert train_command(["--backend", "rllib", "--recipe", "none", "--mode", "torque", "--n-workers", "0",
                          "--n-envs", "2", "--n-steps", "8", "--total-timesteps", "64", "--log-std-init", "-1.5",
                          "--eval-episodes", "1", "--eval-seconds", "0.2", "--train-episode-seconds", "0.5",
                          "--out", str(run_dir), "--no-progress"]) == 0
    description = json.loads((run_dir / "model" / "rllib_module.json").read_text())
    assert description["model_config"]["fcnet_hiddens"] == [128, 128]  # the torque mode's layers, not RLlib's
    import torch

    state = torch.load(run_dir / "model" / "rllib_module.pt", weights_only=True)
    (log_std,) = [value for name, value in state.items() if name.endswith("log_std")]
    np.testing.assert_allclose(log_std.numpy(), -1.5, atol=0.05)  # one small update away from the start
    predict = rllib_predictor(run_dir / "model")
    action = predict(np.zeros(description["observation_shape"], dtype=np.float32))
    assert action.shape == (len(description["action_low"]),)
    timing = json.loads((run_dir / "timing.json").read_text())
    assert timing["env_runners"] == 0 and timing["copies_per_env_runner"] == 2 and timing["agent_steps"] >= 64


def test_the_scaling_benchmark_prints_a_row_per_env_runner_count(capsys):
    pytest.importorskip("ray.rllib")
    from benchmarks import rllib_scaling

    assert rllib_scaling.main(["--runners", "0", "--n-envs", "2", "--iterations", "1"]) == 0
    table = capsys.readouterr().out
    assert "| planar_square | 0 | 2 |" in table and "(driver)" in table
