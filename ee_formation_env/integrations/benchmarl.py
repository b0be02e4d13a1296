"""BenchMARL tasks for the formation env (the ``torchrl`` extra).

    from benchmarl.algorithms import MappoConfig
    from benchmarl.experiment import Experiment, ExperimentConfig
    from benchmarl.models.mlp import MlpConfig
    from ee_formation_env.integrations.benchmarl import EEFormationTask

    task = EEFormationTask.PLANAR_SQUARE.get_task()                       # the scenario as built in
    task = EEFormationTask.PLANAR_SQUARE.get_task({"episode_seconds": 5.0})  # with scenario overrides
    Experiment(task=task, algorithm_config=MappoConfig.get_from_yaml(), model_config=MlpConfig.get_from_yaml(),
               critic_model_config=MlpConfig.get_from_yaml(), seed=0, config=ExperimentConfig.get_from_yaml()).run()

BenchMARL's ``num_envs`` (``on_policy_n_envs_per_worker`` / ``off_policy_n_envs_per_worker``, and
``evaluation_episodes`` for the test env) becomes the batch size of one natively batched env
(``make_torchrl_env(..., num_envs=num_envs)``: K PyBullet clients stepped by one call), as for VMAS.

A task's config is a dict of scenario overrides (any top-level scenario key), plus optionally ``scenario``:
a scenario file or dict to use instead of the member's built-in scenario (e.g. a mixed-robot team). Groups
are :func:`ee_formation_env.integrations.torchrl.group_map`'s: one per robot kind.

:class:`EEFormationTask` has one member per built-in scenario, derived from
:data:`ee_formation_env.builtin.BUILTIN_SCENARIOS` (the YAML files of ``docs/scenarios.md``), never listed here.
"""

from __future__ import annotations

from typing import Any, Callable, Dict, List, Optional

from benchmarl.environments.common import Task, TaskClass
from torchrl.data import Composite
from torchrl.envs import EnvBase

from ee_formation_env.builtin import BUILTIN_SCENARIOS
from ee_formation_env.scenario import load_scenario
from ee_formation_env.integrations.torchrl import make_torchrl_env


class EEFormationTaskClass(TaskClass):
    """How BenchMARL builds and reads one formation task."""

    def _scenario_and_overrides(self) -> tuple[Any, dict[str, Any]]:
        overrides = dict(self.config)
        return overrides.pop("scenario", self.name.lower()), overrides

    def get_env_fun(self, num_envs: int, continuous_actions: bool, seed: Optional[int],
                    device: Any) -> Callable[[], EnvBase]:
        if not continuous_actions:
            raise ValueError("continuous_actions: the formation env has continuous (torque) actions only")
        scenario, overrides = self._scenario_and_overrides()
        # Natively batched: num_envs copies in one TorchRL env of batch size [num_envs] (BenchMARL then wraps
        # no SerialEnv/ParallelEnv around it), as BenchMARL's VMAS tasks do.
        return lambda: make_torchrl_env(scenario, num_envs=num_envs, seed=seed, device=device, **overrides)

    def supports_continuous_actions(self) -> bool:
        return True

    def supports_discrete_actions(self) -> bool:
        return False

    def max_steps(self, env: EnvBase) -> int:
        scenario, overrides = self._scenario_and_overrides()
        return load_scenario(scenario, **overrides).max_steps

    def has_render(self, env: EnvBase) -> bool:
        return False

    def group_map(self, env: EnvBase) -> Dict[str, List[str]]:
        return env.group_map

    def _group_entries(self, env: EnvBase, keep: str) -> Composite:
        spec = env.full_observation_spec_unbatched.clone()  # BenchMARL's specs have no env batch axis
        for group in self.group_map(env):
            for key in list(spec[group].keys()):
                if key != keep:
                    del spec[group][key]
        if "state" in spec.keys():
            del spec["state"]
        return spec

    def observation_spec(self, env: EnvBase) -> Composite:
        return self._group_entries(env, "observation")

    def info_spec(self, env: EnvBase) -> Optional[Composite]:
        return self._group_entries(env, "info")

    def state_spec(self, env: EnvBase) -> Optional[Composite]:
        spec = env.full_observation_spec_unbatched
        if "state" in spec.keys():
            return Composite({"state": spec["state"].clone()})
        return None

    def action_spec(self, env: EnvBase) -> Composite:
        return env.full_action_spec_unbatched

    def action_mask_spec(self, env: EnvBase) -> Optional[Composite]:
        return None

    @staticmethod
    def env_name() -> str:
        return "ee_formation"


class EEFormationTaskBase(Task):
    """The members' behaviour (a task enum of formation scenarios: ``get_task(config)`` builds
    :meth:`associated_class` with the member's name); the members themselves are made from the built-in
    registry below. A task enum on another task class derives from it and overrides :meth:`associated_class`."""

    @staticmethod
    def associated_class():
        return EEFormationTaskClass

    def get_task(self, config: Optional[Dict[str, Any]] = None) -> TaskClass:
        """This task with ``config`` (scenario overrides; none: the built-in scenario as it is)."""
        return self.associated_class()(name=self.name, config=dict(config or {}))


# One member per built-in scenario, ``planar_square`` -> ``EEFormationTask.PLANAR_SQUARE`` (BenchMARL's
# convention: members are None-valued, numbered by Task.__new__; the task class reads the lower-cased name).
EEFormationTask = EEFormationTaskBase(
    "EEFormationTask", [(name.upper(), None) for name in BUILTIN_SCENARIOS], module=__name__,
    qualname="EEFormationTask")
EEFormationTask.__doc__ = "The built-in scenarios as BenchMARL tasks (``ee_formation_env.builtin.BUILTIN_SCENARIOS``)."
