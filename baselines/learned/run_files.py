"""A run's files as every path that reads a run checks them, and the model stamp that binds a model to its run.

Every path that reads a run (``ee-formation evaluate --policy RUN``, ``train.py --eval-only RUN``, ``--resume
RUN``, ``--imitate RUN``, the scoreboard's cells) opens it through
:func:`~ee_formation_env.baselines.learned.policy.open_run`: the folder's marker, ``config.json`` against the
folder's ``SHA256SUMS`` (:func:`read_run_config`), then the model it reads (the final ``model/``, or the
checkpoint ``--resume`` continues from) through
:func:`~ee_formation_env.baselines.learned.policy.load_model`: its files against the model folder's own
``SHA256SUMS``, its stamp against ``config.json`` (:func:`check_model_files`) and against the loaded model
(:func:`check_stamp_sizes`). Each fault is one ``ValueError`` starting with the command's flag (or what reads
the run), naming the file and the field.

The stamp (``stamp.json``, :func:`model_stamp`) is written into the final model and into every checkpoint, and
listed in their ``SHA256SUMS``: the digest of the run's configuration (:func:`config_digest`), so that a
config.json and a model of two runs cannot be put together; what the configuration decides of the model (the
engine, backend, algorithm, policy network, mode, observation features and action convention); and what the
model itself decides (its observation and action sizes). The digest leaves out the budget
(``total_timesteps``): ``--resume RUN --total-timesteps N`` rewrites config.json with a new budget, and the
checkpoints written before it stay the run's own. These checks guard against accidents (an edit, a truncated
copy, a file of another run), not against a forger: whoever can edit a file can rewrite its checksum and stamp.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Mapping

from ee_formation_env.baselines.learned.checkpoint import read_json, verify_checksums
from ee_formation_env.baselines.learned.options import TrainingOptions
from ee_formation_env.baselines.learned.run_folder import require_project_run

CONFIG = "config.json"
STAMP = "stamp.json"
STAMP_FORMAT = 1
ENGINE = "pybullet"  # the physics engine every run trains and acts in
MODEL_FOLDER = "model"  # a run's final model, in the checkpoint format

#: What reloading a run's model needs per backend: the modules, and the pip extra(s) that install them.
BACKEND_MODULES = {"sb3": (("torch", "stable_baselines3"), "train"),
                   "rllib": (("torch", "ray.rllib"), "train,distributed")}

CONFIG_FIX = ("restore the config.json the run wrote (to change the budget, give --resume RUN --total-timesteps N "
              "instead of editing it)")

#: The settings of config.json that ``--resume`` may rewrite (the budget: ``TrainConfig.RESUME_FIELDS``, which
#: imports this module's users and so is not imported here), left out of the stamp's digest.
BUDGET_FIELDS = ("total_timesteps",)

#: The stamp's fields that the model itself decides (checked against the loaded model: :func:`check_stamp_sizes`;
#: those the configuration decides: :func:`stamp_config_fields`).
SIZE_FIELDS = ("observation_size", "action_size")


def model_files(backend: str) -> tuple[str, ...]:
    """The files of a model folder that loading its policy reads, its stamp included."""
    names = ("policy.json", "policy.pt") if backend == "sb3" else ("rllib_module.json", "rllib_module.pt")
    return (*names, "obs_normalizer.json", STAMP)


def config_digest(config: Mapping[str, Any]) -> str:
    """The sha256 of a run's configuration (``config.json``'s content, its keys sorted) less the budget
    (:data:`BUDGET_FIELDS`)."""
    settings = {key: value for key, value in config.items() if key not in BUDGET_FIELDS}
    text = json.dumps(settings, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(text.encode("ascii")).hexdigest()


def stamp_config_fields(config: Mapping[str, Any]) -> dict[str, Any]:
    """What a run's configuration decides of its model, as its stamp holds it (plain JSON values)."""
    options = TrainingOptions.from_saved(config).resolved()
    residual = None
    if options.mode == "residual":
        residual = {"reference": options.reference, "residual_scale": options.residual_scale,
                    "residual_gate": options.residual_gate, "residual_gate_power": options.residual_gate_power}
    action = {"residual": residual, "gravity_compensation": options.gravity_compensation,
              "action_acceleration": options.action_acceleration,
              "env_settings": dict(options.training_mode.env_settings)}
    fields = {"engine": ENGINE, "backend": config.get("backend"), "algo": config.get("algo"),
              "policy_network": options.policy_network, "mode": options.mode, "obs_features": options.obs_features,
              "action": action}
    return json.loads(json.dumps(fields))  # as it reads back from stamp.json


def model_stamp(config: Mapping[str, Any], observation_size: int, action_size: int) -> dict[str, Any]:
    """``stamp.json`` of a model trained with ``config`` (``config.json`` as written) whose policy takes
    ``observation_size`` entries and gives ``action_size`` actions."""
    return {"format": STAMP_FORMAT, "config_digest": config_digest(config), **stamp_config_fields(config),
            "observation_size": int(observation_size), "action_size": int(action_size)}


def read_run_config(run_dir: Path, what: str) -> dict[str, Any]:
    """``run_dir``'s ``config.json``, checked: present, in a folder the project wrote (its marker), the file the run
    wrote (its sha256 in the folder's ``SHA256SUMS``), a run's configuration (a scenario, a known backend, valid
    training options). A fault is one ``ValueError`` starting with ``what``, naming the file."""
    run_dir = Path(run_dir)
    path = run_dir / CONFIG
    if not path.is_file():
        raise ValueError(f"{what}: {run_dir} is not a train.py run folder (no {CONFIG} in it)")
    require_project_run(run_dir, what)
    try:
        verify_checksums(run_dir, [CONFIG], CONFIG_FIX)
    except ValueError as error:
        raise ValueError(f"{what}: {error}") from None
    config = read_json(path, what)
    if not isinstance(config, dict) or config.get("backend") not in BACKEND_MODULES or "scenario" not in config:
        raise ValueError(f"{what}: {path} is not a run's configuration (no scenario, or a backend other than "
                         f"{list(BACKEND_MODULES)})")
    try:
        TrainingOptions.from_saved(config)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{what}: {path}: {error}") from None
    return config


def check_model_files(model_dir: Path, config: Mapping[str, Any], what: str) -> dict[str, Any]:
    """Check the model folder ``model_dir`` of the run whose configuration is ``config``: the files its policy is
    loaded from and its stamp against its ``SHA256SUMS``, each required; the stamp's configuration digest against
    ``config``'s, and each of its fields that the configuration decides against ``config``. Returns the stamp
    (its sizes are checked once the model is loaded: :func:`check_stamp_sizes`)."""
    model_dir = Path(model_dir)
    path = model_dir / STAMP
    try:
        verify_checksums(model_dir, model_files(config["backend"]), _model_fix(model_dir))
    except ValueError as error:
        raise ValueError(f"{what}: {error}") from None
    stamp = read_json(path, what)
    if not isinstance(stamp, dict) or stamp.get("format") != STAMP_FORMAT:
        raise ValueError(f"{what}: {path}: format: expected a stamp of format {STAMP_FORMAT}: "
                         f"{_model_fix(model_dir)}")
    if stamp.get("config_digest") != config_digest(config):
        raise ValueError(f"{what}: {path}: config_digest: the model was trained with another configuration than "
                         f"{_run_dir(model_dir) / CONFIG} (its settings, the budget aside): the model and {CONFIG} "
                         f"are not of one run; {CONFIG_FIX}")
    for field, expected in stamp_config_fields(config).items():
        if field not in stamp:
            raise ValueError(f"{what}: {path}: {field} missing: {_model_fix(model_dir)}")
        if stamp[field] != expected:
            raise ValueError(f"{what}: {path}: {field}: the stamp says {stamp[field]!r}, {CONFIG} {expected!r}: "
                             f"{_model_fix(model_dir)}")
    return stamp


def check_stamp_sizes(model_dir: Path, stamp: Mapping[str, Any], observation_size: int, action_size: int,
                      what: str) -> None:
    """The stamp's observation and action sizes must be those of the loaded model (its normalizer's and its
    actor's): a stamp of another model is refused, naming the field."""
    path = Path(model_dir) / STAMP
    for field, actual in zip(SIZE_FIELDS, (observation_size, action_size)):
        value = stamp.get(field)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{what}: {path}: {field}: expected an integer, got {value!r}: {_model_fix(model_dir)}")
        if value != actual:
            raise ValueError(f"{what}: {path}: {field}: the stamp says {value}, the model has {actual} (its "
                             f"normalizer and actor): the stamp is not this model's; {_model_fix(model_dir)}")


def _run_dir(model_dir: Path) -> Path:
    """The run folder of a model folder: ``RUN/model`` or ``RUN/checkpoints/step_<n>``."""
    model_dir = Path(model_dir)
    return model_dir.parent.parent if model_dir.parent.name == "checkpoints" else model_dir.parent


def _model_fix(model_dir: Path) -> str:
    """What to do about a damaged model folder: a final model is trained again by ``--resume``, a checkpoint is
    removed so that ``--resume`` continues from an older one."""
    if Path(model_dir).name == MODEL_FOLDER:
        return "the model is damaged: `--resume RUN` trains it again from the newest intact checkpoint"
    return "the checkpoint is damaged: remove it to resume from an older one"
