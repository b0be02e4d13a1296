"""The project's BenchMARL configurations for the formation training tasks, as YAML in BenchMARL's layout (the
``torchrl`` extra).

    from ee_formation_env.baselines.learned.benchmarl_configs import (algorithm_config, experiment_config,
                                                                      model_config, task_config)

    experiment = Experiment(task=EEFormationTrainingTask.PLANAR_SQUARE.get_task(task_config("torque")),
                            algorithm_config=algorithm_config("mappo"), model_config=model_config(),
                            critic_model_config=model_config(), seed=0, config=experiment_config("mappo"))

The files lie in :data:`CONFIG_DIR` as BenchMARL lays out its own ``conf/``: ``algorithm/<name>.yaml`` (each
algorithm's file, as the registry names it: :mod:`~ee_formation_env.baselines.learned.algorithms`),
``experiment/on_policy.yaml`` and ``off_policy.yaml`` (every field of BenchMARL's ``base_experiment.yaml``),
``model/layers/mlp.yaml`` and ``task/ee_formation_training/<mode>.yaml``; each loads with BenchMARL's own
``get_from_yaml(path)`` (the task's with the task member's). What they set and why: train.py's PPO settings
where BenchMARL has the knob, the task's TorchRL transforms (observation normalization, reward scale), and two
things BenchMARL's MAPPO and IPPO hard-code: advantage normalization (off there) and a Gaussian scale output by
the actor (a state-dependent one). :class:`FormationMappo` and :class:`FormationIppo` turn the first on and
make the scale one learned parameter through their configs' ``normalize_advantage`` and
``state_independent_scale`` fields. The measurements behind them: docs/training.md ("TorchRL and BenchMARL").
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Optional, Type

import benchmarl.algorithms
import torch
import yaml
from benchmarl.algorithms import Ippo, IppoConfig, Mappo, MappoConfig
from benchmarl.algorithms.common import AlgorithmConfig
from benchmarl.experiment import ExperimentConfig
from benchmarl.models.common import ModelConfig
from benchmarl.models.deepsets import Deepsets, DeepsetsConfig
from benchmarl.models.mlp import MlpConfig

from ee_formation_env.baselines.learned.algorithms import Algorithm, algorithm
from ee_formation_env.baselines.learned.modes import mode_names
from ee_formation_env.baselines.learned.set_network import POOLINGS, masked_pool

#: The folder of the YAML files (installed with the package).
CONFIG_DIR = Path(__file__).with_name("benchmarl_conf")


class StateIndependentScale(torch.nn.Module):
    """The Gaussian's standard deviation as a learned parameter, the same in every state (SB3's and the MAPPO
    authors' ``log_std``): in place of BenchMARL's ``NormalParamExtractor``, it takes the actor's logits
    ``(..., 2 n)``, keeps the first ``n`` as the mean and maps one parameter vector through ``scale_mapping``
    (its value 0 maps to the mapping's bias, the initial standard deviation). The other ``n`` logits are unused."""

    def __init__(self, n_actions: int, scale_mapping: str, device: Any = None):
        super().__init__()
        from tensordict.nn.utils import mappings

        self.scale_parameter = torch.nn.Parameter(torch.zeros(n_actions, device=device))
        self.scale_mapping = mappings(scale_mapping)

    def forward(self, logits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loc = logits[..., : self.scale_parameter.shape[-1]]
        return loc, self.scale_mapping(self.scale_parameter).expand_as(loc)


#: SB3's orthogonal initialization (``ortho_init``): the gain of the hidden layers, of the actor's output layer
#: (its initial mean action is near 0, whatever the observation) and of the critic's output layer.
HIDDEN_GAIN, ACTOR_OUTPUT_GAIN, CRITIC_OUTPUT_GAIN = 2.0 ** 0.5, 0.01, 1.0


def orthogonal_init(model: torch.nn.Module, output_gain: float) -> None:
    """Initialize ``model``'s layers as SB3's PPO does: every weight matrix orthogonal (one per agent where the
    parameters are stacked per agent), gain :data:`HIDDEN_GAIN`, its last one ``output_gain``; biases 0. The
    layers are the model's parameters named ``weight`` in registration order (BenchMARL's MLP and Deepsets
    register their output layer last); BenchMARL's MLP without shared parameters on a centralized input holds
    one network per agent (its ``mlp``, a ``ModuleList``), each initialized so."""
    parts = model.mlp if isinstance(getattr(model, "mlp", None), torch.nn.ModuleList) else [model]
    for part in parts:
        weights = [(name, p) for name, p in part.named_parameters() if name.endswith("weight") and p.dim() >= 2]
        if not weights:
            raise ValueError(f"orthogonal_init: {type(model).__name__} has no weight matrix")
        with torch.no_grad():
            for index, (_, weight) in enumerate(weights):
                gain = output_gain if index == len(weights) - 1 else HIDDEN_GAIN
                for matrix in (weight.unsqueeze(0) if weight.dim() == 2 else weight.flatten(0, -3)):
                    torch.nn.init.orthogonal_(matrix, gain=gain)
    with torch.no_grad():
        for name, bias in model.named_parameters():
            if name.endswith("bias"):
                bias.zero_()


class _FormationPPO:
    """Mixin of an on-policy BenchMARL algorithm: its PPO loss normalizes each minibatch's advantages when
    ``normalize_advantage`` (BenchMARL builds the loss with it off), its Gaussian's scale is
    :class:`StateIndependentScale` when ``state_independent_scale`` (BenchMARL's is an output of the actor), and
    its actor and critic start from SB3's orthogonal initialization when ``orthogonal_init``
    (:func:`orthogonal_init`; BenchMARL keeps PyTorch's default, whose initial mean action depends on the state)."""

    def __init__(self, normalize_advantage: bool, state_independent_scale: bool, orthogonal_init: bool,
                 **kwargs: Any):
        super().__init__(**kwargs)
        self.normalize_advantage = normalize_advantage
        self.state_independent_scale = state_independent_scale
        self.orthogonal_init = orthogonal_init

    def _get_policy_for_loss(self, group: str, model_config: Any, continuous: bool) -> Any:
        policy = super()._get_policy_for_loss(group, model_config, continuous)
        if continuous and self.state_independent_scale:
            extractor = policy.module[0].module[1]  # ProbabilisticActor(TensorDictSequential(actor, extractor))
            n_actions = self.action_spec[group, "action"].shape[-1]
            extractor.module = StateIndependentScale(n_actions, self.scale_mapping, device=self.device)
        if self.orthogonal_init:
            orthogonal_init(policy.module[0].module[0], ACTOR_OUTPUT_GAIN)
        return policy

    def get_critic(self, group: str) -> Any:
        critic = super().get_critic(group)
        if self.orthogonal_init:  # a shared critic's expansion over the agents has no parameters
            orthogonal_init(critic, CRITIC_OUTPUT_GAIN)
        return critic

    def _get_loss(self, group: str, policy_for_loss: Any, continuous: bool) -> Any:
        loss, done = super()._get_loss(group, policy_for_loss, continuous)
        loss.normalize_advantage = self.normalize_advantage
        return loss, done


class FormationMappo(_FormationPPO, Mappo):
    """BenchMARL's MAPPO with the options of :class:`_FormationPPO`."""


class FormationIppo(_FormationPPO, Ippo):
    """BenchMARL's IPPO with the options of :class:`_FormationPPO`."""


@dataclass
class _FormationPPOOptions:
    """The fields of :class:`_FormationPPO`'s options, each True or False; a base listed before BenchMARL's config
    class, so that they follow its fields (which have no defaults) and its YAML may set them."""

    normalize_advantage: bool = True
    state_independent_scale: bool = True
    orthogonal_init: bool = False

    def __post_init__(self) -> None:
        for name in ("normalize_advantage", "state_independent_scale", "orthogonal_init"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"{name}: expected True or False, got {getattr(self, name)!r}")


@dataclass
class FormationMappoConfig(_FormationPPOOptions, MappoConfig):
    """:class:`~benchmarl.algorithms.MappoConfig` plus the options of :class:`_FormationPPOOptions`."""

    @staticmethod
    def associated_class() -> Type[Mappo]:
        return FormationMappo


@dataclass
class FormationIppoConfig(_FormationPPOOptions, IppoConfig):
    """:class:`~benchmarl.algorithms.IppoConfig` plus the options of :class:`_FormationPPOOptions`."""

    @staticmethod
    def associated_class() -> Type[Ippo]:
        return FormationIppo


class _MaskedSlotSet(torch.nn.Module):
    """One Deepsets net over neighbour slots whose aggregation takes the real slots only: a slot is real when its
    first entry, the mask, is > 0.5 (:mod:`ee_formation_env.observation`); an agent with fewer neighbours than the
    group's largest degree has padding slots, whose number changes with the team's size and graph."""

    def __init__(self, local_nn: torch.nn.Module, global_nn: torch.nn.Module, aggr: str):
        super().__init__()
        if aggr not in POOLINGS:
            raise ValueError(f"aggr: the masked slot aggregation is one of {list(POOLINGS)}, got {aggr!r}")
        self.local_nn, self.global_nn, self.aggr = local_nn, global_nn, aggr

    def forward(self, slots: torch.Tensor, own: Optional[torch.Tensor]) -> torch.Tensor:
        pooled = masked_pool(self.local_nn(slots), slots[..., :1] > 0.5, self.aggr)  # (..., S, h) -> (..., h)
        return self.global_nn(pooled if own is None else torch.cat([pooled, own], dim=-1))


class SlotDeepsets(Deepsets):
    """BenchMARL's ``Deepsets`` on the task's ``observation_sets`` with the slot aggregation over the real
    neighbour slots only (:class:`_MaskedSlotSet`), so that padding slots take no part; what agents see is
    otherwise BenchMARL's model (``model/layers/deepsets.yaml``)."""

    def __init__(self, **kwargs: Any):
        super().__init__(**kwargs)
        if hasattr(self, "local_deepsets"):
            self.local_deepsets = torch.nn.ModuleList(
                [_MaskedSlotSet(net.local_nn, net.global_nn, self.aggr) for net in self.local_deepsets])


@dataclass
class SlotDeepsetsConfig(DeepsetsConfig):
    """:class:`~benchmarl.models.DeepsetsConfig` of :class:`SlotDeepsets`."""

    @staticmethod
    def associated_class() -> Type[Deepsets]:
        return SlotDeepsets


#: BenchMARL's algorithm config -> the project's, where it has one (the others are BenchMARL's own).
FORMATION_CONFIGS: Dict[Type[AlgorithmConfig], Type[AlgorithmConfig]] = {MappoConfig: FormationMappoConfig,
                                                                          IppoConfig: FormationIppoConfig}


def _name(value: Any, field: str, choices: Any) -> str:
    if value not in choices:
        raise ValueError(f"{field}: expected one of {list(choices)}, got {value!r}")
    return value


def benchmarl_algorithm(name: Any) -> Algorithm:
    """The registered BenchMARL algorithm ``name``; ``ValueError`` naming ``algorithm``."""
    return algorithm(name, "algorithm", ("benchmarl",))


def algorithm_config_class(name: str, project: bool = True) -> Type[AlgorithmConfig]:
    """The config class of the BenchMARL algorithm ``name``: the registry's ``library_class`` of
    ``benchmarl.algorithms``, or with ``project`` the project's subclass of it where there is one
    (:data:`FORMATION_CONFIGS`)."""
    stock = getattr(benchmarl.algorithms, benchmarl_algorithm(name).library_class)
    return FORMATION_CONFIGS.get(stock, stock) if project else stock


def algorithm_config(name: str) -> AlgorithmConfig:
    """The algorithm's config from its YAML file (``algorithm/<name>.yaml``)."""
    path = benchmarl_algorithm(name).hyperparameter_path
    return algorithm_config_class(name).get_from_yaml(str(path))


def _layout(algorithm_name: str) -> str:
    """The experiment file of an algorithm: ``on_policy`` or ``off_policy`` (the registry says which)."""
    return "on_policy" if benchmarl_algorithm(algorithm_name).on_policy else "off_policy"


def experiment_config(algorithm: str) -> ExperimentConfig:
    """The experiment config for ``algorithm``: ``experiment/on_policy.yaml`` (MAPPO, IPPO) or ``off_policy.yaml``."""
    return ExperimentConfig.get_from_yaml(str(CONFIG_DIR / "experiment" / f"{_layout(algorithm)}.yaml"))


#: Model name -> the config class its YAML file ``model/layers/<name>.yaml`` loads into: the MLP (actor and
#: critic), and the set model over the neighbour slots (the actor, with the task option ``observation_sets``).
MODEL_CONFIGS: Dict[str, Type[ModelConfig]] = {"mlp": MlpConfig, "deepsets": SlotDeepsetsConfig}


def model_config(name: str = "mlp") -> ModelConfig:
    """A model's config from ``model/layers/<name>.yaml`` (:data:`MODEL_CONFIGS`)."""
    name = _name(name, "model", MODEL_CONFIGS)
    return MODEL_CONFIGS[name].get_from_yaml(str(CONFIG_DIR / "model" / "layers" / f"{name}.yaml"))


def config_files(algorithm: str, mode: str, model: str = "mlp") -> dict[str, str]:
    """The project's YAML files a run of ``algorithm`` in ``mode`` with the actor ``model`` (the critic: the MLP)
    reads, path (relative to :data:`CONFIG_DIR`) -> text: what defines it (the scoreboard records them in its
    cells)."""
    layout = _layout(algorithm)
    models = dict.fromkeys([_name(model, "model", MODEL_CONFIGS), "mlp"])
    paths = [benchmarl_algorithm(algorithm).hyperparameter_path, CONFIG_DIR / "experiment" / f"{layout}.yaml",
             *(CONFIG_DIR / "model" / "layers" / f"{name}.yaml" for name in models), task_config_path(mode)]
    return {path.relative_to(CONFIG_DIR).as_posix(): path.read_text(encoding="utf-8") for path in paths}


def task_config_path(mode: str) -> Path:
    """``task/ee_formation_training/<mode>.yaml`` of a built-in training mode."""
    return CONFIG_DIR / "task" / "ee_formation_training" / f"{_name(mode, 'mode', mode_names())}.yaml"


def task_config(mode: str) -> dict[str, Any]:
    """The task config dict of ``task_config_path(mode)`` (what ``EEFormationTrainingTask.X.get_from_yaml(path)``
    reads)."""
    path = task_config_path(mode)
    if not path.is_file():
        raise ValueError(f"mode: no task config for the mode {mode!r} ({path.name}); the built-in modes have one")
    return yaml.safe_load(path.read_text(encoding="utf-8"))
