"""Train a shared formation policy and compare it with the reference controllers on the same metrics.

    python train.py                                   # default: PPO on planar_square, ~10 min on 2 cores
    python train.py --mode residual --total-timesteps 400000
    python train.py --backend rllib --total-timesteps 20000
    python train.py --eval-only runs/<name>           # re-evaluate a saved run

One policy is shared by every agent, each acting on its own local observation (decentralized execution).
``--mode torque``: the policy outputs normalized joint torques. ``--mode residual``: its output, scaled by
``--residual-scale``, is added to a reference controller's action (``--reference``).

Every run writes to ``--out`` (default ``runs/<name>``): ``config.json``, the model and its observation
normalization, TensorBoard logs, checkpoints, ``learning_curve.csv``, and the comparison against every
reference policy on held-out seeds (``comparison.json``, ``comparison.md``, ``comparison.png``), computed by
``baselines.metrics`` exactly as ``python -m baselines.evaluate`` does.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import pickle
import platform
import sys
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

import baselines
import ee_formation_env
from baselines.extras import require
from baselines.metrics import format_table, run_episode, summarize
from baselines.residual import ResidualPolicy, make_training_env

EVAL_SEED_OFFSET = 10_000  # held-out evaluation seeds start here; training resets use seeds below it


# ------------------------------------------------------------------------------------------ arguments
def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="train.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="planar_square", help="built-in name or YAML/JSON scenario file")
    parser.add_argument("--mode", choices=("torque", "residual"), default="torque")
    parser.add_argument("--reference", default="adaptive_jacobian",
                        choices=baselines.MODEL_BASED_POLICIES,
                        help="reference controller of --mode residual")
    parser.add_argument("--residual-scale", type=float, default=0.1, help="residual action scale (0, 1]")
    parser.add_argument("--algo", choices=("ppo", "sac"), default="ppo")
    parser.add_argument("--backend", choices=("sb3", "rllib"), default="sb3")
    parser.add_argument("--total-timesteps", type=int, default=600_000, help="agent steps (all agents count)")
    parser.add_argument("--n-envs", type=int, default=2, help="parallel envs (each with all its agents)")
    parser.add_argument("--n-workers", type=int, default=0,
                        help="worker processes for the envs (0 = step them in this process, the fastest for "
                             "the planar scenarios; use 2 on 2 cores for costlier scenarios)")
    parser.add_argument("--train-episode-seconds", type=float, default=None,
                        help="episode length while training, s (default: the scenario's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="run directory (default runs/<name>)")
    parser.add_argument("--eval-only", metavar="RUN_DIR", default=None, help="evaluate a saved run only")
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--eval-seconds", type=float, default=None,
                        help="episode length for the comparison, s (default: the scenario's)")
    parser.add_argument("--address", default=None, help="rllib: address of an existing Ray cluster")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    if args.total_timesteps < 1 or args.n_envs < 1 or args.eval_episodes < 1:
        parser.error("--total-timesteps, --n-envs and --eval-episodes must be >= 1")
    if not 0 < args.residual_scale <= 1:
        parser.error("--residual-scale: expected a value in (0, 1]")
    if args.n_workers < 0:
        parser.error("--n-workers must be >= 0")
    if args.backend == "rllib" and args.algo != "ppo":
        parser.error("--backend rllib supports --algo ppo only")
    return args


def require_training_extras(args: argparse.Namespace, config: dict[str, Any] | None = None) -> None:
    """Fail in one line naming the pip extra, before anything is created, if a needed package is missing.

    ``config``: a saved run's (``--eval-only``), whose backend decides what reloading its model needs.
    """
    backend = config["backend"] if config else args.backend
    modules = ["torch", "matplotlib"]  # the model, comparison.png
    if backend == "sb3":
        modules += ["stable_baselines3", "tensorboard"]  # SB3 logs to TensorBoard
        if not args.no_progress and not config:
            modules += ["tqdm", "rich"]  # SB3's progress bar
        extras = "train"
    else:
        modules.append("ray.rllib")
        extras = "train,distributed"
    require(modules, extras, f"train.py (--backend {backend})")


def run_name(args: argparse.Namespace) -> str:
    scenario = Path(str(args.scenario)).stem
    return f"{scenario}-{args.mode}-{args.algo}-{args.backend}-seed{args.seed}-{time.strftime('%Y%m%d-%H%M%S')}"


def training_overrides(args: argparse.Namespace) -> dict[str, Any]:
    return {} if args.train_episode_seconds is None else {"episode_seconds": args.train_episode_seconds}


def env_factory(args: argparse.Namespace, overrides: dict[str, Any] | None = None) -> Callable[[], Any]:
    """A picklable factory of the env the learner steps."""
    return functools.partial(make_training_env, args.scenario, overrides, args.mode, args.reference,
                             args.residual_scale)


# ------------------------------------------------------------------------------------------ learned policy
class ObservationNormalizer:
    """Running mean/variance normalization of observations, as learned during training."""

    def __init__(self, mean: np.ndarray, var: np.ndarray, clip: float = 10.0, epsilon: float = 1e-8):
        self.mean, self.var, self.clip, self.epsilon = mean, var, clip, epsilon

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        normalized = (observation - self.mean) / np.sqrt(self.var + self.epsilon)
        return np.clip(normalized, -self.clip, self.clip).astype(np.float32)

    def save(self, path: Path) -> None:
        with open(path, "wb") as handle:
            pickle.dump({"mean": self.mean, "var": self.var, "clip": self.clip, "epsilon": self.epsilon}, handle)

    @classmethod
    def identity(cls, dim: int) -> "ObservationNormalizer":
        """A normalizer that leaves observations unchanged."""
        return cls(np.zeros(dim), np.ones(dim), clip=np.inf, epsilon=0.0)

    @classmethod
    def load(cls, path: Path) -> "ObservationNormalizer":
        with open(path, "rb") as handle:
            return cls(**pickle.load(handle))


class LearnedPolicy:
    """A trained shared policy as a per-agent policy: ``reset()`` and ``__call__(observation)``."""

    def __init__(self, predict: Callable[[np.ndarray], np.ndarray], normalizer: ObservationNormalizer):
        self.predict, self.normalizer = predict, normalizer

    def reset(self) -> None:
        pass

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        return np.clip(self.predict(self.normalizer(observation)), -1.0, 1.0)


def learned_policies(run_dir: Path, env: Any, config: dict[str, Any]) -> dict[str, Any]:
    """Per-agent policies of a saved run, the residual composition included."""
    normalizer = ObservationNormalizer.load(run_dir / "obs_normalizer.pkl")
    if config["backend"] == "sb3":
        from stable_baselines3 import PPO, SAC

        model = (PPO if config["algo"] == "ppo" else SAC).load(run_dir / "model.zip", device="cpu")
        predict = lambda obs: model.predict(obs, deterministic=True)[0]  # noqa: E731
    else:
        predict = _rllib_predictor(run_dir)
    learned = LearnedPolicy(predict, normalizer)
    if config["mode"] == "torque":
        return {agent: learned for agent in env.possible_agents}
    references = baselines.make_policies(config["reference"], env)
    return {agent: ResidualPolicy(references[agent], learned, config["residual_scale"])
            for agent in env.possible_agents}


# ------------------------------------------------------------------------------------------ sb3
def train_sb3(args: argparse.Namespace, out_dir: Path) -> None:
    from stable_baselines3 import PPO, SAC
    from stable_baselines3.common.callbacks import CheckpointCallback
    from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

    from ee_formation_env.sb3 import SharedPolicyVecEnv

    import torch

    torch.set_num_threads(1)  # a 64x64 MLP gains nothing from more threads; they would compete with the envs
    factory = env_factory(args, training_overrides(args))
    venv = SharedPolicyVecEnv([factory] * args.n_envs, n_workers=args.n_workers)
    venv = VecMonitor(venv, filename=str(out_dir / "monitor.csv"))
    venv = VecNormalize(venv, norm_obs=True, norm_reward=True, gamma=0.99)
    # A residual policy should start close to "no correction": a smaller initial action noise.
    policy_kwargs: dict[str, Any] = dict(net_arch=[64, 64])
    if args.mode == "residual":
        policy_kwargs["log_std_init"] = -1.0
    common = dict(seed=args.seed, verbose=0, tensorboard_log=str(out_dir / "tensorboard"), device="cpu",
                  policy_kwargs=policy_kwargs)
    if args.algo == "ppo":
        model = PPO("MlpPolicy", venv, n_steps=256, batch_size=512, n_epochs=5, learning_rate=3e-4,
                    gamma=0.99, gae_lambda=0.95, clip_range=0.2, **common)
    else:
        model = SAC("MlpPolicy", venv, learning_rate=3e-4, buffer_size=200_000, batch_size=256,
                    learning_starts=2_000, gamma=0.99, train_freq=1, gradient_steps=1, **common)
    checkpoints = CheckpointCallback(save_freq=max(args.total_timesteps // (4 * venv.num_envs), 1),
                                     save_path=str(out_dir / "checkpoints"), name_prefix="model")
    callbacks = [checkpoints]
    if not args.no_progress:
        callbacks.append(_progress_callback(_collected_steps(args.total_timesteps, model, venv.num_envs)))
    started = time.time()
    model.learn(total_timesteps=args.total_timesteps, callback=callbacks)
    (out_dir / "timing.json").write_text(json.dumps({"train_seconds": time.time() - started}))
    model.save(out_dir / "model.zip")
    ObservationNormalizer(venv.obs_rms.mean.copy(), venv.obs_rms.var.copy(), venv.clip_obs).save(
        out_dir / "obs_normalizer.pkl")
    venv.close()
    _write_learning_curve_from_monitor(out_dir)


def _collected_steps(total_timesteps: int, model: Any, num_envs: int) -> int:
    """Agent steps SB3 actually collects for ``total_timesteps``: PPO collects whole rollouts of
    ``n_steps * num_envs``, SAC whole vec-env steps of ``num_envs``, so it stops at or after the total."""
    chunk = getattr(model, "n_steps", 1) * num_envs
    return math.ceil(total_timesteps / chunk) * chunk


def _progress_callback(total: int) -> Any:
    """A tqdm bar over the agent steps of training, ``total`` being what will be collected (no overshoot)."""
    from stable_baselines3.common.callbacks import BaseCallback
    from tqdm.auto import tqdm

    class TrainingProgress(BaseCallback):
        def _on_training_start(self) -> None:
            self.bar = tqdm(total=total, desc="training", unit=" agent steps", unit_scale=True)

        def _on_step(self) -> bool:
            self.bar.update(min(self.training_env.num_envs, total - self.bar.n))
            return True

        def _on_training_end(self) -> None:
            self.bar.close()

    return TrainingProgress()


def _write_learning_curve_from_monitor(out_dir: Path) -> None:
    """``learning_curve.csv``: agent steps so far and episode return (mean over agents), per episode."""
    monitor = out_dir / "monitor.csv"
    rows = []
    if monitor.exists():
        lines = [line for line in monitor.read_text().splitlines() if line and not line.startswith("#")]
        total = 0
        for line in lines[1:]:
            reward, length, _ = (float(x) for x in line.split(","))
            total += int(length)
            rows.append((total, reward))
    with open(out_dir / "learning_curve.csv", "w", encoding="utf-8") as handle:
        handle.write("agent_steps,episode_return\n")
        handle.writelines(f"{steps},{ret}\n" for steps, ret in rows)


# ------------------------------------------------------------------------------------------ rllib
def train_rllib(args: argparse.Namespace, out_dir: Path) -> None:
    import ray
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.multi_rl_module import MultiRLModuleSpec
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv
    from ray.tune.registry import register_env

    ray.init(address=args.address, ignore_reinit_error=True, include_dashboard=False, log_to_driver=False,
             num_cpus=None if args.address else max(os.cpu_count() or 1, 1))
    factory = env_factory(args, training_overrides(args))
    register_env("ee_formation", lambda _config: ParallelPettingZooEnv(factory()))
    config = (
        PPOConfig()
        .environment("ee_formation")
        .framework("torch")
        .env_runners(num_env_runners=max(args.n_workers, 0), num_envs_per_env_runner=1,
                     rollout_fragment_length="auto")
        .multi_agent(policies={"shared"}, policy_mapping_fn=lambda agent_id, *a, **k: "shared")
        .rl_module(rl_module_spec=MultiRLModuleSpec(rl_module_specs={"shared": RLModuleSpec()}))
        .training(train_batch_size_per_learner=2048, minibatch_size=256, num_epochs=5, lr=3e-4, gamma=0.99)
        .debugging(seed=args.seed)
    )
    algorithm = config.build_algo() if hasattr(config, "build_algo") else config.build()
    started, history, steps = time.time(), [], 0
    while steps < args.total_timesteps:
        result = algorithm.train()
        steps = int(result.get("num_env_steps_sampled_lifetime", steps + 2048) or steps + 2048)
        ret = result.get("env_runners", {}).get("episode_return_mean", math.nan)
        history.append((steps, float(ret) if ret is not None else math.nan))
    (out_dir / "timing.json").write_text(json.dumps({"train_seconds": time.time() - started}))
    checkpoint = algorithm.save(str((out_dir / "rllib_checkpoint").resolve()))
    del checkpoint
    module = algorithm.get_module("shared")
    _save_rllib_module(module, out_dir)
    with open(out_dir / "learning_curve.csv", "w", encoding="utf-8") as handle:
        handle.write("agent_steps,episode_return\n")
        handle.writelines(f"{s},{r}\n" for s, r in history)
    algorithm.stop()
    if not args.address:
        ray.shutdown()


def _save_rllib_module(module: Any, out_dir: Path) -> None:
    """Save the shared module's weights and an identity normalizer (RLlib's default has no obs filter)."""
    import torch

    torch.save(module, out_dir / "rllib_module.pt")
    dim = int(np.prod(module.observation_space.shape))
    ObservationNormalizer.identity(dim).save(out_dir / "obs_normalizer.pkl")


def _rllib_predictor(run_dir: Path) -> Callable[[np.ndarray], np.ndarray]:
    import torch

    module = torch.load(run_dir / "rllib_module.pt", weights_only=False)
    low, high = module.action_space.low, module.action_space.high

    def predict(observation: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            output = module.forward_inference({"obs": torch.as_tensor(observation[None], dtype=torch.float32)})
        logits = output["action_dist_inputs"][0].numpy()
        mean = logits[: len(low)]  # a diagonal Gaussian: means first, then log-stds
        return np.clip(mean, low, high)

    return predict


# ------------------------------------------------------------------------------------------ comparison
def compare(args: argparse.Namespace, config: dict[str, Any], run_dir: Path) -> dict[str, Any]:
    """Evaluate the learned policy and every reference policy on the same held-out seeds."""
    overrides = {} if args.eval_seconds is None else {"episode_seconds": args.eval_seconds}
    seeds = [EVAL_SEED_OFFSET + k for k in range(args.eval_episodes)]
    results: dict[str, Any] = {}
    with ee_formation_env.parallel_env(config["scenario"], **overrides) as env:
        error_unit = "m²" if env.formation.kind == "distance" else "m"
        candidates = {"learned": lambda: learned_policies(run_dir, env, config)}
        for name in baselines.POLICIES:
            candidates[name] = functools.partial(baselines.make_policies, name, env)
        bar = _evaluation_progress(len(candidates) * len(seeds), args.no_progress)
        for name, build in candidates.items():
            policies = build()
            episodes = []
            for seed in seeds:
                if bar is not None:
                    bar.set_postfix_str(name)
                episodes.append(run_episode(env, policies, seed=seed))
                if bar is not None:
                    bar.update(1)
            if bar is None:
                print(f"evaluated {name} on {len(seeds)} seeds", flush=True)
            results[name] = summarize(episodes)
            results[name]["per_episode"] = [e.as_dict() for e in episodes]
        if bar is not None:
            bar.close()
    label = f"learned ({config['mode']})"
    comparison = {"scenario": config["scenario"], "seeds": seeds, "learned_label": label, "results": results}
    (run_dir / "comparison.json").write_text(json.dumps(comparison, indent=2, default=float))
    table = format_table({label if k == "learned" else k: v for k, v in results.items()})
    (run_dir / "comparison.md").write_text(
        f"# Comparison on {config['scenario']} ({len(seeds)} held-out seeds from {seeds[0]})\n\n{table}\n")
    _plot(run_dir, results, label, error_unit)
    print(table)
    return comparison


def _evaluation_progress(total: int, disabled: bool) -> Any:
    """A tqdm bar over the comparison's episodes, or None (``--no-progress``, or tqdm not installed)."""
    if disabled:
        return None
    try:
        from tqdm.auto import tqdm
    except ImportError:
        return None
    return tqdm(total=total, desc="evaluating", unit=" episodes")


def _plot(run_dir: Path, results: dict[str, Any], label: str, error_unit: str) -> None:
    """``comparison.png``: the learning curve, then the final formation error and the success rate per
    policy as labelled horizontal bars (policy names stay readable; a 0 % bar shows as its empty track)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(results)
    ticks = [label if n == "learned" else n for n in names]
    rows = np.arange(len(names))
    figure, axes = plt.subplots(1, 3, figsize=(15, 4.2), gridspec_kw={"width_ratios": [1.2, 1, 1]})
    curve = np.loadtxt(run_dir / "learning_curve.csv", delimiter=",", skiprows=1, ndmin=2)
    if curve.size:
        axes[0].plot(curve[:, 0], curve[:, 1], ".", alpha=0.4, label="episode")
        if len(curve) >= 10:
            window = max(len(curve) // 20, 5)
            axes[0].plot(curve[window - 1:, 0], np.convolve(curve[:, 1], np.ones(window) / window, mode="valid"),
                         label=f"mean of {window}")
            axes[0].legend(loc="lower right", fontsize=8)
    axes[0].set(title="learning curve", xlabel="agent steps",
                ylabel="episode return per agent\n(sum of step rewards, each in [0, 1])")
    axes[0].ticklabel_format(axis="x", style="sci", scilimits=(0, 3))

    errors = np.array([results[n]["final_formation_error"] for n in names], dtype=np.float64)
    shown = np.where(np.isfinite(errors) & (errors > 0), errors, np.nan)
    axes[1].barh(rows, shown, color="tab:blue")
    axes[1].set_xscale("log")
    axes[1].set(title="final formation error (mean)", xlabel=f"formation error ({error_unit}, log scale)")
    if np.isfinite(shown).any():
        low, high = np.nanmin(shown), np.nanmax(shown)
        axes[1].set_xlim(low / 10, high * 1e3)  # room for the value labels right of the bars
    for row, value in zip(rows, errors):
        axes[1].annotate(f"{value:.2g}", (shown[row] if np.isfinite(shown[row]) else axes[1].get_xlim()[0], row),
                         xytext=(3, 0), textcoords="offset points", va="center", fontsize=8)

    success = 100.0 * np.array([results[n]["success_rate"] for n in names], dtype=np.float64)
    axes[2].barh(rows, np.full(len(rows), 100.0), color="0.92", edgecolor="0.75")  # the empty track
    axes[2].barh(rows, success, color="tab:green")
    axes[2].set(title="success rate", xlabel="episodes that succeeded (%)", xlim=(0, 118))
    axes[2].set_xticks([0, 25, 50, 75, 100])
    for row, value in zip(rows, success):
        axes[2].annotate(f"{value:.0f} %", (value, row), xytext=(3, 0), textcoords="offset points", va="center",
                         fontsize=8)
    for axis in axes[1:]:
        axis.set_yticks(rows, ticks)
        axis.invert_yaxis()  # first policy on top, as in the table
    axes[2].set_yticklabels([])  # same rows as the middle panel
    figure.tight_layout()
    figure.savefig(run_dir / "comparison.png", dpi=110)
    plt.close(figure)


# ------------------------------------------------------------------------------------------ main
def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    if args.eval_only:
        run_dir = Path(args.eval_only)
        config_path = run_dir / "config.json"
        if not config_path.is_file():
            raise SystemExit(f"--eval-only: {config_path} not found")
        config = json.loads(config_path.read_text())
        require_training_extras(args, config)
        compare(args, config, run_dir)
        return 0

    ee_formation_env.load_scenario(args.scenario)  # fail fast on a bad scenario, before any process starts
    require_training_extras(args)
    run_dir = Path(args.out) if args.out else Path("runs") / run_name(args)
    run_dir.mkdir(parents=True, exist_ok=True)
    config = {key: value for key, value in vars(args).items() if key not in ("out", "eval_only")}
    config["scenario_data"] = ee_formation_env.load_scenario(args.scenario).to_dict()
    config["versions"] = _versions()
    (run_dir / "config.json").write_text(json.dumps(config, indent=2, default=str))
    print(f"training {args.algo} ({args.backend}, mode {args.mode}) on {args.scenario} for {args.total_timesteps} "
          f"agent steps -> {run_dir}")
    (train_sb3 if args.backend == "sb3" else train_rllib)(args, run_dir)
    compare(args, config, run_dir)
    print(f"wrote {run_dir}/comparison.md, comparison.json, comparison.png")
    return 0


def _versions() -> dict[str, str]:
    from importlib import metadata

    versions = {"python": platform.python_version()}
    for package in ("numpy", "pybullet", "pettingzoo", "gymnasium", "stable-baselines3", "torch", "ray"):
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            pass
    return versions


if __name__ == "__main__":
    sys.exit(main())
