"""Writes the file system refuses during a run (a file-size limit, a full disk, a folder where a file goes): one
line naming the file, the ``--resume`` command only where the run folder holds something to continue from, and
an ``--eval-only`` that leaves the run as it was."""

from __future__ import annotations

import errno
import os
import resource
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytest.importorskip("stable_baselines3")

from trainer_processes import EVAL_FAST, REPO, TINY, error_lines  # noqa: E402

from ee_formation_env.baselines.cli import train_command  # noqa: E402

_SIZE_LIMITED = textwrap.dedent("""
    import resource, sys
    limit = int(sys.argv[1])
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    from ee_formation_env.baselines.cli import train_command
    if __name__ == "__main__":
        sys.exit(train_command(sys.argv[2:]))
""")
needs_limits = pytest.mark.skipif(not hasattr(resource, "RLIMIT_FSIZE"), reason="file-size limits")


def _size_limited(limit: int, argv: list[str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", _SIZE_LIMITED, str(limit), *argv], cwd=cwd, capture_output=True,
                          text=True, timeout=300, env={**os.environ, "PYTHONPATH": str(REPO)})


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("faults") / "run"
    assert train_command(["--out", str(run_dir), *TINY]) == 0
    return run_dir


def _files(folder: Path) -> dict[str, int]:
    return {str(path.relative_to(folder)): path.stat().st_mtime_ns for path in folder.rglob("*")}


@needs_limits
def test_eval_only_under_a_file_size_limit_is_one_line_naming_the_file_and_changes_nothing(trained_run, tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(trained_run, run_dir)
    before = _files(run_dir)
    result = _size_limited(2000, ["--eval-only", str(run_dir), *EVAL_FAST], tmp_path)
    assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr[-3000:]
    (line,) = error_lines(result.stderr)
    assert line.startswith(f"error: --eval-only: cannot write {run_dir / 'evaluations'}/") and \
        "comparison.png (file too large: over this process's file-size limit (ulimit -f): raise it)" in line, line
    assert line.endswith("the run is unchanged (its partial evaluation removed): the same command evaluates it "
                         "again"), line
    assert _files(run_dir) == before  # no evaluations/ folder left either


@needs_limits
def test_a_file_size_limit_before_any_checkpoint_suggests_no_resume_of_the_removed_folder(tmp_path):
    run_dir = tmp_path / "run"
    result = _size_limited(20_000, ["--out", str(run_dir), *TINY], tmp_path)
    assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr[-3000:]
    (line,) = error_lines(result.stderr)
    assert line.startswith(f"error: checkpoint: cannot write {run_dir / 'checkpoints'}/step_"), line
    assert "--resume" not in line and line.endswith("nothing was saved, so no run folder is left: the same command "
                                                    "starts the run again"), line
    assert not run_dir.exists()


@needs_limits
def test_a_file_size_limit_on_config_json_names_it_and_leaves_no_folder(tmp_path):
    run_dir = tmp_path / "run"
    result = _size_limited(3000, ["--out", str(run_dir), *TINY], tmp_path)
    assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr[-3000:]
    (line,) = error_lines(result.stderr)
    assert line.startswith(f"error: training: cannot write {run_dir / 'config.json'} (file too large"), line
    assert "--resume" not in line and not run_dir.exists()


def test_a_refused_write_after_training_names_the_file_and_the_resume_that_continues(tmp_path, capsys, monkeypatch):
    """model.zip, written after the final model: the run holds that model, so --resume is suggested."""
    from stable_baselines3 import PPO

    def too_large(self, path, *args, **kwargs):
        raise OSError(errno.EFBIG, os.strerror(errno.EFBIG))  # as a write(2) says it: no file name

    monkeypatch.setattr(PPO, "save", too_large)
    run_dir = tmp_path / "run"
    assert train_command(["--out", str(run_dir), *TINY]) == 1
    err = capsys.readouterr().err
    (line,) = error_lines(err)
    assert "Traceback" not in err
    assert line.startswith(f"error: training: cannot write {run_dir / 'model.zip'} (file too large"), line
    assert line.endswith(f"`python train.py --resume {run_dir}` continues from it once there is room"), line
    assert not [path.name for path in run_dir.iterdir() if path.name.endswith(".partial")]
