"""A stable-baselines3 VecEnv over batched formation envs, for one policy shared by every agent.

Each agent of each copy is one slot of the VecEnv (``num_envs = n_envs * n_agents``), acting on its own
local observation: decentralized execution with parameter sharing. The copies are those of batched envs
(:func:`ee_formation_env.vector_env`, or the training env of ``ee_formation_env.baselines.learned``), each
stepped by one call: one in this process and/or one per worker process. Written for this project rather
than taken from SuperSuit 3.11, which gets these wrong (``docs/physics.md``, "SuperSuit and SB3: why the
project has its own VecEnv"), and each is tested:

- timeouts bootstrap: a truncated episode sets ``info["TimeLimit.truncated"]`` and
  ``info["terminal_observation"]``, a terminated one does not claim truncation;
- ``seed()`` works (``PPO(seed=...)`` calls it) and every copy gets its own seed;
- every copy has its own PyBullet client, and with ``n_workers > 0`` the copies are spread over worker
  processes, so rollouts use several cores.

Requires stable-baselines3 (the ``train`` extra). Every agent must have the same spaces; the training env of
``ee_formation_env.baselines.learned`` gives a mixed team's agents padded ones.
"""

from __future__ import annotations

import multiprocessing
import signal
import time
import traceback
from multiprocessing.connection import Connection, wait
from typing import Any, Callable, Sequence

import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices

from ee_formation_env.vector import PER_AGENT_INFO
from ee_formation_env.worker_processes import (exit_if_reimporting_main, ignore_interrupts, interrupts_blocked,
                                               unguarded_main_hint)

#: ``factory(num_envs=K)`` -> a batched env of K copies (picklable for worker processes): ``possible_agents``,
#: ``scenario``, ``observation_space(agent)`` / ``action_space(agent)`` (one copy's), ``reset_arrays(seed,
#: options)`` / ``step_arrays(actions)`` returning a :class:`ee_formation_env.vector.BatchedStep` (SAME_STEP
#: autoreset, per-copy seeds) and ``close()``, as :class:`ee_formation_env.vector.VectorFormationEnv` has.
BatchedEnvFactory = Callable[..., Any]

DEFAULT_WORKER_TIMEOUT = 60.0  # s: a slow reset of 14 residual copies on a loaded 2-core machine fits well within it
#: s: a worker seen stopped (SIGSTOP, state "T") this long while it owes an answer is a fault, whatever
#: ``worker_timeout`` says: a stopped process does not go on by itself. Polled every ``_STOPPED_POLL`` s.
STOPPED_WORKER_SECONDS = 2.0
_STOPPED_POLL = 0.5
_CLOSE_TIMEOUT = 10.0  # s: at most this long for the workers to answer "close" before they are terminated
_SLOT_INFO_SKIPPED = ("final_observation",)  # SB3 gets it as each slot's "terminal_observation"


class _CopyGroup:
    """The copies stepped in one process, one batched env: its agents flattened into slots (copy-major)."""

    def __init__(self, factory: BatchedEnvFactory, count: int, info_keys: Sequence[str] | None = None):
        self.env = factory(num_envs=count)
        self.count = count
        self.agents = list(self.env.possible_agents)
        self.info_keys = None if info_keys is None else tuple(info_keys)
        self._joint_slices = self.env.joint_slices if hasattr(self.env, "joint_slices") else None

    def _slot_infos(self, infos: dict[str, np.ndarray]) -> list[dict]:
        """One info dict per slot with the kept keys, as the batched env's dict API gives them: per-agent
        arrays (K, N, ...) row [k, i], ``applied_torque`` (K, T) agent i's joints, per-copy arrays row [k]."""
        N = len(self.agents)
        keys = [key for key in infos if key not in _SLOT_INFO_SKIPPED] if self.info_keys is None else self.info_keys
        slots: list[dict] = [{} for _ in range(self.count * N)]
        for key in keys:
            value = infos[key]
            for k in range(self.count):
                for i in range(N):
                    if key in PER_AGENT_INFO:
                        entry = value[k, i]
                    elif key == "applied_torque":
                        entry = value[k, self._joint_slices[i]]
                    else:
                        entry = value[k]
                    slots[k * N + i][key] = entry
        return slots

    def reset(self, seeds: Sequence[int | None]) -> tuple[np.ndarray, list[dict]]:
        result = self.env.reset_arrays(seed=list(seeds))
        return result.observations.reshape(self.count * len(self.agents), -1), self._slot_infos(result.infos)

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict]]:
        N = len(self.agents)
        result = self.env.step_arrays(actions)
        ended = result.terminations | result.truncations
        infos = self._slot_infos(result.infos)
        for k in np.flatnonzero(ended):
            final = result.infos["final_observation"][k].reshape(N, -1)
            # Truncation is not termination: SB3 bootstraps only when this is True.
            truncated = bool(result.truncations[k]) and not bool(result.terminations[k])
            # Why the env ended it ("" for none), whatever info_keys keeps: a fault is never hidden.
            reason = str(result.infos["physics_fault_reason"][k]) if "physics_fault_reason" in result.infos else ""
            for i in range(N):
                infos[k * N + i]["terminal_observation"] = final[i]
                infos[k * N + i]["TimeLimit.truncated"] = truncated
                infos[k * N + i]["physics_fault_reason"] = reason
        return (result.observations.reshape(self.count * N, -1), result.rewards.reshape(-1).astype(np.float32),
                np.repeat(ended, N), infos)

    def close(self) -> None:
        self.env.close()


class WorkerFault(RuntimeError):
    """An env worker died, failed or stopped answering; ``index`` is the worker's, ``during`` what it was doing
    ("start-up (building its envs)", "step", ...). The message's first line names the worker; an exception
    inside the worker adds its traceback on the lines after."""

    def __init__(self, message: str, index: int, during: str):
        super().__init__(message)
        self.index, self.during = index, during

    @property
    def during_start_up(self) -> bool:
        return self.during.startswith("start-up")


class WorkerTimeout(WorkerFault, TimeoutError):
    """A worker that did not answer in time, or is stopped (SIGSTOP)."""


def _worker(connection: Connection, factory: BatchedEnvFactory, count: int, info_keys: Sequence[str] | None) -> None:
    # Ctrl-C goes to the whole process group: the learner decides how to stop (and can save its model first).
    # SIGINT is blocked from the spawn until here (SharedPolicyVecEnv._start_worker), so none is missed.
    ignore_interrupts()
    parent = multiprocessing.parent_process()
    watched = [connection] if parent is None else [connection, parent.sentinel]
    group = None
    try:
        group = _CopyGroup(factory, count, info_keys)
        connection.send(("ok", None))
        while True:
            # Wait for a command or for the learner's end: a killed learner leaves no orphan worker behind.
            if connection not in wait(watched):
                break
            try:
                command, payload = connection.recv()
            except (EOFError, OSError):  # the learner closed its end of the pipe, or died
                break
            if command == "reset":
                connection.send(("ok", group.reset(payload)))
            elif command == "step":
                connection.send(("ok", group.step(payload)))
            elif command == "get_attr":
                connection.send(("ok", [getattr(group.env, payload)] * group.count))
            elif command == "pid":
                connection.send(("ok", multiprocessing.current_process().pid))
            elif command == "close":
                connection.send(("ok", None))
                break
    except Exception as error:  # report to the parent instead of dying silently
        try:
            connection.send(("error", (repr(error), traceback.format_exc())))
        except OSError:  # the learner is gone
            pass
    finally:
        if group is not None:
            group.close()
        connection.close()


def _signal_name(number: int) -> str:
    try:
        return signal.Signals(number).name
    except ValueError:
        return f"signal {number}"


def _process_state(pid: int | None) -> str | None:
    """The state letter of ``/proc/<pid>/stat`` (Linux; None elsewhere): "T" stopped, "Z" zombie, ..."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return None


class SharedPolicyVecEnv(VecEnv):
    """``n_envs`` copies of a batched env as a VecEnv of ``n_envs * n_agents`` agent slots.

    ``factory(num_envs=K)`` builds a batched env of K copies (:data:`BatchedEnvFactory`; for instance
    ``functools.partial(ee_formation_env.vector_env, "planar_square")``). ``n_workers = 0`` steps all
    ``n_envs`` copies as one batched env in this process; ``n_workers = k`` spreads them over ``k`` worker
    processes (``spawn`` start method, so each builds fresh PyBullet clients), one batched env each, except
    the first ``in_process_envs`` copies, stepped in this process while the workers step theirs: the
    learner's own work per step (the policy's forward pass, normalization, the rollout buffer) then overlaps
    the workers' instead of leaving a core idle. Slot ``e * n_agents + i`` is agent i of copy e; copy e is
    seeded with the seed of its first slot (``seed(s)`` gives slot j the seed ``s + j``), and an ended copy
    restarts from its own generator (the batched env's SAME_STEP autoreset).

    ``info_keys``: the batched env's info entries each slot's info keeps (None, the default: all of them).
    Training needs none of them (SB3 reads only the ``terminal_observation`` and ``TimeLimit.truncated`` this
    VecEnv adds), and with worker processes every entry kept is pickled through a pipe on every step. The
    slots of a copy whose episode ended always get its ``physics_fault_reason`` ("" for none).

    Worker faults name the worker: its index, pid, the copies it steps (indices and scenario) and what it was
    doing; after one the VecEnv refuses further use. Each is a :class:`WorkerFault` (a ``RuntimeError``).

    - A worker that dies (killed, crashed, out of memory) raises ``WorkerFault("env worker 0 (pid 1234, envs
      18-31 of planar_square) died (exit code -9: SIGKILL) during step")`` as soon as it ends. One that dies
      during its start-up because ``spawn`` re-ran the parent's main script, which has no
      ``if __name__ == "__main__":`` guard, says so, with the fix (:mod:`ee_formation_env.worker_processes`).
    - An exception inside a worker raises ``WorkerFault("SharedPolicyVecEnv worker failed: env worker 0 (pid
      1234, env 0 of planar_square) raised ValueError(...) during step")``, followed by the worker's traceback.
    - A worker that is stopped (SIGSTOP) raises :class:`WorkerTimeout` (also a ``TimeoutError``) once it has
      been seen stopped for :data:`STOPPED_WORKER_SECONDS` (2 s, polled every 0.5 s; Linux, from ``/proc``). One
      that does not answer within ``worker_timeout`` seconds (default 60: a slow reset on a loaded machine fits;
      ``None`` waits forever; the attribute may be changed after the start-up) raises ``WorkerTimeout("env
      worker 1 (pid 1234, env 1 of planar_square) did not answer within 60 s during step ...")``. The wait
      costs one ``select`` per answer when it is there: nothing measurable per step.
    - ``close()`` ends every worker, after a fault too: asked to close, else terminated, else killed, each with
      a timeout, so no process is left behind.

    Workers ignore SIGINT: a Ctrl-C, sent to the whole process group, reaches the learner alone, which decides
    how to stop (a trainer catching ``KeyboardInterrupt`` can still step, save its model, then ``close()``).
    SIGTERM still ends a worker, reported as a death (a learner that is stopping because of the same SIGTERM,
    sent to the whole group, can treat that death as part of its stop). A worker whose learner dies (its pipe
    closes or its parent process ends) exits by itself.
    """

    def __init__(self, factory: BatchedEnvFactory, n_envs: int, n_workers: int = 0,
                 info_keys: Sequence[str] | None = None, in_process_envs: int = 0,
                 worker_timeout: float | None = DEFAULT_WORKER_TIMEOUT):
        exit_if_reimporting_main()  # a spawn child re-running an unguarded main script: start no workers from it
        if not callable(factory):
            raise TypeError(f"factory: expected a callable factory(num_envs=K) of a batched env, got "
                            f"{type(factory).__name__}")
        if isinstance(n_envs, bool) or not isinstance(n_envs, (int, np.integer)) or n_envs < 1:
            raise ValueError(f"n_envs: expected an integer >= 1 (copies), got {n_envs!r}")
        n_envs = int(n_envs)
        if not isinstance(n_workers, int) or n_workers < 0:
            raise ValueError(f"n_workers: expected an integer >= 0, got {n_workers!r}")
        if not isinstance(in_process_envs, int) or not 0 <= in_process_envs < n_envs or \
                (in_process_envs and not n_workers):
            raise ValueError(f"in_process_envs: expected an integer in [0, {n_envs - 1}], and 0 without "
                             f"worker processes, got {in_process_envs!r}")
        if info_keys is not None and (isinstance(info_keys, str) or not all(isinstance(k, str) for k in info_keys)):
            raise TypeError(f"info_keys: expected None or a sequence of info key names, got {info_keys!r}")
        if worker_timeout is not None and (isinstance(worker_timeout, bool) or
                                           not isinstance(worker_timeout, (int, float)) or not worker_timeout > 0):
            raise ValueError(f"worker_timeout: expected None or a number of seconds > 0, got {worker_timeout!r}")
        self.worker_timeout = None if worker_timeout is None else float(worker_timeout)
        # Set before anything can fail, so that close() (and __del__) always find them.
        self._local: _CopyGroup | None = None
        self._connections: list[Connection] = []
        self._processes: list[multiprocessing.Process] = []
        self._envs_per_worker: list[int] = []
        self._worker_labels: list[str] = []
        self._unanswered: list[int] = []  # per worker: commands sent whose answer is not read yet
        self._faulty: set[int] = set()  # workers that died, failed or timed out
        self._fault: str | None = None  # the first fault's message: the VecEnv is unusable after it
        # One copy, built here, checks the scenario and gives the spaces before any worker starts.
        probe = factory(num_envs=1)
        try:
            self.agents = list(probe.possible_agents)
            spaces = [(probe.observation_space(a), probe.action_space(a)) for a in self.agents]
            self.scenario = probe.scenario
            if info_keys is not None:
                known = sorted(set(probe.reset_arrays(seed=0).infos) - set(_SLOT_INFO_SKIPPED))
                unknown = sorted(set(info_keys) - set(known))
                if unknown:
                    raise ValueError(f"info_keys: unknown info key(s) {unknown}; the env's: {known}")
        finally:
            probe.close()
        if any(s != spaces[0] for s in spaces):
            other = next(k for k, s in enumerate(spaces) if s != spaces[0])
            raise ValueError("agents: parameter sharing needs identical observation and action spaces for every agent: "
                             f"{self.agents[other]} differs from {self.agents[0]} (the training env of "
                             "ee_formation_env.baselines.learned pads a mixed team's spaces)")
        self.n_envs = n_envs
        self.n_workers = min(n_workers, self.n_envs - in_process_envs)
        self.n_local = self.n_envs if self.n_workers == 0 else in_process_envs  # copies stepped in this process
        try:
            if self.n_workers:
                context = multiprocessing.get_context("spawn")
                chunks = np.array_split(np.arange(self.n_local, self.n_envs), self.n_workers)
                for index, chunk in enumerate(chunks):
                    parent, child = context.Pipe()
                    process = context.Process(target=_worker, args=(child, factory, len(chunk), info_keys),
                                              daemon=True)
                    self._start_worker(process)
                    child.close()
                    self._connections.append(parent)
                    self._processes.append(process)
                    self._envs_per_worker.append(len(chunk))
                    self._unanswered.append(1)  # its start-up report
                    copies = f"env {chunk[0]}" if len(chunk) == 1 else f"envs {chunk[0]}-{chunk[-1]}"
                    self._worker_labels.append(f"env worker {index} (pid {process.pid}, {copies} of "
                                               f"{self.scenario.name})")
            if self.n_local:  # built while the workers build theirs
                self._local = _CopyGroup(factory, self.n_local, info_keys)
            self._receive_workers("start-up (building its envs)")
        except BaseException:
            self.close()
            raise
        self._pending: np.ndarray | None = None
        super().__init__(self.n_envs * len(self.agents), spaces[0][0], spaces[0][1])

    # -- VecEnv API -----------------------------------------------------------------------------------
    def reset(self) -> np.ndarray:
        n = len(self.agents)
        env_seeds = [self._seeds[e * n] for e in range(self.n_envs)]
        results = self._step_everywhere("reset", self._split_per_worker(env_seeds[self.n_local:]),
                                        lambda: self._local.reset(env_seeds[:self.n_local]))
        observations = np.concatenate([r[0] for r in results])
        infos = [info for r in results for info in r[1]]
        self.reset_infos = infos
        self._reset_seeds()
        self._reset_options()
        return observations

    def step_async(self, actions: np.ndarray) -> None:
        self._pending = np.asarray(actions)

    def step_wait(self):
        actions, self._pending = self._pending, None
        n = len(self.agents)
        if not self._connections:
            return self._local.step(actions)
        splits = np.cumsum([count * n for count in (self.n_local, *self._envs_per_worker)])[:-1]
        local_actions, *worker_actions = np.split(actions, splits)
        results = self._step_everywhere("step", worker_actions, lambda: self._local.step(local_actions))
        return (np.concatenate([r[0] for r in results]), np.concatenate([r[1] for r in results]),
                np.concatenate([r[2] for r in results]), [info for r in results for info in r[3]])

    def close(self) -> None:
        """Close every env; end every worker (asked to close, else terminated, else killed), within seconds even
        after a fault: no worker process is left behind."""
        if self._local is not None:
            self._local.close()
            self._local = None
        if not self._processes:
            return
        timeout = _CLOSE_TIMEOUT if self.worker_timeout is None else min(self.worker_timeout, _CLOSE_TIMEOUT)
        deadline = time.monotonic() + timeout
        for index, connection in enumerate(self._connections):
            if index not in self._faulty and self._processes[index].is_alive():
                try:
                    connection.send(("close", None))
                    self._unanswered[index] += 1
                except OSError:
                    self._faulty.add(index)
        for index, (connection, process) in enumerate(zip(self._connections, self._processes)):
            try:
                # Read what it still owes (an interrupted step's answer, then the close's), so that it is not
                # left blocked writing to a full pipe.
                while index not in self._faulty and self._unanswered[index]:
                    if not connection.poll(max(0.0, deadline - time.monotonic())):
                        break
                    connection.recv()
                    self._unanswered[index] -= 1
            except (OSError, EOFError):
                pass
            if _process_state(process.pid) != "T":  # a stopped worker never ends by itself: killed below
                process.join(timeout=max(0.0, deadline - time.monotonic()))
            if process.is_alive() and _process_state(process.pid) not in ("T", "t"):
                process.terminate()
                process.join(timeout=1.0)
            if process.is_alive():  # stopped (SIGSTOP: SIGTERM would wait for a SIGCONT), or deaf to SIGTERM
                process.kill()
                process.join(timeout=1.0)
            connection.close()
        self._connections, self._processes = [], []

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        if attr_name == "render_mode":
            return [None] * self.num_envs  # batched envs do not render
        per_env = [] if self._local is None else [getattr(self._local.env, attr_name)] * self._local.count
        per_env += [value for values in self._call_workers("get_attr", [attr_name] * self.n_workers,
                                                           f"get_attr({attr_name!r})")
                    for value in values]
        per_slot = [value for value in per_env for _ in self.agents]
        return [per_slot[i] for i in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        raise NotImplementedError("set_attr: slots share an env; set attributes through the scenario instead")

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None, **method_kwargs) -> list[Any]:
        raise NotImplementedError("env_method: not supported by SharedPolicyVecEnv")

    def env_is_wrapped(self, wrapper_class: type, indices: VecEnvIndices = None) -> list[bool]:
        return [False] * len(self._get_indices(indices))

    def worker_pids(self) -> list[int]:
        """Process ids of the worker processes (empty when stepping in-process)."""
        if not self._connections:
            return []
        return [int(pid) for pid in self._call_workers("pid", [None] * self.n_workers, "pid")]

    # -- internals ------------------------------------------------------------------------------------
    @staticmethod
    def _start_worker(process: multiprocessing.Process) -> None:
        """Start ``process`` with SIGINT blocked (its worker then ignores it), so that a Ctrl-C during its
        start-up cannot end it; a SIGINT meant for this process meanwhile stays pending, delivered after."""
        with interrupts_blocked():
            process.start()

    def _split_per_worker(self, items: Sequence[Any]) -> list[list[Any]]:
        out, start = [], 0
        for count in self._envs_per_worker:
            out.append(list(items[start:start + count]))
            start += count
        return out

    def _step_everywhere(self, command: str, worker_payloads: Sequence[Any], local_call: Callable[[], Any]) -> list[Any]:
        """Send ``command`` to the workers, run ``local_call`` on this process's envs (if any) while they work,
        then collect: this process's result first, then each worker's."""
        self._send_workers(command, worker_payloads)
        try:
            local = [] if self._local is None else [local_call()]
        finally:
            remote = self._receive_workers(command)  # read even if local_call raised: the pipes stay in step
        return local + remote

    def _call_workers(self, command: str, payloads: Sequence[Any], doing: str) -> list[Any]:
        self._send_workers(command, payloads)
        return self._receive_workers(doing)

    def _send_workers(self, command: str, payloads: Sequence[Any]) -> None:
        self._check_usable()
        for index, (connection, payload) in enumerate(zip(self._connections, payloads)):
            while self._unanswered[index]:  # an interrupted call's answer (a KeyboardInterrupt while waiting)
                self._receive(index, "an earlier call")
            try:
                connection.send((command, payload))
            except OSError:  # its end of the pipe is closed: it died
                self._raise_fault(index, self._death(index, command), command)
            self._unanswered[index] += 1

    def _receive_workers(self, doing: str) -> list[Any]:
        return [self._receive(index, doing) for index in range(len(self._connections))]

    def _receive(self, index: int, doing: str) -> Any:
        connection, process = self._connections[index], self._processes[index]
        ready = self._wait_for_answer(index, doing)
        if connection in ready:
            try:
                status, payload = connection.recv()
            except (EOFError, OSError):  # it died before answering
                self._raise_fault(index, self._death(index, doing), doing)
        else:
            self._raise_fault(index, self._death(index, doing), doing)
        self._unanswered[index] -= 1
        if status == "error":
            error, trace = payload
            self._raise_fault(index, f"SharedPolicyVecEnv worker failed: {self._worker_labels[index]} raised "
                                     f"{error} during {doing}\nWorker traceback:\n{trace.rstrip()}", doing)
        return payload

    def _wait_for_answer(self, index: int, doing: str) -> list[Any]:
        """Wait for worker ``index``'s answer or its end (what is ready); raise :class:`WorkerTimeout` when it
        has been stopped for :data:`STOPPED_WORKER_SECONDS` or has not answered within ``worker_timeout``. The
        first wait returns at once when the answer is there; a worker that takes longer is polled for its state
        every ``_STOPPED_POLL`` s (a stopped process never answers, whatever the timeout)."""
        connection, process = self._connections[index], self._processes[index]
        started = time.monotonic()
        deadline = None if self.worker_timeout is None else started + self.worker_timeout
        stopped_since = None
        while True:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            ready = wait([connection, process.sentinel], _STOPPED_POLL if left is None else min(left, _STOPPED_POLL))
            if ready:
                return ready
            now = time.monotonic()
            state = _process_state(process.pid)
            if state == "T":
                stopped_since = now if stopped_since is None else stopped_since
                if now - stopped_since >= STOPPED_WORKER_SECONDS:
                    self._raise_fault(index, f"{self._worker_labels[index]} is stopped (SIGSTOP) during {doing}: "
                                             f"seen stopped for {STOPPED_WORKER_SECONDS:g} s, it cannot answer "
                                             "until it is continued (SIGCONT)", doing, WorkerTimeout)
            else:
                stopped_since = None
            if deadline is not None and now >= deadline:
                how = {"t": "; it is stopped by a debugger", "D": "; it is waiting on the disk"}.get(state, "")
                self._raise_fault(index, f"{self._worker_labels[index]} did not answer within "
                                         f"{self.worker_timeout:g} s during {doing}{how} (worker_timeout: None "
                                         "waits forever)", doing, WorkerTimeout)

    def _death(self, index: int, doing: str) -> str:
        process = self._processes[index]
        process.join(timeout=1.0)  # its pipe closes as it ends: the exit code follows within moments
        code = process.exitcode
        if code is None:
            how = "closed its pipe but is still running"
        elif code < 0:
            how = f"exit code {code}: {_signal_name(-code)}"
        else:
            how = f"exit code {code}"
        message = f"{self._worker_labels[index]} died ({how}) during {doing}"
        hint = unguarded_main_hint(code) if doing.startswith("start-up") and code is not None and code > 0 else None
        return message if hint is None else f"{message}: {hint}"

    def _raise_fault(self, index: int, message: str, doing: str, kind: type[WorkerFault] = WorkerFault):
        self._faulty.add(index)
        if self._fault is None:
            self._fault = message.split("\n", 1)[0]
        raise kind(message, index, doing)

    def _check_usable(self) -> None:
        if self._fault is not None:
            raise RuntimeError(f"SharedPolicyVecEnv: unusable after a worker fault ({self._fault}); close it")

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass
