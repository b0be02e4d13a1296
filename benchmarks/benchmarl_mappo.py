"""BenchMARL MAPPO training throughput on a formation task (the ``torchrl`` extra): agent steps/s, updates included.

    python -m benchmarks.benchmarl_mappo                      # the recommended configuration, 4 iterations
    python -m benchmarks.benchmarl_mappo --config default     # BenchMARL's defaults (45 epochs per batch), 2 iterations
    python -m benchmarks.benchmarl_mappo --iterations 6 --task PLANAR_SQUARE

``recommended`` is the configuration of ``docs/training.md`` (64 natively batched copies, 8,000 frames per
batch, 4 epochs over minibatches of 2,000 frames); ``default`` is ``ExperimentConfig.get_from_yaml()`` as it
is. Both: 3 s training episodes, no loggers, no evaluation, no checkpoints (so that only collection and
updates are timed). Agent steps = frames (env steps) x agents; the time is ``Experiment.run()``'s wall
clock (collection, updates, BenchMARL's bookkeeping), the env construction excluded.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import warnings


def configure(config, name: str):
    if name == "recommended":
        config.on_policy_n_envs_per_worker = 64
        config.on_policy_collected_frames_per_batch = 8_000
        config.on_policy_n_minibatch_iters = 4
        config.on_policy_minibatch_size = 2_000
    elif name != "default":
        raise ValueError(f"--config: expected 'recommended' or 'default', got {name!r}")
    return config


def measure(name: str, iterations: int, task_name: str = "PLANAR_SQUARE", seed: int = 0) -> dict:
    import torch
    from benchmarl.algorithms import MappoConfig
    from benchmarl.experiment import Experiment, ExperimentConfig
    from benchmarl.models.mlp import MlpConfig

    from ee_formation_env.integrations.benchmarl import EEFormationTask

    torch.set_num_threads(1)
    config = configure(ExperimentConfig.get_from_yaml(), name)
    config.max_n_iters = iterations
    config.max_n_frames = None
    config.loggers = []
    config.evaluation = False
    config.render = False
    config.create_json = False
    config.checkpoint_at_end = False
    task = EEFormationTask[task_name].get_task({"episode_seconds": 3.0})
    with tempfile.TemporaryDirectory() as folder, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        config.save_folder = folder
        experiment = Experiment(task=task, algorithm_config=MappoConfig.get_from_yaml(),
                                model_config=MlpConfig.get_from_yaml(), critic_model_config=MlpConfig.get_from_yaml(),
                                seed=seed, config=config)
        n_agents = sum(len(agents) for agents in experiment.group_map.values())
        start = time.perf_counter()
        experiment.run()
        seconds = time.perf_counter() - start
    frames = experiment.total_frames
    return {"config": name, "task": task_name, "iterations": experiment.n_iters_performed, "frames": frames,
            "n_agents": n_agents, "seconds": seconds, "frames_per_s": frames / seconds,
            "agent_steps_per_s": frames * n_agents / seconds,
            "n_envs": config.on_policy_n_envs_per_worker, "frames_per_batch": config.on_policy_collected_frames_per_batch,
            "epochs": config.on_policy_n_minibatch_iters, "minibatch_size": config.on_policy_minibatch_size}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.benchmarl_mappo", description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="recommended", choices=("recommended", "default"))
    parser.add_argument("--iterations", type=int, default=None, help="MAPPO iterations (4 recommended, 2 default)")
    parser.add_argument("--task", default="PLANAR_SQUARE")
    args = parser.parse_args(argv)
    iterations = args.iterations or (4 if args.config == "recommended" else 2)
    result = measure(args.config, iterations, args.task)
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
