"""The env a learner steps: the formation env, in residual form, with training-only shaping and features.

:func:`make_training_env` composes, from the inside out: the formation env (``mode="torque"``: actions are the
normalized torques), :class:`~ee_formation_env.baselines.learned.residual.ResidualActionEnv` (``mode="residual"``:
actions are corrections on a reference controller), :class:`~ee_formation_env.baselines.learned.shaping.HoldShapingEnv`
(``hold_penalty > 0``) and :class:`~ee_formation_env.baselines.learned.features.FeatureEnv` (``obs_features``).
It is a module-level function so that ``functools.partial(make_training_env, ...)`` pickles into worker
processes; :func:`env_factory` builds that partial from a run's configuration.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Any, Callable, Mapping

from ee_formation_env.baselines.learned.features import FEATURE_SETS, FeatureEnv
from ee_formation_env.baselines.learned.residual import ResidualActionEnv
from ee_formation_env.baselines.learned.shaping import HoldShapingEnv

if TYPE_CHECKING:
    from ee_formation_env.baselines.learned.config import TrainConfig

TRAINING_MODES = ("torque", "residual")
EVAL_SEED_OFFSET = 10_000  # held-out evaluation seeds start here; training resets use seeds below it


def make_training_env(scenario: Any, overrides: Mapping[str, Any] | None = None, mode: str = "torque",
                      reference: str = "adaptive_jacobian", residual_scale: float = 0.1,
                      correction_penalty: float = 0.5, gate: bool = False, hold_penalty: float = 0.0,
                      obs_features: str = "none") -> Any:
    """The training env of ``scenario`` (plus ``overrides``) in ``mode``, shaped and featured (module docstring)."""
    from ee_formation_env import parallel_env

    if mode not in TRAINING_MODES:
        raise ValueError(f"mode: expected 'torque' or 'residual', got {mode!r}")
    if obs_features not in FEATURE_SETS:
        raise ValueError(f"obs_features: expected one of {FEATURE_SETS}, got {obs_features!r}")
    env = parallel_env(scenario, **dict(overrides or {}))
    try:
        if mode == "residual":
            env = ResidualActionEnv(env, reference=reference, scale=residual_scale,
                                    correction_penalty=correction_penalty, gate=gate)
        if hold_penalty > 0:
            env = HoldShapingEnv(env, hold_penalty)
        return env if obs_features == "none" else FeatureEnv(env, obs_features)
    except Exception:
        env.close()
        raise


def env_factory(config: "TrainConfig", overrides: Mapping[str, Any] | None = None) -> Callable[[], Any]:
    """A picklable factory of the env the learner of ``config`` (resolved) steps; ``overrides`` default to
    the configuration's training overrides (episode length, start noise)."""
    return functools.partial(make_training_env, config.scenario,
                             config.training_overrides() if overrides is None else dict(overrides), config.mode,
                             config.reference, config.residual_scale, config.correction_penalty,
                             config.residual_gate, config.hold_penalty, config.obs_features)
