"""The scoreboard's rows: its cells aggregated per (place, split, method), and their markdown tables.

A row holds a method's seeds, budget, wall time, physics faults, failed training runs (left out: nothing to
evaluate), runs that training stopped early (in, as their saved policy stood at the stop) and every metric of
:data:`METRICS` aggregated over training seeds within each evaluation episode (:func:`studies.bootstrap.aggregate`);
``studies.scoreboard`` computes the cells and merges the rows into the committed board.
"""

from __future__ import annotations

import collections
import json
import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ee_formation_env.baselines.metrics import fault_kinds
from ee_formation_env.scenario_sets import DISTRIBUTIONS
from studies.bootstrap import aggregate

#: The board's metrics, one value per evaluation episode: (key, title, unit, meaning, format).
METRICS: tuple[tuple[str, str, str, str, str], ...] = (
    ("success", "success", "%", "the episode settled and held the formation (metrics' definition)", "{:.0%}"),
    ("settling_time_or_limit", "settle", "s", "settling time, or the episode length when it did not settle", "{:.2f}"),
    ("final_formation_error", "final err", "m² or m", "formation error at the last step", "{:.2e}"),
    ("physics_fault", "faulted", "%", "episodes the env ended with a physics fault", "{:.0%}"),
    ("contact_steps", "contacts", "steps", "env steps with a contact between arms", "{:.1f}"),
    ("mean_return", "return", "", "episode return, mean over agents", "{:,.0f}"),
)


def episode_values(episode: dict[str, Any], episode_seconds: float) -> dict[str, float]:
    """The board's metrics of one episode (an ``EpisodeMetrics.as_dict()``)."""
    settling = episode["settling_time"]
    return {
        "success": float(bool(episode["success"])),
        "settling_time_or_limit": float(settling) if episode["success"] and math.isfinite(settling) else episode_seconds,
        "final_formation_error": float(episode["final_formation_error"]),
        "physics_fault": float(bool(episode["physics_fault"])),
        "contact_steps": float(episode["contact_steps"]),
        "mean_return": float(episode["mean_return"]),
    }


def _place(record: dict[str, Any]) -> tuple[str, str]:
    """(training scenario, evaluated scenario) of a cell: a test scenario may share a built-in's name."""
    return record.get("trained_on", record["scenario"]), record["scenario"]


def rows(records: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per (scenario, method): its seeds, budget, wall time and every metric aggregated."""
    grouped: dict[tuple[tuple[str, str], str, str], list[dict[str, Any]]] = {}
    for record in records:
        grouped.setdefault((_place(record), record.get("split", "train"), record["method"]), []).append(record)
    out = []
    for ((_, scenario), _, method), every_cell in grouped.items():
        # split "train": the scenario the method trains on; "test": a held-out scenario (trained_on says which)
        split = {"split": every_cell[0].get("split", "train"),
                 **({"trained_on": every_cell[0]["trained_on"]} if "trained_on" in every_cell[0] else {})}
        every_cell = sorted(every_cell, key=lambda c: -1 if c["seed"] is None else c["seed"])
        failures = [{"seed": c["seed"], "reason": c["failed"]} for c in every_cell if c.get("failed")]
        cells = [c for c in every_cell if not c.get("failed")]
        # runs that training stopped early, in the row as evaluated at the stop
        stopped = [{"seed": c["seed"], "reason": c["stopped"]} for c in cells if c.get("stopped")]
        if not cells:  # every training run of this row stopped: reported, with no metrics
            out.append({"scenario": scenario, "method": method, **split,
                        "seeds": [c["seed"] for c in every_cell], "eval_seeds": every_cell[0]["eval_seeds"],
                        "episode_seconds": every_cell[0]["episode_seconds"], "budget": {"agent_steps_per_seed": []},
                        "wall_seconds": float(sum(c["wall_seconds"] for c in every_cell)), "faults": [],
                        "failures": failures, "metrics": {}})
            continue
        eval_seeds = cells[0]["eval_seeds"]
        if any(c["eval_seeds"] != eval_seeds for c in cells):
            raise ValueError(f"cells: {scenario} / {method} mixes evaluation seeds; delete its cells and rerun")
        values = [[episode_values(e, c["episode_seconds"]) for e in c["episodes"]] for c in cells]
        out.append({
            "scenario": scenario, "method": method, **split,
            "seeds": [c["seed"] for c in cells if c["seed"] is not None],
            "eval_seeds": eval_seeds, "episode_seconds": cells[0]["episode_seconds"],
            "budget": {"agent_steps_per_seed": [c["budget"].get("agent_steps", 0) for c in cells],
                       **({"total_timesteps": cells[0]["budget"]["total_timesteps"]}
                          if "total_timesteps" in cells[0]["budget"] else {})},
            "wall_seconds": float(sum(c["wall_seconds"] for c in cells)),
            "faults": [{"reason": reason, "episodes": count} for reason, count in fault_kinds(collections.Counter(
                e["physics_fault"] for c in cells for e in c["episodes"] if e["physics_fault"]))],
            "failures": failures,
            **({"stopped": stopped} if stopped else {}),
            "metrics": {key: aggregate([[v[key] for v in run] for run in values]) for key, *_ in METRICS},
            # the code versions of its cells (studies.scoreboard_cells): one, unless stale cells were accepted
            "code": [dict(code) for code in {json.dumps(c.get("code"), sort_keys=True): c.get("code")
                                             for c in cells if c.get("code")}.values()],
        })
    return out


def _interval(spec: str, metric: dict[str, Any]) -> str:
    """One metric as ``mean [ci_low, ci_high]`` in the format ``spec``."""
    return f"{spec.format(metric['mean'])} [{spec.format(metric['ci_low'])}, {spec.format(metric['ci_high'])}]"


def format_board(board_rows: Sequence[dict[str, Any]]) -> str:
    """Markdown: one table per scenario, a row per method, each metric as mean [95 % interval]."""
    lines: list[str] = []

    def table(row: dict[str, Any]) -> tuple[tuple[str, str], str]:
        return _place(row), row["split"]

    for place, split in dict.fromkeys(table(row) for row in board_rows):
        scenario = place[1]
        first = next(row for row in board_rows if table(row) == (place, split))
        if scenario in DISTRIBUTIONS:
            seeds = first["eval_seeds"]
            title = f"{scenario}, {split} set (its draws at the {len(seeds)} reset seeds {seeds[0]}-{seeds[-1]})"
        elif split == "team":
            seeds = first["eval_seeds"]
            title = (f"{scenario} (team size {team_size(scenario)}: policies trained on {place[0]}, evaluated here "
                     f"unchanged on its draws at the {len(seeds)} reset seeds {seeds[0]}-{seeds[-1]})")
        else:
            title = scenario if place[0] == scenario else (
                f"{scenario} (test: policies trained on {place[0]}, evaluated here unchanged)")
        lines += [f"### {title}", "",
                  "| method | seeds | agent steps per seed | " + " | ".join(
                      f"{title} ({unit})" if unit else title for _, title, unit, _, _ in METRICS) + " | wall s |",
                  "|---|---|---:|" + "---:|" * (len(METRICS) + 1)]
        for row in (r for r in board_rows if table(r) == (place, split)):
            if not row["metrics"]:
                lines.append(f"| {row['method']} | {', '.join(map(str, row['seeds']))} | - | " +
                             " | ".join(["training failed"] * len(METRICS)) + f" | {row['wall_seconds']:,.0f} |")
                continue
            cells = [_interval(spec, row["metrics"][key]) for key, _, _, _, spec in METRICS]
            seeds = ", ".join(map(str, row["seeds"])) or "-"
            steps = row["budget"]["agent_steps_per_seed"]  # differ where a wall-clock cap stopped a run
            budget = f"{max(steps):,}" if min(steps) == max(steps) else f"{min(steps):,}-{max(steps):,}"
            lines.append(f"| {row['method']} | {seeds} | {budget} | " + " | ".join(cells) +
                         f" | {row['wall_seconds']:,.0f} |")
        faulted = [row for row in board_rows if table(row) == (place, split) and row["faults"]]
        for row in faulted:
            kinds = "; ".join(f"{fault['reason']} ({fault['episodes']}x)" for fault in row["faults"][:3])
            lines.append(f"\n- {row['method']}: physics faults: {kinds}")
        for row in (r for r in board_rows if table(r) == (place, split) and r["failures"]):
            for failure in row["failures"]:
                lines.append(f"\n- {row['method']}, seed {failure['seed']}: {failure['reason']}")
        for row in (r for r in board_rows if table(r) == (place, split) and r.get("stopped")):
            for stop in row["stopped"]:
                lines.append(f"\n- {row['method']}, seed {stop['seed']}, in the row as its policy stood when "
                             f"training stopped early: {stop['reason']}")
        lines.append("")
    return "\n".join(lines + team_size_table(board_rows)).rstrip() + "\n"


#: The fewest training seeds of a learned row the headline ranks: one or two runs do not make a method's result.
HEADLINE_MIN_SEEDS = 3
#: The training seeds of a headline claim: the headline counts the tasks whose best learned row has as many.
HEADLINE_CLAIM_SEEDS = 5
#: The headline's columns: (metric key, title) of :data:`METRICS`.
HEADLINE_METRICS = (("success", "success (%)"), ("settling_time_or_limit", "settle (s)"),
                    ("contact_steps", "contacts (steps)"))


def _headline_tasks(board_rows: Sequence[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """Task -> its rows with metrics, in board order: a fixed scenario's training-scenario rows, a distribution's
    test-set rows (its held-out draws); test scenarios and team sizes (transfer) are not tasks here."""
    tasks: dict[str, list[dict[str, Any]]] = {}
    for row in board_rows:
        trained_on, scenario = _place(row)
        wanted = "test" if scenario in DISTRIBUTIONS else "train"
        if row["split"] == wanted and trained_on == scenario and row["metrics"]:
            tasks.setdefault(scenario, []).append(row)
    return tasks


def _best(rows_of_kind: Sequence[dict[str, Any]]) -> dict[str, Any] | None:
    """The row of the highest mean success, then the shortest mean settling time."""
    key = lambda row: (-row["metrics"]["success"]["mean"], row["metrics"]["settling_time_or_limit"]["mean"])  # noqa: E731
    return min(rows_of_kind, key=key, default=None)


def beats(learned: dict[str, Any], law: dict[str, Any]) -> list[str]:
    """Why the learned row does not beat the law's (empty: it does): it must succeed at least as often, settle
    faster with disjoint 95 % intervals and have no more contact steps per episode."""
    mine, theirs = learned["metrics"], law["metrics"]
    reasons = []
    if mine["success"]["mean"] < theirs["success"]["mean"]:
        reasons.append("lower success")
    if mine["settling_time_or_limit"]["mean"] >= theirs["settling_time_or_limit"]["mean"]:
        reasons.append("slower")
    elif mine["settling_time_or_limit"]["ci_high"] >= theirs["settling_time_or_limit"]["ci_low"]:
        reasons.append("settling intervals overlap")
    if mine["contact_steps"]["mean"] > theirs["contact_steps"]["mean"]:
        reasons.append("more contacts")
    return reasons


def headline_table(board_rows: Sequence[dict[str, Any]]) -> str:
    """Markdown: per task, the best law, the best learned method from scratch and the best residual (learned rows
    of at least :data:`HEADLINE_MIN_SEEDS` seeds; the best: highest success, then shortest settling), and whether
    each learned one beats the law (:func:`beats`); then the count of tasks a learned method wins."""
    from studies.scoreboard_methods import METHODS  # the methods' kinds; rows of retired methods are left out

    lines = ["| task | kind | method | seeds | " + " | ".join(title for _, title in HEADLINE_METRICS) +
             " | beats the best law |", "|---|---|---|---:|" + "---:|" * len(HEADLINE_METRICS) + "---|"]
    formats = {key: spec for key, *_, spec in METRICS}
    won, claims, tasks = [], [], _headline_tasks(board_rows)
    for task, task_rows in tasks.items():
        kinds = {kind: [row for row in task_rows if row["method"] in METHODS and METHODS[row["method"]].kind == kind
                        and (kind == "law" or len(row["seeds"]) >= HEADLINE_MIN_SEEDS)]
                 for kind in ("law", "from scratch", "residual")}
        law = _best(kinds["law"])
        name = f"{task} (test draws)" if task in DISTRIBUTIONS else task
        for kind, rows_of_kind in kinds.items():
            row = _best(rows_of_kind)
            if row is None:
                continue
            cells = [_interval(formats[key], row["metrics"][key]) for key, _ in HEADLINE_METRICS]
            verdict = ""
            if kind != "law" and law is not None:
                reasons = beats(row, law)
                verdict = "no: " + ", ".join(reasons) if reasons else "**yes**"
                if not reasons and task not in won:
                    won.append(task)
            lines.append(f"| {name} | {kind} | {row['method']} | {len(row['seeds']) or '-'} | " + " | ".join(cells) +
                         f" | {verdict} |")
            name = ""
        best_learned = _best(kinds["from scratch"] + kinds["residual"])
        if best_learned is not None and len(best_learned["seeds"]) >= HEADLINE_CLAIM_SEEDS:
            claims.append(task)
    lines += ["", f"A learned method beats the best law on {len(won)} of {len(tasks)} tasks"
              + (f" ({', '.join(won)})" if won else "") + f"; the best learned row has {HEADLINE_CLAIM_SEEDS} "
              f"seeds or more on {len(claims)} of {len(tasks)}."]
    return "\n".join(lines) + "\n"


def team_size(scenario: str) -> int:
    """The team size N of a team-size split's scenario (``planar_team_5``: 5)."""
    return int(scenario.rsplit("_", 1)[1])


def _team_curves(board_rows: Sequence[dict[str, Any]]) -> dict[tuple[str, str], dict[int, dict[str, Any]]]:
    """(trained on, method) -> {N: row} of the team-size split's rows that have metrics."""
    curves: dict[tuple[str, str], dict[int, dict[str, Any]]] = {}
    for row in board_rows:
        if row["split"] == "team" and row["metrics"]:
            curves.setdefault((row["trained_on"], row["method"]), {})[team_size(row["scenario"])] = row
    return curves


def team_size_table(board_rows: Sequence[dict[str, Any]]) -> list[str]:
    """Markdown lines: per training scenario, success [95 %] and settling (s, mean) of each method at every team
    size of the split (none without team rows)."""
    curves = _team_curves(board_rows)
    lines: list[str] = []
    for trained in dict.fromkeys(trained for trained, _ in curves):
        sizes = sorted({n for (t, _), by_size in curves.items() if t == trained for n in by_size})
        lines += ["", f"### Team size: trained on {trained}, success [95 %] / settling or episode length (s) at each N", "",
                  "| method | " + " | ".join(f"N = {n}" for n in sizes) + " |", "|---|" + "---:|" * len(sizes)]
        for (t, method), by_size in curves.items():
            if t != trained:
                continue
            cells = []
            for n in sizes:
                if n not in by_size:
                    cells.append("-")
                    continue
                success, settle = by_size[n]["metrics"]["success"], by_size[n]["metrics"]["settling_time_or_limit"]
                cells.append(f"{success['mean']:.0%} [{success['ci_low']:.0%}, {success['ci_high']:.0%}] / "
                             f"{settle['mean']:.2f}")
            lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return lines


def team_size_figure(board_rows: Sequence[dict[str, Any]], path: Path) -> Path | None:
    """Success vs team size with 95 % intervals, one line per method and training scenario of the team-size
    split; None (nothing written) without team rows."""
    curves = _team_curves(board_rows)
    if not curves:
        return None
    import importlib.util

    if importlib.util.find_spec("matplotlib") is None:
        import warnings

        warnings.warn(f"scoreboard: {path} not drawn: the team-size figure needs matplotlib (the figures extra)")
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from studies._common import save_figure

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for k, ((trained, method), by_size) in enumerate(curves.items()):
        sizes = sorted(by_size)
        success = [by_size[n]["metrics"]["success"] for n in sizes]
        rate = np.array([100 * s["mean"] for s in success])
        low = np.maximum(rate - [100 * s["ci_low"] for s in success], 0.0)
        high = np.maximum(np.array([100 * s["ci_high"] for s in success]) - rate, 0.0)
        label = method if len({t for t, _ in curves}) == 1 else f"{method} ({trained})"
        ax.errorbar(np.array(sizes) + 0.06 * (k - (len(curves) - 1) / 2), rate, yerr=[low, high], marker="o",
                    capsize=3, label=label)
    trained = sorted({t for t, _ in curves})
    ax.set_xlabel(f"team size N (arms); learned policies trained on {', '.join(trained)} only")
    ax.set_ylabel("success (%)")
    ax.set_ylim(0, 105)
    ax.set_xticks(sorted({n for by_size in curves.values() for n in by_size}))
    ax.legend(loc="lower left", fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    return save_figure(fig, path)


def write_outputs(board_rows: Sequence[dict[str, Any]], json_path: Path, markdown_path: Path | None = None,
                  generated_page: Path | None = None) -> None:
    """``scoreboard.json`` (``{"rows": [...]}``), the markdown tables, and the generated block of a docs page."""
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps({"rows": list(board_rows), "metrics": {k: {"title": t, "unit": u, "meaning": m}
                                                                          for k, t, u, m, _ in METRICS}},
                                    indent=1, default=float) + "\n", encoding="utf-8")
    table = format_board(board_rows)
    if markdown_path is not None:
        markdown_path.write_text(table, encoding="utf-8")
    if generated_page is not None:
        text = generated_page.read_text(encoding="utf-8")
        for block, content in (("scoreboard", table), ("headline", headline_table(board_rows))):
            text = _filled_block(text, block, content, generated_page)
        generated_page.write_text(text, encoding="utf-8")


def _filled_block(text: str, block: str, content: str, page: Path) -> str:
    """``text`` with its ``<!-- generated: block -->`` ... ``<!-- end generated -->`` block holding ``content``."""
    import re

    pattern = rf"(<!-- generated: {block} -->\n)(.*?)(<!-- end generated -->)"
    if not re.search(pattern, text, re.S):
        raise ValueError(f"--docs: {page} has no generated {block} block")
    return re.sub(pattern, lambda m: m.group(1) + content.strip() + "\n" + m.group(3), text, count=1, flags=re.S)
