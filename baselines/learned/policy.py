"""A saved run's learned policy as per-agent policies: the normalizer, the actor, the training env's transforms.

:func:`learned_policies` rebuilds what the learner stepped around the shared network: observation
normalization, then the training env's own transforms (:class:`ComposedPolicy`): the observation features, a
mixed team's padding (the run's ``team_padding``, :mod:`~ee_formation_env.baselines.learned.team`) and the mode's
action rule (residual mode: the reference controller with its error gate). The result plugs into
:func:`ee_formation_env.baselines.metrics.run_episode` like a reference policy. :class:`SavedRun` is a run
folder as the comparison and ``ee-formation evaluate --policy RUN_DIR`` evaluate it: the same policies, in
the env settings the run trained with.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ee_formation_env.baselines.learned.action_scale import rescaling
from ee_formation_env.baselines.learned.algorithms import algorithm
from ee_formation_env.baselines.learned.checkpoint import load_policy, load_tensors, read_json, write_json
from ee_formation_env.baselines.learned.features import FeatureRows, check_invariant_arms, feature_size
from ee_formation_env.baselines.learned.modes import ActionRows
from ee_formation_env.baselines.learned.numpy_layers import apply_numpy_layers, numpy_layers
from ee_formation_env.baselines.learned.options import TrainingOptions
from ee_formation_env.baselines.learned.run_files import (BACKEND_MODULES, MODEL_FOLDER, check_model_files,
                                                          check_stamp_sizes, read_run_config)
from ee_formation_env.baselines.learned.set_network import (check_serves, expanded_statistics, numpy_set_actor,
                                                            pooled_statistics, slot_layout, slot_layout_of)
from ee_formation_env.baselines.learned.team import AgentPadding, PaddingRows, TeamPadding, agent_rules


class ObservationNormalizer:
    """Running mean/variance normalization of observations, as learned during training."""

    def __init__(self, mean: np.ndarray, var: np.ndarray, clip: float = 10.0, epsilon: float = 1e-8):
        self.mean, self.var, self.clip, self.epsilon = mean, var, clip, epsilon

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        normalized = (observation - self.mean) / np.sqrt(self.var + self.epsilon)
        return np.clip(normalized, -self.clip, self.clip).astype(np.float32)

    def save(self, path: Path) -> None:
        """As JSON (``obs_normalizer.json``): plain numbers, exact (floats round-trip through their repr)."""
        write_json(path, {"mean": np.asarray(self.mean).tolist(), "var": np.asarray(self.var).tolist(),
                          "clip": None if np.isinf(self.clip) else float(self.clip), "epsilon": float(self.epsilon)})

    @classmethod
    def identity(cls, dim: int) -> "ObservationNormalizer":
        """A normalizer that leaves observations unchanged."""
        return cls(np.zeros(dim), np.ones(dim), clip=np.inf, epsilon=0.0)

    @classmethod
    def from_checkpoint(cls, directory: Path) -> "ObservationNormalizer":
        """The observation normalization a checkpoint folder saved: its ``obs_normalizer.json``, or, in a
        checkpoint written before checkpoints held that file, the observation statistics of its
        ``vecnormalize.json`` (SB3's ``VecNormalize``)."""
        directory = Path(directory)
        if (directory / "obs_normalizer.json").is_file():
            return cls.load(directory / "obs_normalizer.json")
        return cls._read(directory / "vecnormalize.json", ("obs_mean", "obs_var", "clip_obs", "epsilon"))

    @classmethod
    def load(cls, path: Path) -> "ObservationNormalizer":
        return cls._read(Path(path), ("mean", "var", "clip", "epsilon"))

    @classmethod
    def _read(cls, path: Path, keys: tuple[str, str, str, str]) -> "ObservationNormalizer":
        """The normalizer in the JSON file ``path`` under the keys (mean, var, clip, epsilon); a malformed file
        is a ``ValueError`` naming it."""
        mean_key, var_key, clip_key, epsilon_key = keys
        data = read_json(path, path.name)
        try:
            mean, var = np.asarray(data[mean_key], dtype=np.float64), np.asarray(data[var_key], dtype=np.float64)
            clip = np.inf if data[clip_key] is None else float(data[clip_key])
            epsilon = float(data[epsilon_key])
        except (KeyError, TypeError, ValueError) as error:
            raise ValueError(f"{path.name}: malformed ({error})") from None
        if mean.shape != var.shape or mean.ndim != 1:
            raise ValueError(f"{path.name}: {mean_key} and {var_key} must be vectors of one length, got "
                             f"{mean.shape} and {var.shape}")
        return cls(mean, var, clip=clip, epsilon=epsilon)


class LearnedPolicy:
    """A trained shared policy as a per-agent policy: ``reset()`` and ``__call__(observation)``."""

    def __init__(self, predict: Callable[[np.ndarray], np.ndarray], normalizer: ObservationNormalizer):
        self.predict, self.normalizer = predict, normalizer

    def reset(self) -> None:
        pass

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        return np.clip(self.predict(self.normalizer(observation)), -1.0, 1.0)

    @classmethod
    def stacked(cls, policies: Sequence["LearnedPolicy"]) -> Callable[[np.ndarray], np.ndarray]:
        """A stack of learned policies as one callable ``(k, size) -> (k, n)``, each row its policy's action
        bit for bit: one call of the actor when they share it and it takes stacks row by row exactly
        (``predict.stacks``, the numpy actor), else one call per row."""
        policies = list(policies)
        first = policies[0]
        if getattr(first.predict, "stacks", False) and all(
                policy.predict is first.predict and policy.normalizer is first.normalizer for policy in policies):
            return first
        return lambda observations: np.stack([policy(row) for policy, row in zip(policies, observations)])


def saved_scenario(config: Mapping[str, Any]) -> Any:
    """The scenario a run saved (its parsed data), or, for runs saved without it, its name or file."""
    return config.get("scenario_data") or config["scenario"]


class SavedRun:
    """A ``train.py`` run folder whose learned policy is evaluated: its saved configuration, the scenario it
    trained on, the env settings its policy acts in (:meth:`env_overrides`) and its per-agent policies
    (:meth:`policy_source`). The comparison (:mod:`~ee_formation_env.baselines.learned.compare`), ``ee-formation
    evaluate --policy RUN_DIR`` and the scoreboard's test cells all evaluate a run through it."""

    def __init__(self, run_dir: Path | str, config: Mapping[str, Any]):
        self.run_dir, self.config = Path(run_dir), dict(config)

    @classmethod
    def load(cls, run_dir: Path | str, what: str = "run") -> "SavedRun":
        """The finished run in ``run_dir``, opened by :func:`open_run` (its files, stamp and model checked); a
        fault is refused in one line starting with ``what``."""
        return cls(run_dir, open_run(run_dir, what))

    @property
    def options(self) -> TrainingOptions:
        return TrainingOptions.from_saved(self.config)

    @property
    def scenario(self) -> Any:
        """The scenario the run trained on, as saved with it (not as its file is now)."""
        return saved_scenario(self.config)

    @property
    def scenario_name(self) -> str:
        return str(self.config["scenario"])

    @property
    def label(self) -> str:
        """The learned policy's row name in tables: ``learned (<mode>)``."""
        return f"learned ({self.config['mode']})"

    def env_overrides(self) -> dict[str, Any]:
        """Scenario overrides of every env this run's policy acts in: its action convention
        (:meth:`TrainingOptions.env_overrides`, e.g. ``gravity_compensation``)."""
        return self.options.env_overrides()

    def policy_source(self, checkpoint: Path | None = None) -> Callable[[Any], dict[str, Any]]:
        """``copy_env -> per-agent policies`` (:func:`learned_policy_factory`), the model read with the first
        copy's env, when the evaluation builds it: what :func:`~ee_formation_env.baselines.metrics.run_episodes`
        and :func:`~ee_formation_env.baselines.metrics.run_policies` take as a policy. ``checkpoint``: a
        checkpoint folder of the run to act with instead of its final model (an SB3 PPO run's)."""
        factory: list[Callable[[Any], dict[str, Any]]] = []

        def policies(env: Any) -> dict[str, Any]:
            if not factory:
                factory.append(learned_policy_factory(self.run_dir, env, self.config, checkpoint))
            return factory[0](env)

        return policies


def open_run(run_dir: Path | str, what: str, final_model: bool = True) -> dict[str, Any]:
    """The one check every path that reads a run makes before anything else runs (evaluate --policy,
    --eval-only, --resume, --imitate, the board's cells): its ``config.json``
    (:func:`~ee_formation_env.baselines.learned.run_files.read_run_config`: the folder's marker, the file's sha256,
    a run's configuration) and, with ``final_model``, its final model, loaded by :func:`load_model` (its files'
    sha256, its stamp against config.json and against the loaded model). ``--resume`` opens the configuration
    alone, then loads the checkpoint it continues from. Returns config.json's content; a fault is one
    ``ValueError`` starting with ``what``, naming the file (and the field)."""
    from ee_formation_env.baselines.extras import require

    run_dir = Path(run_dir)
    config = read_run_config(run_dir, what)
    if final_model:
        if not (run_dir / MODEL_FOLDER).is_dir():
            raise ValueError(f"{what}: {run_dir} holds no final model ({MODEL_FOLDER}/): the run has not finished "
                             "(--resume continues it)")
        modules, extras = BACKEND_MODULES[config["backend"]]
        require(modules, extras, f"{what} (a --backend {config['backend']} run)")
        load_model(run_dir / MODEL_FOLDER, config, what)
    return config


@dataclass(frozen=True)
class LoadedModel:
    """A model folder's policy as :func:`load_model` read it: the observation normalization, the deterministic
    actor on normalized observations (None for a set network, rebuilt per team: :func:`_set_policy`) and the
    sizes the model itself has."""

    normalizer: ObservationNormalizer
    predict: Callable[[np.ndarray], np.ndarray] | None
    observation_size: int
    action_size: int


def load_model(model_dir: Path, config: Mapping[str, Any], what: str) -> LoadedModel:
    """The model in ``model_dir`` (a run's ``model/`` or one of its checkpoints) of the run configured by
    ``config``, the one way a saved model is read: its files checked against the folder's ``SHA256SUMS`` and its
    stamp against ``config`` (:func:`~ee_formation_env.baselines.learned.run_files.check_model_files`), the policy
    loaded (tensors and JSON only: nothing in the files is executed, a damaged file is a one-line refusal, not
    a torch traceback), then the stamp's sizes against the loaded normalizer and actor. A fault is one
    ``ValueError`` starting with ``what``."""
    model_dir = Path(model_dir)
    stamp = check_model_files(model_dir, config, what)
    try:
        normalizer = ObservationNormalizer.load(model_dir / "obs_normalizer.json")
        predict = None
        if config["backend"] == "rllib":
            predict = rllib_predictor(model_dir)
        else:
            policy = load_policy(model_dir)  # a set network: as it trained, its own slot count
            _check_fits(normalizer, tuple(policy.observation_space.shape), model_dir)
            if TrainingOptions.from_saved(config).policy_network != "set":
                predict = _numpy_actor(policy) if algorithm(config["algo"]).is_ppo else None
                if predict is None:
                    predict = lambda obs: policy.predict(obs, deterministic=True)[0]  # noqa: E731
        size = normalizer.mean.shape[0]
        if predict is None:
            actions = policy.action_space.shape[0]
        else:
            actions = np.asarray(predict(np.zeros(size, dtype=np.float32))).shape[-1]  # the actor's own output
    except ValueError as error:
        raise ValueError(f"{what}: {error}") from None
    check_stamp_sizes(model_dir, stamp, size, actions, what)
    return LoadedModel(normalizer, predict, size, actions)


def learned_policies(run_dir: Path, env: Any, config: dict[str, Any]) -> dict[str, Any]:
    """Per-agent policies of a saved run (its ``model/`` folder), the residual composition included; nothing in
    the files is executed (:mod:`ee_formation_env.baselines.learned.checkpoint`)."""
    return learned_policy_factory(run_dir, env, config)(env)


def learned_policy_factory(run_dir: Path, env: Any, config: dict[str, Any], checkpoint: Path | None = None,
                           what: str = "policy") -> Callable[[Any], dict[str, Any]]:
    """``env -> per-agent policies`` of a saved run (as :func:`learned_policies`), the model read once: each
    call gives fresh reference controllers (their own internal state) around the one shared, stateless learned
    part, what :func:`ee_formation_env.baselines.metrics.run_episodes` calls once per copy. ``checkpoint``: one
    of the run's checkpoint folders instead of its final model (SB3 runs). The model is read by :func:`load_model`
    (a fault: one ``ValueError`` starting with ``what``)."""
    model_dir = Path(run_dir) / MODEL_FOLDER if checkpoint is None else Path(checkpoint)
    if checkpoint is not None and config["backend"] != "sb3":
        raise ValueError(f"checkpoint: only SB3 runs keep checkpoints (this run: --backend {config['backend']})")
    model = load_model(model_dir, config, what)
    normalizer, predict, size, actions = model.normalizer, model.predict, model.observation_size, model.action_size
    options = TrainingOptions.from_saved(config)
    if options.policy_network == "set":
        learned = _set_policy(model_dir, env, normalizer)
        return composed_policy_factory({agent: learned for agent in env.possible_agents}, env, options)
    padding = TeamPadding.from_saved(config)
    if padding is None:
        check_team(env, size, actions, options.resolved().obs_features)
    else:
        padding.check_fits(size, actions)
    learned = LearnedPolicy(predict, normalizer)
    return composed_policy_factory({agent: learned for agent in env.possible_agents}, env, options, padding)


def _set_policy(model_dir: Path, env: Any, normalizer: ObservationNormalizer) -> LearnedPolicy:
    """A set network's learned part (:mod:`~ee_formation_env.baselines.learned.set_network`) for ``env``'s team
    size: the team checked against the one it trained with (``ValueError`` naming the field), the network
    rebuilt for the env's slot count around the saved weights, the pooled normalization expanded to it."""
    description = read_json(model_dir / "policy.json", "policy.json")
    saved = description.get("policy_kwargs", {}).get("set_network") if isinstance(description, dict) else None
    if not isinstance(saved, dict) or "layout" not in saved or "team" not in saved:
        raise ValueError(f"{model_dir / 'policy.json'}: policy_kwargs.set_network missing: the file is not a set "
                         "network's; restore the one the run wrote")
    check_serves(saved["team"], env)
    trained = slot_layout_of(saved)
    target = slot_layout(env.observation_layout(env.possible_agents[0]), "none")
    mean, var = expanded_statistics(target, *pooled_statistics(trained, normalizer.mean, normalizer.var))
    policy = load_policy(model_dir, n_slots=target.n_slots)
    return LearnedPolicy(numpy_set_actor(policy, target), ObservationNormalizer(mean, var, normalizer.clip,
                                                                                normalizer.epsilon))


def check_team(env: Any, observation_size: int, action_size: int, obs_features: str) -> None:
    """Refuse, in one line, a team a shared policy of these sizes cannot act for: an agent whose observation
    (featured by ``obs_features``, as in training) or action has another size. A network fed a vector of the
    wrong length would fail deep inside torch or numpy, or, worse, broadcast. A mixed team's run checks its
    team by its padding instead (:meth:`~ee_formation_env.baselines.learned.team.TeamPadding.agent_paddings`)."""
    for agent in env.possible_agents:
        layout = env.observation_layout(agent)
        observed = env.observation_space(agent).shape[0] + feature_size(layout, obs_features)
        acted = env.action_space(agent).shape[0]
        if (observed, acted) != (observation_size, action_size):
            raise ValueError(f"policy: the run's policy takes {observation_size} observation entries and gives "
                             f"{action_size} joint actions (obs_features {obs_features}); {agent} of scenario "
                             f"{env.scenario.name} has {observed} and {acted}: it cannot act for this team")


def _check_fits(normalizer: ObservationNormalizer, shape: tuple[int, ...], model_dir: Path) -> None:
    """The normalization must be the policy's observation's own, entry for entry: a vector of another length
    would broadcast (one entry over all of them) or fail deep inside an episode."""
    if np.shape(normalizer.mean) != shape:
        raise ValueError(f"{model_dir / 'obs_normalizer.json'}: mean and var have shape {np.shape(normalizer.mean)}, "
                         f"the policy's observation (policy.json) {shape}: the file is not this model's; restore "
                         "the one the run wrote")


def composed_policy_factory(learned: Mapping[str, Any], env: Any, options: TrainingOptions,
                            padding: TeamPadding | None = None) -> Callable[[Any], dict[str, Any]]:
    """``copy_env -> per-agent policies`` around ``learned`` (agent -> a policy on the observation the learner
    saw: featured by ``options.obs_features``), by the training env's own transforms (:class:`ComposedPolicy`).
    Each call gives fresh state (the residual mode's reference controllers); the learned parts are shared
    (stateless). ``padding``: a mixed team's run's (each agent's observation padded, its joints taken from the
    learned action, as the training env does); a team it cannot serve is refused here, naming the agent."""
    options = options.resolved()
    if options.obs_features == "invariant":
        check_invariant_arms(env.task)
    paddings = None if padding is None else padding.agent_paddings(env, options.obs_features)
    scales = rescaling(env.task, options.action_acceleration)
    mode = options.training_mode

    def build(copy_env: Any) -> dict[str, Any]:
        rules = agent_rules(mode, options, copy_env, scales)  # one rule of one row per agent
        return {agent: ComposedPolicy(learned[agent], copy_env.observation_layout(agent), options.obs_features,
                                      rules[agent], None if paddings is None else paddings[agent])
                for agent in copy_env.possible_agents}

    return build


class ComposedPolicy:
    """One agent's learned part composed as the training env composes it: its raw observation featured
    (:class:`~ee_formation_env.baselines.learned.features.FeatureRows`), the learned action, then the mode's
    action rule (``rows``, a rule of one row); with a mixed team's ``padding``, the featured observation padded
    and the agent's own joints taken from the learned action. It is the one-row case of the training env's
    transforms, and a stack of them (:meth:`stacked`) is their many-row case."""

    def __init__(self, learned: Any, layout: Any, obs_features: str, rows: ActionRows,
                 padding: AgentPadding | None = None):
        self.learned, self.layout, self.obs_features, self.rows = learned, layout, obs_features, rows
        self.features = FeatureRows([layout], [obs_features])
        self.padding = padding
        self._padding_rows = None if padding is None else PaddingRows([padding])

    def reset(self) -> None:
        self.rows.reset()
        self.learned.reset()

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        raw = np.asarray(observation)[None]
        if self._padding_rows is None:
            action = np.asarray(self.learned(self.features(raw)[0]))[None]
        else:
            padded = self._padding_rows.observations(self.features(raw))
            action = self._padding_rows.actions(np.asarray(self.learned(padded[0]))[None])
        return self.rows(raw, action)[0][0]

    @classmethod
    def stacked(cls, policies: Sequence["ComposedPolicy"]) -> Callable[[np.ndarray], np.ndarray]:
        """A stack of them as one callable ``(k, size) -> (k, n)``, each row its policy's action bit for bit:
        the features of the rows of one layout in one call, the learned parts as one stack
        (:func:`~ee_formation_env.baselines.metrics.stack_policies`), the rules of one kind as one rule."""
        from ee_formation_env.baselines.metrics import stack_policies

        policies = list(policies)
        learned = stack_policies([policy.learned for policy in policies])
        features = FeatureRows([policy.layout for policy in policies], [policy.obs_features for policy in policies])
        if any(policy.padding is not None for policy in policies):  # a mixed team's run: every policy is padded
            padding = PaddingRows([policy.padding for policy in policies])
            unpadded = features
            features = lambda observations: padding.observations(unpadded(observations))  # noqa: E731
            actor = learned
            learned = lambda observations: padding.actions(np.asarray(actor(observations)))  # noqa: E731
        groups: dict[Any, list[int]] = {}
        for row, policy in enumerate(policies):
            groups.setdefault(policy.rows.stack_key, []).append(row)
        rules = [(np.array(rows), type(policies[rows[0]].rows).concatenate([policies[r].rows for r in rows]))
                 for rows in groups.values()]

        def act(observations: np.ndarray) -> np.ndarray:
            actions = np.asarray(learned(features(observations)))
            if len(rules) == 1:
                return rules[0][1](observations, actions)[0]
            parts = [(rows, rule(observations[rows], actions[rows])[0]) for rows, rule in rules]
            out = np.empty((len(observations), parts[0][1].shape[1]), dtype=np.result_type(*(p for _, p in parts)))
            for rows, part in parts:
                out[rows] = part
            return out

        return act


def _numpy_actor(policy: Any) -> Callable[[np.ndarray], np.ndarray] | None:
    """PPO's deterministic action (the Gaussian's mean) as numpy matrix products
    (:mod:`~ee_formation_env.baselines.learned.numpy_layers`), or None if the policy is not a plain MLP of
    ``Linear`` and ``Tanh`` layers."""
    import torch

    steps = numpy_layers([*policy.mlp_extractor.policy_net, policy.action_net])
    if not isinstance(policy.features_extractor.flatten, torch.nn.Flatten) or steps is None:
        return None

    def predict(observation: np.ndarray) -> np.ndarray:
        hidden = np.asarray(observation, dtype=np.float64)
        if hidden.ndim == 2:  # a stack: row by row the products of one observation, exactly
            return apply_numpy_layers(steps, hidden[:, None, :])[:, 0, :]
        return apply_numpy_layers(steps, hidden)

    predict.stacks = True  # a stack (k, d) gives each row's action bit for bit (LearnedPolicy.stacked)
    return predict


def rllib_predictor(model_dir: Path) -> Callable[[np.ndarray], np.ndarray]:
    """The deterministic action (the Gaussian's mean) of the RLlib module saved in ``model_dir``, rebuilt as
    RLlib's default PPO module around its saved parameters (read with ``weights_only``)."""
    import gymnasium
    import torch
    from ray.rllib.algorithms.ppo import PPOConfig

    description = read_json(model_dir / "rllib_module.json", "rllib_module.json")
    config = PPOConfig().framework("torch")
    spec = config.get_default_rl_module_spec()
    spec.observation_space = gymnasium.spaces.Box(-np.inf, np.inf, tuple(description["observation_shape"]),
                                                  dtype=np.float32)
    low = np.asarray(description["action_low"], dtype=np.float32)
    high = np.asarray(description["action_high"], dtype=np.float32)
    spec.action_space = gymnasium.spaces.Box(low, high, dtype=np.float32)
    # The module's own settings (older runs saved none: RLlib's defaults then).
    spec.model_config = {**config.model_config, **description.get("model_config", {})}
    module = spec.build()
    module.load_state_dict(load_tensors(model_dir / "rllib_module.pt", "rllib_module.pt"))

    def predict(observation: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            output = module.forward_inference({"obs": torch.as_tensor(observation[None], dtype=torch.float32)})
        logits = output["action_dist_inputs"][0].numpy()
        mean = logits[: len(low)]  # a diagonal Gaussian: means first, then log-stds
        return np.clip(mean, low, high)

    return predict
