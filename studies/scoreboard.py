"""The scoreboard: every built-in scenario x method, over training seeds, on held-out evaluation episodes.

``python -m studies.scoreboard`` runs each cell (scenario x method x training seed) that is not cached yet,
then aggregates every cached cell (of this and earlier invocations) into ``results/scoreboard/scoreboard.json`` and a markdown table;
``--docs`` also merges those rows into the committed board (``docs/results/scoreboard.json``: a row
recomputed here replaces its committed one, the others stay, and none is replaced by one of fewer episodes or
seeds unless ``--replace-smaller``; :func:`merged_rows`), regenerates the tables of ``docs/scoreboard.md``
from it and archives the cells behind the merged rows in ``docs/results/cells/`` (:func:`archive_cells`). A cell
is a JSON file under ``<out>/cells/`` written when the cell is complete, so the command resumes where it
stopped, and the board can be filled over several sessions (a learned cell's training run under ``<out>/runs/``
resumes from its newest checkpoint). Each cell carries the schema, code version and protocol it
was computed with; one computed otherwise, or a corrupt file, is recomputed, never aggregated silently
(:mod:`studies.scoreboard_cells`). ``--quick``: tiny budgets and a few
short episodes, into a temporary folder by default; never writes into ``docs/``. ``--address``: the missing
cells run as tasks on a Ray cluster, and this command writes them (:mod:`studies.scoreboard_cluster`).

Protocol (``docs/scoreboard.md`` has the rationale): reference controllers are evaluated on the held-out
seeds (no training, so one "run"); learned methods are trained with ``train.py``'s presets at the stated
budget, once per training seed, and each trained policy is evaluated on the same held-out seeds
(``EVAL_SEED_OFFSET`` + k). Per metric the board reports the mean, the interquartile mean (IQM) and 95 %
percentile intervals of a stratified bootstrap over training seeds within each evaluation episode (the
resampling of rliable's ``StratifiedBootstrap``, each evaluation episode a stratum; for a reference, over
episodes), plus each seed's mean.

Generalization: a scenario with a test set (:mod:`ee_formation_env.scenario_sets`) also gets ``split: "test"``
rows, one per test scenario: every reference controller evaluated there, and every learned method's policy,
trained on the training scenario only, evaluated there unchanged (zero-shot) on the same held-out seeds.
A scenario distribution (``scenario_sets.DISTRIBUTIONS``) is evaluated on its test set (its draws at the 50
``TEST_SEEDS``: its row is ``split: "test"``) and on its train set (the draws at ``TRAIN_SEEDS``, ``split:
"train"``), the reference controllers and every trained policy alike.

Team size: a distribution with a team family (``planar_random``: ``planar_team``, 3 to 8 arms;
:mod:`ee_formation_env.team_families`) also gets ``split: "team"`` rows, one per team size: the laws, and every
method whose policy serves any team (:attr:`~studies.scoreboard_methods.Method.serves_any_team`, the set
network), trained at the distribution's own size and evaluated unchanged on the family's first
``TEAM_EPISODES`` test draws at each size; a table of success and settling per size and a figure of success
vs size (``team_size_success.png``; with ``--docs``, ``docs/figures/scoreboard_team_size.png``).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any, Callable, Sequence

from ee_formation_env.baselines.atomic_files import make_folder, replacing
from ee_formation_env.builtin import BUILTIN_SCENARIOS
from ee_formation_env.scenario_sets import held_out_scenarios
from studies.scoreboard_cells import read_cell, stale_reason
# The methods and cells, read through this module by the study's users.
from studies.scoreboard_methods import (DEFAULT_EPISODES, DEFAULT_SEEDS, METHODS, QUICK_FLAGS, QUICK_MINUTES,  # noqa: F401
                                        TRAIN_SET, BenchmarlRun, Board, Method, cell_problem, fill, run_cell,
                                        run_test_cell, team_places, train_argv, trained_policies)
# METRICS and episode_values are read through this module by the study's users.
from studies.scoreboard_rows import (METRICS, _place, episode_values, format_board, pareto_figure,  # noqa: F401
                                     rows, team_size_figure, write_outputs)




def _board_places() -> list[tuple[str, str]]:
    """Every (training scenario, evaluated scenario) of the board, in board order: scenarios as the built-ins
    are listed, each followed by its test scenarios and its team family's sizes (the team-size split)."""
    return [(train, name) for train in BUILTIN_SCENARIOS
            for name in (train, *held_out_scenarios(train), *team_places(train))]


def _board_order(places: Sequence[tuple[str, str]]) -> Callable[[dict[str, Any]], tuple[int, int, int]]:
    """Sort key of a cell or a row: its place, its split (a distribution's train set first), its method."""
    methods = list(METHODS)
    return lambda item: (places.index(_place(item)), item.get("split") == "test", methods.index(item["method"]))


def aggregated_cells(board: Board, progress: Callable[[str], None] = print) -> list[tuple[Path, dict[str, Any]]]:
    """Every complete cell under ``board.out`` (whichever invocation ran it) with its file, in board order
    (:func:`_board_order`), then seeds. A cell this invocation did not recompute that is corrupt, or stale
    (another schema, code version or protocol; kept with ``board.accept_stale``), is left out, each in one line."""
    places = _board_places()
    cells = []
    for path in sorted((board.out / "cells").rglob("*.json")):
        record, problem = read_cell(path)
        if record is None:
            progress(f"left out {path}: {problem}; rerun its scenario and method to recompute it")
            continue
        if _place(record) not in places or record["method"] not in METHODS:
            continue
        problem = cell_problem(board, path, record)
        if problem:
            progress(f"left out {path}: {problem}; rerun its scenario and method to recompute it")
            continue
        stale = stale_reason(record, board.protocol(METHODS[record["method"]], _place(record)[0]))
        if stale and not board.accept_stale:
            progress(f"left out {path}: {stale}; rerun its scenario and method to recompute it, or "
                     "--accept-stale-cells to aggregate it")
            continue
        cells.append((path, record))
    order = _board_order(places)
    return sorted(cells, key=lambda cell: (*order(cell[1]), -1 if cell[1]["seed"] is None else cell[1]["seed"]))


def archive_cells(cells: Sequence[tuple[Path, dict[str, Any]]], cells_root: Path, archive: Path) -> None:
    """Copy ``cells`` (files under ``cells_root``) into ``archive`` in the same layout, the folder of each of their
    training scenario x method replaced whole, so that it holds exactly the cells behind the rows last merged
    from it. Copied into another board's ``<out>/cells``, the archive lets a committed row gain training seeds on
    a fresh clone without training its archived seeds again (docs/scoreboard.md, "The cells behind the board")."""
    for scenario, method in {path.relative_to(cells_root).parts[:2] for path, _ in cells}:
        shutil.rmtree(archive / scenario / method, ignore_errors=True)
    for path, _ in cells:
        target = archive / path.relative_to(cells_root)
        make_folder(target.parent)
        with replacing(target) as temporary:
            shutil.copyfile(path, temporary)


def merged_rows(committed: Sequence[dict[str, Any]], fresh: Sequence[dict[str, Any]],
                replace_smaller: bool = False) -> list[dict[str, Any]]:
    """The board ``--docs`` writes: the ``committed`` rows (``docs/results/scoreboard.json``) with each one that
    ``fresh`` recomputes, same place, split and method, replaced by its new row, and ``fresh``'s new rows added;
    in board order. Rows of scenarios or methods the board no longer has are dropped. The cells behind a
    committed row need not be on this machine, so the board can be filled over sessions on fresh clones.

    A fresh row with fewer evaluation episodes or fewer training seeds than the committed row it would replace
    (a ``--episodes 2`` check, a session that ran one seed) is refused, ``ValueError`` naming each, unless
    ``replace_smaller``: a committed result is not lost to a smaller one by accident."""
    places = _board_places()

    def key(row: dict[str, Any]) -> tuple[tuple[str, str], str, str]:
        return _place(row), row["split"], row["method"]

    by_key = {key(row): row for row in committed if _place(row) in places and row["method"] in METHODS}
    smaller = [f"{row['scenario']} ({row['split']}) / {row['method']}: {_size(by_key[key(row)])} -> {_size(row)}"
               for row in fresh if key(row) in by_key and _smaller(row, by_key[key(row)])]
    if smaller and not replace_smaller:
        raise ValueError(f"--docs: {len(smaller)} committed row(s) would be replaced by one with fewer episodes or "
                         f"seeds: {'; '.join(smaller)}; --replace-smaller replaces them anyway (the local board is "
                         "written)")
    by_key.update((key(row), row) for row in fresh)
    return sorted(by_key.values(), key=_board_order(places))


def _size(row: dict[str, Any]) -> str:
    return f"{len(row['eval_seeds'])} episodes x {len(row['seeds'])} seeds"


def _smaller(row: dict[str, Any], committed: dict[str, Any]) -> bool:
    return len(row["eval_seeds"]) < len(committed["eval_seeds"]) or len(row["seeds"]) < len(committed["seeds"])


DOCS_PAGE = Path(__file__).resolve().parent.parent / "docs" / "scoreboard.md"
DOCS_TABLES_PAGE = DOCS_PAGE.parent / "scoreboard-tables.md"  # every row per scenario and split (generated only)
DOCS_JSON = DOCS_PAGE.parent / "results" / "scoreboard.json"
DOCS_FIGURE = DOCS_PAGE.parent / "figures" / "scoreboard_team_size.png"  # the team-size split's success vs N
DOCS_PARETO = DOCS_PAGE.parent / "figures" / "scoreboard_pareto.png"  # per task: time to the 1 mm band vs energy
DOCS_CELLS = DOCS_JSON.parent / "cells"  # the cells behind the rows --docs merged (archive_cells)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m studies.scoreboard", description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenarios", nargs="+", default=sorted(BUILTIN_SCENARIOS), metavar="NAME",
                        help="built-in scenarios (default: all)")
    parser.add_argument("--methods", nargs="+", default=list(METHODS), metavar="METHOD",
                        help=f"methods, of {list(METHODS)} (default: all)")
    parser.add_argument("--seeds", nargs="+", type=int, default=list(DEFAULT_SEEDS),
                        help="training seeds of the learned methods (default 0 1 2)")
    parser.add_argument("--episodes", type=int, default=DEFAULT_EPISODES, help="held-out episodes per cell")
    parser.add_argument("--out", type=Path, default=None,
                        help="cells, runs and results (default results/scoreboard; --quick: a temporary folder)")
    parser.add_argument("--quick", action="store_true",
                        help="tiny budgets and short episodes: a smoke test of the machinery, not a result")
    parser.add_argument("--no-test-sets", action="store_true",
                        help="skip the held-out test scenarios (ee_formation_env.scenario_sets): training splits only")
    parser.add_argument("--docs", action="store_true",
                        help="also merge the rows into docs/results/scoreboard.json (a recomputed row replaces its committed "
                             "one) and regenerate the tables of docs/scoreboard.md")
    parser.add_argument("--replace-smaller", action="store_true",
                        help="--docs: replace committed rows even by rows of fewer episodes or fewer seeds (refused "
                             "otherwise)")
    parser.add_argument("--accept-stale-cells", action="store_true",
                        help="aggregate cached cells of another code version, schema or method definition as they "
                             "are, each reported (default: recompute them, and leave out those not run here)")
    from studies import scoreboard_cluster  # --address: the cells as tasks on a Ray cluster

    scoreboard_cluster.add_arguments(parser)
    args = parser.parse_args(argv)
    if problem := scoreboard_cluster.argument_problem(args):
        parser.error(problem)
    unknown = sorted(set(args.scenarios) - set(BUILTIN_SCENARIOS))
    if unknown:
        parser.error(f"--scenarios: unknown {unknown}; available: {sorted(BUILTIN_SCENARIOS)}")
    unknown = sorted(set(args.methods) - set(METHODS))
    if unknown:
        parser.error(f"--methods: unknown {unknown}; available: {list(METHODS)}")
    if args.episodes < 1:
        parser.error("--episodes: expected an integer >= 1")
    if any(seed < 0 for seed in args.seeds) or len(set(args.seeds)) != len(args.seeds):
        parser.error("--seeds: expected distinct integers >= 0")
    if args.quick and args.docs:
        parser.error("--docs: not with --quick (a smoke test is not a result)")
    if args.replace_smaller and not args.docs:
        parser.error("--replace-smaller: only with --docs (it decides what replaces a committed row)")
    if args.out is not None and args.out.exists() and not args.out.is_dir():
        parser.error(f"--out: {args.out} is a file, not a folder")
    out = args.out or (Path(tempfile.mkdtemp(prefix="scoreboard-")) if args.quick else Path("results/scoreboard"))
    board = Board(out=out, scenarios=tuple(args.scenarios), methods=tuple(args.methods), seeds=tuple(args.seeds),
                  episodes=args.episodes, episode_seconds=0.3 if args.quick else None,
                  extra_train_flags=QUICK_FLAGS if args.quick else (), eval_workers=0 if args.quick else None,
                  test_sets=not args.no_test_sets, accept_stale=args.accept_stale_cells)
    from ee_formation_env.baselines.learned.interruption import TrainingInterrupted

    not_done: list[str] = []
    try:
        if args.address:
            not_done = scoreboard_cluster.fill_on_cluster(board, args.address, args.cpus_per_learned_cell)
        else:
            fill(board)
    except TrainingInterrupted as stopped:  # Ctrl-C or SIGTERM while a cell trained: one line, not a traceback
        print(f"scoreboard: {stopped.signal_name} stopped a cell's training at {stopped.agent_steps} agent steps; its "
              f"model is saved in {stopped.run_dir}. The same command resumes the board: finished cells are kept, "
              "and this cell continues from its newest checkpoint.", file=sys.stderr)
        return stopped.exit_code
    except KeyboardInterrupt:  # Ctrl-C while a cell was evaluated: nothing of it was written
        print("scoreboard: interrupted; the cells finished so far are kept, and the same command resumes the board",
              file=sys.stderr)
        return 130
    except OSError as error:  # a file-system fault writing a cell: one line naming the file
        print(f"scoreboard: could not write {getattr(error, 'filename', None) or 'a cell'}: "
              f"{error.strerror or error}", file=sys.stderr)
        return 1
    board_cells = aggregated_cells(board)  # every cell ever completed here, not only this invocation's
    board_rows = rows([record for _, record in board_cells])
    write_outputs(board_rows, out / "scoreboard.json", out / "scoreboard.md")
    figures = [team_size_figure(board_rows, out / "team_size_success.png"), pareto_figure(board_rows, out / "pareto.png")]
    if args.docs:  # merged into the committed board: its other rows' cells may be on another machine
        committed = json.loads(DOCS_JSON.read_text(encoding="utf-8"))["rows"] if DOCS_JSON.is_file() else []
        merged = merged_rows(committed, board_rows, args.replace_smaller)
        write_outputs(merged, DOCS_JSON, generated_pages=(DOCS_PAGE, DOCS_TABLES_PAGE))
        archive_cells(board_cells, out / "cells", DOCS_CELLS)
        figures += [team_size_figure(merged, DOCS_FIGURE), pareto_figure(merged, DOCS_PARETO)]
    print(format_board(board_rows))
    written = ([out / "scoreboard.json", out / "scoreboard.md"]
               + ([DOCS_JSON, DOCS_PAGE, DOCS_TABLES_PAGE, DOCS_CELLS] if args.docs else [])
               + [figure for figure in figures if figure is not None])
    print(f"wrote {', '.join(map(str, written))}")
    if not_done:
        print(f"scoreboard: {len(not_done)} cell group(s) not done: {'; '.join(not_done)}", file=sys.stderr)
    return 1 if not_done else 0


if __name__ == "__main__":
    try:
        raise SystemExit(main())
    except ValueError as error:  # a refusal (--docs would replace a larger row, ...): one line, as the CLI prints it
        print(f"scoreboard: {error}", file=sys.stderr)
        raise SystemExit(2) from None
