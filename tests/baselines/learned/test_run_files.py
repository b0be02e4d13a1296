"""Every path that reads a run opens it through one loader: the folder's marker, config.json's sha256, the model's
files and its stamp (bound to config.json's digest, its config-decided fields and the model's own sizes), each
fault refused alike in one line naming the file, before anything is evaluated or trained."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

pytest.importorskip("stable_baselines3")

from trainer_processes import EVAL_FAST, TINY  # noqa: E402

from ee_formation_env.baselines.cli import train_command  # noqa: E402
from ee_formation_env.baselines.learned import checkpoint, run_files  # noqa: E402
from ee_formation_env.baselines.learned.policy import SavedRun, load_model, open_run  # noqa: E402
from ee_formation_env.baselines.learned.run_folder import MARKER  # noqa: E402
from ee_formation_env.baselines.learned.saved_run import resume_checkpoint, write_saved_config  # noqa: E402


@pytest.fixture(scope="module")
def residual_run(tmp_path_factory) -> Path:
    """One tiny residual-mode run (its final model and checkpoints stamped), copied per case."""
    run_dir = tmp_path_factory.mktemp("stamped") / "run"
    assert train_command(["--out", str(run_dir), *TINY, "--mode", "residual"]) == 0
    return run_dir


@pytest.fixture
def copy(residual_run, tmp_path) -> Path:
    target = tmp_path / "run"
    shutil.copytree(residual_run, target)
    return target


def _config(run_dir: Path) -> dict:
    return json.loads((run_dir / "config.json").read_text())


def _model_folders(run_dir: Path) -> list[Path]:
    """Every model folder of a run: what each path reads (the final model, the checkpoints --resume reads)."""
    return [run_dir / "model", *checkpoint.checkpoints(run_dir)]


def _resign(folder: Path) -> None:
    """Rewrite ``folder``'s SHA256SUMS over the files it lists, as they are now (what a forger, or a careless
    script, would do), so that the checks behind the checksums are reached."""
    checkpoint.write_checksums(folder, sorted(checkpoint.read_checksums(folder)))


def _edit_json(path: Path, edit) -> None:
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


# ------------------------------------------------------------------------------------------ the stamp
def test_every_model_folder_holds_a_stamp_of_its_run_covered_by_its_checksums(residual_run):
    config = _config(residual_run)
    for folder in _model_folders(residual_run):
        stamp = json.loads((folder / run_files.STAMP).read_text())
        assert checkpoint.read_checksums(folder)[run_files.STAMP] == checkpoint.sha256(folder / run_files.STAMP)
        assert stamp == run_files.model_stamp(config, 19, 2), folder  # planar_square: 19 entries, 2 joints
        assert stamp["engine"] == "pybullet" and stamp["mode"] == "residual" and stamp["backend"] == "sb3"
        assert stamp["action"]["residual"]["reference"] == config["reference"]
        model = load_model(folder, config, "test")
        assert (model.observation_size, model.action_size) == (stamp["observation_size"], stamp["action_size"])


def test_the_config_digest_leaves_the_budget_out_and_nothing_else(residual_run):
    from ee_formation_env.baselines.learned.config import TrainConfig

    assert run_files.BUDGET_FIELDS == TrainConfig.RESUME_FIELDS  # what --resume may rewrite in config.json
    config = _config(residual_run)
    digest = run_files.config_digest(config)
    assert run_files.config_digest({**config, "total_timesteps": config["total_timesteps"] + 1000}) == digest
    assert run_files.config_digest({**config, "seed": config["seed"] + 1}) != digest
    assert run_files.config_digest(dict(reversed(list(config.items())))) == digest  # key order is not content


@pytest.mark.parametrize("field, value, says", [
    ("mode", "torque", "stamp.json: mode: the stamp says 'torque', config.json 'residual'"),
    ("obs_features", "log-error", "stamp.json: obs_features: the stamp says 'log-error', config.json 'none'"),
    ("engine", "mujoco", "stamp.json: engine: the stamp says 'mujoco', config.json 'pybullet'"),
    ("action", None, "stamp.json: action: the stamp says None"),
    ("action_size", 3, "stamp.json: action_size: the stamp says 3, the model has 2 (its normalizer and actor)"),
    ("format", 0, "stamp.json: format: expected a stamp of format 1"),
])
def test_each_field_of_the_stamp_is_checked_behind_its_digest_naming_it(copy, field, value, says):
    """A stamp edited and re-signed, its digest still the config's: each field is checked all the same."""
    _edit_json(copy / "model" / run_files.STAMP, lambda s: s.update({field: value}))
    _resign(copy / "model")
    with pytest.raises(ValueError) as refused:
        open_run(copy, "--policy")
    assert str(refused.value).startswith(f"--policy: {copy / 'model'}/") and says in str(refused.value), refused.value


def test_an_intact_run_opens_on_every_path(copy):
    config = open_run(copy, "--policy")
    assert config == _config(copy) and SavedRun.load(copy, "run").config == config
    steps, folder = resume_checkpoint(copy, config)
    assert folder == copy / "model" and steps == json.loads((folder / "state.json").read_text())["agent_steps"]


# ------------------------------------------------------------------------------------------ every load path
def _edit_config(run_dir: Path) -> None:
    _edit_json(run_dir / "config.json", lambda c: c.update(gamma=0.5))


def _edit_and_resign_config(run_dir: Path) -> None:
    _edit_config(run_dir)
    checkpoint.write_checksums(run_dir, ["config.json"])


def _torque_into_residual(run_dir: Path) -> None:
    """Same sizes, other meaning: without the stamp the residual model would act as torques unnoticed."""
    _edit_json(run_dir / "config.json", lambda c: c.update(mode="torque"))
    checkpoint.write_checksums(run_dir, ["config.json"])


def _remove_marker(run_dir: Path) -> None:
    (run_dir / MARKER).unlink()


def _remove_checksums(run_dir: Path) -> None:
    (run_dir / checkpoint.CHECKSUMS).unlink()


def _other_runs_config(run_dir: Path) -> None:
    """config.json and SHA256SUMS of another run (the same command with another seed), copied in together."""
    other = run_dir.parent / "other"
    other.mkdir()
    write_saved_config(other, {**_config(run_dir), "seed": _config(run_dir)["seed"] + 1})
    for name in ("config.json", checkpoint.CHECKSUMS):
        shutil.copy2(other / name, run_dir / name)


def _truncate_model(run_dir: Path) -> None:
    for folder in _model_folders(run_dir):
        path = folder / "policy.pt"
        path.write_bytes(path.read_bytes()[:100])


def _truncate_and_resign_model(run_dir: Path) -> None:
    """A truncated policy.pt that its SHA256SUMS vouches for: torch itself meets the damage."""
    _truncate_model(run_dir)
    for folder in _model_folders(run_dir):
        _resign(folder)


def _remove_stamp(run_dir: Path) -> None:
    for folder in _model_folders(run_dir):
        (folder / run_files.STAMP).unlink()


def _wrong_stamp_size(run_dir: Path) -> None:
    for folder in _model_folders(run_dir):
        _edit_json(folder / run_files.STAMP, lambda s: s.update(observation_size=s["observation_size"] + 3))
        _resign(folder)


#: corruption -> (what it does, what every refusal says: the file, relative to the run folder, and the fault)
CORRUPTIONS = {
    "config.json edited": (_edit_config, "config.json: damaged (its sha256 differs"),
    "config.json edited and re-signed": (_edit_and_resign_config, "model/stamp.json: config_digest: the model was "
                                         "trained with another configuration"),
    "mode torque written into a residual run, re-signed": (_torque_into_residual, "model/stamp.json: config_digest"),
    "marker removed": (_remove_marker, f"has no {MARKER}: not a run folder train.py wrote"),
    "SHA256SUMS removed": (_remove_checksums, "SHA256SUMS: not found"),
    "another run's config.json and SHA256SUMS": (_other_runs_config, "model/stamp.json: config_digest"),
    "model file truncated": (_truncate_model, "model/policy.pt: damaged (its sha256 differs"),
    "model file truncated and re-signed": (_truncate_and_resign_model, "model/policy.pt holds no plain tensor state"),
    "stamp removed": (_remove_stamp, "model/stamp.json: not found"),
    "stamp with a wrong observation size, re-signed": (_wrong_stamp_size, "model/stamp.json: observation_size: the "
                                                       "stamp says 22, the model has 19"),
}


def _refusal(text: str, flag: str, prog: str = "") -> str:
    """The one refusal line of a command's stderr: ``[<prog>: ]error: <flag>: ...``, no traceback (notes aside,
    and the usage lines argparse writes before a refusal of ``ee-formation evaluate``)."""
    lines = [line for line in text.splitlines() if line.strip() and not line.startswith(("note: ", "usage: ", " "))]
    assert len(lines) == 1 and "Traceback" not in text, text
    assert lines[0].startswith(f"{prog}error: {flag}: "), lines[0]
    return lines[0]


def _exit_code(argv: list[str]) -> int:
    """train.py's exit code: its return value, or the parser's exit for a flag refused while parsing."""
    try:
        return train_command(argv)
    except SystemExit as stopped:
        return stopped.code


def _evaluate(run_dir: Path, tmp_path: Path, capsys) -> str:
    from ee_formation_env.baselines.evaluate import main

    with pytest.raises(SystemExit) as stopped:
        main(["--policy", str(run_dir), "--episodes", "1", "--set", "episode_seconds=0.2"], prog="ee-formation evaluate")
    captured = capsys.readouterr()
    assert stopped.value.code == 2 and "| policy |" not in captured.out  # nothing was evaluated
    return _refusal(captured.err, "--policy", "ee-formation evaluate: ")


def _eval_only(run_dir: Path, tmp_path: Path, capsys) -> str:
    assert train_command(["--eval-only", str(run_dir), *EVAL_FAST]) == 2
    assert not (run_dir / "evaluations").exists()
    return _refusal(capsys.readouterr().err, "--eval-only")


def _resume(run_dir: Path, tmp_path: Path, capsys) -> str:
    assert train_command(["--resume", str(run_dir), "--total-timesteps", "5000", *EVAL_FAST]) == 2
    return _refusal(capsys.readouterr().err, "--resume")


def _imitate(run_dir: Path, tmp_path: Path, capsys) -> str:
    assert _exit_code(["--imitate", str(run_dir), "--out", str(tmp_path / "copy"), *TINY]) == 2
    assert not (tmp_path / "copy").exists()
    return _refusal(capsys.readouterr().err, "--imitate", "train.py: ")  # refused while the flags are read


def _board_cell(run_dir: Path, tmp_path: Path, capsys) -> str:
    """A scoreboard test cell of a learned method evaluates its run through SavedRun.load."""
    from studies.scoreboard_methods import METHODS, _saved_run_metrics

    with pytest.raises(ValueError) as refused:
        _saved_run_metrics(run_dir, METHODS["residual-ppo"], "planar_square", [10_000], 0.2)
    assert "\n" not in str(refused.value) and str(refused.value).startswith("residual-ppo run: ")
    return f"error: {refused.value}"


LOAD_PATHS = [_evaluate, _eval_only, _resume, _imitate, _board_cell]


def _files(run_dir: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(run_dir)): (p.stat().st_size, p.stat().st_mtime_ns) for p in run_dir.rglob("*")
            if p.is_file()}


@pytest.mark.parametrize("corruption", list(CORRUPTIONS))
@pytest.mark.parametrize("load", LOAD_PATHS, ids=lambda f: f.__name__[1:])
def test_every_path_that_reads_a_run_refuses_every_corruption_alike(copy, tmp_path, capsys, load, corruption):
    corrupt, says = CORRUPTIONS[corruption]
    corrupt(copy)
    before = _files(copy)
    capsys.readouterr()
    line = load(copy, tmp_path, capsys)
    assert str(copy) in line and says in line, line  # the file, in the run's folder
    assert _files(copy) == before  # nothing evaluated, trained or rewritten
