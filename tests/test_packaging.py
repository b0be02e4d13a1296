"""Packaging: the wheel ships the package, its robot assets and built-in scenarios, and works installed on its own."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
_IGNORE = shutil.ignore_patterns(".git", "build", "dist", "*.egg-info", "__pycache__", ".pytest_cache",
                                 ".hypothesis", ".venv", "runs", "results")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """Build a wheel from a copy of the checkout (the checkout itself gets no build/ or egg-info churn)."""
    root = tmp_path_factory.mktemp("packaging")
    source = root / "src"
    shutil.copytree(REPO, source, ignore=_IGNORE)
    out = root / "wheels"
    result = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-w", str(out), str(source)],
        capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    wheels = list(out.glob("ee_formation_env-*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0]


def test_wheel_contents(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    for required in ("ee_formation_env/__init__.py", "ee_formation_env/env.py", "ee_formation_env/scenario.py",
                     "ee_formation_env/validation.py", "ee_formation_env/world.py", "ee_formation_env/robot.py",
                     "ee_formation_env/assets/__init__.py", "ee_formation_env/assets/planar_2link.urdf",
                     "ee_formation_env/assets/pera_arm.urdf", "ee_formation_env/py.typed"):
        assert required in names, required
    for required in ("ee_formation_env/integrations/sb3.py", "ee_formation_env/baselines/__init__.py",
                     "ee_formation_env/baselines/reference/controllers.py", "ee_formation_env/baselines/learned/config.py",
                     "ee_formation_env/baselines/cli.py"):
        assert required in names, required
    # Only the env's package at the top: no `baselines` (another project's name too), no studies or benchmarks.
    assert {name.split("/")[0] for name in names if not name.split("/")[0].endswith((".dist-info", ".data"))} == {
        "ee_formation_env"}
    entry_points = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    assert "ee-formation = ee_formation_env.baselines.cli:main" in zipfile.ZipFile(wheel).read(entry_points).decode()
    from ee_formation_env.builtin import BUILTIN_SCENARIOS

    for scenario in BUILTIN_SCENARIOS:  # package data: the built-in scenarios' YAML files
        assert f"ee_formation_env/builtin/{scenario}.yaml" in names, scenario
    assert not any(name.startswith("tests/") for name in names)
    metadata = next(n for n in names if n.endswith(".dist-info/METADATA"))
    text = zipfile.ZipFile(wheel).read(metadata).decode()
    for dependency in ("pybullet", "pettingzoo", "gymnasium", "numpy", "pyyaml"):
        assert dependency in text.lower(), dependency
    import ee_formation_env
    assert f"\nVersion: {ee_formation_env.__version__}\n" in text  # the one definition of the version


#: Where each folder of the checkout goes inside the wheel (pyproject.toml's package-dir).
_INSTALLED_AS = {"ee_formation_env": "ee_formation_env", "assets": "ee_formation_env/assets",
                 "baselines": "ee_formation_env/baselines"}


def test_every_file_the_library_holds_is_in_the_wheel(wheel):
    """Every tracked file under the library's folders (modules, scenarios, URDFs, tuned gains, configs) is shipped,
    so that a new sub-folder or data file cannot drop out of the wheel silently."""
    listed = subprocess.run(["git", "ls-files", *_INSTALLED_AS], cwd=REPO, capture_output=True, text=True)
    if listed.returncode != 0:
        pytest.skip("not a git checkout")
    names = set(zipfile.ZipFile(wheel).namelist())
    tracked = [Path(line) for line in listed.stdout.splitlines()]
    missing = [str(path) for path in tracked
               if "/".join([_INSTALLED_AS[path.parts[0]], *path.parts[1:]]) not in names]
    assert not missing, f"tracked files missing from the wheel (pyproject.toml packages / package-data): {missing}"
    assert any(path.parts[:3] == ("baselines", "reference", "tuned") for path in tracked)


def test_installed_wheel_trains_and_evaluates_outside_the_checkout(wheel, tmp_path):
    """The installed command line alone (no checkout on the path): `train --help`, a short training, `evaluate` of
    its run and of the laws at their tuned gains."""
    target = tmp_path / "site"
    result = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-index", "--target",
                             str(target), str(wheel)], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    environment = dict(os.environ, PYTHONPATH=str(target))
    work = tmp_path / "work"
    work.mkdir()

    def cli(*args: str) -> str:
        run = subprocess.run([sys.executable, "-m", "ee_formation_env.baselines.cli", *args], cwd=work,
                             env=environment, capture_output=True, text=True, timeout=600)
        assert run.returncode == 0, f"ee-formation {' '.join(args)}: " + run.stdout[-3000:] + run.stderr[-3000:]
        return run.stdout

    assert "--total-timesteps" in cli("train", "--help")
    cli("train", "--total-timesteps", "300", "--n-envs", "1", "--n-workers", "0", "--train-episode-seconds", "0.5",
        "--imitation-rounds", "1", "--imitation-episodes", "2", "--eval-episodes", "2", "--eval-seconds", "0.3",
        "--no-progress", "--eval-workers", "0", "--out", "run")
    assert (work / "run" / "config.json").is_file()
    cli("evaluate", "--policy", "run", "--episodes", "1", "--quiet", "--json", "learned.json")
    assert json.loads((work / "learned.json").read_text())["episodes"] == 1
    cli("evaluate", "--scenario", "planar_square", "--policy", "gradient", "--gains", "tuned", "--episodes", "1",
        "--set", "episode_seconds=0.3", "--quiet", "--json", "tuned.json")
    assert list(json.loads((work / "tuned.json").read_text())["results"]) == ["gradient (tuned)"]


def test_installed_wheel_finds_its_assets(wheel, tmp_path):
    """Installed alone (not the editable checkout), the package builds an env from its shipped URDFs."""
    target = tmp_path / "site"
    result = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-index", "--target",
                             str(target), str(wheel)], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    code = (
        "import ee_formation_env, json, pathlib\n"
        "print(pathlib.Path(ee_formation_env.__file__).resolve())\n"
        "from ee_formation_env.scenario import ROBOTS\n"
        "print(ROBOTS['pera_arm'].urdf.resolve())\n"
        "env = ee_formation_env.parallel_env('spatial_tetrahedron', episode_seconds=0.1)\n"
        "obs, _ = env.reset(seed=0)\n"
        "space = env.observation_space('arm_0')\n"
        "print('obs', obs['arm_0'].shape == space.shape and space.contains(obs['arm_0']))\n"
        "env.close()\n"
        "import ee_formation_env.baselines.learned.config\n"
        "print(pathlib.Path(ee_formation_env.baselines.__file__).resolve())\n"
        "try:\n"
        "    import baselines\n"
        "    print('baselines', baselines.__file__)\n"
        "except ImportError:\n"
        "    print('no baselines')\n"
        "from ee_formation_env.builtin import BUILTIN_SCENARIOS, builtin_scenario\n"
        "print(len(BUILTIN_SCENARIOS), all(ee_formation_env.load_scenario(n).name == n for n in BUILTIN_SCENARIOS))\n"
        "print(json.dumps({n: builtin_scenario(n) for n in BUILTIN_SCENARIOS}))\n"
    )
    environment = dict(os.environ, PYTHONPATH=str(target))
    run = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=environment, capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    lines = run.stdout.strip().splitlines()
    package_file, urdf = Path(lines[0]), Path(lines[1])
    assert target.resolve() in package_file.parents
    assert target.resolve() in urdf.parents and urdf.name == "pera_arm.urdf"
    assert lines[2] == "obs True"
    assert target.resolve() in Path(lines[3]).parents  # the learning wing installed inside the env's package
    assert lines[4] == "no baselines"
    from ee_formation_env.builtin import BUILTIN_SCENARIOS, builtin_scenario

    assert lines[5] == f"{len(BUILTIN_SCENARIOS)} True"  # every built-in loads from the installed package data
    assert lines[6] == json.dumps({name: builtin_scenario(name) for name in BUILTIN_SCENARIOS})
