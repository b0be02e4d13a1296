"""The scoreboard's methods and cells: what each method is, what one invocation evaluates (:class:`Board`), how
one cell is computed (:func:`run_cell`, :func:`run_test_cell`) and the local, in-order filling of a board
(:func:`fill`). The command, its aggregation and the protocol are :mod:`studies.scoreboard`'s; the cell cache
is :mod:`studies.scoreboard_cells`'s; running the cells on a Ray cluster, :mod:`studies.scoreboard_cluster`'s.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

from ee_formation_env.baselines import REFERENCE_CONTROLLERS
from ee_formation_env.builtin import BUILTIN_SCENARIOS
from ee_formation_env.baselines.metrics import run_episodes
from ee_formation_env.scenario import load_scenario
from ee_formation_env.scenario_sets import DISTRIBUTIONS, TEST_SEEDS, TRAIN_SEEDS, held_out_scenarios, wide_starts
from ee_formation_env.team_families import TEAM_FAMILIES, TEAM_FAMILY_SOURCES, team_scenario
from studies.scoreboard_cells import cached_cell, mark_run, run_is_current


@dataclass(frozen=True)
class BenchmarlRun:
    """A studies.benchmarl_runs run: algorithm, training-task mode, budget and learning settings. The budget is
    ``minutes`` of wall time, or, where ``frames`` is set, that many frames (env steps of all copies; agent steps
    = frames x agents), which repeats bit for bit on any machine and at any load."""

    algorithm: str
    mode: str
    minutes: float | None
    settings: str = "benchmarl"  # a name of studies.benchmarl_runs.SETTINGS_NAMES
    frames: int | None = None
    model: str = "mlp"  # the actor, of studies.benchmarl_runs.MODELS ("deepsets": for any team size)


@dataclass(frozen=True)
class Method:
    """One row kind of the board: a reference controller, or a ``train.py`` configuration (its flags)."""

    name: str
    reference: str | None = None  # the reference controller's name, for a reference method
    train_flags: tuple[str, ...] = ()  # train.py flags of a learned method (its preset sets the rest)
    needs_invariant_arms: bool = False  # its observation features need arms turning about their base z axis
    benchmarl: BenchmarlRun | None = None  # a BenchMARL method's run
    #: A learned method whose run of the same scenario and seed this method's policy starts as a copy of
    #: (``--imitate RUN_DIR``): its cell is trained first, and its budget counts in this method's.
    teacher: str | None = None
    #: A law's gains: None for its defaults, ``"tuned"`` for its tuned set (make_policies' ``gains``).
    gains: str | None = None

    @property
    def policy_kwargs(self) -> dict[str, Any]:
        """make_policies' keyword arguments of a law's cells."""
        return {} if self.gains is None else {"gains": self.gains}

    @property
    def learned(self) -> bool:
        return self.reference is None

    @property
    def kind(self) -> str:
        """``"law"`` (a reference controller at its default gains), ``"tuned law"`` (at its tuned gains),
        ``"residual"`` (a learned correction on a law: a hybrid) or ``"from scratch"`` (every other learned method):
        the groups the board's headline compares. An SB3 method's mode is its ``--mode`` flag (the board trains
        with ``--recipe none``, so residual without one)."""
        if not self.learned:
            return "tuned law" if self.gains == "tuned" else "law"
        if self.benchmarl is not None:
            mode = self.benchmarl.mode
        else:
            flags = self.train_flags
            mode = next((b for a, b in zip(flags, flags[1:]) if a == "--mode"), "residual")
        return "residual" if mode == "residual" else "from scratch"

    @property
    def serves_any_team(self) -> bool:
        """Whether its policy acts on teams of any size: a law, SB3's set network (``--policy-network set``) or
        BenchMARL's set actor (``model="deepsets"``); the board's team-size split evaluates these."""
        flags = self.train_flags
        return (not self.learned or any(a == "--policy-network" and b == "set" for a, b in zip(flags, flags[1:]))
                or (self.benchmarl is not None and self.benchmarl.model == "deepsets"))

    def unavailable(self, scenario: str) -> str | None:
        """Why the method cannot run on ``scenario`` here (None if it can): features the arms cannot have, or a
        BenchMARL method without the ``torchrl`` extra installed."""
        if self.benchmarl is not None:
            import importlib.util

            if importlib.util.find_spec("benchmarl") is None:
                return "needs the torchrl extra (benchmarl)"
        if self.gains == "tuned":
            from ee_formation_env.baselines.reference.tuned import load_tuned

            try:
                load_tuned(scenario, self.reference)
            except ValueError as error:
                return str(error)
        if self.needs_invariant_arms and not self._invariant_arms(scenario):
            return "its features need arms whose first joint turns about their base z axis"
        return None

    @staticmethod
    def _invariant_arms(scenario: str) -> bool:
        from ee_formation_env.baselines.learned.features import check_invariant_arms
        from ee_formation_env.task import build_task

        try:
            check_invariant_arms(build_task(load_scenario(scenario)))
        except ValueError:
            return False
        return True


#: The learned methods' definitions (data, one entry per method): :func:`load_methods` reads them.
METHODS_FILE = Path(__file__).with_name("board_methods.yaml")
_ENTRY_KEYS = {"about", "train_flags", "needs_invariant_arms", "teacher", "benchmarl"}


def load_methods(path: Path = METHODS_FILE) -> dict[str, Method]:
    """The board's methods in board order: each reference law at its default gains (``<law>``) and at its tuned
    ones (``<law>-tuned``), then the learned methods of ``path`` (a YAML mapping name -> entry; the file's header
    documents the keys). An entry that is not a valid method is one ``ValueError`` naming the file, the method
    and the key: an unknown key, a value of the wrong type, a BenchMARL run with a field it lacks, a teacher
    that is not an earlier learned method, a method with neither flags nor a BenchMARL run."""
    import yaml

    methods = {name: Method(name, reference=name) for name in REFERENCE_CONTROLLERS}
    methods.update({f"{name}-tuned": Method(f"{name}-tuned", reference=name, gains="tuned")
                    for name in REFERENCE_CONTROLLERS})
    try:
        entries = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as error:
        raise ValueError(f"{path}: cannot read the board's methods: {error}") from None
    if not isinstance(entries, dict):
        raise ValueError(f"{path}: expected a mapping of method name -> definition")
    run_fields = {spec.name for spec in dataclasses.fields(BenchmarlRun)}
    for name, entry in entries.items():
        where = f"{path}: method {name!r}"
        if not isinstance(name, str) or name in methods:
            raise ValueError(f"{where}: a name that is not a string, or one given twice (the laws' names included)")
        if not isinstance(entry, dict):
            raise ValueError(f"{where}: expected a mapping of {sorted(_ENTRY_KEYS)}, got {entry!r}")
        if set(entry) - _ENTRY_KEYS:
            unknown = sorted(set(entry) - _ENTRY_KEYS)
            raise ValueError(f"{where}: unknown key(s) {unknown}; expected {sorted(_ENTRY_KEYS)}")
        if not isinstance(entry.get("about"), str) or not entry["about"].strip():
            raise ValueError(f"{where}: about: expected a sentence saying what the method is")
        flags = entry.get("train_flags", [])
        if not isinstance(flags, list) or not all(isinstance(flag, str) for flag in flags):
            raise ValueError(f"{where}: train_flags: expected a list of strings (train.py's flags, numbers quoted)")
        benchmarl = entry.get("benchmarl")
        if benchmarl is not None:
            required = {"algorithm", "mode", "minutes"}
            if not isinstance(benchmarl, dict) or set(benchmarl) - run_fields or not required <= set(benchmarl):
                raise ValueError(f"{where}: benchmarl: expected algorithm, mode and minutes, and only fields of "
                                 f"{sorted(run_fields)}; got {benchmarl!r}")
            benchmarl = BenchmarlRun(**benchmarl)
        if bool(flags) == (benchmarl is not None):
            raise ValueError(f"{where}: expected train_flags (a train.py method) or benchmarl (a BenchMARL one), "
                             "exactly one of them")
        teacher = entry.get("teacher")
        if teacher is not None and (teacher not in methods or not methods[teacher].learned):
            raise ValueError(f"{where}: teacher: {teacher!r} is not a learned method defined before it")
        invariant = entry.get("needs_invariant_arms", False)
        if not isinstance(invariant, bool):
            raise ValueError(f"{where}: needs_invariant_arms: expected true or false, got {invariant!r}")
        methods[name] = Method(name, train_flags=tuple(flags), needs_invariant_arms=invariant, benchmarl=benchmarl,
                               teacher=teacher)
    return methods


#: The board's methods (:func:`load_methods`): the paper's three laws at their default and tuned gains, then the
#: learned methods of :data:`METHODS_FILE`.
METHODS: dict[str, Method] = load_methods()
QUICK_MINUTES = 0.05  # --quick: the BenchMARL methods' wall-clock budget
DEFAULT_SEEDS = (0, 1, 2)  # training seeds of a learned method
DEFAULT_EPISODES = 10  # held-out evaluation episodes per cell
TEAM_EPISODES = 20  # test draws per team size of the team-size split (the team-size study's)
QUICK_FLAGS = ("--total-timesteps", "64", "--n-envs", "1", "--n-steps", "16", "--n-workers", "0")
# ------------------------------------------------------------------------------------------ cells
@dataclass(frozen=True)
class Board:
    """What one invocation evaluates: where, which cells, with which evaluation and training settings."""

    out: Path
    scenarios: tuple[str, ...]
    methods: tuple[str, ...]
    seeds: tuple[int, ...]
    episodes: int
    episode_seconds: float | None  # None: each scenario's own episode length
    extra_train_flags: tuple[str, ...] = ()  # train.py flags added to every learned method's (--quick's budget)
    eval_workers: int | None = None  # train.py's --eval-workers (None: its default)

    test_sets: bool = True  # also evaluate on each scenario's test set (scenario_sets)
    accept_stale: bool = False  # aggregate cells of another code version as they are (each reported)

    #: Fields that choose which cells run or where, or how a cached one is treated, never a cell's numbers; every
    #: other field (and any added later) is part of each cell's key (:meth:`protocol`).
    NOT_IN_CELL_KEY = frozenset({"out", "scenarios", "methods", "seeds", "eval_workers", "test_sets", "accept_stale"})

    def protocol(self, method: Method, scenario: str | None = None) -> dict[str, Any]:
        """What the study sets for a cell of ``method`` (recorded in it; studies.scoreboard_cells): the
        method's definition (its gains, flags or BenchMARL run), the BenchMARL learning settings it names, and
        every board setting that decides a cell's numbers (all fields but :attr:`NOT_IN_CELL_KEY`: episodes,
        episode length, the flags every learned method gets such as ``--quick``'s) and, for a law with tuned gains
        on ``scenario`` (its training scenario), the tuned entry it runs with (a retuned law recomputes its cells
        and no other's). A cached cell computed under another protocol is recomputed."""
        settings = {field.name: getattr(self, field.name) for field in dataclasses.fields(self)
                    if field.name not in self.NOT_IN_CELL_KEY}
        protocol: dict[str, Any] = {"method": dataclasses.asdict(method), "board": settings}
        if method.benchmarl is not None:
            from studies.benchmarl_runs import PROJECT_SETTINGS, SETTINGS

            run = method.benchmarl
            if run.settings != PROJECT_SETTINGS:
                protocol["benchmarl_settings"] = dataclasses.asdict(SETTINGS[run.settings])
            else:  # the project's YAML files, read where the torchrl extra is installed
                try:
                    from ee_formation_env.baselines.learned.benchmarl_configs import config_files
                except ImportError:
                    protocol["benchmarl_settings"] = "the project's YAML files (unread: needs the torchrl extra)"
                else:
                    protocol["benchmarl_settings"] = config_files(run.algorithm, run.mode, run.model)
        if method.teacher is not None:  # a changed teacher is another starting policy
            protocol["teacher"] = self.protocol(METHODS[method.teacher])
        if method.gains == "tuned" and scenario is not None:
            from ee_formation_env.baselines.reference.tuned import load_tuned

            try:
                protocol["tuned"] = load_tuned(scenario, method.reference).record
            except ValueError as error:
                protocol["tuned"] = f"unavailable: {error}"
        return protocol

    def cell_path(self, scenario: str, method: Method, seed: int | None, test: str | None = None) -> Path:
        """A training-split cell, or with ``test`` the cell of that test scenario (of training ``scenario``)."""
        name = "reference.json" if seed is None else f"seed-{seed}.json"
        folder = self.out / "cells" / scenario / method.name
        return folder / name if test is None else folder / "test" / test / name

    def run_dir(self, scenario: str, method: Method, seed: int) -> Path:
        return self.out / "runs" / scenario / method.name / f"seed-{seed}"

    def eval_seeds(self, scenario: str | None = None) -> list[int]:
        """The held-out evaluation seeds: ``episodes`` of them from ``EVAL_SEED_OFFSET``; a scenario
        distribution's test set (``scenario_sets.TEST_SEEDS``, at most ``episodes`` of them under ``--quick``)."""
        from ee_formation_env.baselines.learned.training_env import EVAL_SEED_OFFSET

        if scenario in DISTRIBUTIONS:
            return list(TEST_SEEDS[:self.episodes] if self.extra_train_flags else TEST_SEEDS)
        return [EVAL_SEED_OFFSET + k for k in range(self.episodes)]

    def team_seeds(self) -> list[int]:
        """A team family's test draws at each size: the first :data:`TEAM_EPISODES` ``TEST_SEEDS`` (fewer under
        ``--quick``)."""
        return list(TEST_SEEDS[:self.episodes] if self.extra_train_flags else TEST_SEEDS[:TEAM_EPISODES])

    def train_seeds(self) -> list[int]:
        """A distribution's train-set draws (``scenario_sets.TRAIN_SEEDS``; fewer under ``--quick``)."""
        return list(TRAIN_SEEDS[:self.episodes] if self.extra_train_flags else TRAIN_SEEDS)


def run_cell(board: Board, scenario: str, method: Method, seed: int | None) -> dict[str, Any]:
    """Train (a learned method) and evaluate one cell; its record (per-episode metrics, budget, wall time)."""
    started = time.time()
    seconds = board.episode_seconds or load_scenario(scenario).episode_seconds
    overrides = {"episode_seconds": seconds}
    seeds = board.eval_seeds(scenario)
    split = {"split": "test"} if scenario in DISTRIBUTIONS else {}  # a distribution's held-out draws
    outcome: dict[str, str] = {}  # "stopped" or "failed", with the reason, where training ended early
    if method.learned:
        from ee_formation_env.baselines.learned.policy import MODEL_FOLDER
        from ee_formation_env.baselines.learned.sb3_backend import TrainingFaults

        try:
            episodes, budget = _learned_cell(board, scenario, method, seed, seconds)
        except TrainingFaults as fault:  # a result too: this seed's run of the method stopped here
            run_dir = board.run_dir(scenario, method, seed)
            if (run_dir / MODEL_FOLDER / "state.json").is_file():
                # The policy as it stood at the stop is this seed's result: leaving the seed out of the row
                # would count only the runs that went well.
                episodes = [m.as_dict() for m in _saved_run_metrics(run_dir, method, scenario, seeds, seconds)]
                budget, outcome = _budget(run_dir), {"stopped": str(fault)}
            else:  # nothing saved to evaluate
                episodes, budget, outcome = [], {}, {"failed": str(fault)}
    else:
        metrics = run_episodes(scenario, method.reference, seeds, overrides=overrides,
                               policy_kwargs=method.policy_kwargs)
        episodes, budget = [m.as_dict() for m in metrics], {"agent_steps": 0}
    return {"scenario": scenario, "method": method.name, **split, "seed": seed, "eval_seeds": seeds,
            "episode_seconds": seconds, "budget": budget, "wall_seconds": time.time() - started,
            "episodes": [{k: v for k, v in e.items() if k != "trajectory"} for e in episodes], **outcome}


def _learned_cell(board: Board, scenario: str, method: Method, seed: int, seconds: float
                  ) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Train ``method`` on ``scenario`` with ``seed`` (resuming its run folder if a run stopped) and return the
    learned policy's held-out episodes (the run's own comparison) and the budget."""
    from ee_formation_env.baselines.learned.config import TrainConfig
    from ee_formation_env.baselines.learned.run import train
    from ee_formation_env.baselines.learned.saved_run import newest_intact_checkpoint

    run_dir = board.run_dir(scenario, method, seed)
    # A run started by another code version, or for another definition of the method, is trained again.
    current = run_is_current(run_dir, board.protocol(method))
    if not current:
        mark_run(run_dir, board.protocol(method))
    if method.benchmarl is not None:
        return _benchmarl_cell(board, scenario, method, seed, run_dir, current)
    teacher = None if method.teacher is None else METHODS[method.teacher]
    if teacher is not None:  # its run first (a cell of its own, reused where it is current)
        _learned_cell(board, scenario, teacher, seed, seconds)
    if not current or not (run_dir / "comparison.json").is_file():
        evaluation = ["--eval-episodes", str(len(board.eval_seeds(scenario))), "--eval-seconds", str(seconds),
                      "--no-progress",
                      *(() if board.eval_workers is None else ("--eval-workers", str(board.eval_workers)))]
        # A run killed before its first checkpoint (a lost node, a killed process) starts again.
        if current and (run_dir / "config.json").is_file() and newest_intact_checkpoint(run_dir) is not None:
            argv = ["--resume", str(run_dir), *evaluation]
        else:
            argv = [*train_argv(board, scenario, method, seed), "--out", str(run_dir), "--overwrite", *evaluation]
            if teacher is not None:
                argv += ["--imitate", str(board.run_dir(scenario, teacher, seed))]
        train(TrainConfig.from_args(argv))
    comparison = json.loads((run_dir / "comparison.json").read_text(encoding="utf-8"))
    budget = _budget(run_dir)
    if teacher is not None:
        budget = _with_teacher(budget, _budget(board.run_dir(scenario, teacher, seed)))
    return comparison["results"]["learned"]["per_episode"], budget


def _budget(run_dir: Path) -> dict[str, Any]:
    """A learned cell's budget, from its run folder: agent steps and training seconds done (a copy's
    demonstrations included: ``imitation.json``), the budget asked."""
    timing = json.loads((run_dir / "timing.json").read_text(encoding="utf-8"))
    config = json.loads((run_dir / "config.json").read_text(encoding="utf-8"))
    budget = {"agent_steps": int(timing["agent_steps"]), "train_seconds": float(timing["train_seconds"]),
              "total_timesteps": int(config["total_timesteps"]), "mode": config["mode"],
              "faulted_training_episodes": sum(s.get("faulted_training_episodes", 0) for s in timing["segments"])}
    if (run_dir / "imitation.json").is_file():
        rounds = json.loads((run_dir / "imitation.json").read_text(encoding="utf-8"))["rounds"]
        budget["imitation_seconds"] = float(rounds[-1]["seconds"]) if rounds else 0.0
        budget["train_seconds"] += budget["imitation_seconds"]
    return budget


def _with_teacher(budget: dict[str, Any], teacher: dict[str, Any]) -> dict[str, Any]:
    """A copy's budget with its teacher's counted in: agent steps and seconds are the sums (what the method
    took from scratch), the teacher's own budget kept beside them."""
    return {**budget, "agent_steps": budget["agent_steps"] + teacher["agent_steps"],
            "train_seconds": budget["train_seconds"] + teacher["train_seconds"], "teacher": teacher}


def _saved_run_metrics(run_dir: Path, method: Method, scenario: Any, seeds: Sequence[int], seconds: float
                       ) -> list[Any]:
    """The episode metrics of the SB3 policy saved in ``run_dir`` on ``scenario``, as the run's own comparison
    evaluates it: in the env settings it trained with."""
    from ee_formation_env.baselines.learned.policy import SavedRun

    run = SavedRun.load(run_dir, f"{method.name} run")
    return run_episodes(scenario, run.policy_source(), seeds,
                        overrides={"episode_seconds": seconds, **run.env_overrides()})


def train_argv(board: Board, scenario: str, method: Method, seed: int) -> list[str]:
    """The ``train.py`` flags that define a learned cell's training run (its folder and evaluation aside)."""
    return ["--scenario", scenario, "--recipe", "none", *method.train_flags, *board.extra_train_flags,
            "--seed", str(seed)]


def run_test_cell(board: Board, scenario: str, method: Method, seed: int | None, test: str,
                  test_scenario: Any, trained: dict[str, Any], seeds: Sequence[int] | None = None,
                  split: str = "test") -> dict[str, Any]:
    """Evaluate one cell of a test scenario: a reference controller there, or the policy of the training run
    of (``scenario``, ``method``, ``seed``) (its training cell ``trained``) unchanged there; on ``seeds``
    (default: the held-out ones). A distribution's train-set cell is the distribution itself on its
    ``TRAIN_SEEDS``, ``split="train"``."""
    started = time.time()
    seconds = board.episode_seconds or load_scenario(test_scenario).episode_seconds
    seeds = board.eval_seeds() if seeds is None else list(seeds)
    record = {"scenario": test, "trained_on": scenario, "split": split, "method": method.name, "seed": seed,
              "eval_seeds": seeds, "episode_seconds": seconds, "budget": trained["budget"],
              **({"stopped": trained["stopped"]} if trained.get("stopped") else {})}
    if trained.get("failed"):  # no policy to evaluate: the training cell's failure is this cell's too
        return {**record, "wall_seconds": 0.0, "episodes": [], "failed": trained["failed"]}
    run_dir = board.run_dir(scenario, method, seed)
    if method.benchmarl is not None:  # the exported actors, in the action convention they trained in
        from ee_formation_env.baselines.learned.benchmarl_task import load_benchmarl_policy

        actors = load_benchmarl_policy(run_dir / "policy")
        metrics = run_episodes(test_scenario, actors.policy_factory(), seeds,
                               overrides={"episode_seconds": seconds, **actors.env_overrides()})
    elif method.learned:
        metrics = _saved_run_metrics(run_dir, method, test_scenario, seeds, seconds)
    else:
        metrics = run_episodes(test_scenario, method.reference, seeds, overrides={"episode_seconds": seconds},
                               policy_kwargs=method.policy_kwargs)
    episodes = [{k: v for k, v in m.as_dict().items() if k != "trajectory"} for m in metrics]
    return {**record, "wall_seconds": time.time() - started, "episodes": episodes}


def trained_policies(method: Method, run_dir: Path, env: Any = None) -> Callable[[Any], dict[str, Any]]:
    """``copy_env -> per-agent policies`` of a learned method's trained run in ``run_dir``: a BenchMARL run's
    exported actor, or a ``train.py`` run's model (whose observation layouts and action scales are read from
    ``env``, a single or batched env of the scenario it acts on)."""
    if method.benchmarl is not None:
        from ee_formation_env.baselines.learned.benchmarl_task import load_benchmarl_policy

        return load_benchmarl_policy(run_dir / "policy").policy_factory()
    from ee_formation_env.baselines.learned.policy import SavedRun, learned_policy_factory

    run = SavedRun.load(run_dir, f"{method.name} run")  # its files, stamp and model checked, as the cells' are
    return learned_policy_factory(run_dir, env, run.config)


def _benchmarl_cell(board: Board, scenario: str, method: Method, seed: int, run_dir: Path, current: bool = True
                    ) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Train and evaluate a BenchMARL method (studies.benchmarl_runs; a stopped run starts again: BenchMARL runs
    are not resumed; one ``current`` is False for, another code version's, too) and return its held-out
    episodes and budget."""
    from studies import benchmarl_runs

    spec = method.benchmarl
    if not current or not (run_dir / "evaluation.json").is_file():
        quick = bool(board.extra_train_flags)  # --quick: a tiny wall-clock budget whatever the method's
        benchmarl_runs.run(spec.algorithm, scenario, spec.mode, QUICK_MINUTES if quick else spec.minutes,
                           seed, run_dir, len(board.eval_seeds(scenario)), episode_seconds=board.episode_seconds,
                           settings=benchmarl_runs.SETTINGS.get(spec.settings, spec.settings),
                           frames=None if quick else spec.frames, model=spec.model)
    record = json.loads((run_dir / "evaluation.json").read_text(encoding="utf-8"))
    budget = {"agent_steps": int(record["agent_steps"]), "train_seconds": float(record["train_seconds"]),
              "minutes": record["minutes"], "frame_budget": record.get("frame_budget"), "mode": spec.mode,
              "algorithm": spec.algorithm, "settings": spec.settings, "model": spec.model}
    return record["evaluation"]["per_episode"], budget


@dataclass(frozen=True)
class EvaluationCell:
    """A cell that evaluates a training cell's policy (or a law) elsewhere, unchanged: a held-out test scenario
    (split ``test``), a distribution's train set (``train``) or one team size of the distribution's team family
    (``team``). ``key``: its folder under the training cell's ``test/``; ``name``: the evaluated scenario's."""

    key: str
    label: str
    split: str
    name: str
    scenario: Any  # a built-in name or scenario data
    seeds: tuple[int, ...] | None  # None: the board's held-out seeds

    def run(self, board: Board, scenario: str, method: Method, seed: int | None, trained: dict[str, Any]
            ) -> dict[str, Any]:
        return run_test_cell(board, scenario, method, seed, self.name, self.scenario, trained, self.seeds,
                             split=self.split)


def team_places(scenario: str) -> list[str]:
    """The team-size split's scenarios of a training ``scenario``: its team family at every size
    (``planar_team_3`` ... ``planar_team_8`` for ``planar_random``), none for a scenario without a family."""
    families = [family for family, source in TEAM_FAMILY_SOURCES.items() if source == scenario]
    return [f"{family}_{n}" for family in families for n in range(TEAM_FAMILIES[family][0], TEAM_FAMILIES[family][1] + 1)]


def evaluation_cells(board: Board, scenario: str, method: Method) -> list[EvaluationCell]:
    """Every cell that evaluates a (``scenario``, ``method``) training cell's policy elsewhere, in board order:
    the test scenarios, a distribution's train set, and, for a method that serves any team
    (:attr:`Method.serves_any_team`), each team size of the scenario's family (with the test sets)."""
    cells = []
    if board.test_sets and method.gains != "tuned":  # tuned gains hold for the problem they were tuned on
        cells += [EvaluationCell(test, f"test {test}", "test", test, data, None)
                  for test, data in held_out_scenarios(scenario).items()]
    if board.test_sets and scenario not in DISTRIBUTIONS:  # the same problem from starts beyond training's
        cells.append(EvaluationCell(WIDE_STARTS, "wide starts", "wide", scenario, wide_starts(scenario), None))
    if scenario in DISTRIBUTIONS:  # the train set: the draws at TRAIN_SEEDS
        cells.append(EvaluationCell(TRAIN_SET, "train set", "train", scenario, scenario, tuple(board.train_seeds())))
    if board.test_sets and method.serves_any_team and method.gains != "tuned":
        for name in team_places(scenario):
            family, n = name.rsplit("_", 1)
            cells.append(EvaluationCell(name, f"team {name}", "team", name, team_scenario(family, int(n)),
                                        tuple(board.team_seeds())))
    return cells


def expected_cell(board: Board, record: dict[str, Any]) -> tuple[Path, list[int], float] | None:
    """Where a cell record belongs under ``board.out``, its evaluation seeds and episode length on this board
    (the definitions :func:`fill` computes by); None when the board has no such cell."""
    trained, method, seed = record.get("trained_on", record["scenario"]), METHODS.get(record["method"]), record["seed"]
    if method is None or trained not in BUILTIN_SCENARIOS or isinstance(seed, bool) or not isinstance(seed, (int, type(None))):
        return None
    if "trained_on" not in record:
        seconds = board.episode_seconds or load_scenario(trained).episode_seconds
        return board.cell_path(trained, method, seed), board.eval_seeds(trained), seconds
    for cell in evaluation_cells(board, trained, method):
        if cell.split == record.get("split") and cell.name == record["scenario"]:
            seconds = board.episode_seconds or load_scenario(cell.scenario).episode_seconds
            seeds = board.eval_seeds() if cell.seeds is None else list(cell.seeds)
            return board.cell_path(trained, method, seed, cell.key), seeds, seconds
    return None


def cell_problem(board: Board, path: Path, record: dict[str, Any]) -> str | None:
    """Why the cell ``record`` read from ``path`` cannot be aggregated into ``board`` (None: it can): it is not at
    its own path (a copy such as ``reference.old.json``), or its seeds, episode length or episode count are not
    the ones this board gives it."""
    expected = expected_cell(board, record)
    if expected is None:
        return "not a cell of this board (its scenario, method, split or seed)"
    own_path, seeds, seconds = expected
    if path.resolve() != own_path.resolve():
        return f"not at its own path {own_path}"
    if record["eval_seeds"] != seeds:
        return f"evaluation seeds {str(record['eval_seeds'])[:80]} where this board uses {seeds[0]}-{seeds[-1]}"
    if record["episode_seconds"] != seconds:
        return f"episode_seconds {record['episode_seconds']!r} where this board uses {seconds}"
    if not record.get("failed") and len(record["episodes"]) != len(seeds):
        return f"{len(record['episodes'])} episodes for {len(seeds)} evaluation seeds"
    return None


def fill(board: Board, progress: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Run every cell of ``board`` that is not cached (written atomically when complete), the evaluation cells
    (:func:`evaluation_cells`) after their training cell; every cell record."""
    records = []
    for scenario, method, seed, label in training_cells(board, progress):

        def cached(path: Path, label: str, compute: Callable[[], dict[str, Any]]) -> dict[str, Any]:
            return cached_cell(path, label, board.protocol(method, scenario), compute, progress, board.accept_stale)

        trained = cached(board.cell_path(scenario, method, seed), label,
                         lambda: run_cell(board, scenario, method, seed))
        records.append(trained)
        for cell in evaluation_cells(board, scenario, method):
            records.append(cached(board.cell_path(scenario, method, seed, cell.key), f"{label} -> {cell.label}",
                                  lambda: cell.run(board, scenario, method, seed, trained)))
    return records


def training_cells(board: Board, progress: Callable[[str], None] = print
                   ) -> Iterator[tuple[str, Method, int | None, str]]:
    """(scenario, method, training seed or None for a reference, label) of every training cell of ``board``, in
    board order; a method that cannot run on a scenario is reported (``skipped``) and left out."""
    for scenario in board.scenarios:
        for name in board.methods:
            method = METHODS[name]
            why = method.unavailable(scenario)
            if why:
                progress(f"skipped {scenario} / {name}: {why}")
                continue
            for seed in (board.seeds if method.learned else (None,)):
                yield scenario, method, seed, f"{scenario} / {name}" + ("" if seed is None else f" / seed {seed}")


TRAIN_SET = "train-set"  # a distribution's train-set cells' folder (beside its test scenarios')
WIDE_STARTS = "wide-starts"  # a fixed scenario's wide-start cells' folder
