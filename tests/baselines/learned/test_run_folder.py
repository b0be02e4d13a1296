"""The run folder: every refusal comes before it exists, --overwrite removes only what the project wrote, one
trainer at a time holds it (its lock), and a run that never started leaves none behind."""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytest.importorskip("stable_baselines3")

from conftest import mixed_team  # noqa: E402
from trainer_processes import EVAL_FAST, FAST, TINY  # noqa: E402

from ee_formation_env.baselines.cli import train_command  # noqa: E402
from ee_formation_env.baselines.learned.config import TrainConfig  # noqa: E402
from ee_formation_env.baselines.learned.run_folder import MARKER  # noqa: E402
from ee_formation_env.baselines.learned.run_lock import LOCK_NAME, lock_holder, run_lock  # noqa: E402



@pytest.fixture(scope="module")
def trained_run(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("folder") / "run"
    assert train_command(["--out", str(run_dir), *TINY]) == 0
    return run_dir


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    return lines[0]


# ------------------------------------------------------------------------------------------ refusals first
@pytest.mark.parametrize("seed", ["-1", "4294967296", "10000"])
def test_a_seed_out_of_range_is_refused_naming_the_flag_before_any_run_folder(tmp_path, capsys, seed):
    with pytest.raises(SystemExit):  # the flag's own check: a parser error
        train_command(["--seed", seed, "--out", str(tmp_path / "run"), *TINY])
    assert f"--seed: expected an integer in [0, 10000) (training reset seeds stay below the held-out evaluation " \
           f"seeds), got {seed}" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_a_seed_whose_env_slots_reach_the_held_out_seeds_is_refused_before_any_run_folder(tmp_path, capsys):
    assert train_command(["--seed", "9999", "--out", str(tmp_path / "run"), *TINY]) == 2  # 1 env x 4 agents
    assert _one_error_line(capsys) == ("error: --seed: 9999 + 4 env slots reaches the held-out evaluation seeds "
                                       "(10000 and up): expected at most 9996")
    assert not (tmp_path / "run").exists()


def test_a_seed_that_is_not_an_integer_is_refused_naming_the_flag(tmp_path, capsys):
    with pytest.raises(SystemExit):
        train_command(["--seed", "1.5", "--out", str(tmp_path / "run"), *TINY])
    assert "--seed" in capsys.readouterr().err
    for bad in (True, 1.5, "3"):
        with pytest.raises(TypeError, match="--seed: expected an integer"):
            TrainConfig(seed=bad).resolved()
    assert not (tmp_path / "run").exists()


def test_an_empty_out_is_refused_naming_out_instead_of_training_into_a_default_folder(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit):
        train_command(["--out", "", *TINY])
    assert "--out: expected a folder path, got ''" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []  # no runs/<name> made instead
    with pytest.raises(ValueError, match="--out: expected a folder path"):
        TrainConfig(out="  ").resolved()


def test_a_mixed_team_a_backend_cannot_train_is_refused_before_any_run_folder(tmp_path, capsys):
    scenario = tmp_path / "mixed.json"
    scenario.write_text(json.dumps(mixed_team()))
    assert train_command(["--scenario", str(scenario), "--backend", "rllib", "--out", str(tmp_path / "run"),
                          *TINY]) == 2
    line = _one_error_line(capsys)
    assert line.startswith("error: --backend: rllib cannot train a mixed team yet") and "--backend sb3" in line
    assert not (tmp_path / "run").exists()


def test_an_out_that_cannot_be_made_is_one_line_naming_the_path_and_leaves_nothing(tmp_path, capsys, monkeypatch):
    (tmp_path / "a-file").write_text("x")
    impossible = tmp_path / "a-file" / "run"
    assert train_command(["--out", str(impossible), *TINY]) == 2
    line = _one_error_line(capsys)
    assert line.startswith(f"error: --out: cannot create {impossible} (Not a directory")
    for code in (errno.EACCES, errno.EROFS):
        def refused(self, *args, code=code, **kwargs):
            raise OSError(code, os.strerror(code), str(self))

        target = tmp_path / "new" / "deeper" / "run"
        real_mkdir = Path.mkdir
        calls = []

        def mkdir(self, *args, **kwargs):  # the first folder is made, the next one refused
            calls.append(self)
            return real_mkdir(self, *args, **kwargs) if len(calls) == 1 else refused(self)

        monkeypatch.setattr(Path, "mkdir", mkdir)
        assert train_command(["--out", str(target), *TINY]) == 2
        monkeypatch.undo()
        line = _one_error_line(capsys)
        assert line.startswith(f"error: --out: cannot create {target} ({os.strerror(code)}"), line
        assert not (tmp_path / "new").exists()  # the folder it had made is removed again


def test_a_run_that_never_started_leaves_no_folder_so_the_same_command_runs_again(tmp_path, capsys, monkeypatch):
    from ee_formation_env.baselines.learned import sb3_backend
    from ee_formation_env.integrations.sb3 import WorkerFault

    def worker_died(*args, **kwargs):
        raise WorkerFault("env worker 0 (pid 1, env 1 of planar_square) died (exit code 1) during start-up "
                          "(building its envs)", 0, "start-up (building its envs)")

    run_dir = tmp_path / "runs" / "run"
    command = ["--out", str(run_dir), *TINY]
    monkeypatch.setattr(sb3_backend, "build_sb3_model", worker_died)
    assert train_command(command) == 1
    line = _one_error_line(capsys)
    assert "died (exit code 1) during start-up" in line and "nothing was saved, so no run folder is left" in line
    assert not (tmp_path / "runs").exists()
    monkeypatch.undo()
    assert train_command(command) == 0  # the retry is not refused
    assert (run_dir / MARKER).is_file() and not (run_dir / LOCK_NAME).exists()  # the lock is released


def test_a_sigterm_to_the_group_while_the_workers_start_is_a_stop_with_its_exit_code_not_a_fault(tmp_path,
                                                                                                 monkeypatch):
    """The workers die of the SIGTERM that stops the trainer too: nothing was trained yet, nothing is left."""
    from ee_formation_env.baselines.learned import sb3_backend
    from ee_formation_env.baselines.learned.interruption import RunStopped, StopRequest
    from ee_formation_env.integrations.sb3 import WorkerFault

    def worker_died(*args, **kwargs):
        raise WorkerFault("env worker 0 (pid 1, env 1 of planar_square) died (exit code -15: SIGTERM) during "
                          "start-up (building its envs)", 0, "start-up (building its envs)")

    monkeypatch.setattr(sb3_backend, "build_sb3_model", worker_died)
    config = TrainConfig.from_args(TINY)
    with pytest.raises(RunStopped) as stopped:
        sb3_backend.train_sb3(config, tmp_path, StopRequest("SIGTERM"))
    assert stopped.value.exit_code == 143 and str(stopped.value) == (
        "training: stopped by SIGTERM while its env workers started")
    with pytest.raises(RunStopped) as fault:  # the same death without a stop request: a fault
        sb3_backend.train_sb3(config, tmp_path, StopRequest())
    assert fault.value.exit_code == 1 and "died (exit code -15: SIGTERM)" in str(fault.value)


# ------------------------------------------------------------------------------------------ --overwrite
def _targets(tmp_path: Path, trained_run: Path) -> dict[str, tuple[Path, str]]:
    """What --overwrite must refuse, each with the reason its error gives."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    plain = tmp_path / "plain.txt"
    plain.write_text("keep me")
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "thesis.tex").write_text("keep me")
    run_copy = tmp_path / "run-copy"
    shutil.copytree(trained_run, run_copy)
    links = {"link-to-a-run": run_copy, "link-to-a-file": plain, "dangling-link": tmp_path / "nowhere"}
    for name, target in links.items():
        (tmp_path / name).symlink_to(target)
    return {"fifo": (fifo, "is a FIFO, not a folder"), "device": (Path("/dev/null"), "is a character device"),
            "file": (plain, "is a file, not a folder"), "foreign": (foreign, f"no {MARKER} marker"),
            **{name: (tmp_path / name, "is a symbolic link") for name in links}}


def _snapshot(path: Path):
    info = os.lstat(path)
    content = sorted(p.name for p in path.iterdir()) if path.is_dir() and not path.is_symlink() else None
    return info.st_mode, info.st_ino, content


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="FIFOs")
def test_overwrite_refuses_anything_but_a_run_folder_the_project_wrote_and_removes_nothing(tmp_path, trained_run,
                                                                                           capsys):
    for name, (target, why) in _targets(tmp_path, trained_run).items():
        before = _snapshot(target)
        assert train_command(["--out", str(target), "--overwrite", *TINY]) == 2, name
        line = _one_error_line(capsys)
        assert line.startswith(f"error: --out: {target}") and why in line, (name, line)
        assert _snapshot(target) == before, name
    assert (tmp_path / "plain.txt").read_text() == "keep me" and (tmp_path / "foreign" / "thesis.tex").is_file()
    assert (tmp_path / "run-copy" / "config.json").is_file()


def test_every_run_folder_holds_the_marker_and_overwrite_replaces_such_a_folder(tmp_path, trained_run):
    marker = json.loads((trained_run / MARKER).read_text())
    assert marker["written_by"].startswith("ee-formation-env ")
    copy = tmp_path / "run"
    shutil.copytree(trained_run, copy)
    (copy / "notes.txt").write_text("inside a run folder: replaced with it")
    assert train_command(["--out", str(copy), "--overwrite", "--seed", "4", *TINY]) == 0
    assert json.loads((copy / "config.json").read_text())["seed"] == 4 and not (copy / "notes.txt").exists()
    assert (copy / MARKER).is_file()


# ------------------------------------------------------------------------------------------ the lock
_HOLDER = textwrap.dedent("""
    import sys, time
    from ee_formation_env.baselines.learned.run_lock import run_lock
    with run_lock(sys.argv[1], "--out"):
        print("held", flush=True)
        time.sleep(120)
""")


def test_a_run_folder_a_live_trainer_holds_is_refused_to_train_resume_and_overwrite_naming_its_pid(
        tmp_path, trained_run, capsys):
    copy = tmp_path / "run"
    shutil.copytree(trained_run, copy)
    holder = subprocess.Popen([sys.executable, "-c", _HOLDER, str(copy)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline() == "held\n"
        for flags, flag in ((["--out", str(copy), *TINY], "--out"),
                            (["--out", str(copy), "--overwrite", *TINY], "--out"),
                            (["--resume", str(copy), "--total-timesteps", "5000", *EVAL_FAST], "--resume")):
            assert train_command(flags) == 2
            line = _one_error_line(capsys)
            assert line.startswith(f"error: {flag}: {copy} is in use by another trainer (pid {holder.pid}"), line
        assert (copy / "config.json").is_file() and (copy / "comparison.json").is_file()  # nothing replaced
    finally:
        holder.kill()
        holder.wait(timeout=10)


def test_a_stale_lock_of_a_dead_process_is_taken_over_and_said_in_one_line(tmp_path, capsys):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", _HOLDER, str(run_dir)], stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline() == "held\n"
    assert lock_holder(run_dir)["pid"] == holder.pid
    os.kill(holder.pid, signal.SIGKILL)  # its lock file stays; the kernel drops its flock
    holder.wait(timeout=10)
    assert (run_dir / LOCK_NAME).is_file() and lock_holder(run_dir) is None
    with run_lock(run_dir, "--resume"):
        assert lock_holder(run_dir)["pid"] == os.getpid()
    notes = [line for line in capsys.readouterr().err.splitlines() if line]
    assert notes == [f"note: {run_dir / LOCK_NAME}: took over the stale lock of pid {holder.pid}, which ended "
                     "without releasing it"]


def test_the_lock_is_released_on_every_way_out(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    with pytest.raises(KeyboardInterrupt):
        with run_lock(run_dir, "--out"):
            raise KeyboardInterrupt
    assert not (run_dir / LOCK_NAME).exists() and lock_holder(run_dir) is None
    with run_lock(run_dir, "--out"):
        with pytest.raises(ValueError, match=rf"--out: {run_dir} is in use by another trainer \(pid {os.getpid()}"):
            with run_lock(run_dir, "--out"):  # a second holder, even in the same process
                pass
    assert not (run_dir / LOCK_NAME).exists()


def test_a_lock_that_is_a_link_is_refused_and_nothing_is_written_through_it(tmp_path, trained_run, capsys):
    outside = tmp_path / "outside.txt"
    outside.write_text("precious")
    run_dir = tmp_path / "run"
    shutil.copytree(trained_run, run_dir)
    (run_dir / LOCK_NAME).symlink_to(outside)
    with pytest.raises(ValueError, match="is a link, not a lock file"):
        with run_lock(run_dir, "--resume"):
            pass
    assert lock_holder(run_dir) is None
    # --overwrite of the finished run: refused, the target untouched, the folder kept
    assert train_command(["--out", str(run_dir), "--overwrite", *TINY]) != 0
    assert "is a link, not a lock file" in _one_error_line(capsys)
    assert outside.read_text() == "precious" and (run_dir / "config.json").is_file()
    (run_dir / LOCK_NAME).unlink()
    (run_dir / LOCK_NAME).mkdir()  # a folder where the lock goes
    with pytest.raises(ValueError, match="not a regular file|Is a directory|cannot lock"):
        with run_lock(run_dir, "--resume"):
            pass


def _foreign_lock(run_dir: Path, content: str) -> int:
    """Hold ``run_dir``'s lock as another program would: the file holding ``content`` (no pid of ours), its
    flock taken through a descriptor of its own (a flock conflicts across descriptors, in one process too)."""
    run_dir.mkdir(exist_ok=True)
    (run_dir / LOCK_NAME).write_text(content)
    import fcntl

    descriptor = os.open(run_dir / LOCK_NAME, os.O_RDONLY)
    fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
    return descriptor


@pytest.mark.parametrize("content", ["", "not json", '{"pid": null}', '{"pid": "abc"}'])
def test_a_lock_held_without_a_pid_names_an_unknown_process_and_its_lock_file(tmp_path, content):
    run_dir = tmp_path / "run"
    descriptor = _foreign_lock(run_dir, content)
    try:
        with pytest.raises(ValueError) as refused:
            with run_lock(run_dir, "--resume"):
                pass
    finally:
        os.close(descriptor)
    message = str(refused.value)
    assert message.startswith(f"--resume: {run_dir} is in use by an unknown process (the lock file "
                              f"{run_dir / LOCK_NAME} is held but has no pid)"), message
    assert "None" not in message


def test_eval_only_on_a_run_being_trained_names_the_trainer_not_damage(tmp_path, capsys):
    run_dir = tmp_path / "run"
    descriptor = _foreign_lock(run_dir, json.dumps({"pid": 4321, "host": "here"}))
    try:
        assert train_command(["--eval-only", str(run_dir), *EVAL_FAST]) == 2
        assert _one_error_line(capsys) == (f"error: --eval-only: {run_dir} is being trained by pid 4321: wait for it "
                                           "to end, or stop it (its model is saved when it stops), then evaluate it")
        (run_dir / LOCK_NAME).write_text("")
        assert train_command(["--eval-only", str(run_dir), *EVAL_FAST]) == 2
        assert f"is being trained by an unknown process (its lock file {run_dir / LOCK_NAME} has no pid)" in \
            _one_error_line(capsys)
    finally:
        os.close(descriptor)


def test_too_many_envs_are_refused_naming_n_envs_and_its_bound(tmp_path, capsys):
    assert train_command(["--out", str(tmp_path / "run"), *TINY, "--n-envs", "100000"]) == 2
    assert _one_error_line(capsys) == ("error: --n-envs: 100000 envs x 4 agents = 400000 env slots, whose reset "
                                       "seeds would reach the held-out evaluation seeds (10000 and up): expected at "
                                       "most 2500")
    assert not (tmp_path / "run").exists()
