"""Runs you can trust: loading runs no code, checkpoint writes are atomic, nothing is silently reused.

Signals, kills and worker faults of real trainer processes: test_run_processes.py; the run folder (refusals,
--overwrite, the lock): test_run_folder.py; a saved run's files checked before use: test_saved_run.py."""

from __future__ import annotations

import json
import pickle
import shutil
from pathlib import Path

import pytest

pytest.importorskip("stable_baselines3")

from trainer_processes import EVAL_FAST, FAST  # noqa: E402

from ee_formation_env.baselines.cli import train_command  # noqa: E402
from ee_formation_env.baselines.learned import checkpoint  # noqa: E402


class Payload:
    """Unpickling this writes a marker file: proof that a loader executed code from a run folder."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("safety") / "run"
    assert train_command(["--total-timesteps", "400", "--mode", "torque", "--out", str(run_dir), *FAST]) == 0
    return run_dir


def _plant(path: Path, marker: Path) -> None:
    if path.suffix == ".pt":  # a torch file whose tensors come with an object
        import torch

        torch.save({"weight": Payload(marker)}, path)
    else:
        path.write_bytes(pickle.dumps(Payload(marker)))


def test_a_payload_planted_in_any_file_of_a_run_never_runs(trained_run, tmp_path, capsys):
    files = sorted(path.relative_to(trained_run) for path in trained_run.rglob("*") if path.is_file()
                   and "tensorboard" not in path.parts)
    assert {Path("model/policy.pt"), Path("model/obs_normalizer.json"), Path("config.json"), Path("model.zip")} <= set(
        files)
    for relative in files:
        copy = tmp_path / f"run-{len(list(tmp_path.iterdir()))}"
        shutil.copytree(trained_run, copy)
        marker = tmp_path / f"ran-{relative.name}"
        _plant(copy / relative, marker)
        status = train_command(["--eval-only", str(copy), *EVAL_FAST])
        assert not marker.exists(), f"a payload in {relative} ran"
        error = capsys.readouterr().err
        if status != 0:  # a file evaluation needs: refused with an error naming it
            assert status == 2 and relative.name in error, (relative, error)
        shutil.rmtree(copy)


def test_checkpoints_load_only_plain_tensors(trained_run, tmp_path):
    (newest,) = checkpoint.checkpoints(trained_run)[-1:]
    marker = tmp_path / "ran"
    copy = tmp_path / "checkpoint"
    shutil.copytree(newest, copy)
    _plant(copy / "optimizer.pt", marker)
    with pytest.raises(ValueError, match="optimizer.pt"):
        checkpoint.load_tensors(copy / "optimizer.pt", "optimizer.pt")
    assert not marker.exists()


def test_an_interrupted_checkpoint_write_leaves_no_checkpoint_under_its_name(trained_run, tmp_path, monkeypatch):
    from ee_formation_env.baselines.learned.config import TrainConfig
    from ee_formation_env.baselines.learned.sb3_backend import build_sb3_model

    model = build_sb3_model(TrainConfig.from_args(["--mode", "torque", *FAST]), None)
    try:
        target = tmp_path / "checkpoints" / checkpoint.checkpoint_name(0)
        calls = []

        def full_disk(data, path):
            calls.append(path)
            if len(calls) == 2:
                raise OSError(28, "No space left on device")
            return real_save(data, path)

        import torch

        real_save = torch.save
        monkeypatch.setattr(torch, "save", full_disk)
        with pytest.raises(OSError, match="No space"):
            checkpoint.save_checkpoint(target, model, "ppo", {"net_arch": [8]}, 100)
        assert not target.exists() and list((tmp_path / "checkpoints").iterdir()) == []
        monkeypatch.setattr(torch, "save", real_save)
        checkpoint.save_checkpoint(target, model, "ppo", {"net_arch": [8]}, 100)
        assert (target / "state.json").is_file() and checkpoint.checkpoints(tmp_path) == [target]
    finally:
        model.get_env().close()


def test_an_existing_run_folder_is_never_reused_silently(trained_run, tmp_path, capsys):
    run_dir = tmp_path / "run"
    shutil.copytree(trained_run, run_dir)
    before = (run_dir / "config.json").read_text()
    assert train_command(["--total-timesteps", "300", "--out", str(run_dir), "--seed", "5", *FAST]) == 2
    assert "--resume" in capsys.readouterr().err and (run_dir / "config.json").read_text() == before
    # --overwrite replaces it only once the new configuration validates
    assert train_command(["--total-timesteps", "300", "--out", str(run_dir), "--overwrite", "--scenario", "nope",
                          *FAST]) == 2
    assert (run_dir / "config.json").read_text() == before
    assert train_command(["--total-timesteps", "300", "--out", str(run_dir), "--overwrite", "--seed", "5",
                          *FAST]) == 0
    assert json.loads((run_dir / "config.json").read_text())["seed"] == 5
    assert not (run_dir / "evaluations").exists()


def test_no_run_folder_before_the_scenario_validates(tmp_path, capsys):
    unreachable = {"arms": [{"robot": "planar_2link", "base_position": [6.0 * k, 0, 0], "initial_q": [0.3, 1.0]}
                            for k in range(3)], "edges": [[0, 1], [1, 2], [0, 2]],
                   "shape": [[0, 0], [40, 0], [0, 40]], "dim": 2}
    path = tmp_path / "far.json"
    path.write_text(json.dumps(unreachable))
    assert train_command(["--scenario", str(path), "--out", str(tmp_path / "run"), *FAST]) == 2
    assert capsys.readouterr().err.startswith("error: ")
    assert not (tmp_path / "run").exists()


def test_eval_only_uses_the_saved_scenario_and_keeps_the_originals(tmp_path):
    scenario = tmp_path / "square.json"
    from ee_formation_env.builtin import builtin_scenario

    scenario.write_text(json.dumps(builtin_scenario("planar_square")))
    run_dir = tmp_path / "run"
    assert train_command(["--scenario", str(scenario), "--total-timesteps", "300", "--out", str(run_dir),
                          *FAST]) == 0
    original = (run_dir / "comparison.json").read_text()
    edited = builtin_scenario("planar_square")
    edited["shape"] = [[2.0, 2.0], [4.5, 2.0], [4.5, 4.5], [2.0, 4.5]]  # the file changes after training
    scenario.write_text(json.dumps(edited))
    assert train_command(["--eval-only", str(run_dir), *EVAL_FAST]) == 0
    (evaluation,) = (run_dir / "evaluations").iterdir()
    again = json.loads((evaluation / "comparison.json").read_text())
    assert again["results"]["learned"]["per_episode"] == json.loads(original)["results"]["learned"]["per_episode"]
    assert (run_dir / "comparison.json").read_text() == original


def test_resume_refuses_what_it_cannot_continue(trained_run, tmp_path, capsys):
    with pytest.raises(SystemExit):
        train_command(["--resume", str(trained_run), "--seed", "9"])
    assert "--seed" in capsys.readouterr().err
    assert train_command(["--resume", str(trained_run), *EVAL_FAST]) == 2  # complete: nothing to continue
    assert "complete" in capsys.readouterr().err
    assert train_command(["--resume", str(tmp_path / "nothing")]) == 2
    assert "not found" in capsys.readouterr().err


def test_a_kill_after_the_final_checkpoint_leaves_a_run_that_resume_finishes(trained_run, tmp_path, capsys):
    """Killed between the final model and the segment's end: the segment still ``running``, no learning curve,
    no comparison. ``--resume`` ends the segment as killed, draws the curve and compares, training nothing."""
    from ee_formation_env.baselines.learned.segments import KILLED

    run_dir = tmp_path / "run"
    shutil.copytree(trained_run, run_dir)
    for name in ("learning_curve.csv", "comparison.json", "comparison.md", "comparison.png"):
        (run_dir / name).unlink(missing_ok=True)
    timing = json.loads((run_dir / "timing.json").read_text())
    steps = timing["segments"][-1]["agent_steps"]
    timing["segments"][-1].update(running=True, agent_steps=0)  # its last write before the final model
    (run_dir / "timing.json").write_text(json.dumps(timing))
    capsys.readouterr()
    assert train_command(["--resume", str(run_dir), *EVAL_FAST]) == 0
    assert "training is complete" in capsys.readouterr().out
    (segment,) = json.loads((run_dir / "timing.json").read_text())["segments"]
    assert not segment["running"] and segment["interrupted"] == KILLED and segment["agent_steps"] == steps
    assert (run_dir / "learning_curve.csv").read_text() == (trained_run / "learning_curve.csv").read_text()
    assert (run_dir / "comparison.json").is_file()


# ------------------------------------------------------------------------------------------ resuming
RESUMABLE = ["--mode", "torque", "--n-envs", "1", "--n-workers", "0", "--n-steps", "16", "--train-episode-seconds",
             "0.5", "--total-timesteps", "256"]


def _interrupted_at(agent_steps: int, monkeypatch) -> None:
    """A stop request (as a SIGINT sets it) at the first step from ``agent_steps`` on, instead of a signal, whose
    moment depends on timing."""
    from ee_formation_env.baselines.learned import sb3_backend

    stop_callback = sb3_backend._stop_callback

    def stopping(stop):
        from stable_baselines3.common.callbacks import BaseCallback, CallbackList

        class StopAt(BaseCallback):
            def _on_step(self) -> bool:
                if self.model.num_timesteps >= agent_steps and not stop.requested:
                    stop.signal_name = "SIGINT"
                return True

        return CallbackList([StopAt(), stop_callback(stop)])

    monkeypatch.setattr(sb3_backend, "_stop_callback", stopping)


def _parameters(run_dir: Path):
    import torch

    state = torch.load(run_dir / "model" / "policy.pt", weights_only=True)
    return torch.cat([value.flatten().double() for value in state.values()])


def test_a_run_interrupted_at_the_same_step_and_resumed_ends_the_same_every_time(tmp_path, monkeypatch):
    """docs/training.md ("--resume"): with --n-workers 0, the same interruption step gives the same resumed run,
    bit for bit; it finishes its budget in whole rollouts from that step, with finite parameters."""
    import torch

    ends = []
    for name in ("first", "second"):
        run_dir = tmp_path / name
        with monkeypatch.context() as patch:
            _interrupted_at(100, patch)
            assert train_command(["--out", str(run_dir), *RESUMABLE, *EVAL_FAST]) == 130
        assert json.loads((run_dir / "model" / "state.json").read_text())["agent_steps"] == 100
        assert train_command(["--resume", str(run_dir), *EVAL_FAST]) == 0
        ends.append((_parameters(run_dir), json.loads((run_dir / "timing.json").read_text())["agent_steps"]))
    (first, first_steps), (second, second_steps) = ends
    assert torch.equal(first, second) and torch.isfinite(first).all()
    assert first_steps == second_steps == 100 + 3 * 64  # 156 steps left: three whole rollouts of 16 x 4 slots
