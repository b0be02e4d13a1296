"""Selecting an engine: the scenario key, the env keyword, and the refusals made before any world starts."""

from __future__ import annotations

import sys

import pytest

import ee_formation_env
import ee_formation_env.world
from ee_formation_env.engines import check_engine, require_engine
from ee_formation_env.scenario import load_scenario


@pytest.fixture
def no_physics(monkeypatch):
    """Fail the test if a PyBullet world is created (the refusal must come first)."""

    def forbidden(self, *args, **kwargs):
        raise AssertionError("PhysicsWorld created before the engine was refused")

    monkeypatch.setattr(ee_formation_env.world.PhysicsWorld, "__init__", forbidden)


def test_an_unknown_engine_is_refused_naming_the_key(no_physics):
    message = r"engine: expected one of \['pybullet', 'mujoco'\], got 'bullet'"
    with pytest.raises(ValueError, match=message):
        load_scenario("planar_square", engine="bullet")
    with pytest.raises(ValueError, match=message):
        ee_formation_env.parallel_env("planar_square", engine="bullet")
    with pytest.raises(ValueError, match=r"engine: expected one of .*, got \['mujoco'\]"):
        require_engine(["mujoco"])  # type: ignore[arg-type]  # not a name: refused, not looked up


def test_mujoco_without_its_package_names_the_extra(monkeypatch, no_physics):
    monkeypatch.setitem(sys.modules, "mujoco", None)  # `import mujoco` raises ImportError
    with pytest.raises(ImportError, match=r"""engine: 'mujoco' needs the mujoco package: pip install "ee-formation-env\[mujoco\]"$"""):
        ee_formation_env.parallel_env("planar_square", engine="mujoco")


@pytest.mark.parametrize("num_envs, render_mode, message", [
    (2, None, r"num_envs: the batched env runs on PyBullet only for now; engine 'mujoco' takes num_envs=1 "
              r"\(the parallel env\), got 2"),
    (1, "rgb_array", r"render_mode: frames are PyBullet's only for now; engine 'mujoco' takes render_mode=None, "
                     r"got 'rgb_array'"),
])
def test_what_mujoco_cannot_do_yet_is_refused_before_any_world(num_envs, render_mode, message, no_physics):
    with pytest.raises(ValueError, match=message):
        check_engine("mujoco", num_envs, render_mode)
    with pytest.raises(ValueError, match=message):
        ee_formation_env.vector_env("planar_square", num_envs=num_envs, render_mode=render_mode, engine="mujoco")


def test_pybullet_scenarios_serialize_as_before_and_mujoco_ones_name_their_engine():
    assert "engine" not in load_scenario("planar_square").to_dict()  # PyBullet digests unchanged
    data = load_scenario("planar_square", engine="mujoco").to_dict()
    assert data["engine"] == "mujoco"
    assert load_scenario(data).engine == "mujoco"


def test_the_engine_keeps_tuned_gains():
    """Both engines simulate the same physics: the scenario's tuned gains stay (other physics drop them)."""
    tuned = load_scenario("planar_square").controller_gains
    assert tuned is not None
    assert load_scenario("planar_square", engine="mujoco").controller_gains == tuned
    assert load_scenario("planar_square", physics_hz=500.0).controller_gains is None
