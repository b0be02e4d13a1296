"""The Ray RLlib backend of ``train.py --backend rllib``: PPO with one shared module for every agent, set from
the same resolved :class:`~ee_formation_env.baselines.learned.config.TrainConfig` as the SB3 backend.

:func:`ppo_config` is the one translation of the run's settings into RLlib's: the same batch of agent steps
per update, minibatch, epochs, learning rate (and its decay), discount, GAE, clipping, gradient norm, network
and initial action noise as SB3's PPO gets. What RLlib cannot take from the SB3 recipe is SB3's
``VecNormalize``: RLlib's ``MeanStdFilter`` keeps one statistic per agent id, which one module shared by every
agent cannot carry into evaluation, so observations and rewards go unnormalized. The copies: ``n_envs`` of
them, ``n_envs / n_workers`` in each of ``n_workers`` env runners (all in the driver's local runner with 0).
RLlib 2.x vectorizes a multi-agent env runner by holding several ``MultiAgentEnv`` copies, each stepped on its
own with next-step autoreset, which a batched physics step cannot give without pausing ended copies; so each
copy is one ``ParallelTrainingEnv`` (docs/training.md, "RLlib"). RLlib pins its own gymnasium version, so it
lives in the ``distributed`` extra and its own environment (docs/getting-started.md).
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from ee_formation_env.baselines.atomic_files import write_text
from ee_formation_env.baselines.learned.algorithms import algorithm
from ee_formation_env.baselines.learned.config import TrainConfig
from ee_formation_env.baselines.learned.interruption import StopRequest
from ee_formation_env.baselines.learned.checkpoint import atomic_directory, read_json, write_json
from ee_formation_env.baselines.learned.policy import ObservationNormalizer
from ee_formation_env.baselines.learned.run_files import CONFIG, MODEL_FOLDER, STAMP, model_stamp
from ee_formation_env.baselines.learned.training_env import env_factory

#: RLlib's module settings that make it SB3's ``MlpPolicy``: tanh layers of the mode's widths, separate actor and
#: critic networks, a state-independent log standard deviation.
MODULE_SETTINGS = {"fcnet_activation": "tanh", "vf_share_layers": False, "free_log_std": True}


def env_runner_copies(args: TrainConfig) -> tuple[int, int]:
    """(env runners, copies per runner): ``n_envs`` copies over ``n_workers`` runners (the local one for 0)."""
    runners = max(args.n_workers, 0)
    return runners, args.n_envs // max(runners, 1)


def module_config(args: TrainConfig) -> dict[str, Any]:
    """The shared module's ``DefaultModelConfig`` fields (saved with the module, read back by the predictor)."""
    return {"fcnet_hiddens": list(args.ppo.net_arch), **MODULE_SETTINGS}


def ppo_hyperparameters(args: TrainConfig) -> dict[str, Any]:
    """The PPO settings both backends share: the algorithm's hyperparameter file, as SB3 reads it
    (``algorithm_conf/ppo.yaml``, :func:`~ee_formation_env.baselines.learned.sb3_backend.sb3_hyperparameters`)."""
    from ee_formation_env.baselines.learned.sb3_backend import sb3_hyperparameters

    return sb3_hyperparameters(algorithm(args.algo, "--algo", ("rllib",)))


def minibatch_size(args: TrainConfig, agents: int) -> int:
    """Agent steps per minibatch: SB3's min(batch_size, one update's agent steps) (1,024 in ppo.yaml). RLlib splits each module's rows (agent
    steps) into minibatches but checks the size against the batch in env steps, so an update of fewer than 1,024
    env steps (a smoke run) gets minibatches of that many rows."""
    env_steps_per_update = args.n_steps * args.n_envs
    return min(ppo_hyperparameters(args)["batch_size"], env_steps_per_update * agents, env_steps_per_update)


def ppo_config(args: TrainConfig, agents: int) -> Any:
    """RLlib's ``PPOConfig`` for ``args`` (resolved) on a team of ``agents``: the SB3 recipe's settings, the
    ``ee_formation`` env (registered by :func:`train_rllib`) and one module ``shared`` by every agent."""
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig
    from ray.rllib.core.rl_module.multi_rl_module import MultiRLModuleSpec
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec

    runners, copies = env_runner_copies(args)
    settings = ppo_hyperparameters(args)
    env_steps_per_update = args.n_steps * args.n_envs  # each env step is one step of every agent
    rate = args.ppo.learning_rate
    # SB3 decays linearly to 0 over the run's agent steps; RLlib's schedule is in env steps sampled.
    learning_rate = [[0, rate], [max(args.total_timesteps // agents, 1), 0.0]] if args.ppo.learning_rate_decay else rate
    return (
        PPOConfig()
        .environment("ee_formation", disable_env_checking=True)
        .framework("torch")
        .env_runners(num_env_runners=runners, num_envs_per_env_runner=copies, rollout_fragment_length=args.n_steps,
                     gym_env_vectorize_mode="sync")
        .multi_agent(policies={"shared"}, policy_mapping_fn=lambda agent_id, *a, **k: "shared",
                     count_steps_by="env_steps")
        .rl_module(rl_module_spec=MultiRLModuleSpec(rl_module_specs={"shared": RLModuleSpec()}),
                   model_config=DefaultModelConfig(**module_config(args)))
        .training(train_batch_size_per_learner=env_steps_per_update,
                  minibatch_size=minibatch_size(args, agents), num_epochs=args.ppo.n_epochs,
                  lr=learning_rate, gamma=args.gamma, lambda_=settings["gae_lambda"],
                  clip_param=settings["clip_range"], vf_loss_coeff=settings["vf_coef"],
                  entropy_coeff=settings["ent_coef"], use_kl_loss=False, vf_clip_param=math.inf,
                  grad_clip=settings["max_grad_norm"], grad_clip_by="global_norm")
        .debugging(seed=args.seed)
    )


def _set_initial_log_std(algorithm: Any, log_std: float) -> None:
    """Every learner's shared module starts with the run's ``log_std_init`` (RLlib starts at 0), then the env
    runners get those weights."""
    import torch

    def set_log_std(learner: Any) -> None:
        module = learner.module["shared"]
        with torch.no_grad():
            for name, parameter in module.named_parameters():
                if name.endswith("log_std"):
                    parameter.fill_(log_std)

    algorithm.learner_group.foreach_learner(set_log_std)
    algorithm.env_runner_group.sync_weights(from_worker_or_learner_group=algorithm.learner_group)


def train_rllib(args: TrainConfig, out_dir: Path, stop: StopRequest | None = None) -> dict[str, Any]:
    """Train ``args`` (a resolved configuration) with RLlib's PPO (:func:`ppo_config`) to ``total_timesteps``
    agent steps, or ``max_train_seconds``; writes the module, an identity normalizer, ``timing.json`` and
    ``learning_curve.csv`` into ``out_dir``."""
    import ray
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv
    from ray.tune.registry import register_env

    factory = env_factory(args)
    probe = factory()
    agents = len(probe.possible_agents)
    probe.close()
    # Without --address a fresh local instance: never a cluster someone else started on this machine.
    ray.init(address=args.address or "local", ignore_reinit_error=True, include_dashboard=False, log_to_driver=False,
             num_cpus=None if args.address else max(os.cpu_count() or 1, 1))
    register_env("ee_formation", lambda _config: ParallelPettingZooEnv(factory()))
    config = ppo_config(args, agents)
    algorithm = config.build_algo()
    _set_initial_log_std(algorithm, args.log_std_init)
    started, history, agent_steps, env_steps = time.time(), [], 0, 0
    deadline = math.inf if args.max_train_seconds is None else started + args.max_train_seconds
    while agent_steps < args.total_timesteps and time.time() < deadline and not (stop is not None and stop.requested):
        result = algorithm.train()
        env_steps = int(result.get("num_env_steps_sampled_lifetime") or env_steps + args.n_steps * args.n_envs)
        agent_steps = env_steps * agents
        episode_return = result.get("env_runners", {}).get("episode_return_mean")
        if episode_return is not None and math.isfinite(episode_return):  # None or nan: no episode ended
            history.append((agent_steps, float(episode_return) / agents))
    interrupted = stop.signal_name if stop is not None and stop.requested else None
    seconds = time.time() - started
    timing = {"train_seconds": seconds, "agent_steps": agent_steps, "interrupted": interrupted,
              "agent_steps_per_second": agent_steps / seconds if seconds > 0 else 0.0,
              "env_runners": env_runner_copies(args)[0], "copies_per_env_runner": env_runner_copies(args)[1]}
    write_json(out_dir / "timing.json", timing)
    # RLlib's own checkpoint, for RLlib users: it holds pickles and the project never reads it back.
    algorithm.save(str((out_dir / "rllib_checkpoint").resolve()))
    save_rllib_module(algorithm.get_module("shared"), out_dir / MODEL_FOLDER, module_config(args),
                      read_json(out_dir / CONFIG, CONFIG))
    # the mean return per agent, as SB3's monitor reports it
    rows = "".join(f"{steps},{value}\n" for steps, value in history)
    write_text(out_dir / "learning_curve.csv", "agent_steps,episode_return\n" + rows)
    algorithm.stop()
    if not args.address:
        ray.shutdown()
    return timing


def save_rllib_module(module: Any, model_dir: Path, model_config: dict[str, Any], config: dict[str, Any]) -> None:
    """The shared module as plain data in ``model_dir`` (atomically): its parameters (``rllib_module.pt``, a
    ``state_dict``), its spaces and ``model_config`` (``rllib_module.json``), an identity normalizer (the
    module saw raw observations) and the model's stamp for the run's ``config`` (config.json's content:
    :mod:`~ee_formation_env.baselines.learned.run_files`).
    :func:`ee_formation_env.baselines.learned.policy.rllib_predictor` rebuilds it from RLlib's default PPO
    module."""
    import torch

    with atomic_directory(model_dir) as partial:
        torch.save(module.state_dict(), partial / "rllib_module.pt")
        space = module.action_space
        write_json(partial / "rllib_module.json", {"observation_shape": list(module.observation_space.shape),
                                                    "action_low": space.low.tolist(),
                                                    "action_high": space.high.tolist(),
                                                    "model_config": model_config})
        dim = int(np.prod(module.observation_space.shape))
        ObservationNormalizer.identity(dim).save(partial / "obs_normalizer.json")
        write_json(partial / STAMP, model_stamp(config, dim, int(np.prod(space.shape))))
