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
import re
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ee_formation_env.baselines.atomic_files import make_folder, write_text
from ee_formation_env.baselines.metrics import fault_kinds
from ee_formation_env.baselines.verdict import ENERGY_RATIO, episode_values as verdict_values, judge
from ee_formation_env.scenario import load_scenario
from ee_formation_env.scenario_sets import DISTRIBUTIONS, WIDE_START_NOISE
from studies.bootstrap import aggregate

#: The board's metrics, one value per evaluation episode: (key, title, unit, meaning, format).
METRICS: tuple[tuple[str, str, str, str, str], ...] = (
    ("success", "success", "%", "the episode settled and held the formation (metrics' definition)", "{:.0%}"),
    ("settling_time_or_limit", "settle", "s", "settling time, or the episode length when it did not settle", "{:.2f}"),
    ("settling_time_1mm_or_limit", "to 1 mm", "s", "time after which every edge stays within 1 mm of its length, or "
     "the episode length when it never does", "{:.2f}"),
    ("steady_worst_edge_error", "steady worst", "m", "largest edge length error over the episode's last second",
     "{:.1e}"),
    ("final_formation_error", "final err", "m² or m", "formation error at the last step", "{:.2e}"),
    ("physics_fault", "faulted", "%", "episodes the env ended with a physics fault", "{:.0%}"),
    ("contact_steps", "contacts", "steps", "env steps with a contact between arms", "{:.1f}"),
    ("control_energy", "energy", "N² m² s", "sum over arms of the integral of |τ|² dt", "{:,.0f}"),
    ("torque_rate", "torque rate", "N m/s", "mean |τ_t − τ_t−1| / dt over steps and joints", "{:,.0f}"),
    ("min_singularity_margin", "min sigma", "m", "smallest Jacobian singular value in the episode", "{:.2g}"),
    ("mean_return", "return", "", "episode return, mean over agents", "{:,.0f}"),
)
#: The metrics cells computed before the precision metrics existed do not have (their rows say so).
PRECISION_METRICS = ("settling_time_1mm_or_limit", "steady_worst_edge_error", "torque_rate")


def episode_values(episode: dict[str, Any], episode_seconds: float) -> dict[str, float]:
    """The board's metrics of one episode (an ``EpisodeMetrics.as_dict()``); an episode recorded before the
    precision metrics existed has no :data:`PRECISION_METRICS`."""
    settling = episode["settling_time"]
    values = {
        "success": float(bool(episode["success"])),
        "settling_time_or_limit": float(settling) if episode["success"] and math.isfinite(settling) else episode_seconds,
        "final_formation_error": float(episode["final_formation_error"]),
        "physics_fault": float(bool(episode["physics_fault"])),
        "contact_steps": float(episode["contact_steps"]),
        "mean_return": float(episode["mean_return"]),
    }
    for key in ("control_energy", "min_singularity_margin"):  # every EpisodeMetrics record has them
        if key in episode:
            values[key] = float(episode[key])
    if "settling_time_1mm" in episode:
        precise = verdict_values(episode, episode_seconds)
        values.update(settling_time_1mm_or_limit=precise["settle_1mm"], steady_worst_edge_error=precise["steady_worst"],
                      torque_rate=float(episode["torque_rate"]))
    return values


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
            "metrics": {key: aggregate([[v[key] for v in run] for run in values]) for key, *_ in METRICS
                        if all(key in v for run in values for v in run)},
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
        elif split == "wide":
            seeds = first["eval_seeds"]
            title = (f"{scenario}, wide starts (±{WIDE_START_NOISE} rad about the initial joint angles, at the "
                     f"{len(seeds)} reset seeds {seeds[0]}-{seeds[-1]}; policies trained on the ±"
                     f"{load_scenario(scenario).initial_q_noise} rad starts, evaluated here unchanged)")
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
            cells = [_interval(spec, row["metrics"][key]) if key in row["metrics"] else "old metrics"
                     for key, _, _, _, spec in METRICS]
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
HEADLINE_METRICS = (("success", "success (%)"), ("settling_time_or_limit", "settle 1 cm (s)"),
                    ("settling_time_1mm_or_limit", "to 1 mm (s)"), ("steady_worst_edge_error", "steady worst (m)"),
                    ("contact_steps", "contacts (steps)"), ("control_energy", "energy (N² m² s)"))
#: The headline's kinds of row, in its order, with how each is shown.
HEADLINE_KINDS = (("law", "law, default gains"), ("tuned law", "law, tuned gains"), ("from scratch", "learned"),
                  ("residual", "hybrid: law + learned residual"))
#: The board's metric keys behind each value the verdict rule reads (ee_formation_env.baselines.verdict).
VERDICT_KEYS = {"success": "success", "settle_1mm": "settling_time_1mm_or_limit",
                "steady_worst": "steady_worst_edge_error", "contacts": "contact_steps", "energy": "control_energy",
                "min_sigma": "min_singularity_margin", "return": "mean_return"}


def _headline_tasks(board_rows: Sequence[dict[str, Any]], wide: bool = False) -> dict[str, list[dict[str, Any]]]:
    """Task -> its rows with metrics, in board order: a fixed scenario's training-scenario rows, a distribution's
    test-set rows (its held-out draws); test scenarios and team sizes (transfer) are not tasks here. ``wide``: the
    fixed scenarios' wide-start rows instead (split ``wide``)."""
    tasks: dict[str, list[dict[str, Any]]] = {}
    for row in board_rows:
        trained_on, scenario = _place(row)
        wanted = "wide" if wide else ("test" if scenario in DISTRIBUTIONS else "train")
        if row["split"] == wanted and trained_on == scenario and row["metrics"]:
            tasks.setdefault(scenario, []).append(row)
    return tasks


def precise(row: dict[str, Any]) -> bool:
    """Whether the row was measured with the precision metrics (cells from before them were not)."""
    return all(key in row["metrics"] for key in PRECISION_METRICS)


def _best(rows_of_kind: Sequence[dict[str, Any]]) -> dict[str, Any] | None:
    """The row of the highest mean success, then the fastest to the 1 mm band (rows measured before that metric
    existed come after the others at equal success, by their 1 cm settling)."""
    def key(row: dict[str, Any]) -> tuple[float, int, float]:
        metrics = row["metrics"]
        if precise(row):
            return -metrics["success"]["mean"], 0, metrics["settling_time_1mm_or_limit"]["mean"]
        return -metrics["success"]["mean"], 1, metrics["settling_time_or_limit"]["mean"]
    return min(rows_of_kind, key=key, default=None)


def beats(candidate: dict[str, Any], law: dict[str, Any]) -> list[str]:
    """Why the candidate row does not beat the law's (empty: it does), by the rule of
    :mod:`ee_formation_env.baselines.verdict` (success no lower, faster to the 1 mm band with disjoint 95 %
    intervals, steady worst edge within 1 mm, no more contacts, energy at most 1.5x), each loss named; a row
    measured before the precision metrics existed is not judged, and says so with what it has."""
    if not (precise(candidate) and precise(law)):
        return ["not judged: measured under the old metrics (no 1 mm band, no steady-state error)"] + _old_trade_offs(
            candidate, law)
    verdict = judge(*({key: row["metrics"][board] for key, board in VERDICT_KEYS.items()}
                      for row in (candidate, law)))
    return [] if verdict.beats else verdict.losses + ([f"better: {', '.join(verdict.wins)}"] if verdict.wins else [])


def _old_trade_offs(candidate: dict[str, Any], law: dict[str, Any]) -> list[str]:
    """The metrics an old row has, compared both ways: success, 1 cm settling, contacts, energy."""
    mine, theirs = candidate["metrics"], law["metrics"]
    items = []
    for key, name, spec in (("success", "success", "{:.0%}"), ("settling_time_or_limit", "settle 1 cm", "{:.2f} s"),
                            ("contact_steps", "contacts", "{:.1f}"), ("control_energy", "energy", "{:,.0f}")):
        if key not in mine or key not in theirs:
            continue
        a, b = mine[key]["mean"], theirs[key]["mean"]
        if a == b:
            continue
        better = a > b if key == "success" else a < b
        items.append(f"{name} {spec.format(a)} vs {spec.format(b)} ({'better' if better else 'worse'})")
    if "control_energy" in mine and "control_energy" in theirs and \
            mine["control_energy"]["mean"] > ENERGY_RATIO * theirs["control_energy"]["mean"]:
        items.append(f"energy over {ENERGY_RATIO}x the law's")
    return items


def headline_table(board_rows: Sequence[dict[str, Any]], wide: bool = False) -> str:
    """Markdown: per task, the best law at its default gains, the best law at its tuned gains, the best learned
    method from scratch and the best hybrid (a learned residual on a law) (learned rows of at least
    :data:`HEADLINE_MIN_SEEDS` seeds; the best: highest success, then fastest to the 1 mm band), and whether
    each learned one beats the best tuned law (:func:`beats`; the best default-gain law where no law is tuned);
    then the count of tasks each learned kind wins. ``wide``: the same on the fixed scenarios' wide starts."""
    from studies.scoreboard_methods import METHODS  # the methods' kinds; rows of retired methods are left out

    lines = ["| task | kind | method | seeds | " + " | ".join(title for _, title in HEADLINE_METRICS) +
             " | beats the best tuned law |", "|---|---|---|---:|" + "---:|" * len(HEADLINE_METRICS) + "---|"]
    formats = {key: spec for key, *_, spec in METRICS}
    won: dict[str, list[str]] = {"from scratch": [], "residual": []}
    claims, old, untuned, tasks = [], 0, [], _headline_tasks(board_rows, wide)
    for task, task_rows in tasks.items():
        kinds = {kind: [row for row in task_rows if row["method"] in METHODS and METHODS[row["method"]].kind == kind
                        and (kind in ("law", "tuned law") or len(row["seeds"]) >= HEADLINE_MIN_SEEDS)]
                 for kind, _ in HEADLINE_KINDS}
        law = _best(kinds["tuned law"])
        if law is None:
            law = _best(kinds["law"])
            untuned.append(task)
        name = f"{task} (test draws)" if task in DISTRIBUTIONS else task
        for kind, shown in HEADLINE_KINDS:
            row = _best(kinds[kind])
            if row is None:
                continue
            cells = [_interval(formats[key], row["metrics"][key]) if key in row["metrics"] else "old metrics"
                     for key, _ in HEADLINE_METRICS]
            verdict = ""
            if kind in won and law is not None:
                reasons = beats(row, law)
                verdict = "no: " + "; ".join(reasons) if reasons else "**yes**"
                old += not precise(row)
                if not reasons and task not in won[kind]:
                    won[kind].append(task)
            lines.append(f"| {name} | {shown} | {row['method']} | {len(row['seeds']) or '-'} | " + " | ".join(cells) +
                         f" | {verdict} |")
            name = ""
        best_learned = _best(kinds["from scratch"] + kinds["residual"])
        if best_learned is not None and len(best_learned["seeds"]) >= HEADLINE_CLAIM_SEEDS:
            claims.append(task)

    def wins(kind: str) -> str:
        return f"{len(won[kind])} of {len(tasks)} tasks" + (f" ({', '.join(won[kind])})" if won[kind] else "")

    lines += ["", f"A learned method from scratch beats the best tuned law on {wins('from scratch')}; a hybrid "
              f"(a learned residual on a law) on {wins('residual')}. {old} learned rows were measured before the "
              "precision metrics existed and are not judged"
              + (f"; no law is tuned yet on {', '.join(untuned)} (judged against the default gains)" if untuned else "")
              + f". The best learned row has {HEADLINE_CLAIM_SEEDS} seeds or more on {len(claims)} of {len(tasks)} "
              "tasks."]
    return "\n".join(lines) + "\n"


def pareto_figure(board_rows: Sequence[dict[str, Any]], path: Path) -> Path | None:
    """Per task (one panel each), every row measured with the precision metrics as a point: time to the 1 mm
    band against energy (means with 95 % intervals), marked by kind; None when no row has those metrics."""
    from studies._common import save_figure
    from studies.scoreboard_methods import METHODS

    tasks = {task: [row for row in rows_ if precise(row)] for task, rows_ in _headline_tasks(board_rows).items()}
    tasks = {task: rows_ for task, rows_ in tasks.items() if rows_}
    if not tasks:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    columns = min(3, len(tasks))
    figure, axes = plt.subplots(math.ceil(len(tasks) / columns), columns, figsize=(4.6 * columns,
                                3.6 * math.ceil(len(tasks) / columns)), squeeze=False)
    markers = {"law": "s", "tuned law": "D", "from scratch": "o", "residual": "^"}
    for axis, (task, task_rows) in zip(axes.flat, tasks.items()):
        for row in task_rows:
            kind = METHODS[row["method"]].kind if row["method"] in METHODS else "from scratch"
            x, y = row["metrics"]["control_energy"], row["metrics"]["settling_time_1mm_or_limit"]
            axis.errorbar(x["mean"], y["mean"], xerr=[[x["mean"] - x["ci_low"]], [x["ci_high"] - x["mean"]]],
                          yerr=[[y["mean"] - y["ci_low"]], [y["ci_high"] - y["mean"]]], marker=markers[kind],
                          capsize=2, label=row["method"])
        axis.set(title=task, xlabel="energy (N² m² s)", ylabel="time to the 1 mm band (s)", xscale="log")
        axis.legend(fontsize=6)
    for axis in list(axes.flat)[len(tasks):]:
        axis.axis("off")
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    return save_figure(figure, path)


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
                  generated_pages: Sequence[Path] = ()) -> None:
    """``scoreboard.json`` (``{"rows": [...]}``), the markdown tables, and the generated blocks of the docs pages.

    Each generated block (``headline``, ``headline-wide``, ``scoreboard``) is filled in whichever of
    ``generated_pages`` holds it; a block none of them holds is a ``ValueError`` before any page is written.
    """
    blocks = {"scoreboard": format_board(board_rows), "headline": headline_table(board_rows),
              "headline-wide": headline_table(board_rows, wide=True)}
    pages = {page: page.read_text(encoding="utf-8") for page in generated_pages}
    filled: set[str] = set()
    for page, text in pages.items():
        for block, content in blocks.items():
            if _has_block(text, block):
                pages[page] = text = _filled_block(text, block, content, page)
                filled.add(block)
    if pages and filled != set(blocks):
        missing = "; ".join(f"no generated {block} block" for block in sorted(set(blocks) - filled))
        raise ValueError(f"--docs: {missing} in {', '.join(map(str, pages))}")
    make_folder(json_path.parent)
    write_text(json_path, json.dumps({"rows": list(board_rows), "metrics": {k: {"title": t, "unit": u, "meaning": m}
                                                                          for k, t, u, m, _ in METRICS}},
                                     indent=1, default=float) + "\n")
    if markdown_path is not None:
        write_text(markdown_path, blocks["scoreboard"])
    for page, text in pages.items():
        write_text(page, text)


def _block_pattern(block: str) -> str:
    return rf"(<!-- generated: {block} -->\n)(.*?)(<!-- end generated -->)"


def _has_block(text: str, block: str) -> bool:
    return re.search(_block_pattern(block), text, re.S) is not None


def _filled_block(text: str, block: str, content: str, page: Path) -> str:
    """``text`` with its ``<!-- generated: block -->`` ... ``<!-- end generated -->`` block holding ``content``."""
    pattern = _block_pattern(block)
    if not re.search(pattern, text, re.S):
        raise ValueError(f"--docs: {page} has no generated {block} block")
    return re.sub(pattern, lambda m: m.group(1) + content.strip() + "\n" + m.group(3), text, count=1, flags=re.S)
