"""Tuned gains of the reference laws: opt-in data, one stamped file per built-in scenario.

The laws' defaults (a built-in's carried ``controller_gains``, else the derived rule of
:mod:`ee_formation_env.baselines.reference.gains`) are conservative. For a fair comparison each law is also
shown at its strongest: its gains searched by a seeded optimizer (``python -m studies.tune_gains``; the
objective, budget and seeds are in docs/controllers.md, "Tuned gains") and written here as data,
``tuned/<scenario>.json``. Nothing reads them unless asked: ``make_policies(name, env, gains="tuned")``,
``ee-formation evaluate --gains tuned``, the scoreboard's ``<law>-tuned`` methods.

A tuned set is a point of the search space :data:`SEARCH_SPACE`, relative to the defaults of the task, so one
point serves a fixed scenario and every draw of a distribution alike (:func:`gains_from_point`):

- ``kp_scale``, ``kd_scale``: K_P and K_D times the default's;
- ``saturated`` / ``spring_scale``: saturated springs at ``spring_scale`` times the derived rule's edge forces
  (:func:`~ee_formation_env.baselines.reference.gains.derive_gains`, rule 2), or the paper's unsaturated law;
- ``rate_steps``: gradient-rate damping ``K_R = rate_steps dt`` (0: none);
- ``ki`` (1/s; laws II and III where gravity loads the joints, else 0); ``alpha_scale``,
  ``adaptation_scale`` (law III): alpha and Gamma times the default's.

A file is refused (``ValueError`` naming the file and the field) when its schema is unknown, a field is missing
or out of its range, or it was tuned for other scenario data than the built-in's today (its ``scenario_digest``).
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ee_formation_env.baselines.reference.controllers import Gains
from ee_formation_env.baselines.reference.gains import default_gains, derive_gains, reference_stiffness

TUNED_SCHEMA = 1
TUNED_DIR = Path(__file__).resolve().parent / "tuned"

#: Reset seeds of the tuner's episodes on a fixed scenario (its starts); never an evaluation seed.
TUNING_SEEDS: tuple[int, ...] = tuple(range(90_000, 90_100))
#: Reset seeds of the tuner's episodes on a distribution: training draws (below the held-out seeds, 10000).
DISTRIBUTION_TUNING_SEEDS: tuple[int, ...] = tuple(range(5_000, 5_100))
#: Seeds no tuning or board evaluation looks at: the check that a tuned set holds on unseen starts.
UNSEEN_CHECK_SEEDS: tuple[int, ...] = tuple(range(70_000, 70_050))

#: The tuner's search space: name -> (low, high, log scale). ``saturated`` is a choice (True/False).
SEARCH_SPACE: dict[str, tuple[float, float, bool]] = {
    "kp_scale": (0.1, 100.0, True),
    "kd_scale": (0.05, 20.0, True),
    "spring_scale": (0.1, 100.0, True),
    "rate_steps": (0.0, 5.0, False),
    "ki": (0.1, 100.0, True),
    "alpha_scale": (1e-3, 1e3, True),
    "adaptation_scale": (1e-2, 1e2, True),
}


def law_parameters(law: str, gravity_loads_joints: bool) -> tuple[str, ...]:
    """The points' parameters of ``law`` (the gains it reads): ``ki`` only where gravity loads the joints (law I
    compensates gravity with its model and reads no K_I; elsewhere K_I = 0 keeps laws I and II one law)."""
    names = ["kp_scale", "kd_scale", "saturated", "spring_scale", "rate_steps"]
    if law != "gradient" and gravity_loads_joints:
        names.append("ki")
    if law == "adaptive_jacobian":
        names += ["alpha_scale", "adaptation_scale"]
    return tuple(names)


def gains_from_point(task: Any, index: int, point: Mapping[str, Any]) -> Gains:
    """Arm ``index``'s gains on ``task`` at the search-space ``point`` (module docstring)."""
    base = default_gains(task, index)
    updates: dict[str, Any] = {
        "kp": float(np.max(base.kp)) * float(point["kp_scale"]),
        "kd": _scaled(base.kd, point["kd_scale"]),
        "rate_gain": float(point["rate_steps"]) * task.scenario.control_dt,
        "spring_force": (_scaled(derive_gains(task, index).spring_force, point["spring_scale"])
                         if point["saturated"] else math.inf),
    }
    if "ki" in point:
        updates["ki"] = float(point["ki"])
    if "alpha_scale" in point:
        updates["alpha"] = float(base.alpha) * float(point["alpha_scale"])
        updates["adaptation_gain"] = float(base.adaptation_gain) * float(point["adaptation_scale"])
    if base.reference_stiffness > 0:  # a manoeuvre's hold follows the formation gain (gains.py, rule 6)
        updates["reference_stiffness"] = reference_stiffness(task, updates["kp"])
    return base.with_updates(**updates)


def _scaled(value: Any, scale: float) -> Any:
    array = np.asarray(value, dtype=np.float64) * float(scale)
    return float(array) if array.ndim == 0 else tuple(array.tolist())


def scenario_digest(data: Mapping[str, Any]) -> str:
    """SHA-256 of a scenario's data (canonical JSON): a tuned file names the exact problem it was tuned on."""
    return hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()


@dataclass(frozen=True)
class TunedLaw:
    """One law's tuned point on one scenario, with what it was measured on."""

    law: str
    point: dict[str, Any]
    record: dict[str, Any]  # the tuning's stamp and figures (trials, seeds, objective, default and best)


def tuned_path(scenario_name: str) -> Path:
    return TUNED_DIR / f"{scenario_name}.json"


def load_tuned(scenario_name: str, law: str) -> TunedLaw:
    """The tuned point of ``law`` on the built-in ``scenario_name``, from its verified file; ``ValueError`` when
    there is none, or the file is invalid or was tuned on other scenario data."""
    from ee_formation_env.builtin import BUILTIN_SCENARIOS, builtin_scenario

    if scenario_name not in BUILTIN_SCENARIOS:
        raise ValueError(f"gains: tuned gains exist for built-in scenarios only, not {scenario_name!r}")
    path = tuned_path(scenario_name)
    if not path.is_file():
        raise ValueError(f"gains: no tuned gains for {scenario_name!r} ({path} is missing; "
                         "python -m studies.tune_gains writes it)")
    data = read_tuned_file(path)
    if data["scenario_digest"] != scenario_digest(builtin_scenario(scenario_name)):
        raise ValueError(f"{path}: scenario_digest: tuned on other data than today's {scenario_name!r}; tune again "
                         "(python -m studies.tune_gains)")
    laws = data["laws"]
    if law not in laws:
        raise ValueError(f"gains: {path} has no tuned gains for {law!r} (it has {sorted(laws)})")
    return TunedLaw(law, dict(laws[law]["point"]), laws[law])


def read_tuned_file(path: Path) -> dict[str, Any]:
    """A tuned-gains file, checked field by field (module docstring); ``ValueError`` naming the file and field."""
    from ee_formation_env.baselines import REFERENCE_CONTROLLERS

    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f"{path}: not a readable tuned-gains file ({error})") from None
    if not isinstance(data, dict) or data.get("schema") != TUNED_SCHEMA:
        raise ValueError(f"{path}: schema: expected {TUNED_SCHEMA}, got {data.get('schema') if isinstance(data, dict) else data!r}")
    for key in ("scenario", "scenario_digest", "laws"):
        if key not in data:
            raise ValueError(f"{path}: {key}: missing")
    if not isinstance(data["laws"], dict) or not data["laws"]:
        raise ValueError(f"{path}: laws: expected a mapping of law -> tuned point")
    for law, entry in data["laws"].items():
        if law not in REFERENCE_CONTROLLERS:
            raise ValueError(f"{path}: laws.{law}: unknown law; known: {list(REFERENCE_CONTROLLERS)}")
        point = entry.get("point") if isinstance(entry, dict) else None
        if not isinstance(point, dict):
            raise ValueError(f"{path}: laws.{law}.point: missing")
        check_point(point, law, f"{path}: laws.{law}.point")
    return data


def check_point(point: Mapping[str, Any], law: str, where: str) -> None:
    """``ValueError`` naming ``where`` and the field unless ``point`` has exactly ``law``'s parameters, each in
    its range."""
    for gravity in (False, True):
        if set(point) == set(law_parameters(law, gravity)):
            break
    else:
        raise ValueError(f"{where}: expected the parameters {list(law_parameters(law, True))} "
                         f"(ki only where gravity loads the joints), got {sorted(point)}")
    for name, value in point.items():
        if name == "saturated":
            if not isinstance(value, bool):
                raise ValueError(f"{where}.saturated: expected true or false, got {value!r}")
            continue
        low, high, _ = SEARCH_SPACE[name]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not (low <= value <= high):
            raise ValueError(f"{where}.{name}: expected a number in [{low}, {high}], got {value!r}")


def tuned_gains_source(env: Any, index: int, law: str) -> Any:
    """``() -> Gains`` of arm ``index`` for ``law``'s tuned point on ``env``'s built-in scenario, evaluated on the
    env's current task (each draw of a distribution its own). ``ValueError`` when the env's scenario is not the
    built-in's physics (a change outside ``GAIN_NEUTRAL_FIELDS``: the tuning does not carry over)."""
    from ee_formation_env.scenario import GAIN_NEUTRAL_FIELDS, load_scenario

    name = env.scenario.name
    tuned = load_tuned(name, law)

    def physics(scenario: Any) -> str:
        data = {k: v for k, v in scenario.to_dict().items() if k not in GAIN_NEUTRAL_FIELDS}
        return json.dumps(data, sort_keys=True, default=str)

    if physics(env.scenario) != physics(load_scenario(name)):
        raise ValueError(f"gains: 'tuned' applies to the built-in {name!r} with its own physics; this env changes "
                         "it (tuned gains hold for the problem they were tuned on)")
    return lambda: gains_from_point(env.task, index, tuned.point)


def tuned_gains_table() -> str:
    """Markdown: every committed tuned set beside its law's defaults, measured on the tuning starts (the files'
    records): the time to the 1 mm band, the energy and the point (the docs' table, docs/controllers.md)."""
    lines = ["| scenario | law | trials | default: to 1 mm (s) / energy | tuned: to 1 mm (s) / energy | K_P x | K_D x | "
             "springs | K_R (steps) | K_I (1/s) | alpha x, Gamma x |", "|---|---|---:|---:|---:|---:|---:|---|---:|---:|---|"]

    def band(figures: Mapping[str, Any]) -> str:
        time = figures.get("settling_time_1mm", math.nan)
        shown = "never" if not math.isfinite(time) else f"{time:.2f}"
        broken = [name for name, ok in (("1 cm success", figures["success"] == 1.0),
                                        ("1 mm band", figures["success_1mm"] == 1.0),
                                        ("faults", figures["faults"] == 0), ("contacts", figures["contact_steps"] == 0))
                  if not ok]
        return f"{shown} / {figures['energy']:,.0f}" + (f" (misses: {', '.join(broken)})" if broken else "")

    for path in sorted(TUNED_DIR.glob("*.json")):
        data = read_tuned_file(path)
        for law, entry in data["laws"].items():
            point, same = entry["point"], entry.get("same_as")
            tuned_figures = entry["best"] if entry.get("improved") else entry["default"]
            springs = f"x {point['spring_scale']:.3g} of rule 2" if point["saturated"] else "unsaturated"
            adaptive = (f"{point['alpha_scale']:.3g}, {point['adaptation_scale']:.3g}" if "alpha_scale" in point
                        else "-")
            verdict = "" if entry.get("improved") else " (no better set found: the defaults)"
            ki = f"{point['ki']:.3g}" if "ki" in point else "-"
            lines.append(f"| {data['scenario']} | {law}{f' (= {same})' if same else ''} | {entry['trials']} | "
                         f"{band(entry['default'])} | {band(tuned_figures)}{verdict} | {point['kp_scale']:.3g} | "
                         f"{point['kd_scale']:.3g} | {springs} | {point['rate_steps']:.2f} | {ki} | {adaptive} |")
    return "\n".join(lines)


__all__ = ["tuned_gains_table", "TUNED_SCHEMA", "TUNING_SEEDS", "DISTRIBUTION_TUNING_SEEDS", "UNSEEN_CHECK_SEEDS", "SEARCH_SPACE",
           "law_parameters", "gains_from_point", "load_tuned", "read_tuned_file", "check_point", "tuned_path",
           "tuned_gains_source", "scenario_digest"]
