"""Each entry point, run without one of its optional packages, fails in one line naming the pip extra to add,
before creating anything (no run folder, no output folder, no traceback)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from ee_formation_env.baselines.extras import missing_modules, require

REPO = Path(__file__).resolve().parents[2]

# Runs an entry point as ``python ...`` would, with some modules made unimportable (None in sys.modules).
_WITHOUT = """
import runpy, sys
sys.path.insert(0, {repo!r})
for name in {blocked!r}:
    sys.modules[name] = None
sys.argv = {argv!r}
if sys.argv[0].endswith(".py"):
    runpy.run_path(sys.argv[0], run_name="__main__")
else:
    runpy.run_module(sys.argv[0], run_name="__main__", alter_sys=True)
"""


def _run_without(blocked: list[str], argv: list[str], cwd: Path) -> subprocess.CompletedProcess:
    code = _WITHOUT.format(repo=str(REPO), blocked=blocked, argv=argv)
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, timeout=300)


def _assert_one_line_naming(result: subprocess.CompletedProcess, extra: str) -> None:
    assert result.returncode == 1, result.stdout + result.stderr
    lines = [line for line in result.stderr.splitlines() if line and not line.startswith("pybullet build time")]
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    assert f'pip install -e ".[{extra}]"' in lines[0], lines[0]


def test_train_without_stable_baselines3_creates_no_run_folder(tmp_path):
    result = _run_without(["stable_baselines3"], [str(REPO / "train.py"), "--out", "run"], tmp_path)
    _assert_one_line_naming(result, "train")
    assert "stable_baselines3" in result.stderr
    assert not (tmp_path / "run").exists() and not (tmp_path / "runs").exists()


def test_train_rllib_without_ray_names_the_distributed_extra(tmp_path):
    result = _run_without(["ray"], [str(REPO / "train.py"), "--backend", "rllib", "--out", "run"], tmp_path)
    _assert_one_line_naming(result, "train,distributed")
    assert not (tmp_path / "run").exists()


def test_reproduce_without_matplotlib_creates_no_output_folder(tmp_path):
    result = _run_without(["matplotlib", "matplotlib.pyplot"], ["studies.reproduce", "--out", "out"], tmp_path)
    _assert_one_line_naming(result, "figures")
    assert not (tmp_path / "out").exists()


def test_evaluate_video_without_imageio_creates_no_video_folder(tmp_path):
    result = _run_without(["imageio"], ["ee_formation_env.baselines.evaluate", "--episodes", "1", "--video", "videos"], tmp_path)
    _assert_one_line_naming(result, "video")
    assert not (tmp_path / "videos").exists()


def test_require_names_every_missing_module(monkeypatch):
    monkeypatch.setitem(sys.modules, "no_such_module_a", None)
    assert missing_modules(["json", "no_such_module_a"]) == ["no_such_module_a"]
    with pytest.raises(SystemExit, match=r'needs no_such_module_a, not installed: pip install -e "\.\[x\]"'):
        require(["json", "no_such_module_a"], "x", "thing")
    require(["json"], "x", "thing")  # nothing missing: no error
