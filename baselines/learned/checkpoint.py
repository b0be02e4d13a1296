"""The saved state of a training run: written atomically, loaded without executing anything from the files.

A checkpoint is a folder (``checkpoints/step_<agent steps>/`` during training, ``model/`` for the final model):

========================  ==================================================================================
file                      content
========================  ==================================================================================
``policy.pt``             the policy network's parameters: a ``state_dict`` of tensors, read with
                          ``torch.load(weights_only=True)``
``policy.json``           what rebuilds the network around them: algorithm, observation shape, action bounds,
                          network settings
``optimizer.pt``          the optimizer's state (``weights_only`` too)
``vecnormalize.json``     the observation and return normalization statistics
``state.json``            the agent steps done, the updates done, the budget (written last)
========================  ==================================================================================

A checkpoint is written into a hidden ``.<name>.partial`` folder and renamed into place when complete, so an
interrupted write (a full disk, a kill) never leaves a truncated checkpoint under its own name. Loading reads
tensors and JSON only: a file planted in a run folder runs no code. ``model.zip``, which the SB3 backend also
writes for SB3 users (``PPO.load``), holds pickled objects and is never read by the project (docs/training.md).
"""

from __future__ import annotations

import json
import os
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import numpy as np

FORMAT_VERSION = 1
STEP_PREFIX = "step_"


@contextmanager
def atomic_directory(target: Path) -> Iterator[Path]:
    """Yield a fresh hidden folder beside ``target`` to write into; on success it replaces ``target``."""
    target = Path(target)
    partial = target.with_name(f".{target.name}.partial")
    if partial.exists():
        shutil.rmtree(partial)
    partial.mkdir(parents=True)
    try:
        yield partial
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    if target.exists():
        old = target.with_name(f".{target.name}.old")
        shutil.rmtree(old, ignore_errors=True)
        os.replace(target, old)
        os.replace(partial, target)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(partial, target)


def write_json(path: Path, data: Any) -> None:
    """Write ``data`` as JSON into ``path`` through a temporary file renamed into place."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.partial")
    temporary.write_text(json.dumps(data, indent=2, default=_plain))
    os.replace(temporary, path)


def _plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return str(value)


def read_json(path: Path, what: str) -> Any:
    """JSON from ``path``; a missing or malformed file is a ``ValueError`` naming ``what``."""
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ValueError(f"{what}: {path} not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ValueError(f"{what}: {path} is not valid JSON ({error})") from None


def load_tensors(path: Path, what: str) -> Any:
    """A ``torch.save``d state from ``path``, read with ``weights_only=True`` (tensors and plain containers only:
    a pickled object in the file is refused, not run)."""
    import pickle

    import torch

    if not Path(path).is_file():
        raise ValueError(f"{what}: {path} not found")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, AttributeError, TypeError, ValueError) as error:
        raise ValueError(f"{what}: {path} holds no plain tensor state (refused, nothing in it was run): "
                         f"{str(error).splitlines()[0][:200]}") from None


# ------------------------------------------------------------------------------------------ the policy
def policy_description(model: Any, algo: str, policy_kwargs: dict[str, Any]) -> dict[str, Any]:
    """``policy.json``: what :func:`load_policy` needs to rebuild ``model``'s policy network."""
    space = model.policy.action_space
    return {"format": FORMAT_VERSION, "algo": algo,
            "observation_shape": list(model.policy.observation_space.shape),
            "action_low": space.low.tolist(), "action_high": space.high.tolist(),
            "policy_kwargs": {key: (list(value) if isinstance(value, (tuple, list)) else value)
                              for key, value in policy_kwargs.items()}}


def load_policy(directory: Path) -> Any:
    """The SB3 policy network saved in ``directory`` (``policy.json`` + ``policy.pt``), on the CPU, in eval mode."""
    import gymnasium
    from stable_baselines3 import PPO, SAC

    description = read_json(Path(directory) / "policy.json", "policy.json")
    classes = {"ppo": PPO, "sac": SAC}
    algo = description.get("algo")
    if algo not in classes:
        raise ValueError(f"policy.json: algo: expected one of {sorted(classes)}, got {algo!r}")
    try:
        shape = tuple(int(n) for n in description["observation_shape"])
        low = np.asarray(description["action_low"], dtype=np.float32)
        high = np.asarray(description["action_high"], dtype=np.float32)
        kwargs = {key: description["policy_kwargs"][key] for key in ("net_arch", "log_std_init")
                  if key in description["policy_kwargs"]}
    except (KeyError, TypeError, ValueError) as error:
        raise ValueError(f"policy.json: malformed ({error})") from None
    observation_space = gymnasium.spaces.Box(-np.inf, np.inf, shape, dtype=np.float32)
    action_space = gymnasium.spaces.Box(low, high, dtype=np.float32)
    policy_class = classes[algo].policy_aliases["MlpPolicy"]
    policy = policy_class(observation_space, action_space, lambda _: 0.0, **kwargs)
    try:
        policy.load_state_dict(load_tensors(Path(directory) / "policy.pt", "policy.pt"))
    except RuntimeError as error:
        raise ValueError(f"policy.pt: does not fit policy.json ({str(error).splitlines()[0][:200]})") from None
    policy.set_training_mode(False)
    return policy


# ------------------------------------------------------------------------------------------ training state
def save_checkpoint(directory: Path, model: Any, algo: str, policy_kwargs: dict[str, Any], total_timesteps: int,
                    extra_state: dict[str, Any] | None = None) -> Path:
    """Write ``model``'s complete training state (module docstring) into ``directory``, atomically."""
    import torch

    venv = model.get_env()
    with atomic_directory(Path(directory)) as partial:
        torch.save(model.policy.state_dict(), partial / "policy.pt")
        write_json(partial / "policy.json", policy_description(model, algo, policy_kwargs))
        optimizers = {"policy": model.policy.optimizer.state_dict()} if hasattr(model.policy, "optimizer") else {}
        torch.save(optimizers, partial / "optimizer.pt")
        write_json(partial / "vecnormalize.json", normalization_state(venv))
        write_json(partial / "state.json", {"format": FORMAT_VERSION, "agent_steps": int(model.num_timesteps),
                                            "updates": int(getattr(model, "_n_updates", 0)),
                                            "total_timesteps": int(total_timesteps), **(extra_state or {})})
    return Path(directory)


def normalization_state(venv: Any) -> dict[str, Any]:
    """VecNormalize's statistics as plain data."""
    return {"obs_mean": venv.obs_rms.mean, "obs_var": venv.obs_rms.var, "obs_count": float(venv.obs_rms.count),
            "ret_mean": float(venv.ret_rms.mean), "ret_var": float(venv.ret_rms.var),
            "ret_count": float(venv.ret_rms.count), "returns": venv.returns, "clip_obs": float(venv.clip_obs),
            "clip_reward": float(venv.clip_reward), "epsilon": float(venv.epsilon)}


def restore_checkpoint(directory: Path, model: Any) -> dict[str, Any]:
    """Load the training state in ``directory`` into ``model`` (built from the same configuration); returns
    its ``state.json``."""
    directory = Path(directory)
    state = read_json(directory / "state.json", "state.json")
    model.policy.load_state_dict(load_tensors(directory / "policy.pt", "policy.pt"))
    optimizers = load_tensors(directory / "optimizer.pt", "optimizer.pt")
    if "policy" in optimizers:
        model.policy.optimizer.load_state_dict(optimizers["policy"])
    normalization = read_json(directory / "vecnormalize.json", "vecnormalize.json")
    venv = model.get_env()
    venv.obs_rms.mean = np.asarray(normalization["obs_mean"], dtype=np.float64)
    venv.obs_rms.var = np.asarray(normalization["obs_var"], dtype=np.float64)
    venv.obs_rms.count = float(normalization["obs_count"])
    venv.ret_rms.mean = np.float64(normalization["ret_mean"])
    venv.ret_rms.var = np.float64(normalization["ret_var"])
    venv.ret_rms.count = float(normalization["ret_count"])
    returns = np.asarray(normalization["returns"], dtype=np.float64)
    if returns.shape == venv.returns.shape:
        venv.returns = returns
    model.num_timesteps = int(state["agent_steps"])
    model._n_updates = int(state.get("updates", 0))
    return state


def checkpoints(run_dir: Path) -> list[Path]:
    """The complete checkpoints of a run, oldest first (a complete one has its ``state.json``)."""
    folder = Path(run_dir) / "checkpoints"
    found = [path for path in folder.glob(f"{STEP_PREFIX}*") if (path / "state.json").is_file()]
    return sorted(found, key=lambda path: int(path.name[len(STEP_PREFIX):]))


def checkpoint_name(agent_steps: int) -> str:
    return f"{STEP_PREFIX}{agent_steps:012d}"
