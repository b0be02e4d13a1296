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
