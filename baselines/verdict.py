"""The one rule by which a policy is said to beat a reference law, and the shortfalls it names.

Used by ``train.py``'s comparison (:mod:`ee_formation_env.baselines.learned.compare`) and the scoreboard's
headline (``studies/scoreboard_rows.py``). Both hand it, per policy, an estimate of each metric of
:data:`VERDICT_METRICS`: ``{"mean", "ci_low", "ci_high"}`` (95 % intervals; the comparison's over its evaluation
episodes, :func:`estimates`; the board's over training seeds within each episode). The per-episode values are
:func:`episode_values` of an :class:`~ee_formation_env.baselines.metrics.EpisodeMetrics` record.

A candidate **beats** a law (:func:`judge`) when all of these hold:

- its success rate is no lower;
- it reaches the 1 mm band faster, with disjoint 95 % intervals (an episode that never holds the band counts
  its whole length);
- its steady-state worst edge error is at most :data:`PRECISION_LIMIT` (1 mm);
- it has no more contact steps;
- it spends at most :data:`ENERGY_RATIO` times the law's energy.

Otherwise the verdict lists what it loses on, and what it wins on, metric by metric (a trade-off is named both
ways). :func:`shortfalls` are the failings the comparison warns about, each with its threshold: lower success,
precision (worst edge above 1 mm while the law's is below), singularity (smallest singular value below
:data:`SINGULARITY_RATIO` of the law's), return (mean below the law's lower 95 % bound), effort (energy above
:data:`ENERGY_RATIO` times the law's), contacts, and speed (slower to the 1 mm band at equal success).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from ee_formation_env.baselines.metrics import PRECISION_TOLERANCE

PRECISION_LIMIT = PRECISION_TOLERANCE  # m: the steady-state worst edge error a winner must stay within
ENERGY_RATIO = 1.5  # a winner spends at most this multiple of the law's energy
SINGULARITY_RATIO = 0.1  # a policy whose arms come closer to a singularity than this share of the law's falls short
BOOTSTRAP_REPS = 2000

#: The metrics the rule reads, one value per episode: key -> (title, unit, meaning).
VERDICT_METRICS: dict[str, tuple[str, str, str]] = {
    "success": ("success", "%", "the episode settled in the 1 cm band and held it (metrics' definition)"),
    "settle_1mm": ("to 1 mm", "s", "time after which every edge stays within 1 mm, or the episode length"),
    "steady_worst": ("steady worst", "m", "largest edge length error over the episode's last second"),
    "contacts": ("contacts", "steps", "env steps with a contact between arms"),
    "energy": ("energy", "N² m² s", "sum over arms of the integral of |τ|² dt"),
    "min_sigma": ("min sigma", "m", "smallest singular value of any arm's Jacobian in the episode"),
    "return": ("return", "", "episode return, mean over agents"),
}


def episode_values(episode: Mapping[str, Any], episode_seconds: float) -> dict[str, float]:
    """The rule's values of one episode (an ``EpisodeMetrics.as_dict()``); ``episode_seconds``: its length, the
    time counted for a band never held."""
    settle = episode.get("settling_time_1mm", math.nan)
    return {
        "success": float(bool(episode["success"])),
        "settle_1mm": float(settle) if episode.get("success_1mm") and math.isfinite(settle) else float(episode_seconds),
        "steady_worst": float(episode.get("steady_worst_edge_error", math.nan)),
        "contacts": float(episode["contact_steps"]),
        "energy": float(episode["control_energy"]),
        "min_sigma": float(episode["min_singularity_margin"]),
        "return": float(episode["mean_return"]),
    }


def estimates(episodes: Sequence[Mapping[str, Any]], episode_seconds: float, seed: int = 0
              ) -> dict[str, dict[str, float]]:
    """Mean and 95 % percentile bootstrap interval over ``episodes`` of every value of :func:`episode_values`."""
    values = [episode_values(e, episode_seconds) for e in episodes]
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, len(values), size=(BOOTSTRAP_REPS, len(values)))
    out = {}
    for key in VERDICT_METRICS:
        series = np.array([v[key] for v in values], dtype=np.float64)
        means = series[picks].mean(axis=1)
        low, high = np.percentile(means, [2.5, 97.5])
        out[key] = {"mean": float(series.mean()), "ci_low": float(low), "ci_high": float(high)}
    return out


@dataclass(frozen=True)
class Verdict:
    """Whether a candidate beats a law (:func:`judge`), and why not: what it loses on and what it wins on."""

    beats: bool
    losses: list[str] = field(default_factory=list)
    wins: list[str] = field(default_factory=list)

    def text(self) -> str:
        if self.beats:
            return "yes"
        won = f"; better: {', '.join(self.wins)}" if self.wins else ""
        return "no: " + ", ".join(self.losses) + won


def judge(candidate: Mapping[str, Mapping[str, float]], law: Mapping[str, Mapping[str, float]]) -> Verdict:
    """The rule of the module docstring; each argument maps the keys of :data:`VERDICT_METRICS` to estimates."""
    mine = {key: candidate[key]["mean"] for key in VERDICT_METRICS}
    theirs = {key: law[key]["mean"] for key in VERDICT_METRICS}
    losses, wins = [], []
    if mine["success"] < theirs["success"]:
        losses.append(f"success {mine['success']:.0%} < {theirs['success']:.0%}")
    elif mine["success"] > theirs["success"]:
        wins.append(f"success {mine['success']:.0%} > {theirs['success']:.0%}")
    faster = candidate["settle_1mm"]["ci_high"] < law["settle_1mm"]["ci_low"]
    slower = candidate["settle_1mm"]["ci_low"] > law["settle_1mm"]["ci_high"]
    if faster:
        wins.append(f"to 1 mm {mine['settle_1mm']:.2f} s < {theirs['settle_1mm']:.2f} s")
    else:
        losses.append(f"to 1 mm {mine['settle_1mm']:.2f} s vs {theirs['settle_1mm']:.2f} s"
                      + (" (slower)" if slower else " (intervals overlap)"))
    if not mine["steady_worst"] <= PRECISION_LIMIT:
        losses.append(f"steady worst edge {mine['steady_worst'] * 1e3:.2g} mm > 1 mm")
    if mine["steady_worst"] < theirs["steady_worst"] and mine["steady_worst"] <= PRECISION_LIMIT < theirs["steady_worst"]:
        wins.append(f"steady worst edge within 1 mm ({theirs['steady_worst'] * 1e3:.2g} mm for the law)")
    if mine["contacts"] > theirs["contacts"]:
        losses.append(f"contacts {mine['contacts']:.1f} > {theirs['contacts']:.1f}")
    elif mine["contacts"] < theirs["contacts"]:
        wins.append(f"contacts {mine['contacts']:.1f} < {theirs['contacts']:.1f}")
    if mine["energy"] > ENERGY_RATIO * theirs["energy"]:
        losses.append(f"energy {_ratio(mine['energy'], theirs['energy'])} the law's")
    elif mine["energy"] < theirs["energy"]:
        wins.append(f"energy {_ratio(mine['energy'], theirs['energy'])} the law's")
    beats = not losses
    return Verdict(beats, losses, wins)


def _ratio(mine: float, theirs: float) -> str:
    return f"{mine / theirs:.2g}x" if theirs > 0 else "inf x"


def shortfalls(candidate: Mapping[str, Mapping[str, float]], law: Mapping[str, Mapping[str, float]]
               ) -> list[dict[str, Any]]:
    """The candidate's failings against the law (module docstring): ``[{"metric", "candidate", "law",
    "threshold", "message"}]``, empty when there is none."""
    mine = {key: candidate[key]["mean"] for key in VERDICT_METRICS}
    theirs = {key: law[key]["mean"] for key in VERDICT_METRICS}
    found = []

    def add(metric: str, threshold: str, message: str) -> None:
        found.append({"metric": metric, "candidate": mine.get(metric), "law": theirs.get(metric),
                      "threshold": threshold, "message": message})

    if mine["success"] < theirs["success"]:
        add("success", "no lower than the law's", f"succeeds in {mine['success']:.0%} of the episodes, the law in "
            f"{theirs['success']:.0%}")
    if not mine["steady_worst"] <= PRECISION_LIMIT and theirs["steady_worst"] <= PRECISION_LIMIT:
        add("steady_worst", "worst edge <= 1 mm where the law's is", f"holds its worst edge "
            f"{mine['steady_worst'] * 1e3:.3g} mm off over the last second, the law {theirs['steady_worst'] * 1e3:.2g} mm")
    if mine["min_sigma"] < SINGULARITY_RATIO * theirs["min_sigma"]:
        add("min_sigma", f"min sigma >= {SINGULARITY_RATIO:.0%} of the law's", f"comes within "
            f"{mine['min_sigma']:.2g} m of a singularity (smallest Jacobian singular value), the law "
            f"{theirs['min_sigma']:.2g} m")
    if mine["return"] < law["return"]["ci_low"]:
        add("return", "mean >= the law's lower 95 % bound", f"returns {mine['return']:,.4g} per agent, below the "
            f"law's {theirs['return']:,.4g} (95 % interval from {law['return']['ci_low']:,.4g})")
    if mine["energy"] > ENERGY_RATIO * theirs["energy"]:
        add("energy", f"<= {ENERGY_RATIO}x the law's", f"spends {_ratio(mine['energy'], theirs['energy'])} the "
            "law's energy")
    if mine["contacts"] > theirs["contacts"]:
        add("contacts", "no more than the law's", f"touches other arms in {mine['contacts']:.1f} steps per episode, "
            f"the law in {theirs['contacts']:.1f}")
    if mine["success"] == theirs["success"] and candidate["settle_1mm"]["ci_low"] > law["settle_1mm"]["ci_high"]:
        add("settle_1mm", "no slower to the 1 mm band", f"reaches the 1 mm band in {mine['settle_1mm']:.2f} s, the "
            f"law in {theirs['settle_1mm']:.2f} s")
    return found


def best_law(laws: Mapping[str, Mapping[str, Mapping[str, float]]]) -> str | None:
    """The law of the highest success, then the fastest to the 1 mm band (names -> estimates)."""
    if not laws:
        return None
    return min(laws, key=lambda name: (-laws[name]["success"]["mean"], laws[name]["settle_1mm"]["mean"]))
