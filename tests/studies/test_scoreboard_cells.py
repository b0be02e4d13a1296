"""studies.scoreboard_cells: what a cell carries (schema, code version, protocol) and when a cached one is used."""

from __future__ import annotations

import json
import resource
import subprocess
import sys
from pathlib import Path

import pytest

import ee_formation_env
from studies import scoreboard_cells as cells

REPO = Path(__file__).resolve().parents[2]
PROTOCOL = {"method": {"name": "gradient", "reference": "gradient"}}


def _complete(**fields):
    return {"scenario": "planar_square", "method": "gradient", "seed": None, "eval_seeds": [10_000],
            "episode_seconds": 1.0, "budget": {}, "wall_seconds": 0.0, "episodes": [], **fields}


def test_the_code_version_is_the_package_version_and_a_hash_of_the_files_that_decide_a_result():
    version = cells.code_version()
    assert version["package"] == ee_formation_env.__version__
    assert len(version["source"]) == 16 and int(version["source"], 16) >= 0
    names = [name for name, _ in cells.source_files()]
    assert "ee_formation_env/env.py" in names and "ee_formation_env/builtin/planar_square.yaml" in names
    assert "ee_formation_env.baselines/metrics.py" in names and "ee_formation_env.assets/planar_2link.urdf" in names
    assert "studies/benchmarl_runs.py" in names
    assert not any("__pycache__" in name or name.endswith((".pyc", ".md")) for name in names)
    assert len(names) == len(set(names))


def test_a_written_cell_is_stamped_and_current(tmp_path):
    path = tmp_path / "cell.json"
    record = cells.write_cell(path, _complete(), PROTOCOL)
    assert record["schema"] == cells.CELL_SCHEMA and record["code"] == cells.code_version()
    assert cells.stale_reason(record, PROTOCOL) is None
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cell.json"]  # no partial write left


def test_a_cell_of_another_schema_code_or_method_definition_is_stale_and_says_why(tmp_path):
    record = cells.write_cell(tmp_path / "cell.json", _complete(), PROTOCOL)
    assert "cell schema 0" in cells.stale_reason({**record, "schema": 0}, PROTOCOL)
    old = {**record, "code": {"package": "0.0.1", "source": "0" * 16}}
    assert "computed by ee-formation-env 0.0.1 (source 0000000000000000), this is" in cells.stale_reason(old, PROTOCOL)
    unstamped = {key: value for key, value in record.items() if key != "code"}
    assert "unstamped code" in cells.stale_reason(unstamped, PROTOCOL)
    redefined = {"method": {"name": "gradient", "reference": "approx_jacobian"}}
    assert "defined otherwise" in cells.stale_reason(record, redefined)


def test_a_truncated_cell_is_reported_in_one_line_naming_its_file_and_recomputed(tmp_path):
    path = tmp_path / "cell.json"
    cells.write_cell(path, _complete(), PROTOCOL)
    path.write_text(path.read_text()[:40])  # a write cut short
    lines = []
    record = cells.cached_cell(path, "planar_square / gradient", PROTOCOL, lambda: _complete(wall_seconds=2.0),
                               lines.append)
    assert record["wall_seconds"] == 2.0 and json.loads(path.read_text())["wall_seconds"] == 2.0
    assert lines[0].startswith(f"corrupt planar_square / gradient: {path}: unreadable (") and "recomputing" in lines[0]
    assert len(lines[0].splitlines()) == 1 and lines[1] == "running planar_square / gradient"


def test_a_cell_missing_a_field_is_corrupt_not_aggregated(tmp_path):
    path = tmp_path / "cell.json"
    path.write_text(json.dumps({"scenario": "planar_square", "method": "gradient"}))
    record, problem = cells.read_cell(path)
    assert record is None and "not a complete cell record (missing ['seed'" in problem
    path.write_text("[1, 2]")
    assert cells.read_cell(path) == (None, "not a cell record (a JSON list)")


def test_a_stale_cell_is_recomputed_unless_accepted_and_either_way_reported(tmp_path):
    path = tmp_path / "cell.json"
    cells.write_cell(path, _complete(wall_seconds=1.0), PROTOCOL)
    fabricated = {**json.loads(path.read_text()), "code": {"package": "0.0.1", "source": "0" * 16}}
    path.write_text(json.dumps({**fabricated, "digest": cells.record_digest(fabricated)}))  # as that code signed it
    lines = []
    kept = cells.cached_cell(path, "cell", PROTOCOL, lambda: _complete(wall_seconds=2.0), lines.append,
                             accept_stale=True)
    assert kept["wall_seconds"] == 1.0 and "kept (--accept-stale-cells)" in lines[-1]
    recomputed = cells.cached_cell(path, "cell", PROTOCOL, lambda: _complete(wall_seconds=2.0), lines.append)
    assert recomputed["wall_seconds"] == 2.0 and recomputed["code"] == cells.code_version()
    assert any(line.startswith(f"stale   cell: {path}: computed by ee-formation-env 0.0.1") and
               line.endswith("; recomputing") for line in lines)


def test_a_run_is_current_only_if_this_code_marked_it_for_this_protocol(tmp_path):
    run_dir = tmp_path / "runs" / "seed-0"
    assert not cells.run_is_current(run_dir, PROTOCOL)
    cells.mark_run(run_dir, PROTOCOL)
    assert cells.run_is_current(run_dir, PROTOCOL) and cells.run_code_path(run_dir).name == ".seed-0.code.json"
    assert not cells.run_is_current(run_dir, {"method": {"name": "gradient", "train_flags": ["--mode", "torque"]}})
    cells.run_code_path(run_dir).write_text(json.dumps({"code": {"package": "0.0.1", "source": None},
                                                        "protocol": PROTOCOL}))
    assert not cells.run_is_current(run_dir, PROTOCOL)


def test_an_edited_cell_is_refused_naming_why_and_a_written_cell_reads_back_intact(tmp_path):
    path = tmp_path / "cell.json"
    written = cells.write_cell(path, _complete(), PROTOCOL)
    assert cells.read_cell(path) == (written, None)
    for edit in ({"wall_seconds": 99.0}, {"eval_seeds": [10_001]}, {"episode_seconds": 2.5}):
        path.write_text(json.dumps({**written, **edit}))
        record, problem = cells.read_cell(path)
        assert record is None and "does not match its digest" in problem
    path.write_text(json.dumps({**written, "eval_seeds": ["10000"]}))
    assert cells.read_cell(path) == (None, "eval_seeds: expected a list of integers")
    folder = tmp_path / "folder.json"
    folder.mkdir()
    assert cells.read_cell(folder) == (None, "not a regular file")
    link = tmp_path / "link.json"
    link.symlink_to(path)
    assert cells.read_cell(link) == (None, "not a regular file")


def test_a_folder_where_a_cell_goes_is_one_line_naming_it_before_the_cell_is_computed(tmp_path):
    path = tmp_path / "cells" / "cell.json"
    path.mkdir(parents=True)
    computed = []
    with pytest.raises(OSError) as refused:
        cells.cached_cell(path, "cell", PROTOCOL, lambda: computed.append(1) or _complete(), lambda line: None)
    assert str(refused.value) == (f"cannot write {path} (a folder stands where the cell's file goes: move it away, "
                                  "then run again)") and refused.value.filename == str(path)
    assert not computed
    (tmp_path / "blocked").write_text("a file")
    with pytest.raises(OSError, match=f"cannot write .* \\({tmp_path / 'blocked'} is a file, where a folder"):
        cells.cached_cell(tmp_path / "blocked" / "cell.json", "cell", PROTOCOL, _complete, lambda line: None)


_SIZE_LIMITED_CELL = """
import resource, sys
from pathlib import Path
from ee_formation_env.baselines.cli_errors import report_errors
from studies import scoreboard_cells as cells
record = {"scenario": "planar_square", "method": "gradient", "seed": None, "eval_seeds": [10000],
          "episode_seconds": 1.0, "budget": {}, "wall_seconds": 0.0, "episodes": [{"success": True}] * 50}
resource.setrlimit(resource.RLIMIT_FSIZE, (1000, 1000))
sys.exit(report_errors(lambda: cells.write_cell(Path(sys.argv[1]), record, {}) and 0, False))
"""


@pytest.mark.skipif(not hasattr(resource, "RLIMIT_FSIZE"), reason="file-size limits")
def test_a_cell_over_a_file_size_limit_is_one_line_naming_it_and_the_old_cell_stays(tmp_path):
    path = tmp_path / "cell.json"
    old = cells.write_cell(path, _complete(), PROTOCOL)
    result = subprocess.run([sys.executable, "-c", _SIZE_LIMITED_CELL, str(path)], cwd=REPO, capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 1, result.stderr[-3000:]
    assert result.stderr.splitlines() == [f"error: cannot write {path} (file too large: over this process's "
                                          "file-size limit (ulimit -f): raise it)"]
    assert cells.read_cell(path) == (old, None) and sorted(p.name for p in tmp_path.iterdir()) == ["cell.json"]
