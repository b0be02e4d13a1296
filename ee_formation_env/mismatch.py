"""Model mismatch: the simulated ("true") robot differs from the nominal URDF the controllers know.

Scenario key ``model_mismatch`` = ``{"length": L, "mass": M, "seed": s}``: every joint-origin
translation on each arm's chain (link lengths and offsets, the end-effector offset included) is scaled
by its own factor drawn uniformly from ``[1 - L, 1 + L]``, and every link mass and inertia tensor on the
chain by a factor from ``[1 - M, 1 + M]`` (centres of mass stay where the URDF puts them). Draws come from ``numpy.random.default_rng(seed)``, once per
environment (the bodies are loaded once; resets never reload them). ``L = M = 0`` (the default) means
the simulated robots are exactly the nominal ones.

How the reference controllers stand it: see docs/results.md ("Robustness under model mismatch").
"""

from __future__ import annotations

import os
import tempfile
import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ee_formation_env.inputs import check_known_keys, excerpt


@dataclass(frozen=True)
class MismatchConfig:
    """Half-widths of the relative perturbations (0.2 = +-20 %) and the seed of their draw."""

    length: float = 0.0
    mass: float = 0.0
    seed: int = 0

    @property
    def active(self) -> bool:
        return self.length > 0 or self.mass > 0


def parse_mismatch(value: Any) -> MismatchConfig:
    """``model_mismatch`` from scenario data; ``ValueError`` naming the field on bad input."""
    if isinstance(value, MismatchConfig):
        return value
    if value is None:
        return MismatchConfig()
    if not isinstance(value, Mapping):
        raise ValueError(f"model_mismatch: expected a dict with keys length, mass, seed; got {excerpt(value)}")
    check_known_keys("model_mismatch", value, ['length', 'mass', 'seed'])
    parsed: dict[str, Any] = {}
    for key in ("length", "mass"):
        if key in value:
            number = value[key]
            if isinstance(number, bool) or not isinstance(number, (int, float)) or not 0 <= number < 1:
                raise ValueError(f"model_mismatch.{key}: expected a relative half-width in [0, 1), got {excerpt(number)}")
            parsed[key] = float(number)
    if "seed" in value:
        if isinstance(value["seed"], bool) or not isinstance(value["seed"], int) or value["seed"] < 0:
            raise ValueError(f"model_mismatch.seed: expected an integer >= 0, got {excerpt(value['seed'])}")
        parsed["seed"] = value["seed"]
    return MismatchConfig(**parsed)


def write_perturbed_urdf(urdf: str, chain_joints: list[str], chain_links: list[str],
                         length_scales: np.ndarray, mass_scales: np.ndarray, directory: str) -> str:
    """Write a copy of ``urdf`` with scaled joint origins and link masses/inertias; return its path.

    ``length_scales`` has one factor per joint in ``chain_joints`` and ``mass_scales`` one per link in
    ``chain_links``. Relative mesh paths are made absolute so the copy loads from ``directory``.
    """
    tree = ElementTree.parse(urdf)
    root = tree.getroot()
    joints = {joint.get("name"): joint for joint in root.iter("joint")}
    for name, scale in zip(chain_joints, length_scales):
        origin = joints[name].find("origin")
        if origin is not None and origin.get("xyz"):
            xyz = [float(v) * float(scale) for v in origin.get("xyz").split()]
            origin.set("xyz", " ".join(repr(v) for v in xyz))
    links = {link.get("name"): link for link in root.iter("link")}
    for name, scale in zip(chain_links, mass_scales):
        inertial = links[name].find("inertial")
        if inertial is None:
            continue
        mass = inertial.find("mass")
        if mass is not None:
            mass.set("value", repr(float(mass.get("value")) * float(scale)))
        inertia = inertial.find("inertia")
        if inertia is not None:
            for key in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz"):
                if inertia.get(key) is not None:
                    inertia.set(key, repr(float(inertia.get(key)) * float(scale)))
    return write_urdf_copy(tree, urdf, directory)


def write_urdf_copy(tree: ElementTree.ElementTree, source: str | os.PathLike, directory: str | os.PathLike) -> str:
    """Write an edited URDF ``tree`` read from ``source`` as a new file in ``directory``; return its path.

    Relative mesh paths are made absolute (against ``source``'s folder), so the copy loads from anywhere."""
    source_dir = Path(source).resolve().parent
    for mesh in tree.getroot().iter("mesh"):
        filename = mesh.get("filename", "")
        if filename and "://" not in filename and not os.path.isabs(filename):
            mesh.set("filename", str(source_dir / filename))
    handle, path = tempfile.mkstemp(suffix=".urdf", dir=directory)
    with os.fdopen(handle, "wb") as out:
        tree.write(out)
    return path
