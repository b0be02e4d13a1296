"""BenchMARL tasks on the training env, evaluation with the project's metrics, and actor export (the ``torchrl`` extra).

    from ee_formation_env.baselines.learned.benchmarl_task import (EEFormationTrainingTask, evaluate_benchmarl_policy,
                                                                   export_benchmarl_policy, load_benchmarl_policy)

    task = EEFormationTrainingTask.PLANAR_SQUARE.get_task({"mode": "residual"})  # options + scenario overrides
    experiment = Experiment(task=task, algorithm_config=MappoConfig.get_from_yaml(), ...)
    experiment.run()
    summary = evaluate_benchmarl_policy(experiment, episodes=10)   # what `ee-formation evaluate` reports
    export_benchmarl_policy(experiment, "mappo_actor")             # plain tensors + JSON, no pickle
    actors = load_benchmarl_policy("mappo_actor")                  # numpy actors; BenchMARL not needed

**The env.** A task's ``get_env_fun`` builds the learning wing's
:class:`~ee_formation_env.baselines.learned.training_env.BatchedTrainingEnv` (K copies: torque or residual
actions, observation features, hold penalty, physically scaled actions) and hands it to
:meth:`ee_formation_env.integrations.torchrl.BatchedTorchRLEnv.from_batched`: the env package never imports
the learning wing. The training env shares one policy among identical agents, so a task needs a team of one
robot kind (one BenchMARL group).

**Config.** A task's config is one dict: the fields of :class:`TrainingTaskOptions` (the training options,
:class:`~ee_formation_env.baselines.learned.options.TrainingOptions`; missing ones take their
defaults), the fields of :class:`TaskTransforms` (the TorchRL transforms the task adds: observation
normalization and reward scaling, off by default), optionally ``scenario`` (a scenario file or dict instead of
the member's built-in scenario), and scenario overrides: every other key, checked by the scenario loader (an
unknown key is its error, naming it).
The overrides apply to training and evaluation alike; training then sets ``episode_seconds`` to
``train_episode_seconds`` and, where the options give one, ``initial_q_noise`` to ``train_initial_q_noise``.
Everything is checked when the task is made (``get_task``), before any env is built.

**Evaluation.** BenchMARL builds its test env by the training env's ``get_env_fun`` call, so its own
evaluation (``evaluation_interval``) reports training conditions (episode length, start noise, shaped
rewards): a learning curve. :func:`evaluate_benchmarl_policy` is the project's: the scenario's own episodes (its
``episode_seconds`` and ``initial_q_noise``, with the task's overrides), the env's reward, the metrics of
:mod:`ee_formation_env.baselines.metrics` on held-out seeds >= 10,000 (training resets use seeds below), the
policy deterministic (the Gaussian's mean, through the tanh of BenchMARL's ``TanhNormal``).

**Task YAML.** BenchMARL's ``Task.get_from_yaml()`` reads YAML files inside its own package only; here
``get_from_yaml(path)`` reads a config dict from any YAML file (the project's own per mode:
:mod:`~ee_formation_env.baselines.learned.benchmarl_configs`); the defaults are :class:`TrainingTaskOptions`'s.

**Export.** :func:`export_benchmarl_policy` writes a folder (atomically,
:func:`~ee_formation_env.baselines.learned.checkpoint.atomic_directory`): ``actor.pt``, every group's layer
weights and biases as plain tensors (``torch.load(weights_only=True)``), and ``actor.json``: per group its
agents, layer sizes, activation, whether its agents share parameters, the action distribution and bounds and
the observation normalization (per agent ``loc`` and ``scale`` of the task's
:class:`RunningObservationNorm`, as training left them; null without it), plus the task's options, transforms, scenario and overrides. :func:`load_benchmarl_policy` reads it back into :class:`BenchmarlActors` (numpy),
which :func:`evaluate_benchmarl_policy` also accepts. An actor that is the project's set model on the task's
``observation_sets`` (:class:`~ee_formation_env.baselines.learned.benchmarl_configs.SlotDeepsets`) is exported
with its slot layout (``set_network``) and acts for any team of its robot
(:class:`~ee_formation_env.baselines.learned.benchmarl_actor.GroupActor`).
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, List, Mapping, Optional

import numpy as np
import torch
import yaml
from benchmarl.environments.common import TaskClass
from benchmarl.models.deepsets import Deepsets
from benchmarl.models.mlp import Mlp
from torchrl.envs import EnvBase, Transform
from torchrl.modules.distributions import IndependentNormal, TanhNormal

from ee_formation_env.baselines.learned.benchmarl_actor import ACTIVATIONS, GroupActor  # noqa: F401
from ee_formation_env.baselines.learned.benchmarl_configs import SlotDeepsets
from ee_formation_env.baselines.learned.benchmarl_transforms import (ReturnNormalizedReward, RunningObservationNorm,  # noqa: F401
                                                                     TaskTransforms,
                                                                     task_transforms)
from ee_formation_env.baselines.learned.checkpoint import atomic_directory, load_tensors, read_json, write_json
from ee_formation_env.baselines.learned.options import TrainingOptions
from ee_formation_env.baselines.learned.policy import LearnedPolicy, composed_policy_factory
from ee_formation_env.baselines.learned.set_network import SlotLayout, set_description, slot_layout_of
from ee_formation_env.baselines.learned.team import refuse_mixed_team
from ee_formation_env.baselines.learned.training_env import EVAL_SEED_OFFSET, BatchedTrainingEnv
from ee_formation_env.baselines.metrics import DEFAULT_POSITION_TOLERANCE, run_episodes, summarize
from ee_formation_env.builtin import BUILTIN_SCENARIOS
from ee_formation_env.integrations.benchmarl import EEFormationTaskClass, EEFormationTaskBase
from ee_formation_env.integrations.torchrl import BatchedTorchRLEnv
from ee_formation_env.scenario import load_scenario

EXPORT_FORMAT = 1
ACTOR_TENSORS, ACTOR_DESCRIPTION = "actor.pt", "actor.json"


# ------------------------------------------------------------------------------------------ options
#: A task's options are the training options, the one class ``train.py``'s flags read too.
TrainingTaskOptions = TrainingOptions


def training_env(options: TrainingOptions, scenario: Any, overrides: Mapping[str, Any],
                 num_envs: int) -> BatchedTrainingEnv:
    """The training env of ``options``: ``num_envs`` copies of ``scenario`` with ``overrides`` and then the
    options' training overrides (episode length, start noise). A mixed team is refused (team.py)."""
    env = BatchedTrainingEnv(scenario, {**overrides, **options.training_overrides()}, options, num_envs=num_envs)
    refuse_mixed_team(env, "the BenchMARL task")
    return env


def split_config(config: Mapping[str, Any], default_scenario: Any) -> tuple[TrainingOptions, Any, dict[str, Any]]:
    """A task config as (options, scenario, scenario overrides): the option fields, ``scenario`` (default
    ``default_scenario``) and every other key but the :class:`TaskTransforms` fields as an override. Raises naming
    the first bad option."""
    if not isinstance(config, Mapping):
        raise TypeError(f"config: expected a dict of options and scenario overrides, got {type(config).__name__}")
    names = set(TrainingOptions.fields())
    options = TrainingOptions(**{key: value for key, value in config.items() if key in names})
    if options.policy_network != "mlp":
        raise ValueError(f"policy_network: {options.policy_network!r} is train.py's SB3 network; a BenchMARL "
                         "experiment builds its own models (expected 'mlp')")
    skipped = names | set(TaskTransforms.fields()) | {"scenario"}
    overrides = {key: value for key, value in config.items() if key not in skipped}
    return options, config.get("scenario", default_scenario), overrides


# ------------------------------------------------------------------------------------------ the BenchMARL task
class TrainingTaskClass(EEFormationTaskClass):
    """How BenchMARL builds and reads one formation task on the training env (module docstring). The specs and
    groups are those of :class:`~ee_formation_env.integrations.benchmarl.EEFormationTaskClass`."""

    def __init__(self, name: str, config: Dict[str, Any]):
        super().__init__(name, config)
        self.check()

    def parts(self) -> tuple[TrainingOptions, Any, dict[str, Any]]:
        """(options, scenario, scenario overrides) of the config (:func:`split_config`)."""
        return split_config(self.config, self.name.lower())

    def check(self) -> None:
        """Raise naming the field for a bad option or scenario override (the scenario loads, no physics)."""
        options, scenario, overrides = self.parts()
        load_scenario(scenario, **overrides)
        load_scenario(scenario, **{**overrides, **options.training_overrides()})
        if self.transforms().observation_sets:  # features and a team the slots fit (builds one env, no training)
            self.slot_layout()

    def transforms(self) -> TaskTransforms:
        """The config's :class:`TaskTransforms` (raises naming the field of a bad value)."""
        return task_transforms(self.config)

    def get_env_transforms(self, env: EnvBase) -> List[Transform]:
        """The config's transforms (:class:`TaskTransforms`); the task keeps the observation normalization,
        whose statistics its clones in BenchMARL's envs share (:meth:`observation_statistics`)."""
        chosen = self.transforms()
        layout = self.slot_layout() if chosen.observation_sets else None
        transforms = chosen.transforms(env, self.group_map(env), layout)
        norms = [t for t in transforms if isinstance(t, RunningObservationNorm)]
        self._observation_norm = norms[0] if norms else None
        reward_norms = [t for t in transforms if isinstance(t, ReturnNormalizedReward)]
        self._reward_norm = reward_norms[0] if reward_norms else None
        return transforms

    def take_env_reward(self) -> Optional[float]:
        """With ``reward_normalization``, the mean reward per agent step in the env's units since the last call, over
        every env BenchMARL made (:meth:`ReturnNormalizedReward.take_env_reward`); else None (the batch's rewards
        are the env's times ``reward_scale``)."""
        norm = getattr(self, "_reward_norm", None)
        return None if norm is None else norm.take_env_reward()

    def slot_layout(self) -> SlotLayout:
        """The slot layout of the task's observations (``observation_sets``; ``ValueError`` naming the field for
        features that break the slots or a mixed team)."""
        options, scenario, overrides = self.parts()
        return slot_layout_of(set_description(load_scenario(scenario, **overrides), options.resolved().obs_features))

    def observation_statistics(self, group: str) -> tuple[np.ndarray, np.ndarray]:
        """(loc, scale) (n_agents, obs_dim) of the group's observation normalization, as training left them."""
        norm = getattr(self, "_observation_norm", None)
        if norm is None:
            raise ValueError("observation_normalization: the task made no normalization transform (BenchMARL "
                             "calls get_env_transforms when an Experiment is built)")
        return norm.statistics((group, "observation"))

    def _scenario_and_overrides(self) -> tuple[Any, dict[str, Any]]:
        """The scenario and its overrides as evaluation uses them (without the training options)."""
        _, scenario, overrides = self.parts()
        return scenario, overrides

    def get_env_fun(self, num_envs: int, continuous_actions: bool, seed: Optional[int],
                    device: Any) -> Callable[[], EnvBase]:
        if not continuous_actions:
            raise ValueError("continuous_actions: the formation env has continuous (torque) actions only")
        self.check()  # the config may have been edited since the task was made
        options, scenario, overrides = self.parts()
        # BenchMARL calls this for its test env too, with the same arguments: both are training envs (module
        # docstring); copy k of either resets with seed + k first.
        return lambda: BatchedTorchRLEnv.from_batched(training_env(options, scenario, overrides, num_envs), seed=seed,
                                                      device=device)

    def max_steps(self, env: EnvBase) -> int:
        """The training episode's steps (BenchMARL's test env is a training env)."""
        options, scenario, overrides = self.parts()
        return load_scenario(scenario, **{**overrides, **options.training_overrides()}).max_steps

    @staticmethod
    def env_name() -> str:
        return "ee_formation_training"


class _TrainingTaskBase(EEFormationTaskBase):
    """The members' behaviour (the plain task's, on :class:`TrainingTaskClass`: ``get_task(config)`` takes
    options and scenario overrides and raises naming the field of a bad value); the members themselves are
    made from the built-in registry below."""

    @staticmethod
    def associated_class():
        return TrainingTaskClass

    def get_from_yaml(self, path: Optional[str] = None) -> TaskClass:
        """This task with the config dict of the YAML file ``path`` (none: the defaults, as :meth:`get_task`);
        no YAML ships (module docstring)."""
        if path is None:
            return self.get_task()
        config = yaml.safe_load(Path(path).read_text(encoding="utf-8")) or {}
        if not isinstance(config, dict):
            raise ValueError(f"{path}: expected a mapping of task options and scenario overrides")
        return self.get_task(config)


# One member per built-in scenario, ``planar_square`` -> ``EEFormationTrainingTask.PLANAR_SQUARE`` (BenchMARL's
# convention: members are None-valued, numbered by Task.__new__; the task class reads the lower-cased name).
EEFormationTrainingTask = _TrainingTaskBase(
    "EEFormationTrainingTask", [(name.upper(), None) for name in BUILTIN_SCENARIOS], module=__name__,
    qualname="EEFormationTrainingTask")
EEFormationTrainingTask.__doc__ = ("The built-in scenarios as BenchMARL tasks on the training env "
                                   "(``ee_formation_env.builtin.BUILTIN_SCENARIOS``).")


# ------------------------------------------------------------------------------------------ the actors
#: The torch activation layers the export reads, by the numpy actor's names.
TORCH_ACTIVATIONS = {torch.nn.Tanh: "Tanh", torch.nn.ReLU: "ReLU"}
#: The action distributions the export reads: TorchRL's TanhNormal and IndependentNormal, by the actor's names.
DISTRIBUTIONS = {TanhNormal: "tanh_normal", IndependentNormal: "normal"}


@dataclass
class BenchmarlActors:
    """A trained BenchMARL experiment's deterministic actors (numpy, per group) and the task they trained on:
    its ``options`` (:class:`TrainingOptions`, resolved), ``scenario`` and scenario ``overrides``."""

    groups: Dict[str, GroupActor]
    options: TrainingOptions
    scenario: Any
    overrides: Dict[str, Any]
    task: str = ""  # the task member's name, e.g. "PLANAR_SQUARE"
    transforms: TaskTransforms = TaskTransforms()

    def learned_policies(self) -> dict[str, LearnedPolicy]:
        """Agent -> its learned part on the observation the learner saw (featured, then normalized where the task
        normalizes), output clipped to [-1, 1]; the agents of a group that share parameters and see one
        normalization (none) share one policy object (one stacked call)."""
        policies = {}
        for actor in self.groups.values():
            one_policy = actor.shared and actor.observation_loc is None
            shared = LearnedPolicy(actor.predict(actor.agents[0]), actor.normalizer(actor.agents[0])) if one_policy \
                else None
            for agent in actor.agents:
                policies[agent] = shared or LearnedPolicy(actor.predict(agent), actor.normalizer(agent))
        return policies

    def env_overrides(self) -> dict[str, Any]:
        """Scenario overrides of every env these actors act in: their action convention
        (:meth:`TrainingOptions.env_overrides`, e.g. ``gravity_compensation`` in position and velocity mode), as
        the training env had it."""
        return self.options.env_overrides()

    def policy_factory(self) -> Callable[[Any], dict[str, Any]]:
        """``copy_env -> per-agent policies`` acting as the task's training env did, for
        :func:`~ee_formation_env.baselines.metrics.run_episodes` (fresh reference controllers per call). A set
        actor (:attr:`GroupActor.slots`) acts for every agent of any team it serves (:meth:`GroupActor.serves`)."""
        learned = self.learned_policies()
        (first, *_) = self.groups.values()

        def build(copy_env: Any) -> dict[str, Any]:
            for actor in self.groups.values():
                actor.serves(copy_env)
            agents = learned if first.slots is None else dict.fromkeys(copy_env.possible_agents, learned[first.agents[0]])
            return composed_policy_factory(agents, copy_env, self.options)(copy_env)

        return build

    def description(self) -> dict[str, Any]:
        """``actor.json``: what rebuilds the actors around ``actor.pt``'s tensors (module docstring)."""
        return {"format": EXPORT_FORMAT, "task": self.task, "scenario": _plain_scenario(self.scenario),
                "overrides": self.overrides, "options": self.options.to_dict(),
                "transforms": dataclasses.asdict(self.transforms),
                "groups": {group: {"agents": actor.agents, "layer_sizes": actor.layer_sizes,
                                   "activation": actor.activation, "shared_parameters": actor.shared,
                                   "distribution": actor.distribution, "action_low": actor.low.tolist(),
                                   "action_high": actor.high.tolist(),
                                   "observation_normalization": None if actor.observation_loc is None else
                                   {"loc": actor.observation_loc.tolist(), "scale": actor.observation_scale.tolist()},
                                   "set_network": actor.slots}
                           for group, actor in self.groups.items()}}

    def save(self, path: str | os.PathLike) -> Path:
        """Write ``actor.pt`` and ``actor.json`` into the folder ``path``, atomically; returns it."""
        description = self.description()  # checks the scenario is JSON-ready before anything is written
        # float32, as BenchMARL trains them (exact: the numpy actors hold them widened to float64); torch's
        # (A, out, in) layout.
        tensors = {group: {"weight": [torch.from_numpy(w.transpose(0, 2, 1).astype(np.float32)) for w in actor.weights],
                           "bias": [torch.from_numpy(b.astype(np.float32)) for b in actor.biases]}
                   for group, actor in self.groups.items()}
        with atomic_directory(Path(path)) as partial:
            torch.save(tensors, partial / ACTOR_TENSORS)
            write_json(partial / ACTOR_DESCRIPTION, description)
        return Path(path)


def _plain_scenario(scenario: Any) -> Any:
    """The task's scenario as JSON holds it: a built-in name or file path (str) or a dict."""
    if isinstance(scenario, os.PathLike):
        return os.fspath(scenario)
    if not isinstance(scenario, (str, dict)):
        raise ValueError(f"scenario: an export records a built-in name, a file or a dict, got "
                         f"{type(scenario).__name__}")
    return scenario


def actors_from_experiment(experiment: Any) -> BenchmarlActors:
    """The deterministic actors of a BenchMARL ``experiment`` on a training task, read from its group policies:
    per group, BenchMARL's ``ProbabilisticActor`` around its MLP (``Linear`` layers, a ``Tanh`` or ``ReLU``
    activation, no normalization layers, decentralized), or around a decentralized ``Deepsets`` with shared
    parameters on the task's set observations, and ``NormalParamExtractor``, with a ``TanhNormal`` or
    ``IndependentNormal`` distribution: what MAPPO, IPPO, MASAC and ISAC build (tested with MAPPO). Anything else
    raises ``ValueError``."""
    task = experiment.task
    if not isinstance(task, TrainingTaskClass):
        raise ValueError(f"experiment.task: expected a training task (an EEFormationTrainingTask member: the export "
                         f"and the evaluation read its training options), got {type(task).__name__}")
    options, scenario, overrides = task.parts()
    normalization = ({group: task.observation_statistics(group) for group in experiment.group_map}
                     if task.transforms().observation_normalization else {})
    groups = {}
    for group, actor in experiment.group_policies.items():
        where = f"experiment.group_policies[{group!r}]"
        try:
            network, head = actor.module[0], actor.module[1]
            model = network.module[0]
            distribution = head.distribution_class
        except (AttributeError, IndexError, TypeError) as error:
            raise ValueError(f"{where}: expected BenchMARL's ProbabilisticActor around a model ({error})") from None
        if distribution not in DISTRIBUTIONS:
            raise ValueError(f"{where}: expected a TanhNormal or IndependentNormal actor, got {distribution.__name__}")
        weights, biases, activations = [], [], set()
        slots = None
        if isinstance(model, Deepsets):  # on the task's observation_sets: phi's layers, then rho's
            sets = (group, "observation", "neighbour_slots"), (group, "observation", "own_state")
            if model.centralised or not model.share_params or list(model.in_keys) != list(sets):
                raise ValueError(f"{where}: expected a decentralized Deepsets with shared parameters on {list(sets)}")
            net = model.local_deepsets[0]
            layout = task.slot_layout()
            slots = {"slot_size": layout.slot_size, "own_size": layout.own_size, "aggregation": net.aggr,
                     "local_layers": sum(isinstance(layer, torch.nn.Linear) for layer in net.local_nn),
                     "masked": isinstance(model, SlotDeepsets)}  # BenchMARL's own pools padding slots too
            sequence = [*net.local_nn, *net.global_nn]
            read = lambda index, layer: (layer.weight[None], layer.bias[None])  # noqa: E731 (one shared set)
        elif isinstance(model, Mlp) and not model.mlp.centralized and list(model.in_keys) == [(group, "observation")]:
            params, share = model.mlp.params, model.mlp.share_params
            sequence = list(model.mlp._empty_net)
            read = lambda index, layer: tuple(  # noqa: E731 (shared: a leading axis of 1)
                params[str(index), name][None] if share else params[str(index), name] for name in ("weight", "bias"))
        else:
            raise ValueError(f"{where}: expected a decentralized BenchMARL Mlp on ({group!r}, 'observation') or "
                             "a Deepsets on its observation_sets")
        for index, layer in enumerate(sequence):
            if isinstance(layer, torch.nn.Linear):
                weight, bias = (value.detach().cpu().numpy().astype(np.float64) for value in read(index, layer))
                weights.append(weight.transpose(0, 2, 1))  # (A, out, in) -> (A, in, out)
                biases.append(bias)
            elif type(layer) in TORCH_ACTIVATIONS:
                activations.add(TORCH_ACTIVATIONS[type(layer)])
            else:
                raise ValueError(f"{where}: layer {index} is a {type(layer).__name__}; the export handles Linear "
                                 f"layers and one of the activations {list(ACTIVATIONS)}")
        if len(activations) > 1:
            raise ValueError(f"{where}: expected one activation, got {sorted(activations)}")
        n = weights[-1].shape[-1] // 2  # the MLP outputs loc and scale
        low, high = -np.ones(n), np.ones(n)  # IndependentNormal: unbounded, the env clips
        if distribution is TanhNormal:  # bounds per agent (n_agents, n); a group's agents have one action space
            bounds = [head.distribution_kwargs[key].detach().cpu().numpy().astype(np.float64).reshape(-1, n)
                      for key in ("low", "high")]
            if not all(np.all(bound == bound[0]) for bound in bounds):
                raise ValueError(f"{where}: expected one action range for the group's agents")
            low, high = bounds[0][0], bounds[1][0]
        loc, scale = normalization.get(group, (None, None))
        groups[group] = GroupActor(list(experiment.group_map[group]), weights, biases,
                                   activations.pop() if activations else "Tanh", DISTRIBUTIONS[distribution], low, high,
                                   loc, scale, slots=slots)
    return BenchmarlActors(groups, options.resolved(), scenario, overrides, task=task.name,
                           transforms=task.transforms())


def export_benchmarl_policy(experiment: Any, path: str | os.PathLike) -> Path:
    """Write the deterministic actors of ``experiment`` (:func:`actors_from_experiment`) into the folder ``path``
    (``actor.pt`` + ``actor.json``, module docstring), atomically; returns the folder."""
    return actors_from_experiment(experiment).save(path)


def load_benchmarl_policy(path: str | os.PathLike) -> BenchmarlActors:
    """The actors exported into the folder ``path``, read with ``torch.load(weights_only=True)`` and JSON only
    (nothing in the files is run; BenchMARL is not needed). A malformed folder raises ``ValueError`` naming
    the file."""
    folder = Path(path)
    description = read_json(folder / ACTOR_DESCRIPTION, ACTOR_DESCRIPTION)
    tensors = load_tensors(folder / ACTOR_TENSORS, ACTOR_TENSORS)
    if not isinstance(description, dict) or description.get("format") != EXPORT_FORMAT:
        raise ValueError(f"{ACTOR_DESCRIPTION}: expected format {EXPORT_FORMAT}")
    try:
        options = TrainingOptions(**description["options"])
        groups = {}
        for group, entry in description["groups"].items():
            weights = [np.asarray(w.numpy(), dtype=np.float64).transpose(0, 2, 1) for w in tensors[group]["weight"]]
            biases = [np.asarray(b.numpy(), dtype=np.float64) for b in tensors[group]["bias"]]
            normalization = entry["observation_normalization"]
            if normalization is not None and not isinstance(normalization, dict):
                raise TypeError(f"observation_normalization: expected null or {{loc, scale}}, got {normalization!r}")
            actor = GroupActor(list(entry["agents"]), weights, biases, entry["activation"], entry["distribution"],
                               np.asarray(entry["action_low"], dtype=np.float64),
                               np.asarray(entry["action_high"], dtype=np.float64),
                               *((None, None) if normalization is None else (normalization["loc"], normalization["scale"])),
                               slots=entry.get("set_network"))
            if actor.layer_sizes != list(entry["layer_sizes"]) or actor.shared != entry["shared_parameters"]:
                raise ValueError(f"group {group!r}: {ACTOR_TENSORS} does not fit {ACTOR_DESCRIPTION}")
            groups[group] = actor
        return BenchmarlActors(groups, options, description["scenario"], dict(description["overrides"]),
                               task=str(description.get("task", "")),
                               transforms=TaskTransforms(**description.get("transforms", {})))
    except (KeyError, TypeError, AttributeError, IndexError) as error:
        raise ValueError(f"{ACTOR_DESCRIPTION} / {ACTOR_TENSORS}: malformed ({error!r})") from None


# ------------------------------------------------------------------------------------------ evaluation
def evaluate_benchmarl_policy(source: Any, task: Optional[TrainingTaskClass] = None, episodes: int = 10,
                              seed: int = EVAL_SEED_OFFSET, position_tolerance: float = DEFAULT_POSITION_TOLERANCE,
                              num_envs: Optional[int] = None) -> dict[str, Any]:
    """The project's evaluation of a BenchMARL policy: :func:`~ee_formation_env.baselines.metrics.summarize` of
    ``episodes`` episodes reset with seeds ``seed, seed + 1, ...`` (held out: ``seed`` >= 10,000), plus
    ``"per_episode"`` (each episode's :class:`~ee_formation_env.baselines.metrics.EpisodeMetrics` as a dict):
    what ``ee-formation evaluate`` returns per policy (``format_table({name: summary})`` prints its table).

    ``source``: a BenchMARL ``Experiment`` on a training task, :class:`BenchmarlActors` or an export folder.
    ``task``: the task whose options, scenario and overrides to evaluate with (default: the one the actors
    trained on). The episodes are the scenario's own (its ``episode_seconds`` and ``initial_q_noise``, with the
    task's overrides; not the training ones) in the actors' action convention (:meth:`BenchmarlActors.env_overrides`),
    run on the batched env (``num_envs`` copies, default one per
    episode, at most 16); the policy is the deterministic actor composed as the training env acts
    (residual mode: the reference controller plus the scaled, gated correction).
    """
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes: expected an integer >= 1, got {episodes!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < EVAL_SEED_OFFSET:
        raise ValueError(f"seed: expected an integer >= {EVAL_SEED_OFFSET} (held-out seeds; training resets use "
                         f"seeds below it), got {seed!r}")
    if isinstance(source, BenchmarlActors):
        actors = source
    elif isinstance(source, (str, os.PathLike)):
        actors = load_benchmarl_policy(source)
    else:
        actors = actors_from_experiment(source)
    if task is not None:
        options, scenario, overrides = task.parts()
        actors = dataclasses.replace(actors, options=options, scenario=scenario, overrides=overrides, task=task.name)
    seeds = [seed + k for k in range(episodes)]
    results = run_episodes(actors.scenario, actors.policy_factory(), seeds, position_tolerance=position_tolerance,
                           overrides={**actors.overrides, **actors.env_overrides()}, num_envs=num_envs)
    summary = summarize(results)
    summary["per_episode"] = [result.as_dict() for result in results]
    return summary
