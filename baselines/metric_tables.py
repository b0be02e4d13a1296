"""The metrics tables: the columns of :func:`~ee_formation_env.baselines.metrics.summarize`'s summaries, defined
once (:data:`METRIC_COLUMNS`), their markdown table and definitions, and the fault notes under a table (a summary
never hides a fault). Re-exported by :mod:`ee_formation_env.baselines.metrics`."""

from __future__ import annotations

import math
import re
import textwrap
from dataclasses import dataclass
from typing import Any, Mapping


@dataclass(frozen=True)
class MetricColumn:
    """One column of the metrics tables: the :func:`summarize` key it shows, its title, unit and meaning."""

    key: str
    title: str
    unit: str  # "" when dimensionless
    meaning: str
    format: str  # str.format spec of a cell

    @property
    def header(self) -> str:
        return f"{self.title} ({self.unit})" if self.unit else self.title


#: The metrics tables' columns, defined once: used by :func:`format_table`, ``python -m ee_formation_env.baselines.evaluate
#: --help`` and the README. Each cell is a mean over episodes unless its meaning says otherwise.
METRIC_COLUMNS: tuple[MetricColumn, ...] = (
    MetricColumn("success_rate", "success", "%", "share of episodes whose formation error fell below the tolerance "
                 "(the error of edges --tolerance m off their lengths) and stayed below to the end, for at least 1 s",
                 "{:.0%}"),
    MetricColumn("physics_faults", "faults", "episodes", "episodes the env ended with a physics fault (a "
                 "non-finite joint state, or a joint faster than max_joint_velocity); never a success; their "
                 "reasons are listed under the table", "{:d}"),
    MetricColumn("final_formation_error", "final err", "m² or m", "formation error at the last step: RMS over edges "
                 "of |e_k|, e_k = |z_k|² − d_k² (m², distance formations) or z_k − z*_k (m, displacement)", "{:.2e}"),
    MetricColumn("settling_time", "settle", "s", "time after which the formation error stays within the tolerance; "
                 "mean over successful episodes only (n/a: none succeeded)", "{:.2f}"),
    MetricColumn("success_rate_1mm", "1 mm", "%", "share of episodes in which every edge's length error (| |z_k| − "
                 "d_k | distance, |z_k − z*_k| displacement) fell below 1 mm and stayed below to the end, for at least "
                 "1 s", "{:.0%}"),
    MetricColumn("settling_time_1mm", "settle 1 mm", "s", "time after which every edge's length error stays below "
                 "1 mm; mean over the episodes that reached it (n/a: none)", "{:.2f}"),
    MetricColumn("steady_rms_edge_error", "steady rms", "m", "RMS of the edges' length errors over the last second "
                 "of the episode", "{:.1e}"),
    MetricColumn("steady_worst_edge_error", "steady worst", "m", "largest edge length error over the last second of "
                 "the episode", "{:.1e}"),
    MetricColumn("control_energy", "energy", "N² m² s", "sum over arms of the integral of |τ|² dt, τ the applied "
                 "joint torques", "{:.3g}"),
    MetricColumn("torque_rate", "torque rate", "N m/s", "smoothness: mean over steps and joints of |τ_t − τ_t−1| / "
                 "dt (the first step's jump from rest left out)", "{:.3g}"),
    MetricColumn("peak_torque", "peak", "N m", "largest |τ| of any joint at any step", "{:.3g}"),
    MetricColumn("saturation_fraction", "saturated", "%", "share of (step, joint) actions clipped at the torque "
                 "limit", "{:.1%}"),
    MetricColumn("min_singularity_margin", "min sigma", "m", "smallest singular value of any arm's Jacobian "
                 "(formation axes) seen in any episode: near 0 means near a singularity", "{:.3f}"),
    MetricColumn("contact_steps", "contacts", "steps", "env steps with any contact between arms", "{:.1f}"),
    MetricColumn("centroid_drift", "drift", "m", "distance the end-effectors' centroid moved from start to end "
                 "(a formation goal allows any translation; large drift means wandering)", "{:.3f}"),
)


def format_table(rows: Mapping[str, Mapping[str, Any]]) -> str:
    """A markdown table, one row per policy, from :func:`summarize` outputs (columns: :data:`METRIC_COLUMNS`)."""
    header = "| policy | " + " | ".join(column.header for column in METRIC_COLUMNS) + " |"
    lines = [header, "|" + "---|" * (len(METRIC_COLUMNS) + 1)]
    for name, summary in rows.items():
        cells = []
        for column in METRIC_COLUMNS:
            value = summary.get(column.key, math.nan)
            cells.append("n/a" if isinstance(value, float) and math.isnan(value) else column.format.format(value))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    notes = fault_notes(rows)
    return "\n".join(lines + ([""] + notes if notes else []))


def fault_kind(reason: str) -> str:
    """A fault reason with its numbers masked ("arm_1: joint speed # rad/s exceeds max_joint_velocity # rad/s"):
    faults of one kind on one arm count together."""
    return re.sub(r"(?<![\w.])\d+(\.\d+)?(e[+-]?\d+)?", "#", reason)


def fault_kinds(reasons: Mapping[str, int]) -> list[tuple[str, int]]:
    """``{reason: count}`` grouped by :func:`fault_kind`: (an example reason of the kind, its count), most
    frequent first."""
    counts: dict[str, int] = {}
    examples: dict[str, str] = {}
    for reason, count in reasons.items():
        kind = fault_kind(reason)
        counts[kind] = counts.get(kind, 0) + count
        examples[kind] = reason
    return sorted(((examples[kind], count) for kind, count in counts.items()), key=lambda item: (-item[1], item[0]))


def fault_notes(rows: Mapping[str, Mapping[str, Any]], shown: int = 3) -> list[str]:
    """One line per policy with faulted episodes: how many, and the ``shown`` most frequent kinds of fault
    (:func:`fault_kinds`: an example reason each) with their counts (a summary never hides a fault)."""
    notes = []
    for name, summary in rows.items():
        reasons = summary.get("physics_fault_reasons") or {}
        if not reasons:
            continue
        ranked = fault_kinds(reasons)
        listed = "; ".join(f"{reason} ({count}x)" for reason, count in ranked[:shown])
        more = f"; {len(ranked) - shown} other kinds" if len(ranked) > shown else ""
        notes.append(f"- {name}: {summary['physics_faults']} of {summary['episodes']} episodes ended in a physics "
                     f"fault: {listed}{more}")
    return notes


def metric_definitions(markdown: bool = False) -> str:
    """The columns' units and meanings: plain text (for ``--help``) or a markdown table (for the README)."""
    if markdown:
        lines = ["| column | unit | meaning |", "|---|---|---|"]
        lines += [f"| {c.title} | {c.unit or '-'} | {c.meaning.replace('|', chr(92) + '|')} |" for c in METRIC_COLUMNS]
        return "\n".join(lines)
    width = max(len(c.header) for c in METRIC_COLUMNS)
    return "\n".join(textwrap.fill(c.meaning, 110, initial_indent=f"  {c.header:<{width}}  ",
                                   subsequent_indent=" " * (width + 4)) for c in METRIC_COLUMNS)
