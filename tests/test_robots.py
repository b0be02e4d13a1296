"""The robot registry (``ee_formation_env.robots``): every robot the package uses is one entry, and the random
spatial family draws from the entries, so its draws stay those it was pinned with."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pybullet_data
import pytest

from ee_formation_env import generators
from ee_formation_env.kinematics import chain_model, singularity_margins
from ee_formation_env.robots import PYBULLET_DATA_ROBOTS, RANDOM_SPATIAL_ROBOTS, ROBOTS

#: sha256 (first 16 hex digits) of spatial_scenario(0..3) and planar_scenario(0..3) as JSON, pybullet_data
#: paths made relative: the draws as the generators made them when they kept their own table of robots.
PINNED_DRAWS_DIGEST = "4f4fc8198a80c734"


def test_the_random_spatial_family_reads_its_robots_from_the_registry():
    assert list(RANDOM_SPATIAL_ROBOTS) == ["kuka_iiwa", "franka_panda", "pera_arm"]  # the draws index this order
    assert RANDOM_SPATIAL_ROBOTS["pera_arm"] is ROBOTS["pera_arm"]
    assert {name: spec.random_base_height for name, spec in RANDOM_SPATIAL_ROBOTS.items()} == {
        "kuka_iiwa": 0.0, "franka_panda": 0.0, "pera_arm": 1.0}
    assert ROBOTS["planar_2link"].random_base_height is None
    assert not set(PYBULLET_DATA_ROBOTS) & set(ROBOTS)  # a scenario names only the package's own robots


@pytest.mark.parametrize("name", sorted(PYBULLET_DATA_ROBOTS))
def test_pybullet_data_robots_exist_and_start_away_from_singularities(name):
    spec = PYBULLET_DATA_ROBOTS[name]
    assert spec.urdf.is_file() and spec.urdf.is_relative_to(pybullet_data.getDataPath())
    model = chain_model(str(spec.urdf), spec.ee_link)
    q = np.asarray(spec.start_q)
    assert q.shape == (model.n_joints,)
    assert singularity_margins(model.jacobian(q)[None], 3)[0] > 0.05


def _portable(value):
    """``value`` with absolute pybullet_data paths made relative (the digest does not depend on the machine)."""
    if isinstance(value, dict):
        return {key: _portable(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_portable(item) for item in value]
    if isinstance(value, str) and value.startswith(pybullet_data.getDataPath()):
        return Path(value).relative_to(pybullet_data.getDataPath()).as_posix()
    return value


def test_the_random_families_draw_what_they_were_pinned_with():
    draws = [generators.spatial_scenario(seed) for seed in range(4)] + [generators.planar_scenario(seed)
                                                                         for seed in range(4)]
    text = json.dumps(_portable(draws), sort_keys=True)
    assert hashlib.sha256(text.encode()).hexdigest()[:16] == PINNED_DRAWS_DIGEST
