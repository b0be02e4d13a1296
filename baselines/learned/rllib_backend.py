"""The Ray RLlib backend of ``train.py --backend rllib``: PPO with one shared module for every agent.

RLlib pins its own gymnasium version, so it lives in the ``distributed`` extra and its own environment
(docs/training.md).
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from ee_formation_env.baselines.learned.config import TrainConfig
from ee_formation_env.baselines.learned.interruption import StopRequest
from ee_formation_env.baselines.learned.checkpoint import atomic_directory, write_json
from ee_formation_env.baselines.learned.policy import MODEL_FOLDER, ObservationNormalizer
from ee_formation_env.baselines.learned.training_env import env_factory


def train_rllib(args: TrainConfig, out_dir: Path, stop: StopRequest | None = None) -> dict[str, Any]:
    """Train ``args`` (a resolved configuration) with RLlib's PPO; writes the module, an identity normalizer
    (RLlib's default has no observation filter), ``timing.json`` and ``learning_curve.csv`` into ``out_dir``."""
    import ray
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.multi_rl_module import MultiRLModuleSpec
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv
    from ray.tune.registry import register_env

    ray.init(address=args.address, ignore_reinit_error=True, include_dashboard=False, log_to_driver=False,
             num_cpus=None if args.address else max(os.cpu_count() or 1, 1))
    factory = env_factory(args)
    register_env("ee_formation", lambda _config: ParallelPettingZooEnv(factory()))
    config = (
        PPOConfig()
        .environment("ee_formation")
        .framework("torch")
        .env_runners(num_env_runners=max(args.n_workers, 0), num_envs_per_env_runner=1,
                     rollout_fragment_length="auto")
        .multi_agent(policies={"shared"}, policy_mapping_fn=lambda agent_id, *a, **k: "shared")
        .rl_module(rl_module_spec=MultiRLModuleSpec(rl_module_specs={"shared": RLModuleSpec()}))
        .training(train_batch_size_per_learner=2048, minibatch_size=256, num_epochs=5, lr=3e-4, gamma=args.gamma)
        .debugging(seed=args.seed)
    )
    algorithm = config.build_algo() if hasattr(config, "build_algo") else config.build()
    started, history, steps = time.time(), [], 0
    while steps < args.total_timesteps and not (stop is not None and stop.requested):
        result = algorithm.train()
        steps = int(result.get("num_env_steps_sampled_lifetime", steps + 2048) or steps + 2048)
        ret = result.get("env_runners", {}).get("episode_return_mean", math.nan)
        history.append((steps, float(ret) if ret is not None else math.nan))
    interrupted = stop.signal_name if stop is not None and stop.requested else None
    timing = {"train_seconds": time.time() - started, "agent_steps": steps, "interrupted": interrupted}
    write_json(out_dir / "timing.json", timing)
    # RLlib's own checkpoint, for RLlib users: it holds pickles and the project never reads it back.
    algorithm.save(str((out_dir / "rllib_checkpoint").resolve()))
    save_rllib_module(algorithm.get_module("shared"), out_dir / MODEL_FOLDER)
    with open(out_dir / "learning_curve.csv", "w", encoding="utf-8") as handle:
        handle.write("agent_steps,episode_return\n")
        handle.writelines(f"{s},{r}\n" for s, r in history)
    algorithm.stop()
    if not args.address:
        ray.shutdown()
    return timing


def save_rllib_module(module: Any, model_dir: Path) -> None:
    """The shared module as plain data in ``model_dir`` (atomically): its parameters (``rllib_module.pt``, a
    ``state_dict``), its spaces (``rllib_module.json``) and an identity normalizer (RLlib's default has no
    observation filter). :func:`ee_formation_env.baselines.learned.policy.rllib_predictor` rebuilds it from
    RLlib's default PPO module."""
    import torch

    with atomic_directory(model_dir) as partial:
        torch.save(module.state_dict(), partial / "rllib_module.pt")
        space = module.action_space
        write_json(partial / "rllib_module.json", {"observation_shape": list(module.observation_space.shape),
                                                    "action_low": space.low.tolist(),
                                                    "action_high": space.high.tolist()})
        dim = int(np.prod(module.observation_space.shape))
        ObservationNormalizer.identity(dim).save(partial / "obs_normalizer.json")
