"""A saved run's files are checked before use against the run's own configuration and checksums; a refused write
leaves the older checkpoints intact; --resume --total-timesteps extends a finished run."""

from __future__ import annotations

import errno
import hashlib
import json
import os
import resource
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytest.importorskip("stable_baselines3")

from trainer_processes import EVAL_FAST, FAST, TINY, REPO, error_lines  # noqa: E402

from ee_formation_env.baselines.cli import train_command  # noqa: E402
from ee_formation_env.baselines.learned import checkpoint  # noqa: E402
from ee_formation_env.baselines.learned.config import TrainConfig  # noqa: E402
from ee_formation_env.baselines.learned.policy import load_model  # noqa: E402



@pytest.fixture(scope="module")
def trained_run(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("saved") / "run"
    assert train_command(["--out", str(run_dir), *TINY]) == 0
    return run_dir


@pytest.fixture
def copy(trained_run, tmp_path) -> Path:
    target = tmp_path / "run"
    shutil.copytree(trained_run, target)
    return target


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("note: ")]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    return lines[0]


def _edit_json(path: Path, edit) -> None:
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


def _resign(folder: Path) -> None:
    """Rewrite ``folder``'s SHA256SUMS over its files as they are now, so that the checks behind the checksums
    are reached."""
    checkpoint.write_checksums(folder, sorted(p.name for p in folder.iterdir()
                                              if p.is_file() and p.name != checkpoint.CHECKSUMS))


# ------------------------------------------------------------------------------------------ checksums
def test_config_json_and_every_checkpoint_file_carry_a_sha256_that_sha256sum_reads(trained_run):
    folders = [trained_run, trained_run / "model", *checkpoint.checkpoints(trained_run)]
    for folder in folders:
        sums = checkpoint.read_checksums(folder)
        expected = ["config.json"] if folder == trained_run else sorted(
            p.name for p in folder.iterdir() if p.name != checkpoint.CHECKSUMS)
        assert sorted(sums) == expected, folder
        for name, digest in sums.items():
            assert hashlib.sha256((folder / name).read_bytes()).hexdigest() == digest
    assert {"policy.pt", "optimizer.pt", "vecnormalize.json", "obs_normalizer.json", "state.json"} <= set(
        checkpoint.read_checksums(folders[-1]))
    if shutil.which("sha256sum"):
        subprocess.run(["sha256sum", "--check", "--quiet", checkpoint.CHECKSUMS], cwd=folders[-1], check=True)


@pytest.mark.parametrize("edit", [
    pytest.param(lambda c: c.update(mode="residual"), id="mode"),
    pytest.param(lambda c: c.update(residual_scale=1e6), id="residual_scale"),
    pytest.param(lambda c: c.update(obs_features="none"), id="obs_features"),
    pytest.param(lambda c: c.pop("backend"), id="backend-missing"),
])
def test_an_edited_config_json_is_refused_naming_the_file_and_the_fix(copy, capsys, edit):
    _edit_json(copy / "config.json", edit)
    for command in (["--resume", str(copy), "--total-timesteps", "5000", *EVAL_FAST], ["--eval-only", str(copy),
                                                                                      *EVAL_FAST]):
        assert train_command(command) == 2
        line = _one_error_line(capsys)
        assert line.startswith(f"error: {command[0]}: {copy / 'config.json'}: damaged (its sha256 differs") and \
            "restore the config.json the run wrote" in line and "--total-timesteps N" in line, line


@pytest.mark.parametrize("edit, says", [
    (lambda c: c.update(residual_scale=1e6), "--residual-scale: expected a value in (0, 1]"),
    (lambda c: c.update(residual_scale="0.3"), "residual_scale: expected a finite number, got '0.3'"),
    (lambda c: c.update(obs_features="squared"), "obs_features: expected one of none, log-error, invariant"),
    (lambda c: c.pop("backend"), "backend missing (every setting of the run is saved)"),
    (lambda c: c.update(n_envs=2.5), "n_envs: expected an integer, got 2.5"),
    (lambda c: c.update(residual_gate="yes"), "residual_gate: expected true or false"),
    (lambda c: c.update(total_timesteps=None), "total_timesteps: expected an integer, got None"),
    (lambda c: c.update(mode="flying"), "--mode"),
])
def test_each_saved_setting_is_checked_for_presence_type_and_range_naming_the_file(trained_run, edit, says):
    data = json.loads((trained_run / "config.json").read_text())
    edit(data)
    with pytest.raises(ValueError) as error:
        TrainConfig.from_saved(data, "runs/x/config.json")
    assert str(error.value).startswith("runs/x/config.json: ") and says in str(error.value), str(error.value)
    assert str(error.value).endswith("restore the config.json the run wrote (its sha256 is in the run's SHA256SUMS)")
    assert "\n" not in str(error.value)


def test_a_damaged_newest_checkpoint_is_passed_over_for_the_newest_intact_one_said_in_one_line(copy, capsys):
    shutil.rmtree(copy / "model")  # as if killed before the final model was saved
    (copy / "comparison.json").unlink()
    *_, older, newest = checkpoint.checkpoints(copy)
    policy = newest / "policy.pt"
    policy.write_bytes(policy.read_bytes()[: policy.stat().st_size // 2])  # truncated
    steps = json.loads((older / "state.json").read_text())["agent_steps"]
    budget = json.loads((newest / "state.json").read_text())["agent_steps"]  # beyond the older one: it trains
    assert train_command(["--resume", str(copy), "--total-timesteps", str(budget), *EVAL_FAST]) == 0
    captured = capsys.readouterr()
    notes = [line for line in captured.err.splitlines() if line.startswith("note: ")]
    assert notes == [f"note: {copy}: passed over, damaged: checkpoints/{newest.name}/policy.pt: damaged (its sha256 "
                     f"differs from the one written with it in checkpoints/{newest.name}/SHA256SUMS); resuming from "
                     f"checkpoints/{older.name} ({steps} agent steps), the newest intact checkpoint"]
    assert f"resuming {copy} from {older.name}" in captured.out
    assert (copy / "comparison.json").is_file()


@pytest.mark.parametrize("stray", ["step_abc", "step_12", "step_000000000099.bak"])
def test_a_stray_step_folder_is_refused_naming_it(copy, capsys, stray):
    (copy / "checkpoints" / stray).mkdir()
    assert train_command(["--resume", str(copy), "--total-timesteps", "5000", *EVAL_FAST]) == 2
    assert _one_error_line(capsys) == (f"error: {copy / 'checkpoints' / stray}: not a checkpoint of this run "
                                       f"(checkpoints are folders named step_000000000000, by agent steps): remove it")


def test_a_checkpoint_whose_state_does_not_match_its_name_is_passed_over(copy, capsys):
    newest = checkpoint.checkpoints(copy)[-1]
    planted = copy / "checkpoints" / checkpoint.checkpoint_name(999_999)
    shutil.copytree(newest, planted)  # another step count's checkpoint under a higher name
    (copy / "comparison.json").unlink()
    shutil.rmtree(copy / "model")
    assert train_command(["--resume", str(copy), *EVAL_FAST]) == 0
    (note,) = [line for line in capsys.readouterr().err.splitlines() if line.startswith("note: ")]
    assert f"checkpoints/{planted.name}/state.json: says " in note and f"resuming from checkpoints/{newest.name}" in note


@pytest.mark.parametrize("content, says", [("{not json", "not valid JSON"), ('{"segments": 5}', "a list of 'segments'"),
                                           ('{"segments": [{"monitor": "../x", "start_agent_steps": 0}]}',
                                            "segments[0].monitor")])
def test_a_corrupt_timing_json_is_refused_naming_it_and_the_fix(copy, capsys, content, says):
    (copy / "timing.json").write_text(content)
    assert train_command(["--resume", str(copy), "--total-timesteps", "5000", *EVAL_FAST]) == 2
    line = _one_error_line(capsys)
    assert line.startswith(f"error: {copy / 'timing.json'}: ") and says in line and "remove it" in line, line


def test_normalization_statistics_of_another_shape_or_missing_are_refused_not_broadcast(copy, tmp_path):
    from ee_formation_env.baselines.learned.sb3_backend import build_sb3_model

    newest = checkpoint.checkpoints(copy)[-1]
    config = TrainConfig.from_saved(json.loads((copy / "config.json").read_text()))
    model = build_sb3_model(config, None)
    try:
        for edit, says in ((lambda v: v.update(obs_mean=[0.0]), r"obs_mean: expected shape \(\d+,\) \(the run's "
                                                                 r"observation\), got \(1,\)"),
                           (lambda v: v.pop("obs_mean"), "obs_mean missing"),
                           (lambda v: v.update(obs_count="many"), "obs_count: expected a finite number")):
            folder = tmp_path / "checkpoint"
            shutil.rmtree(folder, ignore_errors=True)
            shutil.copytree(newest, folder)
            _edit_json(folder / "vecnormalize.json", edit)
            before = model.get_env().obs_rms.mean.copy()
            with pytest.raises(ValueError, match=rf"vecnormalize.json: {says}"):
                checkpoint.restore_checkpoint(folder, model)
            assert (model.get_env().obs_rms.mean == before).all()  # nothing loaded
    finally:
        model.get_env().close()


def test_an_evaluated_normalizer_of_another_length_is_refused_naming_it(copy, capsys):
    _edit_json(copy / "model" / "obs_normalizer.json", lambda n: n.update(mean=[0.0], var=[1.0]))
    _resign(copy / "model")  # past the checksums: the check behind them
    assert train_command(["--eval-only", str(copy), *EVAL_FAST]) == 2
    line = _one_error_line(capsys)
    assert f"{copy / 'model' / 'obs_normalizer.json'}: mean and var have shape (1,), the policy's observation" in line


def test_a_damaged_model_is_refused_by_the_evaluation_naming_the_file(copy, capsys):
    (copy / "model" / "policy.pt").write_bytes(b"")
    assert train_command(["--eval-only", str(copy), *EVAL_FAST]) == 2
    line = _one_error_line(capsys)
    assert line.startswith(f"error: --eval-only: {copy / 'model' / 'policy.pt'}: damaged") and "--resume RUN" in line


# ------------------------------------------------------------------------------------------ refused writes
def test_a_full_disk_at_a_checkpoint_is_one_line_naming_it_and_the_older_checkpoints_stay_intact(tmp_path, capsys,
                                                                                                 monkeypatch):
    import torch

    real_save, calls = torch.save, []

    def full_after_the_first_checkpoint(data, path, *args, **kwargs):
        calls.append(Path(path))
        if len([p for p in calls if p.name == "policy.pt"]) > 1:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return real_save(data, path, *args, **kwargs)

    monkeypatch.setattr(torch, "save", full_after_the_first_checkpoint)
    run_dir = tmp_path / "run"
    assert train_command(["--out", str(run_dir), *TINY]) == 1
    line = _one_error_line(capsys)
    (intact,) = checkpoint.checkpoints(run_dir)
    second = checkpoint.checkpoint_name(2 * int(intact.name.split("_")[1]))
    assert line.startswith(f"error: checkpoint: cannot write {run_dir / 'checkpoints' / second} (No space left on "
                           "device"), line
    assert line.endswith(f"the older checkpoints are intact (newest: {intact.name}): `python train.py --resume "
                         f"{run_dir}` continues from it once there is room"), line
    checkpoint.verify_checksums(intact, checkpoint.TRAINING_STATE_FILES, "intact")
    assert not [p for p in (run_dir / "checkpoints").iterdir() if p.name.startswith(".")]  # no partial write left
    monkeypatch.undo()
    assert train_command(["--resume", str(run_dir), *EVAL_FAST]) == 0  # room again: it continues


_SIZE_LIMITED = textwrap.dedent("""
    import resource, sys
    limit = int(sys.argv[1])
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    from ee_formation_env.baselines.cli import train_command
    if __name__ == "__main__":
        sys.exit(train_command(sys.argv[2:]))
""")


@pytest.mark.skipif(not hasattr(resource, "RLIMIT_FSIZE"), reason="file-size limits")
def test_a_file_size_limit_during_a_checkpoint_is_one_line_naming_it(tmp_path):
    """torch.save under the limit raises RuntimeError "enforce fail ... unexpected pos": named as a refused
    write. Nothing could be saved, so no run folder is left."""
    run_dir = tmp_path / "run"
    result = subprocess.run([sys.executable, "-c", _SIZE_LIMITED, str(64 * 1024), "--out", str(run_dir), *TINY],
                            cwd=tmp_path, capture_output=True, text=True, timeout=300,
                            env={**os.environ, "PYTHONPATH": str(REPO)})
    assert result.returncode == 1, result.stderr[-3000:]
    assert "Traceback" not in result.stderr, result.stderr[-3000:]
    (line,) = error_lines(result.stderr)
    assert line.startswith(f"error: checkpoint: cannot write {run_dir / 'checkpoints'}/step_") and \
        "a full disk or a file-size limit" in line, line
    assert "no checkpoint was saved before" in line and not run_dir.exists()


# ------------------------------------------------------------------------------------------ the budget
def test_resume_with_a_larger_budget_extends_a_finished_run_and_compares_it_again(copy, capsys):
    done = json.loads((copy / "timing.json").read_text())["agent_steps"]
    before = (copy / "comparison.json").stat().st_mtime_ns
    written_before = checkpoint.checkpoints(copy)
    assert train_command(["--resume", str(copy), "--total-timesteps", str(done + 256), *EVAL_FAST]) == 0
    timing = json.loads((copy / "timing.json").read_text())
    assert len(timing["segments"]) == 2 and timing["agent_steps"] >= done + 256
    assert (copy / "comparison.json").stat().st_mtime_ns != before
    config = json.loads((copy / "config.json").read_text())
    assert config["total_timesteps"] == done + 256
    # The stamps bind the settings less the budget: the checkpoints written before the new budget, and those
    # written after it, are all the run's own.
    written_after = [c for c in checkpoint.checkpoints(copy) if c not in written_before]
    assert written_after
    for folder in (*written_before, *written_after, copy / "model"):
        load_model(folder, config, "test")
    assert train_command(["--eval-only", str(copy), *EVAL_FAST]) == 0  # config.json's checksum follows the budget
    capsys.readouterr()
    assert train_command(["--resume", str(copy), "--total-timesteps", "10", *EVAL_FAST]) == 2
    assert _one_error_line(capsys) == (f"error: --total-timesteps: 10 is below the {timing['agent_steps']} agent "
                                       f"steps {copy} has done: a budget can only be lowered to the steps done, "
                                       "or raised")
    assert train_command(["--resume", str(copy), *EVAL_FAST]) == 2
    assert "--total-timesteps N (more than that) extends it" in _one_error_line(capsys)


# ------------------------------------------------------------------------------------------ --imitate's --out
def _exit_code(argv: list[str]) -> int:
    """train.py's exit code: its return value, or the parser's exit for a flag refused while parsing."""
    try:
        return train_command(argv)
    except SystemExit as stopped:
        return stopped.code


def test_imitate_refuses_its_own_out_before_anything_is_removed(copy, capsys):
    assert _exit_code(["--imitate", str(copy), "--out", str(copy), "--overwrite", *TINY]) == 2
    assert "--imitate:" in capsys.readouterr().err and (copy / "model" / "policy.pt").is_file()
    assert _exit_code(["--imitate", str(copy), "--out", str(copy / "inner"), *TINY]) == 2
    assert "holds it" in capsys.readouterr().err and not (copy / "inner").exists()
