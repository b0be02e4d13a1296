"""Demonstrations of a reference policy, for a learned policy to start from (DAgger).

A torque-mode policy outputs the joint torques itself, to 1 cm on 3 m edges. Learned from the reward it
gets there with log-scaled error features, a hold penalty and half an hour of training (README,
"Training"); started as a copy of a reference it gets there in minutes, because the copy is close enough
that the formation's own stiffness holds it. :func:`demonstrations` rolls episodes and labels every agent's
observation with the reference's normalized action (clipped to the action space, as the env applies it).
In the first round the reference drives; in later rounds the learner drives for a share of the steps, so
that the data covers the states the learner itself visits and the reference says what it would do there
(DAgger: Ross, Gordon and Bagnell, 2011).

The reference is one of the model-based laws (by name), or a saved run's learned policy (its run folder):
what that policy applies in the env, the torques of its own mode's rule (a joint-position policy's PD hold,
say), is the label, so a torque policy can start as a copy of a policy of another action convention. A run
reference must have trained on the same scenario with the same env settings (gravity compensation) and the
copy sees the observation features it saw (:func:`check_reference_run`). Labels come from one reference
policy per agent, reset with each episode: ``gradient`` (law-I) and a learned policy without filtered
targets are stateless, so their label depends on the observation only; law-II and law-III carry internal
states along the trajectory that was actually driven.
"""

from __future__ import annotations

import functools
import json
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping

import numpy as np

from ee_formation_env import baselines
from ee_formation_env.baselines.atomic_files import write_text
from ee_formation_env.baselines.learned.policy import SavedRun
from ee_formation_env.baselines.reference.team import PolicyTeam

if TYPE_CHECKING:
    from ee_formation_env.baselines.learned.config import TrainConfig

# --imitate (docs/training.md): DAgger rounds, each this many training episodes, the learner driving this share of
# the steps after the first round, then PPO.
IMITATION_ROUNDS = 3
IMITATION_EPISODES = 60
IMITATION_LEARNER_SHARE = 0.5
IMITATION_EPOCHS = (30, 15)  # epochs over all the data so far: first round, later rounds
IMITATION_TIMESTEPS = 0  # PPO agent steps after the imitation: none by default (PPO degraded the copy)
IMITATION_LOG_STD = -2.5  # PPO's exploration around the imitated policy: std 0.08 of the torque range

Learner = Callable[[np.ndarray], np.ndarray]  # stacked observations (k, size) -> actions (k, n)


def reference_run(reference: str) -> SavedRun | None:
    """The saved run ``reference`` names (``--imitate RUN_DIR``), or None for a law's name or ``none``;
    ``ValueError`` naming ``--imitate`` for anything else (a folder that is not a finished run included)."""
    if not isinstance(reference, str):
        raise TypeError(f"--imitate: expected a reference law's name, a run folder or none, got {reference!r}")
    if reference in baselines.MODEL_BASED_POLICIES or reference == "none":
        return None
    if not Path(reference).is_dir():
        raise ValueError(f"--imitate: expected one of {list(baselines.MODEL_BASED_POLICIES)}, none or a train.py "
                         f"run folder, got {reference!r} (no such folder)")
    return SavedRun.load(reference, "--imitate")


def reference_features(reference: str) -> str:
    """The observation features a copy of ``reference`` sees: none for a law, a run's own for a run."""
    run = reference_run(reference)
    return "none" if run is None else run.options.resolved().obs_features


def check_reference_run(run: SavedRun, config: "TrainConfig", scenario: Any) -> None:
    """Refuse, naming ``--imitate``, a saved run a policy of ``config`` on ``scenario`` cannot copy: another
    scenario, other env settings (the labels would be torques for another plant) or other observation
    features (the copy maps what the reference saw)."""
    from ee_formation_env.scenario import load_scenario

    if load_scenario(run.scenario).to_dict() != scenario.to_dict():
        raise ValueError(f"--imitate: {run.run_dir} trained on scenario {run.scenario_name!r}, not on this run's "
                         f"{scenario.name!r} as given: a reference run must have trained on the same scenario")
    theirs, ours = run.env_overrides(), config.options.env_overrides()
    if theirs != ours:
        raise ValueError(f"--imitate: {run.run_dir} acts with env settings {theirs}, this run with {ours}: the "
                         "labels would be torques for another plant (give --gravity-compensation to match a "
                         "position or velocity run)")
    features = run.options.resolved().obs_features
    if config.options.obs_features != features:
        raise ValueError(f"--imitate: {run.run_dir} saw --obs-features {features}; its copy sees the same, got "
                         f"{config.options.obs_features}")


def reference_policies(reference: str | SavedRun, env: Any) -> dict[str, Any]:
    """Per-agent policies of ``reference`` on ``env``'s raw observations (a law, or a saved run's learned
    policy, its features and mode's rule included)."""
    if isinstance(reference, SavedRun):  # built on the raw env: a training env's spaces carry its features
        return reference.policy_source()(env.batched.env.copy_view(0) if hasattr(env, "batched") else env)
    if reference not in baselines.MODEL_BASED_POLICIES:
        raise ValueError(f"reference: expected one of {list(baselines.MODEL_BASED_POLICIES)}, got {reference!r}")
    return baselines.make_policies(reference, env)


def demonstrations(env: Any, reference: str | SavedRun, episodes: int, seeds: np.ndarray,
                   learner: Learner | None = None, learner_share: float = 0.0,
                   rng: np.random.Generator | None = None, action_scales: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Roll ``episodes`` episodes of ``env`` (reset seeds ``seeds``) and return every agent's observations
    (samples, size) and the reference's normalized actions there (samples, n), clipped to [-1, 1]. The
    reference (:func:`reference_policies`) acts on the raw part of each observation (``env``'s features are
    appended to it).

    ``action_scales`` (N, n): ``env`` takes learned actions scaled per joint by them
    (torque mode, :mod:`~ee_formation_env.baselines.learned.torque`); the labels are then the
    reference's actions divided by them (clipped to [-1, 1]: the reference drives within the learned range).

    The reference drives, except that with ``learner`` given each step is driven by the learner (all
    agents, its actions clipped to [-1, 1]) with probability ``learner_share`` (``rng`` decides).
    Agents must share one observation and action size (the learner is shared).
    """
    if not isinstance(episodes, int) or episodes < 1 or len(seeds) < episodes:
        raise ValueError(f"episodes: expected an integer >= 1 with as many seeds, got {episodes!r} and {len(seeds)} seeds")
    if not 0.0 <= learner_share <= 1.0:
        raise ValueError(f"learner_share: expected a value in [0, 1], got {learner_share!r}")
    if learner_share > 0 and learner is None:
        raise ValueError("learner: a learner_share above 0 needs a learner")
    rng = rng or np.random.default_rng(0)
    team = PolicyTeam(reference_policies(reference, env))
    agents = list(env.possible_agents)
    raw_size = env.observation_layout(agents[0]).size  # a uniform team (a mixed team is refused before)
    observations_seen, labels = [], []
    for episode in range(episodes):
        observations, _ = env.reset(seed=int(seeds[episode]))
        team.reset()
        while env.agents:
            stacked = np.stack([observations[agent] for agent in agents])
            reference_actions = team({agent: observations[agent][:raw_size] for agent in agents})
            wanted = np.stack([reference_actions[agent] for agent in agents])
            wanted = np.clip(wanted if action_scales is None else wanted / action_scales, -1.0, 1.0)
            observations_seen.append(stacked)
            labels.append(wanted)
            driving = wanted
            if learner is not None and learner_share > 0 and rng.random() < learner_share:
                driving = np.clip(learner(stacked), -1.0, 1.0)
            observations, *_ = env.step(_per_agent(agents, driving))
    return np.concatenate(observations_seen).astype(np.float64), np.concatenate(labels).astype(np.float64)


def _per_agent(agents: list[str], actions: np.ndarray) -> Mapping[str, np.ndarray]:
    return {agent: np.asarray(action, dtype=np.float32) for agent, action in zip(agents, actions)}


def imitate(model: Any, args: "TrainConfig", out_dir: Path) -> None:
    """Start ``model``'s policy as a copy of the reference ``args.imitate`` (a law, or a saved run's policy):
    DAgger rounds of demonstrations in the training env (:func:`demonstrations`), the actor's mean fitted to the
    reference's actions after each round, the observation normalization set from the data; then PPO's
    exploration noise is narrowed to ``IMITATION_LOG_STD``. Writes ``imitation.json``."""
    import torch

    from ee_formation_env.baselines.learned.action_scale import rescaling
    from ee_formation_env.baselines.learned.training_env import EVAL_SEED_OFFSET, ParallelTrainingEnv

    venv = model.get_env()  # VecNormalize: the policy sees normalized observations
    env = ParallelTrainingEnv(args.scenario, args.training_overrides(), args.options)
    scales = rescaling(env.task, args.options.action_acceleration)  # the learned actions' per-joint scales, if any
    scales = None if scales is None else np.stack([scales[agent] for agent in env.possible_agents])
    reference = reference_run(args.imitate) or args.imitate
    rng = np.random.default_rng(args.seed)
    seeds = rng.integers(0, EVAL_SEED_OFFSET, size=args.imitation_rounds * args.imitation_episodes)
    observations, labels, rounds, started = [], [], [], time.time()
    try:
        for index in range(args.imitation_rounds):
            learner = None if index == 0 else functools.partial(actor_mean, model, venv)
            episode_seeds = seeds[index * args.imitation_episodes:(index + 1) * args.imitation_episodes]
            seen, wanted = demonstrations(env, reference, args.imitation_episodes, episode_seeds, learner,
                                          0.0 if index == 0 else IMITATION_LEARNER_SHARE, rng, scales)
            observations.append(seen)
            labels.append(wanted)
            loss = fit_actor(model, venv, np.concatenate(observations), np.concatenate(labels),
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
    write_text(out_dir / "imitation.json", json.dumps({"reference": args.imitate, "rounds": rounds,
                                                       "log_std_after": IMITATION_LOG_STD}, indent=2))


def _normalized(venv: Any, observations: np.ndarray) -> Any:
    import torch

    return torch.as_tensor(venv.normalize_obs(observations), dtype=torch.float32)


def actor_mean(model: Any, venv: Any, observations: np.ndarray) -> np.ndarray:
    """The policy's deterministic action (its Gaussian's mean) for raw observations (k, size)."""
    import torch

    policy = model.policy
    with torch.no_grad():
        latent = policy.mlp_extractor.forward_actor(policy.features_extractor(_normalized(venv, observations)))
        return policy.action_net(latent).numpy().astype(np.float64)


def fit_actor(model: Any, venv: Any, observations: np.ndarray, labels: np.ndarray, epochs: int, seed: int) -> float:
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
