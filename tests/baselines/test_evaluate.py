"""The ``python -m ee_formation_env.baselines.evaluate`` command line: table, --policy all, bad arguments, --help, --video."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from ee_formation_env.baselines import POLICIES
from ee_formation_env.baselines.evaluate import main
from ee_formation_env.baselines.metrics import METRIC_COLUMNS, metric_definitions

SHORT = ["--episodes", "1", "--set", "episode_seconds=0.3"]
RESULTS_PAGE = Path(__file__).resolve().parents[2] / "docs" / "results.md"  # where the metrics are defined for readers


def _table_rows(output: str) -> dict[str, list[str]]:
    rows = {}
    for line in output.splitlines():
        cells = [cell.strip() for cell in line.strip("|").split("|")]
        if line.startswith("| ") and cells[0] != "policy":
            rows[cells[0]] = cells[1:]
    return rows


def test_table_has_one_row_per_policy_and_every_column_with_its_unit(capsys, tmp_path):
    assert main(["--policy", "gradient", *SHORT, "--json", str(tmp_path / "r.json")]) == 0
    output = capsys.readouterr().out
    header = next(line for line in output.splitlines() if line.startswith("| policy"))
    assert header == "| policy | " + " | ".join(c.header for c in METRIC_COLUMNS) + " |"
    assert "energy (N² m² s)" in header and "drift (m)" in header
    rows = _table_rows(output)
    assert list(rows) == ["gradient"] and len(rows["gradient"]) == len(METRIC_COLUMNS)
    saved = json.loads((tmp_path / "r.json").read_text())
    assert saved["episodes"] == 1 and saved["overrides"] == {"episode_seconds": 0.3}
    assert len(saved["results"]["gradient"]["per_episode"]) == 1


def test_policy_all_evaluates_every_policy(capsys):
    assert main(["--policy", "all", *SHORT]) == 0
    assert list(_table_rows(capsys.readouterr().out)) == list(POLICIES)


@pytest.mark.parametrize("argv, message", [
    (["--episodes", "0"], "--episodes"),
    (["--policy", "no_such_policy"], "unknown policy 'no_such_policy'"),
    (["--set", "frame_skip"], "KEY=VALUE"),
    (["--set", "no_such_key=1"], "no_such_key"),
    (["--scenario", "no_such_scenario"], "no_such_scenario"),
    (["--episodes", "two"], "invalid int value"),
])
def test_bad_arguments_give_a_clear_usage_error(capsys, argv, message):
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    error = capsys.readouterr().err
    assert "usage:" in error and message in error


def test_help_defines_every_column(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    for column in METRIC_COLUMNS:
        assert column.header in help_text
        assert " ".join(column.meaning.split()) in help_text


def test_results_page_shows_the_column_definitions():
    assert metric_definitions(markdown=True) in RESULTS_PAGE.read_text(encoding="utf-8")


def test_video_writes_one_file_per_episode_at_simulated_speed(tmp_path):
    imageio = pytest.importorskip("imageio")
    videos = tmp_path / "videos"
    assert main(["--policy", "zero", "--episodes", "2", "--set", "episode_seconds=0.5", "--video", str(videos)]) == 0
    files = sorted(videos.iterdir())
    assert [f.stem for f in files] == ["planar_square-zero-seed0", "planar_square-zero-seed1"]
    frames = imageio.mimread(files[0], memtest=False)
    # 50 env steps at 100 Hz, one frame every 3 steps (33.3 frames/s) plus the frame after the reset.
    assert len(frames) == 17
    assert frames[0].shape[0] >= 360 and frames[0].shape[1] >= 480 and frames[0].shape[2] == 3
    assert frames[0].std() > 0  # not blank


def test_faulted_episodes_are_counted_and_explained_under_the_table(capsys):
    """Torque limits far beyond what the arms take: every random episode ends in a joint-speed fault."""
    assert main(["--policy", "random", "--episodes", "2", "--set", "episode_seconds=0.3", "torque_limits=100000"]) == 0
    output = capsys.readouterr().out
    faults_column = [c.key for c in METRIC_COLUMNS].index("physics_faults")
    assert _table_rows(output)["random"][faults_column] == "2"
    note = next(line for line in output.splitlines() if line.startswith("- random:"))
    assert note.startswith("- random: 2 of 2 episodes ended in a physics fault: arm_")
    assert "joint speed" in note and "exceeds max_joint_velocity" in note


def test_progress_shows_each_round_as_it_starts_and_each_episode_on_stderr_unless_quiet(capsys, monkeypatch):
    import ee_formation_env.baselines.evaluate as evaluate

    monkeypatch.setattr(evaluate, "DEFAULT_EVALUATION_COPIES", 2)  # rounds of two episodes
    assert main(["--policy", "zero", "--episodes", "3", "--set", "episode_seconds=0.05"]) == 0
    err = capsys.readouterr().err.splitlines()
    assert err[0] == "  zero: running episodes 1-2/3 together ..."
    assert err[1].startswith("  zero: episode 1/3 (seed 0) ") and err[2].startswith("  zero: episode 2/3 (seed 1) ")
    assert err[3] == "  zero: running episodes 3-3/3 together ..." and err[4].startswith("  zero: episode 3/3 (seed 2)")
    assert main(["--policy", "zero", "--episodes", "3", "--set", "episode_seconds=0.05", "--quiet"]) == 0
    assert capsys.readouterr().err == ""


def test_rounds_give_the_metrics_of_one_batched_call(monkeypatch):
    import ee_formation_env.baselines.evaluate as evaluate
    from ee_formation_env.baselines.metrics import run_episodes

    overrides = {"episode_seconds": 0.05}
    monkeypatch.setattr(evaluate, "DEFAULT_EVALUATION_COPIES", 2)
    rounds = evaluate.evaluate_policy("planar_square", "gradient", 3, 5, overrides=overrides)["per_episode"]
    together = [m.as_dict() for m in run_episodes("planar_square", "gradient", [5, 6, 7], overrides=overrides)]
    assert rounds == together
