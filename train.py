"""Train a shared formation policy and compare it with the reference controllers on the same metrics.

    python train.py                                   # default: residual PPO on planar_square, 3-9 min on 2 cores
    python train.py --mode torque                     # the policy outputs the torques itself
    python train.py --backend rllib --total-timesteps 20000
    python train.py --eval-only runs/<name>           # re-evaluate a saved run

One policy is shared by every agent, each acting on its own local observation (decentralized execution).
``--mode residual`` (default): the policy's output, scaled by ``--residual-scale``, is added to a reference
controller's action (``--reference``); rewards are scaled by ``1 - correction_penalty * mean(residual^2)``.
``--mode torque``: the policy outputs normalized joint torques, learned from the reward (with log-scaled error
features and, in training, a hold penalty); or, with ``--imitate REFERENCE``, it starts as a copy of a
reference controller learned from its demonstrations (DAgger), and PPO adds ``--total-timesteps`` (none by
default). The training design (episode length, start noise, PPO settings) is in README, "Training".

Every run writes to ``--out`` (default ``runs/<name>``): ``config.json``, the model and its observation
normalization, TensorBoard logs, checkpoints, ``learning_curve.csv``, and the comparison against every
reference policy on held-out seeds (``comparison.json``, ``comparison.md``, ``comparison.png``), computed by
``ee_formation_env.baselines.metrics`` exactly as ``python -m ee_formation_env.baselines.evaluate`` does.
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

from ee_formation_env import baselines
import ee_formation_env
from ee_formation_env.baselines.extras import require
from ee_formation_env.baselines.learned.features import FEATURE_SETS, FeaturePolicy, make_feature_env
from ee_formation_env.baselines.metrics import format_table, run_episode, summarize
from ee_formation_env.baselines.learned.residual import ResidualPolicy, make_training_env
from ee_formation_env.baselines.learned.shaping import SPEED_SCALE

EVAL_SEED_OFFSET = 10_000  # held-out evaluation seeds start here; training resets use seeds below it
# Training design (README, "Training"): short episodes give many starts per budget (the references settle in
# ~1 s); torque mode also widens the start distribution. The comparison runs the scenario's own episodes (30 s)
# and start noise.
DEFAULT_TIMESTEPS = {"residual": 600_000, "torque": 5_000_000}
TRAIN_EPISODE_SECONDS = {"residual": 3.0, "torque": 10.0}
TRAIN_INITIAL_Q_NOISE = {"residual": None, "torque": 0.1}  # rad; None: the scenario's
# Torque mode's observation features (baselines/features.py: edge errors in tolerances, log-scaled, from the
# agent's own observation) and PPO settings; residual mode keeps the raw observation and the common settings.
OBS_FEATURES = {"residual": "none", "torque": "log-error"}
GAMMA = {"residual": 0.99, "torque": 0.99}
# baselines/shaping.py: charge joint speed once in formation (training only; the learning curve's returns are
# the shaped ones, the comparison uses the env's reward and metrics)
HOLD_PENALTY = {"residual": 0.0, "torque": 0.5}
LOG_STD_INIT = {"residual": -1.0, "torque": -2.0}
PPO_SETTINGS = {
    "residual": dict(net_arch=[64, 64], n_epochs=5, learning_rate=3e-4, learning_rate_decay=False),
    "torque": dict(net_arch=[128, 128], n_epochs=10, learning_rate=3e-4, learning_rate_decay=True),
}
# Rollout layout per mode (README, "Training"): residual mode steps 32 envs, 32 steps per slot (throughput): 14 in
# one worker process while the learner's process steps the other 18 (on 2 cores the learner's own work per step
# then overlaps the worker's); torque mode keeps the layout its documented run used (8 envs in-process, 128 steps).
N_ENVS = {"residual": 32, "torque": 8}
N_STEPS = {"residual": 32, "torque": 128}
N_WORKERS = {"residual": 1, "torque": 0}
IN_PROCESS_ENVS = {"residual": 18, "torque": 0}  # of the n_envs, with worker processes: stepped by the learner
# --imitate: start from demonstrations of a reference (README, "Training"): DAgger rounds, each this many
# training episodes, the learner driving this share of the steps after the first round, then PPO.
IMITATION_ROUNDS = 3
IMITATION_EPISODES = 60
IMITATION_LEARNER_SHARE = 0.5
IMITATION_EPOCHS = (30, 15)  # epochs over all the data so far: first round, later rounds
IMITATION_TIMESTEPS = 0  # PPO agent steps after the imitation: none by default (README: PPO degraded the copy)
IMITATION_LOG_STD = -2.5  # PPO's exploration around the imitated policy: std 0.08 of the torque range
REFERENCE_CURVE_EPISODES = 4  # episodes per reference policy for the learning curve's reference lines


# ------------------------------------------------------------------------------------------ arguments
def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="train.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="planar_square", help="built-in name or YAML/JSON scenario file")
    parser.add_argument("--mode", choices=("torque", "residual"), default="residual",
                        help="residual (default): learn a correction on top of --reference; torque: learn torques")
    parser.add_argument("--reference", default="adaptive_jacobian",
                        choices=baselines.MODEL_BASED_POLICIES,
                        help="reference controller of --mode residual")
    parser.add_argument("--residual-scale", type=float, default=0.3, help="residual action scale (0, 1]")
    parser.add_argument("--correction-penalty", type=float, default=0.5,
                        help="residual mode: rewards are scaled by 1 - this * mean(residual^2), in [0, 1]")
    parser.add_argument("--residual-gate", action=argparse.BooleanOptionalAction, default=True,
                        help="residual mode: scale the correction by min(1, the agent's error in tolerances), so "
                             "that it fades out at the goal (default on)")
    parser.add_argument("--imitate", choices=(*baselines.MODEL_BASED_POLICIES, "none"), default=None,
                        help="torque mode: start the policy as a copy of this reference controller, learned from its "
                             "demonstrations (DAgger) before PPO (default none: learn from the reward alone); "
                             "residual mode: none only")
    parser.add_argument("--imitation-rounds", type=int, default=IMITATION_ROUNDS,
                        help="--imitate: demonstration rounds (the first driven by the reference, the next ones "
                             "partly by the learner)")
    parser.add_argument("--imitation-episodes", type=int, default=IMITATION_EPISODES,
                        help="--imitate: training episodes per demonstration round")
    parser.add_argument("--algo", choices=("ppo", "sac"), default="ppo")
    parser.add_argument("--backend", choices=("sb3", "rllib"), default="sb3")
    parser.add_argument("--total-timesteps", type=int, default=None,
                        help=f"agent steps (all agents count); default {DEFAULT_TIMESTEPS}")
    parser.add_argument("--n-envs", type=int, default=None,
                        help=f"parallel envs (each with all its agents; default {N_ENVS})")
    parser.add_argument("--n-steps", type=int, default=None,
                        help="ppo: steps per env slot per update (an update learns from n_steps x n_envs x agents "
                             f"agent steps: 4,096 with either mode's defaults on 4 agents; default {N_STEPS})")
    parser.add_argument("--n-workers", type=int, default=None,
                        help=f"worker processes for the envs (0 = step them in this process; default {N_WORKERS})")
    parser.add_argument("--in-process-envs", type=int, default=None,
                        help="with worker processes: how many of the envs the learner's process steps while the "
                             f"workers step the others (default {IN_PROCESS_ENVS}; 0 without workers)")
    parser.add_argument("--train-episode-seconds", type=float, default=None,
                        help=f"episode length while training, s (default {TRAIN_EPISODE_SECONDS})")
    parser.add_argument("--train-initial-q-noise", type=float, default=None,
                        help="half-width of the uniform noise on the initial joint positions while training, rad "
                             f"(default {TRAIN_INITIAL_Q_NOISE}, None: the scenario's; evaluation uses the scenario's)")
    parser.add_argument("--gamma", type=float, default=None, help=f"discount per control step (default {GAMMA})")
    parser.add_argument("--log-std-init", type=float, default=None,
                        help=f"initial log standard deviation of the Gaussian policy (ppo; default {LOG_STD_INIT})")
    parser.add_argument("--obs-features", choices=FEATURE_SETS, default=None,
                        help="features appended to each agent's observation, computed from it alone "
                             f"(baselines/features.py; default {OBS_FEATURES})")
    parser.add_argument("--hold-penalty", type=float, default=None,
                        help=f"training only: subtract this times min(1, |dq| / {SPEED_SCALE} rad/s) from an agent's "
                             "reward on steps where it is in formation (baselines/shaping.py), in [0, 1]; "
                             f"default {HOLD_PENALTY}")
    parser.add_argument("--max-train-seconds", type=float, default=None,
                        help="sb3: stop training after this wall time, s, even if --total-timesteps is not reached "
                             "(default: no limit)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="run directory (default runs/<name>)")
    parser.add_argument("--eval-only", metavar="RUN_DIR", default=None, help="evaluate a saved run only")
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--eval-workers", type=int, default=2,
                        help="processes for the evaluation episodes (0 = run them in this process)")
    parser.add_argument("--eval-seconds", type=float, default=None,
                        help="episode length for the comparison, s (default: the scenario's)")
    parser.add_argument("--address", default=None, help="rllib: address of an existing Ray cluster")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    if args.imitate is None:
        args.imitate = "none"
    if args.total_timesteps is None:
        args.total_timesteps = DEFAULT_TIMESTEPS[args.mode] if args.imitate == "none" else IMITATION_TIMESTEPS
    if args.train_episode_seconds is None:
        args.train_episode_seconds = TRAIN_EPISODE_SECONDS[args.mode]
    if args.train_initial_q_noise is None:
        args.train_initial_q_noise = TRAIN_INITIAL_Q_NOISE[args.mode]
    if args.gamma is None:
        args.gamma = GAMMA[args.mode]
    if args.log_std_init is None:
        args.log_std_init = LOG_STD_INIT[args.mode]
    if args.obs_features is None:  # an imitated policy sees what its reference sees
        args.obs_features = OBS_FEATURES[args.mode] if args.imitate == "none" else "none"
    for name, table in (("n_envs", N_ENVS), ("n_steps", N_STEPS), ("n_workers", N_WORKERS)):
        if getattr(args, name) is None:
            setattr(args, name, table[args.mode])
    if args.in_process_envs is None:  # the mode's share, where it leaves the workers envs to step
        share = IN_PROCESS_ENVS[args.mode]
        args.in_process_envs = share if args.n_workers > 0 and share < args.n_envs else 0
    if args.hold_penalty is None:
        args.hold_penalty = HOLD_PENALTY[args.mode]
    if args.total_timesteps < (0 if args.imitate != "none" else 1):
        parser.error("--total-timesteps must be >= 1 (>= 0 with --imitate: the imitated policy as it is)")
    if args.n_envs < 1 or args.n_steps < 1 or args.eval_episodes < 1:
        parser.error("--n-envs, --n-steps and --eval-episodes must be >= 1")
    if args.imitate != "none" and args.obs_features != "none":
        parser.error("--obs-features: expected none with --imitate (the policy sees what its reference sees)")
    if not 0 < args.residual_scale <= 1:
        parser.error("--residual-scale: expected a value in (0, 1]")
    if args.imitate != "none" and (args.mode != "torque" or args.backend != "sb3" or args.algo != "ppo"):
        parser.error("--imitate: expected none, except with --mode torque, --backend sb3 and --algo ppo")
    if args.imitation_rounds < 1 or args.imitation_episodes < 1:
        parser.error("--imitation-rounds and --imitation-episodes must be >= 1")
    if args.n_workers < 0 or args.eval_workers < 0:
        parser.error("--n-workers and --eval-workers must be >= 0")
    if args.in_process_envs and not (args.n_workers > 0 and 0 < args.in_process_envs < args.n_envs):
        parser.error("--in-process-envs: expected 0, or with --n-workers >= 1 a number below --n-envs")
    if args.backend == "rllib" and args.algo != "ppo":
        parser.error("--backend rllib supports --algo ppo only")
    if not 0 <= args.correction_penalty <= 1:
        parser.error("--correction-penalty: expected a value in [0, 1]")
    if not 0 < args.gamma <= 1:
        parser.error("--gamma: expected a value in (0, 1]")
    if not 0 <= args.hold_penalty <= 1:
        parser.error("--hold-penalty: expected a value in [0, 1]")
    if args.max_train_seconds is not None and not args.max_train_seconds > 0:
        parser.error("--max-train-seconds: expected a value > 0")
    if not math.isfinite(args.log_std_init):
        parser.error("--log-std-init: expected a finite number")
    if (args.train_initial_q_noise is not None and args.train_initial_q_noise < 0) or args.train_episode_seconds <= 0:
        parser.error("--train-initial-q-noise must be >= 0 and --train-episode-seconds > 0")
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


def training_overrides(args: argparse.Namespace | dict[str, Any]) -> dict[str, Any]:
    """Scenario overrides of the training env (from parsed arguments or a saved config): episode length
    and start randomization."""
    settings = vars(args) if isinstance(args, argparse.Namespace) else args
    overrides = {"episode_seconds": settings["train_episode_seconds"]}
    if settings.get("train_initial_q_noise") is not None:
        overrides["initial_q_noise"] = settings["train_initial_q_noise"]
    return overrides


def env_factory(args: argparse.Namespace, overrides: dict[str, Any] | None = None) -> Callable[[], Any]:
    """A picklable factory of the env the learner steps."""
    return functools.partial(make_feature_env, args.obs_features, make_training_env, args.scenario, overrides,
                             args.mode, args.reference, args.residual_scale, args.correction_penalty,
                             args.residual_gate, hold_penalty=args.hold_penalty)


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
        predict = _numpy_actor(model) if config["algo"] == "ppo" else None
        if predict is None:
            predict = lambda obs: model.predict(obs, deterministic=True)[0]  # noqa: E731
    else:
        predict = _rllib_predictor(run_dir)
    learned = LearnedPolicy(predict, normalizer)
    features = config.get("obs_features", "none")  # runs saved before the option had none
    per_agent = {agent: learned if features == "none" else
                 FeaturePolicy(learned, env.observation_layout(agent), features) for agent in env.possible_agents}
    if config["mode"] == "torque":
        return per_agent
    references = baselines.make_policies(config["reference"], env)
    gate = config.get("residual_gate", False)
    return {agent: ResidualPolicy(references[agent], per_agent[agent], config["residual_scale"],
                                  env.observation_layout(agent) if gate else None)
            for agent in env.possible_agents}


def _numpy_actor(model: Any) -> Callable[[np.ndarray], np.ndarray] | None:
    """PPO's deterministic action (the Gaussian's mean) as numpy matrix products, or None if the policy is not
    a plain MLP of ``Linear`` and ``Tanh`` layers. One agent at a time, as the evaluation calls it, this is
    ~20x cheaper than ``model.predict``, whose per-call overhead would dominate a 30 s evaluation."""
    import torch

    policy = model.policy
    layers = [*policy.mlp_extractor.policy_net, policy.action_net]
    if not isinstance(policy.features_extractor.flatten, torch.nn.Flatten) or not all(
            isinstance(layer, (torch.nn.Linear, torch.nn.Tanh)) for layer in layers):
        return None
    steps = [(layer.weight.detach().numpy().astype(np.float64).T, layer.bias.detach().numpy().astype(np.float64))
             if isinstance(layer, torch.nn.Linear) else None for layer in layers]

    def predict(observation: np.ndarray) -> np.ndarray:
        hidden = np.asarray(observation, dtype=np.float64)
        for step in steps:
            hidden = np.tanh(hidden) if step is None else hidden @ step[0] + step[1]
        return hidden

    return predict


# ------------------------------------------------------------------------------------------ sb3
def build_sb3_model(args: argparse.Namespace, out_dir: Path | None) -> Any:
    """The SB3 model (with its normalized, monitored VecEnv as ``model.get_env()``) that ``train_sb3`` trains;
    ``out_dir`` None: no monitor file and no TensorBoard logs (the throughput benchmark)."""
    from stable_baselines3 import PPO, SAC
    from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

    from ee_formation_env.integrations.sb3 import SharedPolicyVecEnv

    import torch

    torch.set_num_threads(1)  # a 64x64 MLP gains nothing from more threads; they would compete with the envs
    factory = env_factory(args, training_overrides(args))
    # No per-step infos cross the worker pipes: the learner reads none (the VecEnv adds what SB3 needs).
    venv = SharedPolicyVecEnv([factory] * args.n_envs, n_workers=args.n_workers, info_keys=(),
                              in_process_envs=args.in_process_envs)
    venv = VecMonitor(venv, filename=None if out_dir is None else str(out_dir / "monitor.csv"))
    venv = VecNormalize(venv, norm_obs=True, norm_reward=True, gamma=args.gamma)
    # A small initial action noise (log_std -1: std 0.37 of the action range): with the default 0 a residual
    # policy starts far from "no correction" and a torque policy saturates its joints half of the time.
    settings = PPO_SETTINGS[args.mode]
    # A copy of a reference controller (--imitate) needs a wider actor than learning from the reward did.
    policy_kwargs: dict[str, Any] = dict(net_arch=list(settings["net_arch"]) if args.imitate == "none" else [256, 256])
    if args.algo == "ppo":
        policy_kwargs["log_std_init"] = args.log_std_init
    common = dict(seed=args.seed, verbose=0, device="cpu", policy_kwargs=policy_kwargs,
                  tensorboard_log=None if out_dir is None else str(out_dir / "tensorboard"))
    if args.algo == "ppo":
        rate = settings["learning_rate"]
        # A linear decay to 0 over the run (SB3 passes the remaining progress, 1 -> 0) settles the final policy.
        learning_rate = functools.partial(_linear_schedule, rate) if settings["learning_rate_decay"] else rate
        # n_steps x (n_envs x agents) slots per update: 4,096 agent steps with either mode's defaults.
        return PPO("MlpPolicy", venv, n_steps=args.n_steps, batch_size=min(1024, args.n_steps * venv.num_envs),
                   n_epochs=settings["n_epochs"], learning_rate=learning_rate, gamma=args.gamma, gae_lambda=0.95,
                   clip_range=0.2, **common)
    return SAC("MlpPolicy", venv, learning_rate=3e-4, buffer_size=200_000, batch_size=256,
               learning_starts=2_000, gamma=args.gamma, train_freq=1, gradient_steps=1, **common)


def _linear_schedule(initial: float, progress_remaining: float) -> float:
    return initial * progress_remaining


def train_sb3(args: argparse.Namespace, out_dir: Path) -> None:
    from stable_baselines3.common.callbacks import CheckpointCallback

    model = build_sb3_model(args, out_dir)
    venv = model.get_env()
    if args.imitate != "none":
        imitate(model, args, out_dir)
    checkpoints = CheckpointCallback(save_freq=max(args.total_timesteps // (4 * venv.num_envs), 1),
                                     save_path=str(out_dir / "checkpoints"), name_prefix="model")
    callbacks = [checkpoints]
    if args.max_train_seconds is not None:
        callbacks.append(_time_limit_callback(args.max_train_seconds))
    if not args.no_progress:
        callbacks.append(_progress_callback(_collected_steps(args.total_timesteps, model, venv.num_envs)))
    started = time.time()
    if args.total_timesteps > 0:
        model.learn(total_timesteps=args.total_timesteps, callback=callbacks)
    seconds = time.time() - started
    (out_dir / "timing.json").write_text(json.dumps({"train_seconds": seconds, "agent_steps": model.num_timesteps,
                                                     "agent_steps_per_s": model.num_timesteps / max(seconds, 1e-9)}))
    model.save(out_dir / "model.zip")
    ObservationNormalizer(venv.obs_rms.mean.copy(), venv.obs_rms.var.copy(), venv.clip_obs).save(
        out_dir / "obs_normalizer.pkl")
    venv.close()
    _write_learning_curve_from_monitor(out_dir)


def imitate(model: Any, args: argparse.Namespace, out_dir: Path) -> None:
    """Start ``model``'s policy as a copy of the reference ``args.imitate``: DAgger rounds of demonstrations
    in the training env (:func:`ee_formation_env.baselines.learned.imitation.demonstrations`), the actor's mean fitted to the
    reference's actions after each round, the observation normalization set from the data; then PPO's
    exploration noise is narrowed to ``IMITATION_LOG_STD``. Writes ``imitation.json``."""
    import torch

    from ee_formation_env.baselines.learned.imitation import demonstrations

    venv = model.get_env()  # VecNormalize: the policy sees normalized observations
    env = make_training_env(args.scenario, training_overrides(args), "torque")
    rng = np.random.default_rng(args.seed)
    seeds = rng.integers(0, EVAL_SEED_OFFSET, size=args.imitation_rounds * args.imitation_episodes)
    observations, labels, rounds, started = [], [], [], time.time()
    try:
        for index in range(args.imitation_rounds):
            learner = None if index == 0 else functools.partial(_actor_mean, model, venv)
            episode_seeds = seeds[index * args.imitation_episodes:(index + 1) * args.imitation_episodes]
            seen, wanted = demonstrations(env, args.imitate, args.imitation_episodes, episode_seeds, learner,
                                          0.0 if index == 0 else IMITATION_LEARNER_SHARE, rng)
            observations.append(seen)
            labels.append(wanted)
            loss = _fit_actor(model, venv, np.concatenate(observations), np.concatenate(labels),
                              IMITATION_EPOCHS[min(index, 1)], args.seed + index)
            rounds.append({"round": index, "samples": int(sum(len(x) for x in observations)), "loss": loss,
                           "seconds": time.time() - started})
            if not args.no_progress:
                print(f"imitation round {index + 1}/{args.imitation_rounds}: {rounds[-1]['samples']} samples, "
                      f"weighted loss {loss:.2e}, {rounds[-1]['seconds']:.0f} s", flush=True)
    finally:
        env.close()
    with torch.no_grad():
        model.policy.log_std.fill_(IMITATION_LOG_STD)
    (out_dir / "imitation.json").write_text(json.dumps({"reference": args.imitate, "rounds": rounds,
                                                        "log_std_after": IMITATION_LOG_STD}, indent=2))


def _normalized(venv: Any, observations: np.ndarray) -> Any:
    import torch

    return torch.as_tensor(venv.normalize_obs(observations), dtype=torch.float32)


def _actor_mean(model: Any, venv: Any, observations: np.ndarray) -> np.ndarray:
    """The policy's deterministic action (its Gaussian's mean) for raw observations (k, size)."""
    import torch

    policy = model.policy
    with torch.no_grad():
        latent = policy.mlp_extractor.forward_actor(policy.features_extractor(_normalized(venv, observations)))
        return policy.action_net(latent).numpy().astype(np.float64)


def _fit_actor(model: Any, venv: Any, observations: np.ndarray, labels: np.ndarray, epochs: int, seed: int) -> float:
    """Fit the actor's mean to ``labels`` by weighted least squares; returns the last minibatch's loss.

    The observation normalization is set from the data first (and keeps updating in PPO afterwards).
    Each sample is weighted by ``1 / (mean |label| + 0.02)``: near the goal the reference's torques are a
    few percent of the range, and holding 1 cm needs them right to about that precision.
    """
    import torch

    venv.obs_rms.mean = observations.mean(axis=0)
    venv.obs_rms.var = observations.var(axis=0)
    venv.obs_rms.count = float(len(observations))
    inputs = _normalized(venv, observations)
    targets = torch.as_tensor(labels, dtype=torch.float32)
    weights = 1.0 / (targets.abs().mean(dim=1, keepdim=True) + 0.02)
    policy = model.policy
    parameters = [*policy.mlp_extractor.policy_net.parameters(), *policy.action_net.parameters()]
    optimizer = torch.optim.Adam(parameters, lr=1e-3)
    generator = torch.Generator().manual_seed(seed)
    loss = torch.zeros(())
    for _ in range(epochs):
        order = torch.randperm(len(inputs), generator=generator)
        for start in range(0, len(inputs), 1024):
            batch = order[start:start + 1024]
            latent = policy.mlp_extractor.forward_actor(policy.features_extractor(inputs[batch]))
            loss = (weights[batch] * (policy.action_net(latent) - targets[batch]) ** 2).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    return float(loss.detach())


def _time_limit_callback(seconds: float) -> Any:
    """Ends ``learn`` at the first step after ``seconds`` of wall time (from the start of training)."""
    from stable_baselines3.common.callbacks import BaseCallback

    class TimeLimit(BaseCallback):
        def _on_training_start(self) -> None:
            self.deadline = time.time() + seconds

        def _on_step(self) -> bool:
            return time.time() < self.deadline

    return TimeLimit()


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
        .training(train_batch_size_per_learner=2048, minibatch_size=256, num_epochs=5, lr=3e-4, gamma=args.gamma)
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
    """Evaluate the learned policy and every reference policy on the same held-out seeds.

    Episodes run in ``--eval-workers`` processes (each its own env), or in this one with 0; an episode's
    result does not depend on where it runs (same seed, same episode, bit for bit).
    """
    overrides = {} if args.eval_seconds is None else {"episode_seconds": args.eval_seconds}
    seeds = [EVAL_SEED_OFFSET + k for k in range(args.eval_episodes)]
    names = ["learned", *baselines.POLICIES]
    jobs = [(name, seed) for name in names for seed in seeds]
    episodes: dict[tuple[str, int], Any] = {}
    setup = (config["scenario"], overrides, str(run_dir), config)
    bar = _evaluation_progress(len(jobs), args.no_progress)

    def done(job: tuple[str, int], metrics: Any) -> None:
        episodes[job] = metrics
        if bar is not None:
            bar.set_postfix_str(job[0])
            bar.update(1)

    if args.eval_workers == 0:
        _evaluation_worker_setup(*setup)
        try:
            for job in jobs:
                done(job, _evaluate_episode(*job))
        finally:
            _evaluation_worker_teardown()
    else:
        import concurrent.futures
        import multiprocessing

        with concurrent.futures.ProcessPoolExecutor(
                args.eval_workers, mp_context=multiprocessing.get_context("spawn"),
                initializer=_evaluation_worker_setup, initargs=setup) as pool:
            futures = {pool.submit(_evaluate_episode, *job): job for job in jobs}
            for future in concurrent.futures.as_completed(futures):
                done(futures[future], future.result())
    if bar is not None:
        bar.close()
    else:
        print(f"evaluated {len(names)} policies on {len(seeds)} seeds", flush=True)
    error_unit = "m²" if ee_formation_env.load_scenario(config["scenario"]).formation == "distance" else "m"
    results: dict[str, Any] = {}
    for name in names:
        runs = [episodes[(name, seed)] for seed in seeds]
        results[name] = summarize(runs)
        results[name]["per_episode"] = [e.as_dict() for e in runs]
    label = f"learned ({config['mode']})"
    comparison = {"scenario": config["scenario"], "seeds": seeds, "learned_label": label, "results": results}
    (run_dir / "comparison.json").write_text(json.dumps(comparison, indent=2, default=float))
    table = format_table({label if k == "learned" else k: v for k, v in results.items()})
    (run_dir / "comparison.md").write_text(
        f"# Comparison on {config['scenario']} ({len(seeds)} held-out seeds from {seeds[0]})\n\n{table}\n")
    _plot(run_dir, results, label, error_unit)
    print(table)
    return comparison


_EVALUATION: dict[str, Any] = {}  # one evaluation worker's env and policies


def _evaluation_worker_setup(scenario: Any, overrides: dict[str, Any], run_dir: str, config: dict[str, Any]) -> None:
    _EVALUATION.clear()
    _EVALUATION.update(env=ee_formation_env.parallel_env(scenario, **overrides), run_dir=Path(run_dir), config=config,
                       policies={})


def _evaluation_worker_teardown() -> None:
    _EVALUATION["env"].close()
    _EVALUATION.clear()


def _evaluate_episode(name: str, seed: int) -> Any:
    """One held-out episode of policy ``name`` ("learned" or a reference) in this worker's env."""
    env, policies = _EVALUATION["env"], _EVALUATION["policies"]
    if name not in policies:
        policies[name] = (learned_policies(_EVALUATION["run_dir"], env, _EVALUATION["config"]) if name == "learned"
                          else baselines.make_policies(name, env))
    return run_episode(env, policies[name], seed=seed)


def reference_returns(config: dict[str, Any], episodes: int = REFERENCE_CURVE_EPISODES) -> dict[str, float]:
    """Mean per-agent episode return of each reference policy in the *training* env (its episode length and
    start noise, torque mode), on held-out seeds: the lines the learning curve is drawn against.

    In residual mode the reference alone is the learner's zero correction, whose return is the same.
    """
    overrides = training_overrides(config)
    seeds = [EVAL_SEED_OFFSET + 5_000 + k for k in range(episodes)]
    returns = {}
    with ee_formation_env.parallel_env(config["scenario"], **overrides) as env:
        for name in baselines.POLICIES:
            policies = baselines.make_policies(name, env)
            returns[name] = float(np.mean([run_episode(env, policies, seed=seed).mean_return for seed in seeds]))
    return returns


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
    lines = (run_dir / "learning_curve.csv").read_text().splitlines()[1:]  # none when no PPO step ran (--imitate)
    curve = np.loadtxt(lines, delimiter=",", ndmin=2) if lines else np.empty((0, 2))
    if curve.size:
        axes[0].plot(curve[:, 0], curve[:, 1], ".", alpha=0.4, label="episode")
        if len(curve) >= 10:
            window = max(len(curve) // 20, 5)
            axes[0].plot(curve[window - 1:, 0], np.convolve(curve[:, 1], np.ones(window) / window, mode="valid"),
                         label=f"mean of {window}")
    references_path = run_dir / "reference_returns.json"
    if references_path.is_file():  # each reference policy's return in the training episodes
        for (name, value), color in zip(json.loads(references_path.read_text()).items(), plt.cm.Dark2.colors):
            axes[0].axhline(value, linestyle="--", linewidth=1, color=color, label=name)
    if curve.size or references_path.is_file():
        axes[0].legend(loc="best", fontsize=7)
    axes[0].set(title="learning curve (training episodes)", xlabel="agent steps",
                ylabel="episode return per agent\n(sum of step rewards, each in [0, 2])")
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

    started = time.time()
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
    (run_dir / "reference_returns.json").write_text(json.dumps(reference_returns(config), indent=2))
    compare(args, config, run_dir)
    timing = json.loads((run_dir / "timing.json").read_text())
    timing["total_seconds"] = time.time() - started  # training, reference lines and evaluation
    (run_dir / "timing.json").write_text(json.dumps(timing))
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
