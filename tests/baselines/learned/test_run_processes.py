"""Trainers as real processes: a signal to the whole process group stops and saves the run (SIGTERM as SIGINT),
a worker fault is one line with the --resume command, a kill keeps every log for the resume, a signal during the
comparison leaves a run that --resume compares, and a script without the main guard is told how to fix it."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

pytest.importorskip("stable_baselines3")

from trainer_processes import (EVAL_FAST, REPO, WITH_A_WORKER, children, error_lines, finish, gone,  # noqa: E402
                               start_trainer, training_started, wait_for)

from ee_formation_env.baselines.cli import train_command  # noqa: E402
from ee_formation_env.baselines.learned.run_lock import LOCK_NAME  # noqa: E402
from ee_formation_env.baselines.learned.segments import KILLED  # noqa: E402

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="signals, process groups and /proc")


def _state(run_dir: Path) -> dict:
    return json.loads((run_dir / "model" / "state.json").read_text())


@pytest.mark.parametrize("signal_number", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_to_the_whole_process_group_stops_saves_and_resume_finishes_the_run(tmp_path, capsys,
                                                                                      signal_number):
    """Sent to every process of the group, as a Ctrl-C or a service manager sends it: the workers die of
    SIGTERM (they ignore SIGINT), and the trainer, stopping for the same signal, takes that as part of its stop."""
    name = signal.Signals(signal_number).name
    run_dir = tmp_path / "run"
    budget = 200_000  # far more than the seconds before the signal
    process = start_trainer([*WITH_A_WORKER, "--total-timesteps", str(budget), "--out", str(run_dir)], tmp_path)
    try:
        assert wait_for(training_started(run_dir), 240), "training did not start"
        # Meanwhile the folder is locked: a second command on it is refused, naming the trainer.
        assert train_command(["--resume", str(run_dir), *EVAL_FAST]) == 2
        assert f"is in use by another trainer (pid {process.pid}" in capsys.readouterr().err
        sent = time.monotonic()
        os.killpg(process.pid, signal_number)
    finally:
        _, err = finish(process, 60)
    assert time.monotonic() - sent < 30  # within seconds (a loaded 2-core machine included)
    assert process.returncode == 128 + signal_number, err
    assert "Traceback" not in err, err
    (line,) = error_lines(err)
    assert line.startswith(f"training: stopped by {name} at ") and \
        line.endswith(f"`python train.py --resume {run_dir}` continues it"), line
    state = _state(run_dir)
    assert 0 < state["agent_steps"] < budget and state["interrupted"] == name
    for file in ("policy.pt", "optimizer.pt", "vecnormalize.json", "obs_normalizer.json", "SHA256SUMS"):
        assert (run_dir / "model" / file).is_file(), file
    assert not (run_dir / LOCK_NAME).exists()  # released on the way out
    # Resume the run to a budget it can reach here: a new one, given with --resume.
    target = state["agent_steps"] + 512
    assert train_command(["--resume", str(run_dir), "--total-timesteps", str(target), *EVAL_FAST]) == 0
    timing = json.loads((run_dir / "timing.json").read_text())
    assert [segment["interrupted"] for segment in timing["segments"]] == [name, None]
    assert timing["segments"][1]["start_agent_steps"] == state["agent_steps"]
    assert timing["agent_steps"] >= target and json.loads((run_dir / "config.json").read_text())[
        "total_timesteps"] == target
    assert _state(run_dir)["interrupted"] is None and (run_dir / "comparison.json").is_file()
    steps = [int(line.split(",")[0]) for line in (run_dir / "learning_curve.csv").read_text().splitlines()[1:]]
    assert steps == sorted(steps) and steps[-1] > state["agent_steps"]


@pytest.mark.parametrize("signal_number, what", [
    (signal.SIGKILL, "died (exit code -9: SIGKILL) during step"),
    (signal.SIGTERM, "died (exit code -15: SIGTERM) during step"),  # sent to the worker alone: a fault
    (signal.SIGSTOP, "is stopped (SIGSTOP) during step"),
], ids=["SIGKILL", "SIGTERM", "SIGSTOP"])
def test_a_worker_fault_is_one_line_naming_the_worker_and_the_resume_command_with_the_model_kept(
        tmp_path, signal_number, what):
    run_dir = tmp_path / "run"
    process = start_trainer([*WITH_A_WORKER, "--total-timesteps", "200000", "--out", str(run_dir)], tmp_path)
    try:
        assert wait_for(training_started(run_dir), 240), "training did not start"
        workers = children(process.pid, spawned_workers_only=True)
        assert len(workers) == 1, "expected one worker process"
        sent = time.monotonic()
        for pid in workers:
            os.kill(pid, signal_number)
    finally:
        _, err = finish(process, 60)
    assert time.monotonic() - sent < 20  # a stopped worker too: seen stopped for 2 s, then the model is saved
    assert process.returncode == 1, err
    assert "Traceback" not in err, err
    (line,) = error_lines(err)
    assert line.startswith("error: training: env worker 0 (pid ") and what in line, line
    assert f"(pid {workers[0]}, env 1 of planar_square)" in line
    assert line.endswith(f"`python train.py --resume {run_dir}` continues the run"), line
    state = _state(run_dir)
    assert state["agent_steps"] > 0 and state["interrupted"].startswith("Worker")
    assert wait_for(lambda: gone(workers[0]), 10)  # no worker left behind, stopped or not


def test_resuming_a_killed_run_keeps_every_segments_log_and_lists_every_segment(tmp_path, capsys):
    run_dir = tmp_path / "run"
    process = start_trainer(["--n-envs", "1", "--n-workers", "0", "--total-timesteps", "40000",
                             "--out", str(run_dir)], tmp_path)

    def progress() -> int:  # the segment's agent steps, written to timing.json at each checkpoint
        try:
            return int(json.loads((run_dir / "timing.json").read_text())["segments"][0]["agent_steps"])
        except (OSError, ValueError, KeyError, IndexError):
            return 0

    try:  # killed after its first checkpoint, long before its end
        assert wait_for(lambda: progress() > 0, 240), "no checkpoint"
        os.killpg(process.pid, signal.SIGKILL)
    finally:
        finish(process, 30)
    assert process.returncode == -signal.SIGKILL
    first_monitor = (run_dir / "monitor.csv").read_text()
    assert first_monitor.splitlines()[2:], "no training episode logged before the kill"
    steps = progress()
    capsys.readouterr()
    assert train_command(["--resume", str(run_dir), "--total-timesteps", str(steps + 256), *EVAL_FAST]) == 0
    err = capsys.readouterr().err
    assert f"took over the stale lock of pid {process.pid}" in err  # the kill left its lock
    assert (run_dir / "monitor.csv").read_text().startswith(first_monitor)  # appended to, never truncated
    assert (run_dir / "resumed-1.monitor.csv").is_file()
    timing = json.loads((run_dir / "timing.json").read_text())
    first, second = timing["segments"]
    assert first["monitor"] == "monitor.csv" and first["start_agent_steps"] == 0 and first["interrupted"] == KILLED
    assert not first["running"] and second["start_agent_steps"] == steps and second["interrupted"] is None
    curve = [int(line.split(",")[0]) for line in (run_dir / "learning_curve.csv").read_text().splitlines()[1:]]
    assert curve[0] <= 1_000 and curve[-1] > steps  # from the start of the first segment to the end of the second


def test_a_signal_during_the_comparison_leaves_a_run_that_resume_compares_alone(tmp_path, capsys):
    run_dir = tmp_path / "run"
    process = start_trainer(["--n-envs", "1", "--n-workers", "0", "--total-timesteps", "256",
                             "--eval-episodes", "20", "--eval-seconds", "10", "--eval-workers", "1",
                             "--out", str(run_dir)], tmp_path)
    try:  # the reference lines come first in the comparison phase, then the held-out episodes (minutes here)
        assert wait_for(lambda: (run_dir / "reference_returns.json").is_file(), 240)
        time.sleep(1.0)
        os.killpg(process.pid, signal.SIGINT)
    finally:
        _, err = finish(process, 60)
    assert process.returncode == 130, err
    assert "Traceback" not in err, err
    (line,) = error_lines(err)
    assert line.startswith("comparison: stopped by SIGINT; training is complete (") and \
        line.endswith(f"`python train.py --resume {run_dir}` runs the comparison"), line
    assert not (run_dir / "comparison.json").exists()
    segments = json.loads((run_dir / "timing.json").read_text())["segments"]
    capsys.readouterr()
    assert train_command(["--resume", str(run_dir), *EVAL_FAST]) == 0
    assert "training is complete" in capsys.readouterr().out
    assert (run_dir / "comparison.json").is_file()
    assert json.loads((run_dir / "timing.json").read_text())["segments"] == segments  # no training again
    assert train_command(["--resume", str(run_dir), *EVAL_FAST]) == 2  # now complete
    assert "is complete" in capsys.readouterr().err


_UNGUARDED = textwrap.dedent("""
    import sys
    from ee_formation_env.baselines.cli import train_command

    sys.exit(train_command(sys.argv[1:]))  # at the top level: no `if __name__ == "__main__":`
""")


def test_a_script_without_the_main_guard_is_told_the_fix_in_one_line_and_leaves_no_run_folder(tmp_path):
    script = tmp_path / "my_training.py"
    script.write_text(_UNGUARDED)
    run_dir = tmp_path / "run"
    result = subprocess.run([sys.executable, str(script), "--mode", "torque", "--total-timesteps", "300",
                             "--train-episode-seconds", "0.5", *WITH_A_WORKER, *EVAL_FAST, "--out", str(run_dir)],
                            cwd=tmp_path, capture_output=True, text=True, timeout=300,
                            env={**os.environ, "PYTHONPATH": str(REPO)})
    assert result.returncode == 1, result.stderr[-3000:]
    assert "Traceback" not in result.stderr, result.stderr[-3000:]
    (line,) = error_lines(result.stderr)
    assert line.startswith("error: training: env worker 0 (pid ") and "during start-up" in line, line
    assert f"re-imports the main script {script} in every worker process" in line
    assert 'no `if __name__ == "__main__":` guard' in line and "put the code that trains" in line
    assert line.endswith("nothing was saved, so no run folder is left: the same command starts the run again")
    assert not run_dir.exists()
