"""studies.scoreboard --address: the board's cell groups as tasks on a real local Ray cluster (a head and a
second node, each a process session of this machine), the second node killed while it trains a learned cell;
and ``--address`` refused before any folder is made where it cannot be used (these run without Ray too)."""

from __future__ import annotations

import contextlib
import importlib.util
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest

from ee_formation_env.scenario_sets import held_out_scenarios
from studies import scoreboard, scoreboard_cluster
from studies.scoreboard_cells import read_cell, stale_reason, write_cell

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("argv, message", [
    (["--address", "localhost"], "--address: expected auto or HOST:PORT"),
    (["--address", "head:70000"], "--address: expected auto or HOST:PORT"),
    (["--address", "ray://head:10001"], "--address: expected auto or HOST:PORT"),
    (["--cpus-per-learned-cell", "2"], "--cpus-per-learned-cell: only with --address"),
    (["--address", "auto", "--cpus-per-learned-cell", "0"], "--cpus-per-learned-cell: expected an integer >= 1"),
])
def test_bad_address_values_are_refused_before_any_folder_is_made(argv, message, tmp_path, capsys):
    out = tmp_path / "board"
    with pytest.raises(SystemExit):
        scoreboard.main([*argv, "--quick", "--out", str(out)])
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_address_without_ray_names_the_distributed_extra(tmp_path, capsys, monkeypatch):
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(scoreboard_cluster.importlib.util, "find_spec",
                        lambda name, *args: None if name == "ray" else find_spec(name, *args))
    out = tmp_path / "board"
    with pytest.raises(SystemExit):
        scoreboard.main(["--quick", "--out", str(out), "--address", "127.0.0.1:6379"])
    error = capsys.readouterr().err
    assert "--address: needs Ray" in error and "distributed extra" in error
    assert not out.exists()


def _quick_board(out, **fields):
    settings = dict(scenarios=("planar_square",), methods=("gradient",), seeds=(0,), episodes=1, episode_seconds=0.3,
                    extra_train_flags=scoreboard.QUICK_FLAGS, eval_workers=0)
    return scoreboard.Board(out=out, **{**settings, **fields})


def test_a_group_is_a_training_cell_and_its_test_cells_and_only_missing_cells_are_computed(tmp_path):
    """Without Ray: the groups the driver would submit, and what a task returns for one."""
    board = _quick_board(tmp_path)
    tests = [*held_out_scenarios("planar_square"), "wide-starts"]  # the test scenarios, then the wide starts
    (group,) = scoreboard_cluster.cell_groups(board, progress=lambda line: None)
    assert group.label == "planar_square / gradient" and group.trained is None
    assert [cell.path for cell in group.missing] == [
        "cells/planar_square/gradient/reference.json",
        *(f"cells/planar_square/gradient/test/{test}/reference.json" for test in tests)]
    assert scoreboard_cluster.group_cpus(board, group) == scoreboard_cluster.REFERENCE_CPUS
    results = scoreboard_cluster.compute_group(board, group)
    assert [path for path, _ in results] == [cell.path for cell in group.missing]
    assert not (tmp_path / "cells").exists()  # a task returns its cells; only the driver writes them
    protocol = board.protocol(scoreboard.METHODS["gradient"])
    for path, record in results[:2]:  # the training cell and one test cell were written by an earlier driver
        write_cell(tmp_path / path, record, protocol)
    lines = []
    (group,) = scoreboard_cluster.cell_groups(board, progress=lines.append)
    assert lines == ["cached  planar_square / gradient", f"cached  planar_square / gradient -> test {tests[0]}"]
    assert group.trained is not None and [cell.test for cell in group.missing] == tests[1:]
    assert [path for path, _ in scoreboard_cluster.compute_group(board, group)] == [c.path for c in group.missing]
    for path, record in results[2:]:
        write_cell(tmp_path / path, record, protocol)
    assert scoreboard_cluster.cell_groups(board, progress=lambda line: None) == []  # nothing left to submit


def test_a_node_evaluates_a_stopped_run_only_where_its_saved_model_is(tmp_path):
    """A run that training stopped early has its saved model and no comparison: a node holding that model can
    evaluate its test cells; one without it trains the cell again."""
    board = _quick_board(tmp_path, methods=("torque-ppo",))
    (group,) = scoreboard_cluster.cell_groups(board, progress=lambda line: None)
    method = scoreboard.METHODS["torque-ppo"]
    stopped = {"stopped": "training: 91 of the last 100 training episodes ended in a physics fault"}
    assert not scoreboard_cluster._trained_here(board, group, method, stopped)
    model = board.run_dir("planar_square", method, 0) / "model"
    model.mkdir(parents=True)
    (model / "state.json").write_text("{}", encoding="utf-8")
    assert scoreboard_cluster._trained_here(board, group, method, stopped)
    assert scoreboard_cluster._trained_here(board, group, method, {"failed": "training: ..."})  # nothing to evaluate
    assert not scoreboard_cluster._trained_here(board, group, method, {})  # a finished run needs its comparison


def test_a_learned_group_declares_its_training_processes():
    board = _quick_board(Path("unused"), methods=("residual-ppo",))
    group = scoreboard_cluster.CellGroup("planar_square", "residual-ppo", 0, "label", None, (), None)
    assert scoreboard_cluster.group_cpus(board, group) == 1  # --quick: --n-workers 0 and no evaluation workers
    full = scoreboard.Board(out=Path("unused"), scenarios=("planar_square",), methods=("residual-ppo",), seeds=(0,),
                            episodes=1, episode_seconds=None)
    from ee_formation_env.baselines.learned.config import TrainConfig

    preset = TrainConfig.from_args(scoreboard.train_argv(full, "planar_square", scoreboard.METHODS["residual-ppo"], 0))
    assert scoreboard_cluster.group_cpus(full, group) == max(preset.n_workers, preset.eval_workers) + 1
    assert scoreboard_cluster.group_cpus(full, group, cpus_per_learned_cell=6) == 6


def test_a_node_of_another_code_version_is_refused_by_name():
    driver = {**scoreboard_cluster.code_version(), "source": "0" * 16}
    mismatch = "node abc123 \\(10.0.0.7\\) runs ee-formation-env"
    with pytest.raises(scoreboard_cluster.CodeVersionMismatch, match=mismatch):
        scoreboard_cluster.check_code("abc123", "10.0.0.7", driver)
    scoreboard_cluster.check_code("abc123", "10.0.0.7", scoreboard_cluster.code_version())


# ------------------------------------------------------------------------------------------ a real cluster
CLUSTER_ENV = {"RAY_AUTH_MODE": "disabled",  # loopback only; Ray's token would otherwise need handing to each node
               "RAY_health_check_period_ms": "1000", "RAY_health_check_failure_threshold": "3"}  # a dead node: ~3 s


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _start_node(ray_cli: Path, args: list[str], log: Path, env: dict[str, str]) -> subprocess.Popen:
    """``ray start ... --block`` in a session of its own: the node's processes (raylet, agents, and its workers,
    which Ray puts in process groups of their own) are that session, which the test can kill alone; ``ray
    stop`` would stop every Ray node on the machine."""
    with log.open("w") as handle:
        process = subprocess.Popen([str(ray_cli), "start", *args, "--block"], stdout=handle, stderr=subprocess.STDOUT,
                                   env=env, start_new_session=True)
    deadline = time.monotonic() + 90
    while "Ray runtime started" not in log.read_text():
        if process.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"ray start {' '.join(args)} did not start:\n{log.read_text()[-3000:]}")
        time.sleep(0.5)
    return process


def _session(pid: int) -> int | None:
    try:
        return os.getsid(pid)
    except ProcessLookupError:
        return None


def _kill_session(session: int, sig: int = signal.SIGKILL) -> int:
    """Send ``sig`` to every process of ``session`` (a node started by :func:`_start_node`); how many."""
    pids = [int(entry.name) for entry in Path("/proc").iterdir() if entry.name.isdigit()]
    hit = 0
    for pid in pids:
        if pid != os.getpid() and _session(pid) == session:
            try:
                os.kill(pid, sig)
                hit += 1
            except ProcessLookupError:
                pass
    return hit


def _stop_node(process: subprocess.Popen) -> None:
    _kill_session(process.pid, signal.SIGTERM)
    try:
        process.wait(timeout=15)
    except subprocess.TimeoutExpired:
        pass
    deadline = time.monotonic() + 10
    while _kill_session(process.pid) and time.monotonic() < deadline:
        time.sleep(0.5)
    process.poll()


@contextlib.contextmanager
def _local_cluster(tmp_path: Path, second_node: bool = True, head_pythonpath: str | None = None):
    """A head (1 CPU) and a second node (1 CPU) on this machine, in a temporary Ray folder of their own (short:
    Ray's socket paths must stay under 108 characters); every process of both stopped on the way out. Yields
    the head's address, the second node's ``ray start`` process (None without one) and the environment."""
    pytest.importorskip("ray")
    if not Path("/proc").is_dir():
        pytest.skip("finds a node's processes in /proc")
    ray_cli = Path(sys.executable).with_name("ray")
    if not ray_cli.is_file():
        pytest.skip(f"no ray command beside {sys.executable}")
    env = {key: value for key, value in os.environ.items() if key != "RAY_ADDRESS"}
    env.update(CLUSTER_ENV)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])
    temp = Path(tempfile.mkdtemp(prefix="ray-"))
    port = _free_port()
    address = f"127.0.0.1:{port}"
    common = ["--num-cpus", "1", "--disable-usage-stats", "--node-ip-address", "127.0.0.1", "--temp-dir", str(temp)]
    nodes = []
    try:
        head_env = env if head_pythonpath is None else {**env, "PYTHONPATH": head_pythonpath}
        nodes.append(_start_node(ray_cli, ["--head", "--port", str(port), "--include-dashboard", "false", *common],
                                 tmp_path / "head.log", head_env))
        if second_node:
            nodes.append(_start_node(ray_cli, ["--address", address, *common], tmp_path / "node.log", env))
        yield address, nodes[1] if second_node else None, env
    finally:
        for node in reversed(nodes):
            _stop_node(node)
        shutil.rmtree(temp, ignore_errors=True)


@pytest.fixture
def cluster(tmp_path):
    with _local_cluster(tmp_path) as running:
        yield running


def test_the_board_runs_on_a_cluster_and_a_lost_node_s_cell_is_retried(cluster, tmp_path):
    address, second_node, env = cluster
    out = tmp_path / "board"
    argv = [sys.executable, "-u", "-m", "studies.scoreboard", "--quick", "--out", str(out), "--address", address,
            "--scenarios", "planar_square", "--methods", "residual-ppo", "--seeds", "0", "1", "--episodes", "1"]
    started = time.monotonic()
    board = subprocess.Popen(argv, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    killed: list[str] = []  # the learned group that was running on the second node when it was killed

    def read() -> None:
        start = re.compile(r"^started (\S+ / residual-ppo / seed \d) on node \S+ \(\S+\), worker pid (\d+)$")
        for line in board.stdout:
            lines.append(line.rstrip("\n"))
            match = start.match(lines[-1])
            if match and not killed and _session(int(match.group(2))) == second_node.pid:
                time.sleep(2)  # into its training
                _kill_session(second_node.pid)  # the whole node: raylet, agents, the worker
                killed.append(match.group(1))

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        returncode = board.wait(timeout=420)
    finally:
        if board.poll() is None:
            board.kill()
        reader.join(timeout=10)
    seconds = time.monotonic() - started
    progress = "\n".join(line for line in lines if line.startswith(("queued", "started", "retry", "failed", "done")))
    assert returncode == 0, "\n".join(lines)[-6000:]
    assert killed, f"no learned cell started on the second node (session {second_node.pid}):\n{progress}"
    print(f"board on the cluster: {seconds:.0f} s; killed the second node while it ran {killed[0]}\n{progress}")

    # The killed group was started again (a second attempt), and every cell was written once, by the driver.
    assert sum(line.startswith(f"started {killed[0]} on ") for line in lines) == 1
    assert sum(line.startswith(f"retry   {killed[0]}: attempt 2 on ") for line in lines) == 1
    tests = list(held_out_scenarios("planar_square"))
    groups = [f"planar_square / residual-ppo / seed {seed}" for seed in (0, 1)]  # one task on each node at first
    labels = [label for group in groups
              for label in (group, *(f"{group} -> test {test}" for test in tests), f"{group} -> wide starts")]
    done = [line.split(" (node ")[0][len("done    "):] for line in lines if line.startswith("done    ")]
    assert sorted(done) == sorted(labels)  # each cell exactly once
    cells = sorted((out / "cells").rglob("*"))
    files = [path for path in cells if path.is_file()]
    assert len(files) == len(labels) and all(path.suffix == ".json" for path in files)  # no partial file left
    quick = scoreboard.Board(out=out, scenarios=(), methods=(), seeds=(), episodes=1, episode_seconds=0.3,
                             extra_train_flags=scoreboard.QUICK_FLAGS)
    for path in files:
        record, problem = read_cell(path)
        assert problem is None, path
        assert stale_reason(record, quick.protocol(scoreboard.METHODS[record["method"]])) is None
        assert len(record["episodes"]) == 1
    table = (out / "scoreboard.md").read_text()
    assert "### planar_square" in table and "| residual-ppo | 0, 1 |" in table


def test_a_node_of_another_code_version_fails_its_cells_by_name(tmp_path):
    """A head whose package differs from the driver's by one comment: the task refuses to compute, the command
    names the node and exits 1, and no cell is written. (The command runs outside the checkout, which Ray would
    otherwise put first on the workers' path: on one machine they would import the driver's package.)"""
    copy = tmp_path / "other-code"
    shutil.copytree(REPO / "ee_formation_env", copy / "ee_formation_env",
                    ignore=shutil.ignore_patterns("__pycache__"))
    with (copy / "ee_formation_env" / "__init__.py").open("a") as handle:
        handle.write("# another code version\n")
    out = tmp_path / "board"
    with _local_cluster(tmp_path, second_node=False,
                        head_pythonpath=os.pathsep.join([str(copy), str(REPO)])) as (address, _, env):
        board = subprocess.run([sys.executable, "-m", "studies.scoreboard", "--quick", "--out", str(out), "--address",
                                address, "--scenarios", "planar_square", "--methods", "gradient", "--episodes", "1",
                                "--no-test-sets"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    failed = [line for line in board.stdout.splitlines() if line.startswith("failed  planar_square / gradient")]
    assert board.returncode == 1, board.stdout[-4000:] + board.stderr[-4000:]
    assert len(failed) == 1 and "CodeVersionMismatch: node " in failed[0] and "the driver" in failed[0], failed
    print(failed[0])
    assert "1 cell group(s) not done: planar_square / gradient" in board.stderr
    assert not (out / "cells").exists() and (out / "scoreboard.md").is_file()


def test_a_copys_task_waits_for_its_teachers_task_of_the_same_scenario_and_seed():
    def group(method, seed=0, scenario="spatial_tetrahedron"):
        return scoreboard_cluster.CellGroup(scenario, method, seed, "label", None, (), None)

    submitted = {("spatial_tetrahedron", "position-ppo", 0): "teacher task",
                 ("spatial_tetrahedron", "position-ppo", 1): "other seed's"}
    assert scoreboard_cluster.teacher_task(group("torque-gc-copy-ppo"), submitted) == "teacher task"
    assert scoreboard_cluster.teacher_task(group("torque-gc-copy-ppo", seed=2), submitted) is None  # cached: none
    assert scoreboard_cluster.teacher_task(group("torque-gc-copy-ppo", scenario="planar_square"), submitted) is None
    assert scoreboard_cluster.teacher_task(group("position-ppo"), submitted) is None  # no teacher
