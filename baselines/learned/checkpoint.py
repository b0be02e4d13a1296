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
``obs_normalizer.json``   the observation normalization the evaluation applies (SB3 runs)
``state.json``            the agent steps done, the updates done, the budget
``stamp.json``            the model's stamp: its run's configuration digest, mode, spaces
                          (:mod:`~ee_formation_env.baselines.learned.run_files`)
``SHA256SUMS``            the sha256 of every other file (``sha256sum -c SHA256SUMS`` checks them), written last
========================  ==================================================================================

A checkpoint is written into a hidden ``.<name>.partial`` folder and renamed into place when complete, so an
interrupted write (a full disk, a kill) never leaves a truncated checkpoint under its own name; a write the
file system refuses (a full disk, a file-size limit) is a :class:`CheckpointWriteError` naming the checkpoint,
and whatever was under its name stays as it was. Loading checks each file it reads against ``SHA256SUMS``
(:func:`verify_checksums`: a damaged file is refused, naming it) and reads tensors and JSON only: a file planted
in a run folder runs no code. ``model.zip``, which the SB3 backend also writes for SB3 users (``PPO.load``),
holds pickled objects and is never read by the project (docs/training.md).
"""

from __future__ import annotations

import errno
import hashlib
import json
import math
import os
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping

import numpy as np

from ee_formation_env.baselines.atomic_files import write_text
from ee_formation_env.baselines.learned.algorithms import algorithm

FORMAT_VERSION = 1
STEP_PREFIX = "step_"
CHECKSUMS = "SHA256SUMS"  # sha256sum's own format: "<hex>  <name>" per line
#: What a file system says when it refuses a write for want of room or rights: full, over a quota or a
#: file-size limit, read-only.
DISK_ERRORS = frozenset({errno.ENOSPC, errno.EFBIG, errno.EDQUOT, errno.EROFS})


class CheckpointWriteError(OSError):
    """The file system refused a checkpoint's write (a full disk, a file-size limit, a read-only folder):
    ``path`` is the checkpoint that was being written, ``reason`` why; what was under its name is unchanged
    and the partial write is removed."""

    def __init__(self, path: Path, reason: str, code: int | None = None):
        super().__init__(f"checkpoint: cannot write {path} ({reason})")
        self.path, self.reason, self.errno = Path(path), reason, code


def write_failure(error: BaseException) -> str | None:
    """Why a write failed, in a few words, if ``error`` is the file system refusing it (an ``OSError``, or
    torch's ``RuntimeError`` "enforce fail ... unexpected pos" for a file it could not write in full); else
    None."""
    if isinstance(error, OSError):
        return f"{error.strerror or error}" + (f": {error.filename}" if error.filename else "")
    if isinstance(error, RuntimeError) and ("enforce fail" in str(error) or "write" in str(error).lower()):
        return (f"the file system refused the write: a full disk or a file-size limit (torch: "
                f"{str(error).splitlines()[0][:120]})")
    return None


@contextmanager
def atomic_directory(target: Path) -> Iterator[Path]:
    """Yield a fresh hidden folder beside ``target`` to write into; on success its ``SHA256SUMS`` is written and
    it replaces ``target``. A write the file system refuses raises :class:`CheckpointWriteError` (``target``
    unchanged, the partial folder removed)."""
    target = Path(target)
    partial = target.with_name(f".{target.name}.partial")
    try:
        if partial.exists():
            shutil.rmtree(partial)
        partial.mkdir(parents=True)
    except OSError as error:
        raise CheckpointWriteError(target, write_failure(error), error.errno) from None
    try:
        yield partial
        write_checksums(partial, [path.relative_to(partial).as_posix() for path in sorted(partial.rglob("*"))
                                  if path.is_file() and path.name != CHECKSUMS])
    except BaseException as error:
        shutil.rmtree(partial, ignore_errors=True)
        reason = write_failure(error)
        if reason is None:
            raise
        raise CheckpointWriteError(target, reason, getattr(error, "errno", None)) from None
    try:
        if target.exists():
            old = target.with_name(f".{target.name}.old")
            shutil.rmtree(old, ignore_errors=True)
            os.replace(target, old)
            os.replace(partial, target)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(partial, target)
    except OSError as error:
        shutil.rmtree(partial, ignore_errors=True)
        raise CheckpointWriteError(target, write_failure(error), error.errno) from None


def write_json(path: Path, data: Any) -> None:
    """Write ``data`` as JSON into ``path`` whole or not at all (:func:`~ee_formation_env.baselines.atomic_files.
    write_text`: a refused write is a ``WriteRefused`` naming ``path``)."""
    write_text(path, json.dumps(data, indent=2, default=_plain))


# ------------------------------------------------------------------------------------------ checksums
def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def write_checksums(folder: Path, names: Iterable[str]) -> None:
    """``folder/SHA256SUMS``: the sha256 of each file ``names`` (relative to ``folder``), as ``sha256sum``
    writes them."""
    write_text(Path(folder) / CHECKSUMS, "".join(f"{sha256(Path(folder) / name)}  {name}\n" for name in sorted(names)))


def read_checksums(folder: Path) -> dict[str, str] | None:
    """name -> sha256 from ``folder/SHA256SUMS``; None if there is none; a malformed file is a ``ValueError``
    naming it."""
    path = Path(folder) / CHECKSUMS
    if not path.is_file():
        return None
    sums: dict[str, str] = {}
    try:
        for line in path.read_text(encoding="utf-8").splitlines():
            digest, separator, name = line.partition("  ")
            if not separator or len(digest) != 64 or not all(c in "0123456789abcdef" for c in digest) or not name:
                raise ValueError(line[:80])
            sums[name] = digest
    except (ValueError, UnicodeDecodeError) as error:
        raise ValueError(f"{path}: malformed (expected sha256sum lines '<sha256>  <name>'; {error}): restore the "
                         "file the run wrote") from None
    return sums


def verify_checksums(folder: Path, names: Iterable[str], fix: str, required: bool = True) -> None:
    """Check the files ``names`` of ``folder`` against its ``SHA256SUMS``: a file missing, not listed or whose
    sha256 differs is a ``ValueError`` naming it, ending with ``fix`` (what to do). ``required`` False: a folder
    without ``SHA256SUMS`` (written before checksums existed) is accepted unchecked."""
    folder = Path(folder)
    sums = read_checksums(folder)
    if sums is None:
        if required:
            raise ValueError(f"{folder / CHECKSUMS}: not found, so {folder} cannot be checked (incomplete or "
                             f"damaged): {fix}")
        return
    for name in names:
        path = folder / name
        if not path.is_file():
            raise ValueError(f"{path}: not found: {fix}")
        if name not in sums:
            raise ValueError(f"{path}: not listed in {folder / CHECKSUMS}, so not a file the run wrote: {fix}")
        if sha256(path) != sums[name]:
            raise ValueError(f"{path}: damaged (its sha256 differs from the one written with it in "
                             f"{folder / CHECKSUMS}): {fix}")


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


def load_policy(directory: Path, n_slots: int | None = None) -> Any:
    """The SB3 policy network saved in ``directory`` (``policy.json`` + ``policy.pt``), on the CPU, in eval mode.
    ``n_slots``: a set network's (``policy_network`` set) rebuilt for observations of that many neighbour slots
    (the same weights: none depends on the slot count); None: the observation it trained on."""
    import gymnasium
    import stable_baselines3

    from ee_formation_env.baselines.learned.set_network import sb3_policy_kwargs

    description = read_json(Path(directory) / "policy.json", "policy.json")
    library_class = algorithm(description.get("algo"), "policy.json: algo", ("sb3",)).library_class
    try:
        shape = tuple(int(n) for n in description["observation_shape"])
        low = np.asarray(description["action_low"], dtype=np.float32)
        high = np.asarray(description["action_high"], dtype=np.float32)
        kwargs = sb3_policy_kwargs(description["policy_kwargs"])
        if n_slots is not None and "features_extractor_kwargs" in kwargs:
            extractor = kwargs["features_extractor_kwargs"]
            extractor["n_slots"] = int(n_slots)
            shape = (extractor["n_slots"] * extractor["slot_size"] + extractor["own_size"],)
    except (KeyError, TypeError, ValueError) as error:
        raise ValueError(f"policy.json: malformed ({error})") from None
    observation_space = gymnasium.spaces.Box(-np.inf, np.inf, shape, dtype=np.float32)
    action_space = gymnasium.spaces.Box(low, high, dtype=np.float32)
    policy_class = getattr(stable_baselines3, library_class).policy_aliases["MlpPolicy"]
    policy = policy_class(observation_space, action_space, lambda _: 0.0, **kwargs)
    try:
        policy.load_state_dict(load_tensors(Path(directory) / "policy.pt", "policy.pt"))
    except RuntimeError as error:
        raise ValueError(f"policy.pt: does not fit policy.json ({str(error).splitlines()[0][:200]})") from None
    policy.set_training_mode(False)
    return policy


# ------------------------------------------------------------------------------------------ training state
#: The files of a checkpoint that resuming reads.
TRAINING_STATE_FILES = ("state.json", "policy.json", "policy.pt", "optimizer.pt", "vecnormalize.json")


def save_checkpoint(directory: Path, model: Any, algo: str, policy_kwargs: dict[str, Any], total_timesteps: int,
                    extra_state: dict[str, Any] | None = None,
                    files: Mapping[str, Callable[[Path], None]] | None = None) -> Path:
    """Write ``model``'s complete training state (module docstring) into ``directory``, atomically; ``files``:
    more files of the checkpoint, name -> a writer of that path (``obs_normalizer.json``)."""
    import torch

    venv = model.get_env()
    with atomic_directory(Path(directory)) as partial:
        torch.save(model.policy.state_dict(), partial / "policy.pt")
        write_json(partial / "policy.json", policy_description(model, algo, policy_kwargs))
        optimizers = {"policy": model.policy.optimizer.state_dict()} if hasattr(model.policy, "optimizer") else {}
        torch.save(optimizers, partial / "optimizer.pt")
        write_json(partial / "vecnormalize.json", normalization_state(venv))
        for name, write in (files or {}).items():
            write(partial / name)
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
    its ``state.json``. Every file is checked against the model first: a state that does not fit (a tensor or a
    normalization statistic of another shape, a missing entry) is a ``ValueError`` naming the file, and nothing
    is loaded."""
    directory = Path(directory)
    fix = "the checkpoint does not fit this run; remove it to resume from an older one"
    state = checkpoint_state(directory)
    policy_state = load_tensors(directory / "policy.pt", "policy.pt")
    optimizers = load_tensors(directory / "optimizer.pt", "optimizer.pt")
    venv = model.get_env()
    normalization = _checked_normalization(read_json(directory / "vecnormalize.json", "vecnormalize.json"),
                                           venv.obs_rms.mean.shape, directory / "vecnormalize.json", fix)
    try:
        model.policy.load_state_dict(policy_state)
        if isinstance(optimizers, dict) and "policy" in optimizers:
            model.policy.optimizer.load_state_dict(optimizers["policy"])
    except (RuntimeError, ValueError, KeyError, TypeError) as error:
        raise ValueError(f"{directory}: policy.pt or optimizer.pt does not fit the run's network "
                         f"({str(error).splitlines()[0][:160]}): {fix}") from None
    venv.obs_rms.mean, venv.obs_rms.var = normalization["obs_mean"], normalization["obs_var"]
    venv.obs_rms.count = normalization["obs_count"]
    venv.ret_rms.mean = np.float64(normalization["ret_mean"])
    venv.ret_rms.var = np.float64(normalization["ret_var"])
    venv.ret_rms.count = normalization["ret_count"]
    returns = np.asarray(normalization.get("returns", []), dtype=np.float64)
    if returns.shape == venv.returns.shape:  # per env slot: kept when the layout is the same
        venv.returns = returns
    model.num_timesteps = int(state["agent_steps"])
    model._n_updates = int(state.get("updates", 0))
    return state


def _checked_normalization(data: Any, shape: tuple[int, ...], path: Path, fix: str) -> dict[str, Any]:
    """``vecnormalize.json``'s statistics, checked: the observation mean and variance of ``shape`` exactly (a
    length-1 vector would broadcast silently over every observation entry), finite, the variance >= 0; the
    counts and the return statistics finite numbers."""
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object of normalization statistics: {fix}")
    checked = dict(data)
    for key in ("obs_mean", "obs_var"):
        if key not in data:
            raise ValueError(f"{path}: {key} missing: {fix}")
        try:
            value = np.asarray(data[key], dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{path}: {key}: expected a vector of numbers: {fix}") from None
        if value.shape != tuple(shape):
            raise ValueError(f"{path}: {key}: expected shape {tuple(shape)} (the run's observation), got "
                             f"{value.shape}: {fix}")
        if not np.isfinite(value).all() or (key == "obs_var" and (value < 0).any()):
            raise ValueError(f"{path}: {key}: expected finite values (a variance >= 0): {fix}")
        checked[key] = value
    for key in ("obs_count", "ret_mean", "ret_var", "ret_count"):
        value = data.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ValueError(f"{path}: {key}: expected a finite number, got {value!r}: {fix}")
        checked[key] = float(value)
    return checked


def checkpoint_state(directory: Path) -> dict[str, Any]:
    """``directory/state.json``, checked: ``agent_steps`` an integer >= 0 (the step count its folder is named
    after, for a checkpoint of ``checkpoints/``); a ``ValueError`` naming the file otherwise."""
    directory = Path(directory)
    path = directory / "state.json"
    state = read_json(path, str(path))
    steps = state.get("agent_steps") if isinstance(state, dict) else None
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 0:
        raise ValueError(f"{path}: agent_steps: expected an integer >= 0, got {steps!r}: the checkpoint is damaged; "
                         "remove it to resume from an older one")
    if directory.parent.name == "checkpoints" and directory.name != checkpoint_name(steps):
        raise ValueError(f"{path}: says {steps} agent steps, not the {directory.name} its folder is named after: "
                         "not a checkpoint this run wrote there; remove it")
    return state


def checkpoints(run_dir: Path) -> list[Path]:
    """The checkpoint folders of a run, oldest first (hidden partial writes aside). Anything else named
    ``step_*`` there is a ``ValueError`` naming it: no stray folder or file is taken for a checkpoint or
    passed over in silence."""
    folder = Path(run_dir) / "checkpoints"
    found = []
    for path in folder.glob(f"{STEP_PREFIX}*"):
        digits = path.name[len(STEP_PREFIX):]
        if not (path.is_dir() and not path.is_symlink() and digits.isdigit() and path.name == checkpoint_name(int(digits))):
            raise ValueError(f"{path}: not a checkpoint of this run (checkpoints are folders named "
                             f"{checkpoint_name(0)}, by agent steps): remove it")
        found.append(path)
    return sorted(found, key=lambda path: int(path.name[len(STEP_PREFIX):]))


def checkpoint_name(agent_steps: int) -> str:
    return f"{STEP_PREFIX}{agent_steps:012d}"
