"""The scoreboard on a Ray cluster: ``python -m studies.scoreboard --address auto|HOST:PORT``.

The driver (the command) connects to the cluster (``ray.init(address=...)``) and submits each **cell group**
that has a missing cell as one Ray task. A group is one (scenario, method, training seed) training cell with
the test-set and train-set cells that evaluate its trained policy (:mod:`studies.scoreboard`): they need its
run folder, so they run in the same task, after it. A reference method's group (no training) is a task too.
A group whose cells are all cached (:func:`studies.scoreboard_cells.cached_record`: this code's, per
``stale_reason``) is not submitted; a task computes only its group's missing cells (and trains again where its
node has no trained policy for a cached training cell, whose record it then replaces).

CPUs: each task declares ``num_cpus``: :data:`REFERENCE_CPUS` for a reference group; for a ``train.py`` method
its run's processes, ``max(worker processes, evaluation workers) + 1`` (the learner), read from the method's
flags and its mode's preset (:func:`learned_cpus`); :data:`BENCHMARL_CPUS` for a BenchMARL method (its env
copies are batched in the learner's process); ``--cpus-per-learned-cell N`` declares N for every learned group
instead. A group that no node of the cluster can hold is reported and not submitted.

Cells: a task returns its records (each with its path relative to the board's folder), the node that computed
them and that node's :func:`~studies.scoreboard_cells.code_version`; the driver writes each with the atomic
:func:`~studies.scoreboard_cells.write_cell` as results arrive. Only the driver writes cells, and only from a
returned, complete result: a task that dies leaves nothing, so a half-written cell cannot exist, and the nodes
need no shared filesystem for the cells. A task checks first that its node runs the driver's code version; one
that does not is an error naming the node, and its cells are not written (never aggregated silently). The
``studies`` folder travels with the job (Ray's ``py_modules``); the package must be installed on every node
(Ray also puts the command's working directory first on the workers' path, so where that folder exists, a
checkout there is what a worker imports, and what its code version describes).

Run folders: a learned task trains under the board's ``runs/`` path (absolute, as the driver resolves it) on
whatever node runs it. On one machine or a shared filesystem that is one folder, so a retried task resumes its
run from the newest checkpoint; on separate disks a retry on another node trains again from the start.

Failures: a task whose worker or node dies is retried by Ray up to :data:`MAX_RETRIES` times (system failures
only; an exception in the task is not retried). Each task's start is recorded with the driver's start log (a
small actor on the driver's node), so the driver prints one line per start and per retry (its attempt, and the
node the previous attempt was lost on). A group that still fails is reported in one line naming it and the
error; its cells are not written, the board aggregates the others, and the command exits 1.

``import ray`` happens only when a board runs on a cluster: this module imports without Ray.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

from studies.scoreboard_methods import (METHODS, Board, Method, evaluation_cells, run_cell, train_argv,
                                        training_cells)
from studies.scoreboard_cells import _describe, cached_record, code_version, write_cell

#: Retries of a task whose worker process or node died (Ray's ``max_retries``; exceptions are not retried).
MAX_RETRIES = 3
#: CPUs a reference method's group declares (its episodes run in the task's process).
REFERENCE_CPUS = 1
#: CPUs a BenchMARL method's group declares (its env copies are batched in the learner's process).
BENCHMARL_CPUS = 1
#: Seconds between two looks at the start log while tasks run.
POLL_SECONDS = 1.0
#: The folder shipped with the job to every worker (``import studies`` there).
STUDIES_DIR = Path(__file__).resolve().parent
_HOST_PORT = re.compile(r"^(?:[A-Za-z0-9](?:[A-Za-z0-9.-]*[A-Za-z0-9])?|\[[0-9A-Fa-f:.]+\]):(\d{1,5})$")


class CodeVersionMismatch(RuntimeError):
    """A node runs another code version than the driver's: its cells would not be this board's."""


@dataclass(frozen=True)
class Cell:
    """One cell of a group: ``test`` None for the training cell, else its evaluation cell's key
    (:class:`studies.scoreboard_methods.EvaluationCell`)."""

    test: str | None
    path: str  # relative to the board's folder, POSIX
    label: str


@dataclass
class CellGroup:
    """A training cell and the cells that evaluate its policy: one task. ``missing``: those to compute;
    ``trained``: the training cell's cached record, None when it is missing."""

    scenario: str
    method: str
    seed: int | None
    label: str
    training: Cell
    missing: tuple[Cell, ...]
    trained: dict[str, Any] | None


# ------------------------------------------------------------------------------------------ arguments
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--address", default=None, metavar="auto|HOST:PORT",
                        help="run the missing cells as tasks on this Ray cluster (a head started with `ray start "
                             "--head`; needs the distributed extra): one task per training seed and its test-set "
                             "cells, written here as results arrive")
    parser.add_argument("--cpus-per-learned-cell", type=int, default=None, metavar="N",
                        help="--address: the CPUs each learned cell's task declares (default: its train.py worker "
                             "processes, or evaluation workers if more, plus the learner; 1 for BenchMARL)")


def argument_problem(args: argparse.Namespace) -> str | None:
    """Why ``--address`` / ``--cpus-per-learned-cell`` cannot be used as given (None if they can): checked before
    any cell runs or folder is made."""
    if args.cpus_per_learned_cell is not None:
        if args.address is None:
            return "--cpus-per-learned-cell: only with --address (it is what a cluster task declares)"
        if args.cpus_per_learned_cell < 1:
            return "--cpus-per-learned-cell: expected an integer >= 1"
    if args.address is None:
        return None
    match = _HOST_PORT.match(args.address)
    if args.address != "auto" and not (match and 1 <= int(match.group(1)) <= 65535):
        return (f"--address: expected auto or HOST:PORT (the head's address, as `ray start --head` prints it), "
                f"got {args.address!r}")
    if importlib.util.find_spec("ray") is None:
        return ("--address: needs Ray, which is not installed here: install the distributed extra "
                "(pip install -e '.[distributed]')")
    return None


# ------------------------------------------------------------------------------------------ groups
def cell_groups(board: Board, progress: Callable[[str], None] = print) -> list[CellGroup]:
    """The groups of ``board`` with a missing cell, in board order (as ``fill`` runs them); each cached cell is
    reported as ``fill`` reports it."""
    groups = []
    for scenario, method, seed, label in training_cells(board, progress):

        def cell(test: str | None, text: str) -> Cell:
            path = board.cell_path(scenario, method, seed, test).relative_to(board.out)
            return Cell(test, path.as_posix(), text)

        training = cell(None, label)
        cells = [training, *(cell(evaluation.key, f"{label} -> {evaluation.label}")
                             for evaluation in evaluation_cells(board, scenario, method))]
        protocol = board.protocol(method, scenario)
        cached = {c: cached_record(board.out / c.path, c.label, protocol, progress, board.accept_stale)
                  for c in cells}
        missing = tuple(c for c in cells if cached[c] is None)
        if missing:
            groups.append(CellGroup(scenario, method.name, seed, label, training, missing, cached[training]))
    return groups


def teacher_task(group: CellGroup, submitted: Mapping[tuple[str, str, int | None], Any]) -> Any:
    """The task already submitted that trains ``group``'s teacher run (same scenario and seed; ``submitted``:
    (scenario, method, seed) -> task), or None: a copy's task takes it as an argument, so Ray starts the copy
    after it, where the two would otherwise race for one run folder on a shared filesystem."""
    teacher = METHODS[group.method].teacher
    return None if teacher is None else submitted.get((group.scenario, teacher, group.seed))


def learned_cpus(board: Board, group: CellGroup) -> int:
    """The CPUs a learned group's training uses: ``max(n_workers, eval_workers) + 1`` of its resolved
    ``train.py`` configuration (the method's flags, the board's, the mode's preset); BenchMARL's
    :data:`BENCHMARL_CPUS`."""
    method = METHODS[group.method]
    if method.benchmarl is not None:
        return BENCHMARL_CPUS
    from ee_formation_env.baselines.learned.config import TrainConfig

    config = TrainConfig.from_args(train_argv(board, group.scenario, method, group.seed))
    evaluation = config.eval_workers if board.eval_workers is None else board.eval_workers
    return max(config.n_workers, evaluation) + 1


def group_cpus(board: Board, group: CellGroup, cpus_per_learned_cell: int | None = None) -> int:
    """What ``group``'s task declares (``num_cpus``)."""
    if not METHODS[group.method].learned:
        return REFERENCE_CPUS
    return cpus_per_learned_cell or learned_cpus(board, group)


# ------------------------------------------------------------------------------------------ the task
def compute_group(board: Board, group: CellGroup) -> list[tuple[str, dict[str, Any]]]:
    """(relative path, record) of each cell ``group``'s task computes: its missing cells, after its training
    cell, which is trained again if it is cached but this node has no trained policy for it."""
    method = METHODS[group.method]
    trained = group.trained
    results = []
    if trained is None or (method.learned and not _trained_here(board, group, method, trained)):
        trained = run_cell(board, group.scenario, method, group.seed)
        results.append((group.training.path, trained))
    evaluations = {evaluation.key: evaluation for evaluation in evaluation_cells(board, group.scenario, method)}
    for cell in group.missing:
        if cell.test is not None:
            results.append((cell.path, evaluations[cell.test].run(board, group.scenario, method, group.seed, trained)))
    return results


def _trained_here(board: Board, group: CellGroup, method: Method, trained: dict[str, Any]) -> bool:
    """Whether this node can evaluate the cached training cell's policy (or its failure needs none); a run
    stopped early has its saved model and no comparison."""
    from ee_formation_env.baselines.learned.policy import MODEL_FOLDER

    run_dir = board.run_dir(group.scenario, method, group.seed)
    if trained.get("stopped"):
        return (run_dir / MODEL_FOLDER / "state.json").is_file()
    return bool(trained.get("failed")) or any((run_dir / name).is_file()
                                              for name in ("comparison.json", "evaluation.json"))


def run_group(board: Board, group: CellGroup, driver_code: dict[str, Any], start_log: Any,
              teacher_result: Any = None) -> dict[str, Any]:
    """The task: record this start, check this node's code version against the driver's, compute the group.
    ``teacher_result``: the result of the task that trains this group's teacher run (a method with a
    ``teacher``), passed so that Ray starts this task only after it; unused here."""
    import ray

    node = ray.get_runtime_context().get_node_id()
    address = ray.util.get_node_ip_address()
    attempt = ray.get(start_log.started.remote(group.label, node, address, os.getpid()))
    check_code(node, address, driver_code)
    return {"node": node, "address": address, "attempt": attempt, "code": code_version(),
            "cells": compute_group(board, group)}


def check_code(node: str, address: str, driver_code: dict[str, Any]) -> None:
    """Raise :class:`CodeVersionMismatch` naming the node if its code version is not the driver's."""
    if code_version() != driver_code:
        raise CodeVersionMismatch(f"node {node} ({address}) runs {_describe(code_version())}, the driver "
                                  f"{_describe(driver_code)}: install the driver's code on every node")


class StartLog:
    """Every start of a group's task, in order: (group label, attempt, node id, node address, worker pid)."""

    def __init__(self) -> None:
        self.starts: list[tuple[str, int, str, str, int]] = []
        self.attempts: dict[str, int] = {}

    def started(self, label: str, node: str, address: str, pid: int) -> int:
        attempt = self.attempts[label] = self.attempts.get(label, 0) + 1
        self.starts.append((label, attempt, node, address, pid))
        return attempt

    def since(self, index: int) -> list[tuple[str, int, str, str, int]]:
        return self.starts[index:]


# ------------------------------------------------------------------------------------------ the driver
def fill_on_cluster(board: Board, address: str, cpus_per_learned_cell: int | None = None,
                    progress: Callable[[str], None] = print) -> list[str]:
    """Run every missing cell group of ``board`` as a task on the Ray cluster at ``address``, writing each
    returned cell; the labels of the groups not done (each reported when it failed)."""
    import ray
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    board = dataclasses.replace(board, out=board.out.resolve())  # the same path on every node
    groups = cell_groups(board, progress)
    if not groups:
        return []
    ray.init(address=address, runtime_env={"py_modules": [str(STUDIES_DIR)]})
    try:
        node_cpus = max((node["Resources"].get("CPU", 0) for node in ray.nodes() if node["Alive"]), default=0)
        start_log = ray.remote(num_cpus=0)(StartLog).options(scheduling_strategy=NodeAffinitySchedulingStrategy(
            ray.get_runtime_context().get_node_id(), soft=False)).remote()
        task = ray.remote(max_retries=MAX_RETRIES, retry_exceptions=False)(run_group)
        driver_code = code_version()
        pending, not_done, submitted = {}, [], {}
        for group in groups:
            cpus = group_cpus(board, group, cpus_per_learned_cell)
            if cpus > node_cpus:
                progress(f"failed  {group.label}: its task needs {cpus} CPUs and the largest node has {node_cpus:g} "
                         "(--cpus-per-learned-cell declares another number); its cells are not written")
                not_done.append(group.label)
                continue
            after = teacher_task(group, submitted)
            ref = task.options(num_cpus=cpus, name=group.label).remote(board, group, driver_code, start_log, after)
            pending[ref], submitted[(group.scenario, group.method, group.seed)] = group, ref
            progress(f"queued  {group.label}: {len(group.missing)} cell(s) as one task, {cpus} CPU(s)")
        starts = _StartReporter(start_log, progress)
        try:
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1, timeout=POLL_SECONDS)
                starts.report()
                for ref in ready:
                    group = pending.pop(ref)
                    if not _write_result(board, group, ref, driver_code, progress):
                        not_done.append(group.label)
            starts.report()
        except KeyboardInterrupt:
            progress(f"interrupted: {len(pending)} cell group(s) not done (their tasks end with this driver); the "
                     "same command resumes the board, written cells are kept")
            raise SystemExit(130) from None
        return not_done
    finally:
        ray.shutdown()


class _StartReporter:
    """Prints each start recorded in the start log since the last look: a first start, or a retry."""

    def __init__(self, start_log: Any, progress: Callable[[str], None]) -> None:
        self.start_log, self.progress, self.seen = start_log, progress, 0
        self.last_node: dict[str, str] = {}

    def report(self) -> None:
        import ray

        for label, attempt, node, address, pid in ray.get(self.start_log.since.remote(self.seen)):
            self.seen += 1
            where = f"node {node[:12]} ({address}), worker pid {pid}"
            if attempt == 1:
                self.progress(f"started {label} on {where}")
            else:
                self.progress(f"retry   {label}: attempt {attempt} on {where} (attempt {attempt - 1}, on node "
                              f"{self.last_node.get(label, '?')[:12]}, was lost with its worker or node)")
            self.last_node[label] = node


def _write_result(board: Board, group: CellGroup, ref: Any, driver_code: dict[str, Any],
                  progress: Callable[[str], None]) -> bool:
    """Write the cells of ``group``'s finished task ``ref`` (True), or report why there are none (False)."""
    import ray
    from ray.exceptions import RayError, RayTaskError

    try:
        result = ray.get(ref)
    except RayError as error:
        if isinstance(error, RayTaskError):  # the task raised: its exception, and where (Ray's header says)
            cause = error.cause if error.cause is not None else error
            found = re.search(r"\(pid=(\d+), ip=([^)\s]+)\)", str(error))
            where = f" (on {found.group(2)}, worker pid {found.group(1)})" if found else ""
        else:  # its worker or node died on every attempt, or Ray could not run it
            cause, where = error, ""
        reason = (str(cause).strip().splitlines() or [""])[0]
        progress(f"failed  {group.label}{where}: {type(cause).__name__}: {reason}; its cells are not written")
        return False
    if result["code"] != driver_code:  # run_group checks first; a result of other code is never written
        progress(f"failed  {group.label}: node {result['node']} ({result['address']}) computed it with "
                 f"{_describe(result['code'])}, the driver runs {_describe(driver_code)}; its cells are not written")
        return False
    allowed = {group.training.path: group.training, **{cell.path: cell for cell in group.missing}}
    protocol = board.protocol(METHODS[group.method], group.scenario)
    for path, record in result["cells"]:
        write_cell(board.out / allowed[path].path, record, protocol)
        progress(f"done    {allowed[path].label} (node {result['node'][:12]}, attempt {result['attempt']})")
    return True

