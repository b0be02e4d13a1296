"""The ``python -m ee_formation_env.baselines.evaluate`` command line: table, --policy all, bad arguments, --help,
--video, and a train.py run folder as the policy."""

from __future__ import annotations

import json
import resource
import subprocess
import sys
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
    (["--episodes", "0"], "--episodes: expected an integer >= 1, got 0"),
    (["--episodes", "-3"], "--episodes: expected an integer >= 1, got -3"),
    (["--seed", "-1"], "--seed: expected an integer >= 0, got -1"),
    (["--tolerance", "nan"], "--tolerance: expected an edge accuracy > 0 m"),
    (["--policy", "no_such_policy"],
     f"--policy: unknown policy 'no_such_policy'; available: {list(POLICIES)}, 'all', a train.py run folder"),
    (["--set", "frame_skip"], "KEY=VALUE"),
    (["--set", "no_such_key=1"], "no_such_key"),
    (["--scenario", "no_such_scenario"], "no_such_scenario"),
    (["--episodes", "two"], "invalid int value"),
    # A law on a gravity-compensated scenario would be refused as its first episode starts: refused up front.
    (["--policy", "all", "--set", "gravity_compensation=true"], "gradient sends the paper's raw joint torques"),
])
def test_bad_arguments_are_refused_in_one_line_before_any_episode_or_file(capsys, argv, message, monkeypatch, tmp_path):
    import ee_formation_env.baselines.evaluate as evaluate

    monkeypatch.setattr(evaluate, "run_episodes", lambda *args, **kwargs: pytest.fail("an episode ran"))
    with pytest.raises(SystemExit) as exit_info:
        main([*argv, "--json", str(tmp_path / "results.json")])
    assert exit_info.value.code == 2
    error = capsys.readouterr().err
    assert "usage:" in error and message in error
    assert len([line for line in error.splitlines() if "error:" in line]) == 1
    assert not (tmp_path / "results.json").exists()


def test_json_into_a_folder_is_refused_naming_json_before_any_episode(capsys, monkeypatch, tmp_path):
    """``--json DIR`` used to run every episode and then fail with a traceback opening the folder."""
    import ee_formation_env.baselines.evaluate as evaluate

    monkeypatch.setattr(evaluate, "run_episodes", lambda *args, **kwargs: pytest.fail("an episode ran"))
    with pytest.raises(SystemExit) as exit_info:
        main(["--policy", "zero", "--json", str(tmp_path)])
    assert exit_info.value.code == 2
    assert f"error: --json: {tmp_path} is a folder; expected the path of a file to write" in capsys.readouterr().err


def test_json_that_cannot_be_written_is_refused_naming_json_and_leaves_no_file(capsys, tmp_path):
    """An unwritable target is found by opening it (permission bits do not stop root; a read-only file system
    does), not by running every episode first."""
    import os

    if os.geteuid() != 0:  # a folder without write permission
        locked = tmp_path / "locked"
        locked.mkdir()
        locked.chmod(0o500)
        target = locked / "results.json"
    elif Path("/proc/self").is_dir():  # /proc takes no new files, even from root
        target = Path("/proc/ee-formation-results.json")
    else:
        pytest.skip("no folder this process cannot write into")
    with pytest.raises(SystemExit):
        main(["--policy", "zero", "--json", str(target)])
    assert f"error: --json: {target} cannot be written" in capsys.readouterr().err
    assert not target.exists()


def test_json_next_to_an_existing_file_keeps_it_until_the_results_are_written(tmp_path):
    """The writability probe opens an existing file for appending: a refused run leaves its content as it was."""
    target = tmp_path / "results.json"
    target.write_text("earlier results")
    with pytest.raises(SystemExit):
        main(["--policy", "zero", "--scenario", "no_such_scenario", "--json", str(target)])  # refused after the probe
    assert target.read_text() == "earlier results"


_SIZE_LIMITED = """
import resource, sys
resource.setrlimit(resource.RLIMIT_FSIZE, (200, 200))
from ee_formation_env.baselines.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.skipif(not hasattr(resource, "RLIMIT_FSIZE"), reason="file-size limits")
def test_json_over_a_file_size_limit_is_one_line_naming_it_and_keeps_the_earlier_file(tmp_path):
    """The probe passes (appending nothing); the results, written whole or not at all, exceed the limit."""
    target = tmp_path / "results.json"
    target.write_text("earlier results")
    result = subprocess.run([sys.executable, "-c", _SIZE_LIMITED, "evaluate", "--policy", "zero", "--quiet", *SHORT,
                             "--json", str(target)], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr[-3000:]
    assert result.stderr.splitlines() == [f"error: cannot write {target} (file too large: over this process's "
                                          "file-size limit (ulimit -f): raise it)"]
    assert target.read_text() == "earlier results" and sorted(p.name for p in tmp_path.iterdir()) == ["results.json"]


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


# ------------------------------------------------------------------------------------ a train.py run as the policy
RUN_EVALUATION = ["--episodes", "2", "--seed", "10000", "--set", "episode_seconds=0.3", "--quiet"]


@pytest.fixture(scope="module")
def gravity_compensated_run(tmp_path_factory):
    """A tiny torque run on the spatial arms (whose g(q) is not 0), trained with gravity_compensation and the
    torque preset's log-error features: what evaluating it must apply again (the env adding g(q), the
    features, the normalization)."""
    pytest.importorskip("stable_baselines3")
    from ee_formation_env.baselines.cli import train_command

    run_dir = tmp_path_factory.mktemp("runs") / "torque-gc"
    assert train_command(["--scenario", "spatial_tetrahedron", "--total-timesteps", "300", "--mode", "torque",
                          "--gravity-compensation",
                          "--out", str(run_dir), "--n-envs", "1", "--n-workers", "0",
                          "--train-episode-seconds", "0.5", "--eval-episodes", "2", "--eval-seconds", "0.3",
                          "--no-progress", "--eval-workers", "0"]) == 0
    return run_dir


def _same(a, b) -> bool:
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)  # NaN equal to NaN, as in the files


def test_a_run_folder_is_evaluated_with_its_own_env_settings_as_its_comparison_is(gravity_compensated_run, tmp_path,
                                                                                   capsys):
    from ee_formation_env.baselines.learned.policy import SavedRun
    from ee_formation_env.baselines.metrics import run_episodes

    out = tmp_path / "evaluation.json"
    assert main(["--policy", str(gravity_compensated_run), *RUN_EVALUATION, "--json", str(out)]) == 0
    assert "| learned (torque) |" in capsys.readouterr().out
    evaluated = json.loads(out.read_text())
    comparison = json.loads((gravity_compensated_run / "comparison.json").read_text())
    assert evaluated["scenario"] == "spatial_tetrahedron" and evaluated["learned_label"] == comparison["learned_label"]
    assert evaluated["overrides"] == {"episode_seconds": 0.3, "gravity_compensation": True}
    assert _same(evaluated["results"]["learned"], comparison["results"]["learned"])  # same seeds, same metrics
    # Without the run's action convention the same policy does something else: the setting is what matters.
    run = SavedRun.load(gravity_compensated_run)
    raw = run_episodes(run.scenario, run.policy_source(), [10_000, 10_001], overrides={"episode_seconds": 0.3})
    assert not _same([m.as_dict() for m in raw], comparison["results"]["learned"]["per_episode"])


def test_a_run_folder_is_refused_a_team_of_other_sizes_in_one_line_before_any_episode(gravity_compensated_run,
                                                                                      capsys, tmp_path):
    with pytest.raises(SystemExit):
        main(["--policy", str(gravity_compensated_run), "--scenario", "planar_square",
              "--json", str(tmp_path / "r.json")])
    error = capsys.readouterr().err
    assert ("error: policy: the run's policy takes 59 observation entries and gives 7 joint actions "
            "(obs_features log-error); arm_0 of scenario planar_square has 30 and 2: it cannot act for this team"
            ) in error
    assert not (tmp_path / "r.json").exists()


def test_a_run_folder_runs_on_another_scenario_of_the_same_sizes(gravity_compensated_run, capsys):
    assert main(["--policy", str(gravity_compensated_run), "--scenario", "spatial_random", "--episodes", "1",
                 "--set", "episode_seconds=0.05", "--quiet"]) == 0
    assert capsys.readouterr().out.startswith("scenario spatial_random, 1 episodes")


def test_a_run_keeps_its_action_convention_against_set(gravity_compensated_run, capsys):
    """Its torques mean 'on top of g(q)': evaluating them without it would score another policy."""
    with pytest.raises(SystemExit):
        main(["--policy", str(gravity_compensated_run), "--set", "gravity_compensation=false"])
    assert "error: --set: gravity_compensation: the run's policy acts with gravity_compensation True" in (
        capsys.readouterr().err)


def test_a_folder_that_is_not_a_finished_run_is_refused_naming_it(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--policy", str(tmp_path)])
    assert f"error: --policy: {tmp_path} is not a train.py run folder (no config.json in it)" in capsys.readouterr().err
    from ee_formation_env.baselines.learned.run_folder import MARKER
    from ee_formation_env.baselines.learned.saved_run import write_saved_config

    write_saved_config(tmp_path, {"scenario": "planar_square", "backend": "sb3", "mode": "torque"})
    with pytest.raises(SystemExit):
        main(["--policy", str(tmp_path)])
    assert f"error: --policy: {tmp_path} has no {MARKER}: not a run folder train.py wrote" in capsys.readouterr().err
    (tmp_path / MARKER).write_text("{}")  # a run killed before it saved its model
    with pytest.raises(SystemExit):
        main(["--policy", str(tmp_path)])
    assert "holds no final model (model/): the run has not finished" in capsys.readouterr().err


def test_video_of_a_run_writes_one_file_per_episode_named_by_its_folder(gravity_compensated_run, tmp_path):
    pytest.importorskip("imageio")
    videos = tmp_path / "videos"
    out = tmp_path / "r.json"
    assert main(["--policy", str(gravity_compensated_run), *RUN_EVALUATION, "--video", str(videos),
                 "--json", str(out)]) == 0
    assert sorted(f.stem for f in videos.iterdir()) == ["spatial_tetrahedron-torque-gc-seed10000",
                                                        "spatial_tetrahedron-torque-gc-seed10001"]
    assert all(f.stat().st_size > 0 for f in videos.iterdir())
    # Rendered episodes in a single env score as the batched comparison's: the same policy, the same settings.
    comparison = json.loads((gravity_compensated_run / "comparison.json").read_text())
    assert _same(json.loads(out.read_text())["results"]["learned"], comparison["results"]["learned"])


def test_a_residual_sac_run_is_evaluated_as_its_comparison_is(tmp_path):
    """The other policy kind (SB3's own predict, not the numpy actor) and the residual mode's composition
    around the reference controller."""
    pytest.importorskip("stable_baselines3")
    from ee_formation_env.baselines.cli import train_command

    run_dir = tmp_path / "residual-sac"
    assert train_command(["--total-timesteps", "300", "--algo", "sac", "--out", str(run_dir), "--n-envs", "1",
                          "--n-workers", "0", "--train-episode-seconds", "0.5", "--eval-episodes", "2",
                          "--eval-seconds", "0.3", "--no-progress", "--eval-workers", "0"]) == 0
    out = tmp_path / "r.json"
    assert main(["--policy", str(run_dir), *RUN_EVALUATION, "--json", str(out)]) == 0
    comparison = json.loads((run_dir / "comparison.json").read_text())
    evaluated = json.loads(out.read_text())
    assert evaluated["learned_label"] == "learned (residual)" and evaluated["overrides"] == {"episode_seconds": 0.3}
    assert _same(evaluated["results"]["learned"], comparison["results"]["learned"])


def test_two_scenario_names_that_read_alike_once_made_safe_get_two_video_files():
    """``a/b`` and ``a_b`` (or two long names with one beginning) used to share one file: the second episode's
    video replaced the first's."""
    from ee_formation_env.baselines.evaluate import file_stem, video_path

    pairs = [("a/b", "a_b"), ("x" * 150 + "1", "x" * 150 + "2"), (".hidden", "hidden"), ("a b", "a_b")]
    for first, second in pairs:
        assert video_path("v", first, "zero", 0) != video_path("v", second, "zero", 0), (first, second)
        assert len(file_stem(first)) <= 100 and len(file_stem(second)) <= 100
    assert file_stem("planar_square") == "planar_square"  # a safe name is kept as it is
    assert file_stem("a/b") == file_stem("a/b")  # and the suffix is the same every time (a hash of the name)


def test_an_rllib_run_without_ray_is_refused_in_one_line_naming_the_extra(tmp_path, capsys):
    import importlib.util

    if importlib.util.find_spec("ray") is not None:
        pytest.skip("ray is installed: the RLlib run would load")
    from ee_formation_env.baselines.learned.run_folder import MARKER
    from ee_formation_env.baselines.learned.saved_run import write_saved_config

    (tmp_path / MARKER).write_text("{}")
    (tmp_path / "model").mkdir()
    (tmp_path / "model" / "obs_normalizer.json").write_text("{}")
    write_saved_config(tmp_path, {"scenario": "planar_square", "backend": "rllib", "mode": "torque", "algo": "ppo"})
    with pytest.raises(SystemExit) as exit_info:
        main(["--policy", str(tmp_path)])
    assert "--policy (a --backend rllib run) needs ray.rllib, not installed" in str(exit_info.value)
    assert 'pip install -e ".[train,distributed]"' in str(exit_info.value)


def test_a_scenario_and_policy_split_differently_at_the_separator_get_two_video_files():
    from ee_formation_env.baselines.evaluate import video_path

    assert video_path("v", "a-b", "c", 0) != video_path("v", "a", "b-c", 0)
    assert video_path("v", "planar_square", "gradient", 3).name == "planar_square-gradient-seed3"  # plain: kept


@pytest.mark.skipif(__import__("importlib").util.find_spec("benchmarl") is not None, reason="the torchrl extra is installed")
def test_a_benchmarl_export_without_the_torchrl_extra_names_the_extra(tmp_path):
    (tmp_path / "actor.json").write_text("{}")
    with pytest.raises(SystemExit, match=r"--policy with a BenchMARL export folder needs .*\[torchrl\]"):
        main(["--policy", str(tmp_path), "--episodes", "1"])


def test_gains_tuned_evaluates_each_law_with_its_tuned_set_as_its_own_row(capsys, tmp_path, monkeypatch):
    from conftest import write_tuned_file
    from ee_formation_env.baselines.reference import tuned

    monkeypatch.setattr(tuned, "TUNED_DIR", tmp_path)
    write_tuned_file(tmp_path)
    assert main(["--scenario", "planar_square", "--policy", "gradient", "--gains", "tuned", *SHORT,
                 "--json", str(tmp_path / "r.json")]) == 0
    assert list(_table_rows(capsys.readouterr().out)) == ["gradient (tuned)"]
    assert list(json.loads((tmp_path / "r.json").read_text())["results"]) == ["gradient (tuned)"]
    with pytest.raises(SystemExit):  # no tuned set for this law: refused before any episode
        main(["--scenario", "planar_square", "--policy", "adaptive_jacobian", "--gains", "tuned", *SHORT])
    assert "no tuned gains for 'adaptive_jacobian'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--policy", str(tmp_path), "--gains", "tuned", *SHORT])
    assert "--gains: applies to the reference laws" in capsys.readouterr().err


def test_a_missing_run_folder_is_named_as_such_not_as_an_unknown_policy(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--policy", str(tmp_path / "runs" / "missing"), *SHORT])
    assert "no such folder" in capsys.readouterr().err
