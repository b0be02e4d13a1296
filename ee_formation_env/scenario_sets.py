"""Held-out scenario sets: the test scenarios of a training scenario, for the generalization protocol.

A policy trained on a built-in scenario is evaluated, unchanged, on the scenarios of its test set: the same
team of arms (so the same observation and action spaces) on problems it never trained on. The scoreboard
(``studies/scoreboard.py``) reports each learned method on them beside the reference controllers, which need
no training and set the bar. Every test scenario is plain scenario data (``docs/scenarios.md``), built here
from its training scenario by changing only what the entry says:

- ``planar_square`` / ``planar_square_displacement``:

  - ``..._rotated``: the arms' bases turned by 0.4, -1.1, 2.3 and 0.9 rad about their own z axes, the initial
    joint angles turned back, so the physical problem is the training one (the built-in
    ``planar_square_rotated`` and its displacement twin): what changes is each arm's local view of it;
  - ``..._3.5m`` and ``..._4.0m``: squares of 3.5 m and 4.0 m sides about the same centre (the training square's
    is 3.0 m), farther out in the arms' 3.0 m reach;
  - ``..._rect_2.5x3.5m``: a 2.5 m (x) by 3.5 m (y) rectangle about the same centre.

Test sets are fixed: a scenario's name here names one problem for good. Random scenario families and
sampled distributions are in :mod:`ee_formation_env.generators`.
"""

from __future__ import annotations

import copy
from typing import Any, Callable

from ee_formation_env.builtin import builtin_scenario
from ee_formation_env.generators import square_vertices

CENTRE = (3.0, 3.0)  # m, the built-in planar squares' centre


def _with_shape(train: str, shape: list[list[float]]) -> Callable[[], dict[str, Any]]:
    def build() -> dict[str, Any]:
        scenario = builtin_scenario(train)
        scenario["shape"] = shape
        return scenario
    return build


def _rotated(train: str) -> Callable[[], dict[str, Any]]:
    """``train`` with the bases and initial joint angles of ``planar_square_rotated``."""
    def build() -> dict[str, Any]:
        scenario = builtin_scenario(train)
        rotated = builtin_scenario("planar_square_rotated")
        for arm, turned in zip(scenario["arms"], rotated["arms"]):
            arm["base_rpy"], arm["initial_q"] = list(turned["base_rpy"]), list(turned["initial_q"])
        return scenario
    return build


def _rectangle(width: float, height: float) -> list[list[float]]:
    """The corners of a ``width`` (x) by ``height`` (y) m rectangle about :data:`CENTRE`, counter-clockwise
    from the lower left (the order of :func:`~ee_formation_env.generators.square_vertices`)."""
    cx, cy = CENTRE
    return [[cx - width / 2, cy - height / 2], [cx + width / 2, cy - height / 2],
            [cx + width / 2, cy + height / 2], [cx - width / 2, cy + height / 2]]


def _planar_test_set(train: str) -> dict[str, Callable[[], dict[str, Any]]]:
    return {
        f"{train}_rotated": _rotated(train),
        f"{train}_3.5m": _with_shape(train, square_vertices(3.5, CENTRE)),
        f"{train}_4.0m": _with_shape(train, square_vertices(4.0, CENTRE)),
        f"{train}_rect_2.5x3.5m": _with_shape(train, _rectangle(2.5, 3.5)),
    }


#: training scenario -> {test scenario name -> builder of its scenario data}.
TEST_SETS: dict[str, dict[str, Callable[[], dict[str, Any]]]] = {
    "planar_square": _planar_test_set("planar_square"),
    "planar_square_displacement": _planar_test_set("planar_square_displacement"),
}


def held_out_scenarios(train: str) -> dict[str, dict[str, Any]]:
    """The test set of training scenario ``train``: name -> fresh scenario data (``name`` set to it); empty for a
    scenario without one."""
    if not isinstance(train, str):
        raise TypeError(f"train: expected a built-in scenario name, got {type(train).__name__}")
    out = {}
    for name, build in TEST_SETS.get(train, {}).items():
        scenario = copy.deepcopy(build())
        scenario["name"] = name
        out[name] = scenario
    return out
