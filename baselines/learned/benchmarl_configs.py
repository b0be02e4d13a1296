"""The project's BenchMARL configurations for the formation training tasks, as YAML in BenchMARL's layout (the
``torchrl`` extra).

    from ee_formation_env.baselines.learned.benchmarl_configs import (algorithm_config, experiment_config,
                                                                      model_config, task_config)

    experiment = Experiment(task=EEFormationTrainingTask.PLANAR_SQUARE.get_task(task_config("torque")),
                            algorithm_config=algorithm_config("mappo"), model_config=model_config(),
                            critic_model_config=model_config(), seed=0, config=experiment_config("mappo"))

The files lie in :data:`CONFIG_DIR` as BenchMARL lays out its own ``conf/``: ``algorithm/<name>.yaml``,
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
from typing import Any, Dict, Type

import torch
import yaml
from benchmarl.algorithms import Ippo, IppoConfig, Mappo, MappoConfig, MasacConfig
from benchmarl.algorithms.common import AlgorithmConfig
from benchmarl.experiment import ExperimentConfig
from benchmarl.models.mlp import MlpConfig

from ee_formation_env.baselines.learned.modes import mode_names

#: The folder of the YAML files (installed with the package).
CONFIG_DIR = Path(__file__).with_name("benchmarl_conf")
ON_POLICY_ALGORITHMS = ("mappo", "ippo")


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


class _FormationPPO:
    """Mixin of an on-policy BenchMARL algorithm: its PPO loss normalizes each minibatch's advantages when
    ``normalize_advantage`` (BenchMARL builds the loss with it off), and its Gaussian's scale is
    :class:`StateIndependentScale` when ``state_independent_scale`` (BenchMARL's is an output of the actor)."""

    def __init__(self, normalize_advantage: bool, state_independent_scale: bool, **kwargs: Any):
        super().__init__(**kwargs)
        self.normalize_advantage = normalize_advantage
        self.state_independent_scale = state_independent_scale

    def _get_policy_for_loss(self, group: str, model_config: Any, continuous: bool) -> Any:
        policy = super()._get_policy_for_loss(group, model_config, continuous)
        if continuous and self.state_independent_scale:
            extractor = policy.module[0].module[1]  # ProbabilisticActor(TensorDictSequential(actor, extractor))
            n_actions = self.action_spec[group, "action"].shape[-1]
            extractor.module = StateIndependentScale(n_actions, self.scale_mapping, device=self.device)
        return policy

    def _get_loss(self, group: str, policy_for_loss: Any, continuous: bool) -> Any:
        loss, done = super()._get_loss(group, policy_for_loss, continuous)
        loss.normalize_advantage = self.normalize_advantage
        return loss, done


class FormationMappo(_FormationPPO, Mappo):
    """BenchMARL's MAPPO with the options of :class:`_FormationPPO`."""


class FormationIppo(_FormationPPO, Ippo):
    """BenchMARL's IPPO with the options of :class:`_FormationPPO`."""


def _check_flags(config: Any) -> None:
    for name in ("normalize_advantage", "state_independent_scale"):
        if not isinstance(getattr(config, name), bool):
            raise TypeError(f"{name}: expected True or False, got {getattr(config, name)!r}")


@dataclass
class FormationMappoConfig(MappoConfig):
    """:class:`~benchmarl.algorithms.MappoConfig` plus ``normalize_advantage`` and ``state_independent_scale``."""

    normalize_advantage: bool = True
    state_independent_scale: bool = True

    def __post_init__(self) -> None:
        _check_flags(self)

    @staticmethod
    def associated_class() -> Type[Mappo]:
        return FormationMappo


@dataclass
class FormationIppoConfig(IppoConfig):
    """:class:`~benchmarl.algorithms.IppoConfig` plus ``normalize_advantage`` and ``state_independent_scale``."""

    normalize_advantage: bool = True
    state_independent_scale: bool = True

    def __post_init__(self) -> None:
        _check_flags(self)

    @staticmethod
    def associated_class() -> Type[Ippo]:
        return FormationIppo


#: Algorithm name -> the config class its YAML file loads into.
ALGORITHM_CONFIGS: Dict[str, Type[AlgorithmConfig]] = {"mappo": FormationMappoConfig,
                                                       "ippo": FormationIppoConfig,
                                                       "masac": MasacConfig}


def _name(value: Any, field: str, choices: Any) -> str:
    if value not in choices:
        raise ValueError(f"{field}: expected one of {list(choices)}, got {value!r}")
    return value


def algorithm_config(name: str) -> AlgorithmConfig:
    """The algorithm's config from ``algorithm/<name>.yaml`` (``mappo``, ``ippo`` or ``masac``)."""
    name = _name(name, "algorithm", ALGORITHM_CONFIGS)
    return ALGORITHM_CONFIGS[name].get_from_yaml(str(CONFIG_DIR / "algorithm" / f"{name}.yaml"))


def experiment_config(algorithm: str) -> ExperimentConfig:
    """The experiment config for ``algorithm``: ``experiment/on_policy.yaml`` (MAPPO, IPPO) or ``off_policy.yaml``."""
    layout = "on_policy" if _name(algorithm, "algorithm", ALGORITHM_CONFIGS) in ON_POLICY_ALGORITHMS else "off_policy"
    return ExperimentConfig.get_from_yaml(str(CONFIG_DIR / "experiment" / f"{layout}.yaml"))


def model_config() -> MlpConfig:
    """The actor's and critic's MLP from ``model/layers/mlp.yaml``."""
    return MlpConfig.get_from_yaml(str(CONFIG_DIR / "model" / "layers" / "mlp.yaml"))


def config_files(algorithm: str, mode: str) -> dict[str, str]:
    """The project's YAML files a run of ``algorithm`` in ``mode`` reads, path (relative to :data:`CONFIG_DIR`)
    -> text: what defines it (the scoreboard records them in its cells)."""
    layout = "on_policy" if _name(algorithm, "algorithm", ALGORITHM_CONFIGS) in ON_POLICY_ALGORITHMS else "off_policy"
    paths = [CONFIG_DIR / "algorithm" / f"{algorithm}.yaml", CONFIG_DIR / "experiment" / f"{layout}.yaml",
             CONFIG_DIR / "model" / "layers" / "mlp.yaml", task_config_path(mode)]
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
