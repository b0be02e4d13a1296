"""The comparison of a run: its learned policy and every reference policy on the same held-out seeds.

Each policy runs ``eval_episodes`` episodes (seeds from :data:`~ee_formation_env.baselines.learned.training_env.EVAL_SEED_OFFSET`),
each scored by :func:`ee_formation_env.baselines.metrics.run_episode` exactly as ``ee-formation evaluate`` scores
it; the tables and the figure show the same summary. On a built-in scenario with tuned gains
(:mod:`ee_formation_env.baselines.reference.tuned`) each law also runs with them (rows ``<law> (tuned)``), and the
learned policy is judged against the best tuned law, else against the laws' defaults (``comparison.json``'s
``reference_gains`` says which), by the rule of :mod:`ee_formation_env.baselines.verdict`: its shortfalls
(success, precision, singularity, return, effort, contacts, speed) are each named in the console and in
``comparison.json``.
"""

from __future__ import annotations

import functools
import json
import multiprocessing
from pathlib import Path
from typing import Any, Callable

import numpy as np

import ee_formation_env
from ee_formation_env import baselines
from ee_formation_env.baselines.atomic_files import make_folder, replacing, write_text
from ee_formation_env.baselines.learned.checkpoint import read_json
from ee_formation_env.baselines.learned.config import TrainConfig
from ee_formation_env.baselines.learned.interruption import RunStopped
from ee_formation_env.worker_processes import ignore_interrupts, interrupts_blocked, unguarded_main_hint
from ee_formation_env.baselines.learned.training_env import EVAL_SEED_OFFSET
from ee_formation_env.baselines.learned.policy import MODEL_FOLDER, SavedRun, load_model, saved_scenario
from ee_formation_env.baselines.metrics import format_table, run_policies, summarize
from ee_formation_env.baselines.verdict import best_law, estimates, shortfalls

REFERENCE_CURVE_EPISODES = 4  # episodes per reference policy for the learning curve's reference lines


def compare(args: TrainConfig, config: dict[str, Any], run_dir: Path, results_dir: Path | None = None
            ) -> dict[str, Any]:
    """Evaluate the learned policy of the run in ``run_dir`` (its saved ``config``, on the scenario saved with
    it) and every reference policy on the same held-out seeds, with the evaluation settings of ``args``
    (``eval_episodes``, ``eval_seconds``, ``eval_workers``, ``no_progress``); writes ``comparison.json``, ``.md``
    and ``.png`` into ``results_dir`` (default: the run folder), each whole or not at all: a write the file system
    refuses is a :class:`~ee_formation_env.baselines.atomic_files.WriteRefused` naming the file.

    All (policy, seed) episodes run together as the copies of one batched env
    (:func:`~ee_formation_env.baselines.metrics.run_policies`), the policies shared among ``--eval-workers``
    processes (each its own batched env), or all in this one with 0. Each copy runs one episode from a fresh
    world, so an episode's result does not depend on where or with which others it runs (same seed, same
    episode, bit for bit).
    """
    overrides = {} if args.eval_seconds is None else {"episode_seconds": args.eval_seconds}
    seeds = [EVAL_SEED_OFFSET + k for k in range(args.eval_episodes)]
    scenario = ee_formation_env.load_scenario(saved_scenario(config))
    tuned = tuned_laws(scenario, overrides)
    names = ["learned", *baselines.POLICIES, *(tuned_row(law) for law in tuned)]
    episodes: dict[tuple[str, int], Any] = {}
    results_dir = Path(run_dir) if results_dir is None else Path(results_dir)
    make_folder(results_dir)
    setup = (scenario, overrides, str(run_dir), config)
    episode_seconds = scenario.episode_seconds if args.eval_seconds is None else args.eval_seconds
    progress = EvaluationProgress(len(names) * len(seeds), max(1, round(episode_seconds / scenario.control_dt)),
                                  f"comparison: learned + {len(names) - 1} reference rows x {len(seeds)} episodes",
                                  args.no_progress)

    def done(runs: dict[str, list[Any]]) -> None:
        for name, metrics in runs.items():
            episodes.update(((name, seed), m) for seed, m in zip(seeds, metrics))
            progress.finished(len(metrics))

    load_model(Path(run_dir) / MODEL_FOLDER, config, "comparison")  # before any episode: files, stamp, sizes
    workers = min(args.eval_workers, len(names))
    if workers == 0:
        _evaluation_worker_setup(*setup, progress.stepped if progress.shown else None)
        try:
            done(_evaluate_policies(names, seeds))
        finally:
            _evaluation_worker_teardown()
    else:
        _evaluate_in_workers(workers, setup, names, seeds, done, progress)
    progress.close()
    if not progress.shown:
        print(f"evaluated {len(names)} policies on {len(seeds)} seeds", flush=True)
    error_unit = "m²" if scenario.formation == "distance" else "m"
    results: dict[str, Any] = {}
    for name in names:
        runs = [episodes[(name, seed)] for seed in seeds]
        results[name] = summarize(runs)
        results[name]["per_episode"] = [e.as_dict() for e in runs]
    label = SavedRun(run_dir, config).label
    judged = judged_laws(results, tuned)
    found, best = learned_shortfalls(results, judged, episode_seconds)
    shortfall = "; ".join(item["message"] for item in found) or None
    comparison = {"scenario": config["scenario"], "seeds": seeds, "learned_label": label, "results": results,
                  "reference_gains": "tuned" if tuned else "default", "best_law": best,
                  "shortfall": None if shortfall is None else f"against {best!r}: the learned policy {shortfall}",
                  "shortfalls": found}
    notes = coinciding_laws(results)
    comparison["notes"] = notes
    table = format_table({label if k == "learned" else k: v for k, v in results.items()})
    write_text(results_dir / "comparison.md",
               f"# Comparison on {config['scenario']} ({len(seeds)} held-out seeds from {seeds[0]})\n\n{table}\n"
               + "".join(f"\n{note}\n" for note in notes))
    _plot(run_dir, results_dir, results, label, error_unit)
    # Last: a run folder holding comparison.json has its complete comparison.
    write_text(results_dir / "comparison.json", json.dumps(comparison, indent=2, default=float))
    print(table)
    for note in notes:
        print(note, flush=True)
    gains = "tuned gains" if tuned else "default gains (no tuned gains for this scenario)"
    print(f"judged against the best law with {gains}: {best}", flush=True)
    for item in found:
        print(f"warning: {item['metric']}: the learned policy {item['message']} (threshold: {item['threshold']})",
              flush=True)
    return comparison


def coinciding_laws(results: dict[str, Any]) -> list[str]:
    """A note for each law whose episodes are another law's, step for step (``per_episode`` of :func:`compare`'s
    results equal): ``approx_jacobian`` and ``gradient`` on arms no joint of which gravity loads, where law II
    (K_I = 0, the exact kinematic estimate) is law I; said so that two equal rows are not taken for a fault."""
    notes = []
    for name in ("approx_jacobian", tuned_row("approx_jacobian")):
        same = "gradient" if name == "approx_jacobian" else tuned_row("gradient")
        if name in results and same in results and results[name]["per_episode"] == results[same]["per_episode"]:
            notes.append(f"note: {name} gives {same}'s episodes step for step: no joint of these arms carries "
                         "gravity, and law II with K_I = 0 and the exact kinematic estimate is law I "
                         "(docs/controllers.md).")
    return notes


def tuned_row(law: str) -> str:
    """A law's row with its tuned gains."""
    return f"{law} (tuned)"


def tuned_laws(scenario: Any, overrides: dict[str, Any]) -> list[str]:
    """The laws with tuned gains for ``scenario`` (a built-in with its own physics and a tuned file), else []."""
    from ee_formation_env.baselines.reference.tuned import tuned_path

    if not tuned_path(scenario.name).is_file():
        return []
    laws = []
    with ee_formation_env.parallel_env(scenario, **overrides) as env:
        for law in baselines.MODEL_BASED_POLICIES:
            try:
                baselines.make_policies(law, env, gains="tuned")
            except ValueError:
                continue
            laws.append(law)
    return laws


def reference_gains(scenario: Any) -> str:
    """Which gains the reference laws of the comparison run with on ``scenario`` (:func:`tuned_laws`), in words."""
    from ee_formation_env.baselines.reference.tuned import tuned_path

    tuned = tuned_laws(scenario, {})
    if tuned:
        return f"tuned gains ({', '.join(tuned)}; defaults for the others)" if len(tuned) < len(
            baselines.MODEL_BASED_POLICIES) else "tuned gains"
    if tuned_path(scenario.name).is_file():
        return "default gains (the tuned file of this scenario's name was tuned on another scenario)"
    return "default gains (no tuned file for this scenario)"


def judged_laws(results: dict[str, Any], tuned: list[str]) -> list[str]:
    """The rows the learned policy is judged against: the tuned laws where there are any, else the defaults."""
    return [tuned_row(law) for law in tuned] if tuned else [n for n in baselines.MODEL_BASED_POLICIES if n in results]


def learned_shortfalls(results: dict[str, Any], laws: list[str], episode_seconds: float
                       ) -> tuple[list[dict[str, Any]], str | None]:
    """The learned policy's shortfalls against the best of ``laws`` (:mod:`ee_formation_env.baselines.verdict`),
    and that law's row name."""
    per = {name: estimates(results[name]["per_episode"], episode_seconds) for name in ["learned", *laws]}
    best = best_law({name: per[name] for name in laws})
    if best is None:
        return [], None
    return shortfalls(per["learned"], per[best]), best


def _evaluate_in_workers(workers: int, setup: tuple, names: list[str], seeds: list[int],
                         done: Callable[[dict[str, list[Any]]], None], progress: EvaluationProgress) -> None:
    """The policies ``names`` shared among ``workers`` spawned processes, each result handed to ``done``; the
    episode steps the workers take are counted in shared memory and shown by ``progress`` twice a second.

    The workers ignore SIGINT (blocked from their start), as the env workers do: a Ctrl-C to the process group
    reaches this process alone, and whatever ends the comparison early (a signal, an error) ends the workers at
    once rather than waiting for their episodes. A worker that dies is one line; one that died during its
    start-up because ``spawn`` re-ran an unguarded main script says so, with the fix."""
    import concurrent.futures
    import multiprocessing

    context = multiprocessing.get_context("spawn")
    steps = context.Value("q", 0) if progress.shown else None  # passed at the workers' start, as spawn requires
    pool = concurrent.futures.ProcessPoolExecutor(workers, mp_context=context, initializer=_evaluation_worker_setup,
                                                  initargs=(*setup, steps))
    try:
        with interrupts_blocked():  # the processes start with the submissions
            pending = {pool.submit(_evaluate_policies, names[i::workers], seeds) for i in range(workers)}
        while pending:
            finished, pending = concurrent.futures.wait(pending, timeout=0.5,
                                                        return_when=concurrent.futures.FIRST_COMPLETED)
            for future in finished:
                done(future.result())
            if steps is not None:
                progress.stepped_in_all(steps.value)
    except concurrent.futures.process.BrokenProcessPool:
        codes = [process.exitcode for process in getattr(pool, "_processes", {}).values()]
        _end_workers(pool)
        hint = unguarded_main_hint(next((code for code in codes if code), None))
        raise RunStopped("comparison: an evaluation worker process died" + (
            f" during its start-up: {hint}" if hint else f" (exit codes {codes})")) from None
    except BaseException:
        _end_workers(pool)
        raise
    pool.shutdown()


def _end_workers(pool: Any) -> None:
    """Stop ``pool`` without waiting for the episodes it runs: its processes are killed."""
    processes = list(getattr(pool, "_processes", {}).values())  # the executor has no public way to end them
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        if process.is_alive():
            process.kill()
    for process in processes:
        process.join(timeout=5.0)


_EVALUATION: dict[str, Any] = {}  # one evaluation worker's settings


def _evaluation_worker_setup(scenario: Any, overrides: dict[str, Any], run_dir: str, config: dict[str, Any],
                             steps: Any = None) -> None:
    """``steps``: where the episode steps taken are counted, a callable (this process) or a shared
    ``multiprocessing.Value`` (a worker); None: not counted."""
    if multiprocessing.parent_process() is not None:  # a worker process: Ctrl-C is its parent's to handle
        ignore_interrupts()
    _EVALUATION.clear()
    _EVALUATION.update(scenario=scenario, overrides=overrides, run_dir=Path(run_dir), config=config,
                       on_steps=steps if steps is None or callable(steps) else functools.partial(_count, steps))


def _count(shared: Any, steps: int) -> None:
    with shared.get_lock():
        shared.value += steps


def _evaluation_worker_teardown() -> None:
    _EVALUATION.clear()


def _evaluate_policies(names: list[str], seeds: list[int]) -> dict[str, list[Any]]:
    """The held-out episodes of the policies ``names`` ("learned" or references), together in one batched env
    of this worker (two when the learned policy's action convention, e.g. ``gravity_compensation``, is not the
    reference laws' raw torque: the same scenario and seeds, each policy in its own convention)."""
    run = SavedRun(_EVALUATION["run_dir"], _EVALUATION["config"])
    learned_overrides = run.env_overrides()
    sources: dict[str, Any] = {name: run.policy_source() if name == "learned" else _law_source(name) for name in names}
    scenario, overrides, on_steps = _EVALUATION["scenario"], _EVALUATION["overrides"], _EVALUATION["on_steps"]
    if not learned_overrides or "learned" not in sources:
        return run_policies(scenario, sources, seeds, overrides=overrides, on_steps=on_steps)
    learned = run_policies(scenario, {"learned": sources.pop("learned")}, seeds,
                           overrides={**overrides, **learned_overrides}, on_steps=on_steps)
    return {**learned, **(run_policies(scenario, sources, seeds, overrides=overrides, on_steps=on_steps)
                          if sources else {})}


def _law_source(name: str) -> Any:
    """A reference row's policies: the law's name, or for ``<law> (tuned)`` its tuned gains."""
    for law in baselines.MODEL_BASED_POLICIES:
        if name == tuned_row(law):
            return lambda copy_env, law=law: baselines.make_policies(law, copy_env, gains="tuned")
    return name


def reference_returns(config: dict[str, Any], episodes: int = REFERENCE_CURVE_EPISODES) -> dict[str, float]:
    """Mean per-agent episode return of each reference policy in the *training* env (its episode length and
    start noise, torque mode), on held-out seeds: the lines the learning curve is drawn against.

    In residual mode the reference alone is the learner's zero correction, whose return is the same.
    """
    overrides = TrainConfig.from_dict(config).options.episode_overrides()  # the laws' raw torques
    seeds = [EVAL_SEED_OFFSET + 5_000 + k for k in range(episodes)]
    runs = run_policies(saved_scenario(config), dict(zip(baselines.POLICIES, baselines.POLICIES)), seeds,
                        overrides=overrides)
    return {name: float(np.mean([m.mean_return for m in runs[name]])) for name in baselines.POLICIES}


class EvaluationProgress:
    """The comparison's progress bar over its ``total`` episodes, labelled with what runs (``label``): the
    episodes run together and end together, so it advances with the steps they take (``episode_steps`` steps of
    one episode make one), and is set to the episodes done as each worker's results arrive. Nothing is shown
    with ``disabled`` (``--no-progress``) or without tqdm (``shown`` False)."""

    def __init__(self, total: int, episode_steps: int, label: str, disabled: bool):
        self.total, self.episode_steps, self.steps, self.done = total, episode_steps, 0, 0
        self.bar = None
        if not disabled:
            try:
                from tqdm.auto import tqdm
            except ImportError:
                return
            self.bar = tqdm(total=total, desc=label, unit=" episodes",
                            bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total} episodes "
                                       "[{elapsed}<{remaining}]")

    @property
    def shown(self) -> bool:
        return self.bar is not None

    def stepped(self, steps: int) -> None:
        """``steps`` more episode steps taken (this process)."""
        self.stepped_in_all(self.steps + steps)

    def stepped_in_all(self, steps: int) -> None:
        """``steps`` episode steps taken in all, so far (the workers' shared count)."""
        self.steps = steps
        self._show()

    def finished(self, episodes: int) -> None:
        """``episodes`` more episodes whose results arrived."""
        self.done += episodes
        self._show()

    @property
    def episodes(self) -> float:
        """The episodes shown as done: those whose results arrived, or more as counted by their steps."""
        return min(float(self.total), max(float(self.done), self.steps / self.episode_steps))

    def _show(self) -> None:
        if self.bar is not None and self.episodes > self.bar.n:
            self.bar.update(self.episodes - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _learning_curve(path: Path) -> np.ndarray:
    """``learning_curve.csv`` as rows (agent steps, return); none when no PPO step ran (``--imitate``)."""
    try:
        lines = path.read_text().splitlines()[1:]
        return np.loadtxt(lines, delimiter=",", ndmin=2) if lines else np.empty((0, 2))
    except (ValueError, UnicodeDecodeError) as error:
        raise ValueError(f"learning_curve.csv: {path} is malformed ({str(error)[:200]})") from None


def _plot(run_dir: Path, results_dir: Path, results: dict[str, Any], label: str, error_unit: str) -> None:
    """``comparison.png``: the learning curve, then the final formation error and the success rate per
    policy as labelled horizontal bars (policy names stay readable; a 0 % bar shows as its empty track)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(results)
    ticks = [label if n == "learned" else n for n in names]
    rows = np.arange(len(names))
    figure, axes = plt.subplots(1, 3, figsize=(15, 4.2), gridspec_kw={"width_ratios": [1.2, 1, 1]})
    curve = _learning_curve(run_dir / "learning_curve.csv")
    if curve.size:
        axes[0].plot(curve[:, 0], curve[:, 1], ".", alpha=0.4, label="episode")
        if len(curve) >= 10:
            window = max(len(curve) // 20, 5)
            axes[0].plot(curve[window - 1:, 0], np.convolve(curve[:, 1], np.ones(window) / window, mode="valid"),
                         label=f"mean of {window}")
    references_path = run_dir / "reference_returns.json"
    if references_path.is_file():  # each reference policy's return in the training episodes
        for (name, value), color in zip(read_json(references_path, "reference_returns.json").items(),
                                        plt.cm.Dark2.colors):
            axes[0].axhline(value, linestyle="--", linewidth=1, color=color, label=name)
    if curve.size or references_path.is_file():
        axes[0].legend(loc="best", fontsize=7)
    axes[0].set(title="learning curve (training episodes)", xlabel="agent steps",
                ylabel="episode return per agent\n(sum of step rewards, each in [0, 2])")
    axes[0].ticklabel_format(axis="x", style="sci", scilimits=(0, 3))

    errors = np.array([results[n]["final_formation_error"] for n in names], dtype=np.float64)
    shown = np.where(np.isfinite(errors) & (errors > 0), errors, np.nan)
    axes[1].barh(rows, shown, color="tab:blue")
    axes[1].set_xscale("log")
    axes[1].set(title="final formation error (mean)", xlabel=f"formation error ({error_unit}, log scale)")
    if np.isfinite(shown).any():
        low, high = np.nanmin(shown), np.nanmax(shown)
        axes[1].set_xlim(low / 10, high * 1e3)  # room for the value labels right of the bars
    for row, value in zip(rows, errors):
        axes[1].annotate(f"{value:.2g}", (shown[row] if np.isfinite(shown[row]) else axes[1].get_xlim()[0], row),
                         xytext=(3, 0), textcoords="offset points", va="center", fontsize=8)

    success = 100.0 * np.array([results[n]["success_rate"] for n in names], dtype=np.float64)
    axes[2].barh(rows, np.full(len(rows), 100.0), color="0.92", edgecolor="0.75")  # the empty track
    axes[2].barh(rows, success, color="tab:green")
    axes[2].set(title="success rate", xlabel="episodes that succeeded (%)", xlim=(0, 118))
    axes[2].set_xticks([0, 25, 50, 75, 100])
    for row, value in zip(rows, success):
        axes[2].annotate(f"{value:.0f} %", (value, row), xytext=(3, 0), textcoords="offset points", va="center",
                         fontsize=8)
    for axis in axes[1:]:
        axis.set_yticks(rows, ticks)
        axis.invert_yaxis()  # first policy on top, as in the table
    axes[2].set_yticklabels([])  # same rows as the middle panel
    figure.tight_layout()
    try:
        with replacing(results_dir / "comparison.png") as temporary:
            figure.savefig(temporary, dpi=110, format="png")
    finally:
        plt.close(figure)
