"""The Stable-Baselines3 backend of ``train.py``: the model, its VecEnv, callbacks and the saved artefacts.

One policy is shared by every agent: :class:`ee_formation_env.integrations.sb3.SharedPolicyVecEnv` gives each
agent of each copy of the batched training env
(:class:`~ee_formation_env.baselines.learned.training_env.BatchedTrainingEnv`) a slot, normalized by
``VecNormalize`` and monitored by ``VecMonitor``. The algorithm's settings come from its hyperparameter file
(``algorithm_conf/<algo>.yaml``, :mod:`~ee_formation_env.baselines.learned.algorithms`) and, for PPO, the run's
configuration (:class:`ee_formation_env.baselines.learned.config.TrainConfig` and its mode's preset);
docs/training.md explains them.
"""

from __future__ import annotations

import collections
import functools
import math
import re
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ee_formation_env.baselines.atomic_files import WriteRefused, refused, replacing
from ee_formation_env.baselines.learned.algorithms import Algorithm, algorithm, read_hyperparameters
from ee_formation_env.baselines.learned.checkpoint import (DISK_ERRORS, CheckpointWriteError, checkpoint_name,
                                                           checkpoints, read_json, restore_checkpoint,
                                                           save_checkpoint, write_json)
from ee_formation_env.baselines.learned.config import FAULT_WINDOW, TrainConfig
from ee_formation_env.baselines.learned.imitation import imitate
from ee_formation_env.baselines.learned.interruption import RunStopped, StopRequest
from ee_formation_env.baselines.learned.policy import ObservationNormalizer
from ee_formation_env.baselines.learned.run_files import CONFIG, MODEL_FOLDER, STAMP, model_stamp
from ee_formation_env.baselines.learned.run_folder import has_resumable_state
from ee_formation_env.baselines.learned.set_network import (pooled_running_statistics, sb3_policy_kwargs,
                                                            set_description, slot_layout_of)
from ee_formation_env.baselines.learned.segments import (close_killed_segments, new_monitor_name, read_timing,
                                                         start_segment, update_segment, write_learning_curve,
                                                         write_timing)
from ee_formation_env.baselines.learned.training_env import batched_env_factory
from ee_formation_env.baselines.metrics import fault_kinds


class TrainingFaults(ValueError):
    """Most training episodes end in physics faults: the run cannot learn from them (the scenario's arms are not
    drivable at these torques). Raised by the fault monitor of :func:`train_sb3`, message starting
    ``training:``."""


def policy_kwargs(args: TrainConfig) -> dict[str, Any]:
    """The policy network's settings: the mode's hidden layers and, for PPO, the initial log standard deviation.

    A small initial action noise (log_std -1: std 0.37 of the action range): with the default 0 a residual
    policy starts far from "no correction" and a torque policy saturates its joints half of the time.

    With gSDE (``sde_sample_freq`` not 0) it adds ``use_sde``: the network holds gSDE's noise parameters, so
    rebuilding it needs the flag. A run with ``policy_network`` set adds ``set_network``: the slot layout and the
    team signature of its scenario (:func:`~ee_formation_env.baselines.learned.set_network.set_description`).
    Plain data (a run's ``policy.json`` saves it);
    :func:`~ee_formation_env.baselines.learned.set_network.sb3_policy_kwargs` turns it into SB3's."""
    kwargs: dict[str, Any] = dict(net_arch=list(args.ppo.net_arch))  # --imitate: the wider actor
    if algorithm(args.algo).is_ppo:
        kwargs["log_std_init"] = args.log_std_init
    if args.sde_sample_freq:  # gSDE's noise matrix is a parameter of the network (latent x action)
        kwargs["use_sde"] = True
    if args.options.policy_network == "set":
        kwargs["set_network"] = set_description(args.scenario, args.options.obs_features)
    return kwargs


def build_sb3_model(args: TrainConfig, out_dir: Path | None, monitor_name: str = "monitor.csv") -> Any:
    """The SB3 model (with its normalized, monitored VecEnv as ``model.get_env()``) that ``train_sb3`` trains;
    ``out_dir`` None: no monitor file and no TensorBoard logs (the throughput benchmark)."""
    import stable_baselines3
    from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

    from ee_formation_env.integrations.sb3 import SharedPolicyVecEnv

    import torch

    entry = algorithm(args.algo, backends=("sb3",))
    hyperparameters = sb3_hyperparameters(entry)  # a faulty file is refused before any env starts
    torch.set_num_threads(1)  # a 64x64 MLP gains nothing from more threads; they would compete with the envs
    # No per-step infos cross the worker pipes: the learner reads none (the VecEnv adds what SB3 needs).
    venv = SharedPolicyVecEnv(batched_env_factory(args), args.n_envs, n_workers=args.n_workers, info_keys=(),
                              in_process_envs=args.in_process_envs)
    venv = VecMonitor(venv, filename=None if out_dir is None else str(out_dir / monitor_name))
    venv = VecNormalize(venv, norm_obs=True, norm_reward=True, gamma=args.gamma)
    plain_kwargs = policy_kwargs(args)
    if "set_network" in plain_kwargs:  # statistics shared across slots (set_network.py)
        venv.obs_rms = pooled_running_statistics(slot_layout_of(plain_kwargs["set_network"]))
    sb3_kwargs = sb3_policy_kwargs(plain_kwargs)
    use_sde = sb3_kwargs.pop("use_sde", False)  # PPO passes it to the policy itself
    kwargs = dict(hyperparameters, gamma=args.gamma, seed=args.seed, verbose=0, device="cpu",
                  policy_kwargs=sb3_kwargs, tensorboard_log=None if out_dir is None else str(out_dir / "tensorboard"))
    if entry.is_ppo:
        settings = args.ppo
        rate = settings.learning_rate
        # A linear decay to 0 over the run (SB3 passes the remaining progress, 1 -> 0) settles the final policy.
        learning_rate = functools.partial(_linear_schedule, rate) if settings.learning_rate_decay else rate
        # n_steps x (n_envs x agents) slots per update: 4,096 agent steps with either mode's defaults; a minibatch
        # is at most one update.
        kwargs.update(n_steps=args.n_steps, n_epochs=settings.n_epochs, learning_rate=learning_rate, use_sde=use_sde,
                      sde_sample_freq=args.sde_sample_freq if use_sde else -1)
        kwargs["batch_size"] = min(kwargs["batch_size"], args.n_steps * venv.num_envs)
    return getattr(stable_baselines3, entry.library_class)("MlpPolicy", venv, **kwargs)


#: The arguments of SB3's algorithm classes that the run sets itself, never its hyperparameter file: the env,
#: the policy, the discount, the seed and the outputs; for PPO also the mode preset's and the run's PPO settings.
RUN_ARGUMENTS = ("policy", "env", "gamma", "seed", "verbose", "device", "policy_kwargs", "tensorboard_log",
                 "_init_setup_model")
PPO_RUN_ARGUMENTS = ("n_steps", "n_epochs", "learning_rate", "use_sde", "sde_sample_freq")


def sb3_hyperparameters(entry: Algorithm) -> dict[str, Any]:
    """The hyperparameters of the SB3 algorithm ``entry`` (its YAML file, :mod:`~ee_formation_env.baselines.
    learned.algorithms`), checked against its SB3 class: each key one of its arguments that the run does not set
    (:data:`RUN_ARGUMENTS`), its value of the type of SB3's default."""
    import inspect

    import stable_baselines3

    library = getattr(stable_baselines3, entry.library_class)
    refused = {*RUN_ARGUMENTS, *(PPO_RUN_ARGUMENTS if entry.is_ppo else ())}
    accepted = {name: parameter.default for name, parameter in inspect.signature(library).parameters.items()
                if name not in refused}
    return read_hyperparameters(entry, accepted)


def _linear_schedule(initial: float, progress_remaining: float) -> float:
    return initial * progress_remaining


def train_sb3(args: TrainConfig, out_dir: Path, stop: StopRequest | None = None,
              resume_from: Path | None = None) -> dict[str, Any]:
    """Train ``args`` (a resolved configuration) with SB3 into ``out_dir``: checkpoints during training, the final
    model (``model/``, and ``model.zip`` for SB3 users), the segment's monitor file, ``timing.json`` and
    ``learning_curve.csv`` (:mod:`~ee_formation_env.baselines.learned.segments`); returns the run's timing.
    ``stop``: ends training at the next step once set (a signal); ``resume_from``: a checkpoint of this run to
    continue from, to the budget.

    Faults outside the configuration are :class:`RunStopped`, one line each with what is saved and the
    ``--resume`` command: an env worker that dies, fails or is stopped (the model so far saved first), a write
    the file system refuses (the older checkpoints intact). An env worker that dies of the SIGTERM that also
    stops this process (sent to the whole process group) is part of that stop, not a fault."""
    from ee_formation_env.integrations.sb3 import WorkerFault

    timing = read_timing(out_dir) if resume_from is not None else {"segments": []}
    close_killed_segments(timing)
    monitor_name = new_monitor_name(out_dir, timing)
    try:
        model = build_sb3_model(args, out_dir, monitor_name)
    except WorkerFault as fault:  # at start-up: nothing trained, nothing to save (the caller says what is left)
        if _stopping_for_the_same_signal(fault, stop):
            raise RunStopped(f"training: stopped by {stop.signal_name} while its env workers started",
                             signal_name=stop.signal_name) from None
        first, _, rest = str(fault).partition("\n")
        raise RunStopped(f"training: {first}", details=rest or None) from fault
    venv = model.get_env()
    print(f"TensorBoard logs: {out_dir / 'tensorboard'} (watch with `tensorboard --logdir {out_dir / 'tensorboard'}`)",
          flush=True)
    interrupted = None
    try:
        # The model's stamp, written into every checkpoint and the final model: config.json as this command
        # wrote it (a resume with a new budget rewrote it first), the policy's own sizes.
        stamp = model_stamp(read_json(out_dir / CONFIG, CONFIG), model.policy.observation_space.shape[0],
                            model.policy.action_space.shape[0])
        if resume_from is not None:
            restore_checkpoint(resume_from, model)
        elif args.imitate != "none":
            imitate(model, args, out_dir)
        start_steps = int(model.num_timesteps)
        segment = start_segment(out_dir, timing, monitor_name, start_steps)
        started = time.time()

        def progress() -> None:  # at each checkpoint: a kill loses at most what came after it
            update_segment(out_dir, timing, segment, agent_steps=int(model.num_timesteps),
                           train_seconds=time.time() - started)

        saver = _checkpoint_callback(out_dir, args, stamp, max(args.total_timesteps // (4 * venv.num_envs), 1),
                                     progress)
        callbacks = [saver]
        if stop is not None:
            callbacks.append(_stop_callback(stop))
        if args.max_train_seconds is not None:
            callbacks.append(_time_limit_callback(args.max_train_seconds))
        if not args.no_progress:
            callbacks.append(_progress_callback(collected_steps(args.total_timesteps - start_steps, model,
                                                                venv.num_envs), start_steps))
        faults = FaultTally()
        callbacks.append(_fault_callback(faults, args.max_fault_fraction, len(venv.unwrapped.agents),
                                         int(args.fault_guard_start * args.total_timesteps)))
        remaining = args.total_timesteps - start_steps
        stopped_by: TrainingFaults | None = None
        if remaining > 0:
            try:
                if resume_from is None:
                    model.learn(total_timesteps=args.total_timesteps, callback=callbacks)
                else:  # SB3 counts the budget from the restored step count: the schedules continue where they were
                    model.learn(total_timesteps=remaining, callback=callbacks, reset_num_timesteps=False)
            except TrainingFaults as fault:  # the model, timing.json and the curve end at the stop, then raised
                stopped_by = fault
            except WorkerFault as fault:  # an env worker died or stopped: the model itself is fine
                if not _stopping_for_the_same_signal(fault, stop):
                    _save_model(out_dir, model, args, stamp, f"{type(fault).__name__}: {fault}")
                    first, _, rest = str(fault).partition("\n")
                    raise RunStopped(f"training: {first}; the model at {model.num_timesteps} agent steps is saved "
                                     f"in {out_dir / MODEL_FOLDER}", out_dir, "continues the run",
                                     details=rest or None) from fault
        if stopped_by is not None:
            interrupted = "physics faults"
        else:
            interrupted = stop.signal_name if stop is not None and stop.requested else None
        _save_model(out_dir, model, args, stamp, interrupted)
        if stopped_by is None:  # SB3's own format, for SB3 users; never read by the project
            with replacing(out_dir / "model.zip") as temporary:
                model.save(temporary)  # SB3 adds .zip only to a name without a suffix
    except OSError as error:
        raise _refused_write(error, out_dir) from None
    finally:
        venv.close()
    seconds = time.time() - started
    try:
        update_segment(out_dir, timing, segment, agent_steps=int(model.num_timesteps), train_seconds=seconds,
                       interrupted=interrupted, running=False, **faults.as_dict())
        timing["agent_steps_per_s"] = (model.num_timesteps - start_steps) / max(seconds, 1e-9)  # this segment's
        write_timing(out_dir, timing)
        write_learning_curve(out_dir, timing["segments"])
    except OSError as error:
        raise _refused_write(error, out_dir) from None
    if stopped_by is not None:
        raise TrainingFaults(f"{stopped_by} (the model so far is saved in {out_dir / MODEL_FOLDER})")
    return timing


def _normalizer(model: Any) -> ObservationNormalizer:
    """The observation normalization the evaluation applies: the VecEnv's running statistics, as now."""
    venv = model.get_env()
    return ObservationNormalizer(venv.obs_rms.mean.copy(), venv.obs_rms.var.copy(), venv.clip_obs)


def _evaluation_files(model: Any, stamp: dict[str, Any]) -> dict[str, Callable[[Path], None]]:
    """The files of a checkpoint that the evaluation reads besides the policy: the observation normalization it
    applies and the model's stamp (:mod:`~ee_formation_env.baselines.learned.run_files`)."""
    return {"obs_normalizer.json": _normalizer(model).save, STAMP: lambda path: write_json(path, stamp)}


def _save_model(out_dir: Path, model: Any, args: TrainConfig, stamp: dict[str, Any], interrupted: str | None) -> None:
    """The final model (``model/``): a complete checkpoint with the observation normalization the evaluation
    applies and the stamp, ``state.json`` saying why training ended early (``interrupted``; None: it did not)."""
    save_checkpoint(out_dir / MODEL_FOLDER, model, args.algo, policy_kwargs(args), args.total_timesteps,
                    {"interrupted": interrupted}, files=_evaluation_files(model, stamp))


def _stopping_for_the_same_signal(fault: Exception, stop: StopRequest | None) -> bool:
    """Whether ``fault`` is a worker that died of a SIGTERM (or SIGINT) sent to the whole process group, which
    stops this process too. The signal reached this process when it reached the worker, so its stop request
    comes within moments (its handler runs at the next bytecode of the main thread); it is waited for here
    for at most a second. A worker sent SIGTERM alone is a fault."""
    if stop is None or not re.search(r"\(exit code -(15|2): SIG(TERM|INT)\)", str(fault)):
        return False
    deadline = time.monotonic() + 1.0
    while not stop.requested and time.monotonic() < deadline:
        time.sleep(0.02)  # lets the handler run
    return stop.requested


def _refused_write(error: OSError, out_dir: Path) -> Exception:
    """What a write the file system refused during training raises: a :class:`RunStopped` naming the file (or
    the checkpoint) and, only when ``out_dir`` holds something to continue from, the ``--resume`` command (else
    the caller says that nothing was saved). Any other ``OSError`` is returned as it is."""
    if isinstance(error, CheckpointWriteError):
        message = str(error)
    elif isinstance(error, WriteRefused) or (error.errno in DISK_ERRORS and error.filename):
        message = f"training: {refused(Path(error.filename), error)}"
    elif error.errno in DISK_ERRORS:  # an appended log (its writer does not say which): the monitor or TensorBoard's
        message = (f"training: cannot write the logs in {out_dir}, its monitor file or tensorboard/ "
                   f"({refused(out_dir, error).reason})")
    else:
        return error
    if not has_resumable_state(out_dir):
        return RunStopped(f"{message}; no checkpoint was saved before")
    return RunStopped(f"{message}; {_intact_checkpoints(out_dir)}", out_dir, "continues from it once there is room")


def _intact_checkpoints(out_dir: Path) -> str:
    """Which checkpoint a resume would continue from, after a refused write (each is complete or absent)."""
    try:
        found = checkpoints(out_dir)
    except ValueError:
        found = []
    if not found:
        return "no checkpoint was saved before"
    return f"the older checkpoints are intact (newest: {found[-1].name})"


def _checkpoint_callback(out_dir: Path, args: TrainConfig, stamp: dict[str, Any], every: int,
                         saved: Callable[[], None]) -> Any:
    """Every ``every`` vec-env steps, a complete checkpoint (:func:`save_checkpoint`) of the model, with the
    observation normalization the evaluation applies and the stamp; then ``saved()``."""
    from stable_baselines3.common.callbacks import BaseCallback

    class CheckpointSaver(BaseCallback):
        def _on_step(self) -> bool:
            if self.n_calls % every == 0:
                save_checkpoint(out_dir / "checkpoints" / checkpoint_name(self.model.num_timesteps), self.model,
                                args.algo, policy_kwargs(args), args.total_timesteps,
                                files=_evaluation_files(self.model, stamp))
                saved()
            return True

    return CheckpointSaver()


class FaultTally:
    """Training episodes seen by the fault monitor, how many ended in a physics fault, and why (grouped by
    kind, numbers masked: :func:`~ee_formation_env.baselines.metrics.fault_kinds`)."""

    def __init__(self) -> None:
        self.episodes = 0
        self.reasons: collections.Counter[str] = collections.Counter()
        self.recent: collections.deque[bool] = collections.deque(maxlen=FAULT_WINDOW)

    @property
    def faulted(self) -> int:
        return sum(self.reasons.values())

    def add(self, reason: str) -> None:
        self.episodes += 1
        self.recent.append(bool(reason))
        if reason:
            self.reasons[reason] += 1

    def as_dict(self) -> dict[str, Any]:
        return {"training_episodes": self.episodes, "faulted_training_episodes": self.faulted,
                "fault_reasons": dict(fault_kinds(self.reasons)[:5])}


def _fault_callback(tally: FaultTally, max_fraction: float, n_agents: int, start_steps: int = 0) -> Any:
    """Counts every training episode's end (its ``physics_fault_reason``, on the first slot of its copy) into
    ``tally``; from ``start_steps`` agent steps on, raises :class:`TrainingFaults` when more than ``max_fraction``
    of the last :data:`~ee_formation_env.baselines.learned.config.FAULT_WINDOW` episodes faulted."""
    from stable_baselines3.common.callbacks import BaseCallback

    class FaultMonitor(BaseCallback):
        def _on_step(self) -> bool:
            ended = np.asarray(self.locals["dones"]).reshape(-1, n_agents)[:, 0]
            if not ended.any():
                return True
            infos = self.locals["infos"]
            for copy in np.flatnonzero(ended):
                tally.add(str(infos[copy * n_agents].get("physics_fault_reason", "")))
            faulted = sum(tally.recent)
            if (self.model.num_timesteps >= start_steps and len(tally.recent) == FAULT_WINDOW
                    and faulted > max_fraction * FAULT_WINDOW):
                example, count = fault_kinds(tally.reasons)[0]
                raise TrainingFaults(
                    f"training: {faulted} of the last {FAULT_WINDOW} training episodes ended in a physics fault "
                    f"(most often {example!r}: {count} of the {tally.faulted} faulted episodes so far), "
                    f"after {self.model.num_timesteps:,} agent steps; the policy cannot learn from episodes the "
                    "physics ends. Make the arms drivable: lower --action-acceleration (rad/s^2), --residual-scale or "
                    "the scenario's torque_limits (N m), or raise its max_joint_velocity (--max-fault-fraction 1 "
                    "trains anyway)")
            return True

    return FaultMonitor()


def _stop_callback(stop: StopRequest) -> Any:
    """Ends ``learn`` at the first step after ``stop`` was requested."""
    from stable_baselines3.common.callbacks import BaseCallback

    class StopOnRequest(BaseCallback):
        def _on_step(self) -> bool:
            return not stop.requested

    return StopOnRequest()


def _time_limit_callback(seconds: float) -> Any:
    """Ends ``learn`` at the first step after ``seconds`` of wall time (from the start of training)."""
    from stable_baselines3.common.callbacks import BaseCallback

    class TimeLimit(BaseCallback):
        def _on_training_start(self) -> None:
            self.deadline = time.time() + seconds

        def _on_step(self) -> bool:
            return time.time() < self.deadline

    return TimeLimit()


def collected_steps(total_timesteps: int, model: Any, num_envs: int) -> int:
    """Agent steps SB3 actually collects for ``total_timesteps``: PPO collects whole rollouts of
    ``n_steps * num_envs``, SAC whole vec-env steps of ``num_envs``, so it stops at or after the total."""
    chunk = getattr(model, "n_steps", 1) * num_envs
    return math.ceil(total_timesteps / chunk) * chunk


def _progress_callback(total: int, done: int = 0) -> Any:
    """A tqdm bar over the agent steps of the run: from ``done`` (the steps a resumed run has done) to ``done``
    plus ``total``, what this segment will collect (no overshoot)."""
    from stable_baselines3.common.callbacks import BaseCallback
    from tqdm.auto import tqdm

    class TrainingProgress(BaseCallback):
        def _on_training_start(self) -> None:
            self.bar = tqdm(total=done + total, initial=done, desc="training", unit=" agent steps", unit_scale=True)

        def _on_step(self) -> bool:
            self.bar.update(min(self.training_env.num_envs, done + total - self.bar.n))
            return True

        def _on_training_end(self) -> None:
            self.bar.close()

    return TrainingProgress()
