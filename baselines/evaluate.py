"""Evaluate reference policies, or a trained run's policy, on seeded episodes and print a metrics table.

    ee-formation evaluate --scenario planar_square --policy adaptive_jacobian --episodes 10 --seed 0
    ee-formation evaluate --scenario spatial_tetrahedron --policy all --json results.json
    ee-formation evaluate --policy adaptive_jacobian --episodes 2 --video videos   # one MP4 per episode
    ee-formation evaluate --policy runs/NAME --episodes 10 --video videos          # a train.py run folder
    ee-formation evaluate --policy RUN/policy --seed 10000 --set episode_seconds=10  # a BenchMARL export folder

(``python -m ee_formation_env.baselines.evaluate`` is the same command.)

Episode ``k`` uses reset seed ``seed + k``, so every policy sees the same initial states. Metrics are
defined in :mod:`ee_formation_env.baselines.metrics` (the same module ``train.py`` uses). A run folder is
evaluated as its comparison evaluates it (:class:`~ee_formation_env.baselines.learned.policy.SavedRun`): on
the scenario saved with it unless ``--scenario`` is given, in the env settings it trained with (its action
convention, e.g. ``gravity_compensation``), with its observation features and normalization. A BenchMARL
export folder (``actor.json`` + ``actor.pt``, :func:`~ee_formation_env.baselines.learned.benchmarl_task.export_benchmarl_policy`;
the ``torchrl`` extra) is evaluated as
:func:`~ee_formation_env.baselines.learned.benchmarl_task.evaluate_benchmarl_policy` does: on its task's
scenario with the task's overrides, in its action convention, deterministic.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import json
import math
import re
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

import ee_formation_env
from ee_formation_env.baselines import POLICIES, REFERENCE_CONTROLLERS, make_policies
from ee_formation_env.baselines.atomic_files import write_text
from ee_formation_env.baselines.extras import require
from ee_formation_env.baselines.metrics import (DEFAULT_EVALUATION_COPIES, DEFAULT_POSITION_TOLERANCE, EpisodeMetrics,
                                                PolicySource, format_table, metric_definitions, run_episode,
                                                run_episodes, summarize)
from ee_formation_env.env import FormationEnv


class EpisodeVideo:
    """Frames of one episode, rendered every ``stride`` env steps so that the video plays at simulated speed.

    Use :meth:`capture` as :func:`ee_formation_env.baselines.metrics.run_episode`'s ``on_step`` (plus once after the reset),
    then :meth:`write`.
    """

    def __init__(self, env: FormationEnv):
        self.env = env
        self.fps = float(env.metadata["render_fps"])
        self.stride = max(1, round(env.scenario.control_hz / self.fps))
        self.fps = env.scenario.control_hz / self.stride  # the exact playback rate of simulated time
        self.frames: list[np.ndarray] = []
        self._steps = 0

    def capture(self, env: FormationEnv | None = None) -> None:
        if self._steps % self.stride == 0:
            self.frames.append(self.env.render())
        self._steps += 1

    def write(self, path: Path) -> Path:
        """Write an MP4 (imageio-ffmpeg installed) or else a GIF; returns the path written."""
        import imageio

        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            import imageio_ffmpeg  # noqa: F401  (imageio's MP4 writer)
        except ImportError:
            path = path.with_name(path.name + ".gif")  # not with_suffix: a name may contain dots
            imageio.mimwrite(path, self.frames, duration=1000.0 / self.fps, loop=0)
        else:
            path = path.with_name(path.name + ".mp4")
            # H.264 wants sides divisible by 16: pad by repeating the edge instead of letting imageio resize.
            height, width = self.frames[0].shape[:2]
            padding = ((0, -height % 16), (0, -width % 16), (0, 0))
            imageio.mimwrite(path, [np.pad(frame, padding, mode="edge") for frame in self.frames], fps=self.fps)
        return path


def file_stem(name: str, fallback: str = "scenario", max_length: int = 100) -> str:
    """``name`` as a safe file name: characters outside ``[A-Za-z0-9_.-]`` (path separators included) become
    ``_``, leading dots are dropped (no ``..``, no hidden files), at most ``max_length`` characters. Where that
    changed the name, the stem ends with ``-`` and 8 hex digits of the name's SHA-256, so that two names that
    read alike once made safe (``a/b`` and ``a_b``, or two long names with one beginning) get two files; a name
    that is already safe is its own stem."""
    name = str(name)
    stem = re.sub(r"[^A-Za-z0-9_.-]", "_", name).lstrip(".")
    if stem == name and 0 < len(stem) <= max_length:
        return stem
    digest = hashlib.sha256(name.encode("utf-8", "surrogatepass")).hexdigest()[:8]
    return f"{stem[:max_length - 9] or fallback}-{digest}"


def video_path(video_dir: Path | str, scenario: str, policy: str, seed: int) -> Path:
    """Where an episode's video goes: ``video_dir/<scenario>-<policy>-seed<k>`` (the writer adds ``.mp4`` or
    ``.gif``), scenario and policy names made safe by :func:`file_stem`, so it is always inside ``video_dir``
    and two scenario names never share a file. Where the scenario's stem holds the separator ``-`` (scenario
    ``a-b`` with policy ``c`` would read as scenario ``a`` with policy ``b-c``), 8 hex digits of the pair's SHA-256
    follow the policy; without one, the scenario is what comes before the first ``-``, so names stay plain."""
    scenario_stem, policy_stem = file_stem(scenario), file_stem(policy, "policy")
    name = f"{scenario_stem}-{policy_stem}"
    if "-" in scenario_stem:
        pair = f"{scenario}\0{policy}".encode("utf-8", "surrogatepass")
        name += f"-{hashlib.sha256(pair).hexdigest()[:8]}"
    return Path(video_dir) / f"{name}-seed{int(seed)}"


def evaluate_policy(scenario: Any, policy: str | PolicySource, episodes: int, seed: int,
                    position_tolerance: float = DEFAULT_POSITION_TOLERANCE, overrides: dict | None = None,
                    policy_kwargs: dict | None = None, video_dir: Path | None = None,
                    on_episode: Callable[[str, int, EpisodeMetrics], None] | None = None,
                    on_round: Callable[[str, list[int]], None] | None = None, name: str | None = None,
                    video_name: str | None = None) -> dict[str, Any]:
    """Summary (see :func:`ee_formation_env.baselines.metrics.summarize`) of ``policy`` over seeded episodes.

    ``policy``: a reference policy's name, or a callable ``env -> {agent: policy}`` (a
    :class:`~ee_formation_env.baselines.learned.policy.SavedRun`'s ``policy_source()``), called once per env;
    ``name`` names it in the callbacks (default: ``policy``, a name) and ``video_name`` in the video files
    (default: ``name``). ``video_dir``: also write one video per episode there
    (``<scenario>-<video_name>-seed<k>.mp4``, or ``.gif``; the names made safe by :func:`file_stem`, so that a
    scenario's ``name`` cannot put it elsewhere), rendered as ``rgb_array``. ``on_episode(name, seed,
    metrics)`` is called after each episode. Without videos, the episodes run together on the batched env
    (:func:`~ee_formation_env.baselines.metrics.run_episodes`) in rounds of at most
    :data:`~ee_formation_env.baselines.metrics.DEFAULT_EVALUATION_COPIES` seeds, each on a fresh env as
    ``run_episodes`` itself makes them: ``on_round(name, seeds)`` is called as a round starts and
    ``on_episode`` for each of its episodes once they have all ended.
    """
    name = name if name is not None else str(policy)
    if video_dir is None:  # the episodes together on the batched env: the same metrics, bit for bit
        seeds = [seed + k for k in range(episodes)]
        results = []
        for start in range(0, len(seeds), DEFAULT_EVALUATION_COPIES):
            chunk = seeds[start:start + DEFAULT_EVALUATION_COPIES]
            if on_round is not None:
                on_round(name, chunk)
            chunk_results = run_episodes(scenario, policy, chunk, position_tolerance=position_tolerance,
                                         overrides=overrides, policy_kwargs=policy_kwargs)
            results += chunk_results
            if on_episode is not None:
                for episode_seed, metrics in zip(chunk, chunk_results):
                    on_episode(name, episode_seed, metrics)
        summary = summarize(results)
        summary["per_episode"] = [r.as_dict() for r in results]
        return summary
    results = []
    with ee_formation_env.parallel_env(scenario, render_mode="rgb_array", **(overrides or {})) as env:
        policies = (make_policies(policy, env, **(policy_kwargs or {})) if isinstance(policy, str)
                    else policy(env))
        for k in range(episodes):
            video = EpisodeVideo(env)
            metrics = run_episode(env, policies, seed=seed + k, position_tolerance=position_tolerance,
                                  on_reset=video.capture, on_step=video.capture)
            video.write(video_path(video_dir, env.scenario.name, video_name or name, seed + k))
            results.append(metrics)
            if on_episode is not None:
                on_episode(name, seed + k, metrics)
    summary = summarize(results)
    summary["per_episode"] = [r.as_dict() for r in results]
    return summary


def parse_key_values(pairs: Sequence[str], flag: str = "--set") -> dict[str, Any]:
    """Command-line ``KEY=VALUE`` pairs as a dict, each VALUE read as JSON (kept as the string where it is not
    JSON); a pair without ``=`` or without a key raises ``ValueError`` naming ``flag``."""
    overrides = {}
    for pair in pairs:
        key, separator, value = pair.partition("=")
        if not separator or not key:
            raise ValueError(f"{flag}: expected KEY=VALUE (VALUE in JSON), got {pair!r}")
        try:
            overrides[key] = json.loads(value)
        except json.JSONDecodeError:
            overrides[key] = value
    return overrides


DEFAULT_SCENARIO = "planar_square"  # what --scenario is unless given (a run folder: the scenario saved with it)


def build_parser(prog: str = "python -m ee_formation_env.baselines.evaluate") -> argparse.ArgumentParser:
    """The command's flags (every one with its help)."""
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="table columns (mean over episodes unless said otherwise):\n"
                                            + metric_definitions())
    parser.add_argument("--scenario", default=None,
                        help=f"built-in name or YAML/JSON file (default: {DEFAULT_SCENARIO}; with --policy RUN_DIR, "
                             "the scenario saved with the run)")
    parser.add_argument("--policy", default="all",
                        help=f"one of {list(POLICIES)}, 'all', a train.py run folder RUN_DIR (its learned "
                             "policy, in the env settings it trained with), or a BenchMARL export folder "
                             "(actor.json, actor.pt; the torchrl extra)")
    parser.add_argument("--episodes", type=int, default=10, help="episodes per policy (default 10)")
    parser.add_argument("--seed", type=int, default=0,
                        help="reset seed of the first episode; episode k uses seed + k (default 0; a run's "
                             "comparison uses 10000)")
    parser.add_argument("--tolerance", type=float, default=DEFAULT_POSITION_TOLERANCE,
                        help="edge-length accuracy (m) that counts as success")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                        help="scenario overrides, VALUE in JSON, e.g. --set torque_limits=1e6 frame_skip=1")
    parser.add_argument("--gains", choices=("default", "tuned"), default="default",
                        help="the laws' gains: their defaults, or their tuned sets for this built-in scenario "
                             "(baselines/reference/tuned/; docs/controllers.md, 'Tuned gains')")
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON (a file path)")
    parser.add_argument("--video", metavar="DIR", type=Path,
                        help="also write one video per episode into DIR (MP4, or GIF without imageio-ffmpeg; "
                             "needs the 'video' extra)")
    parser.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    parser.add_argument("--debug", action="store_true", help="on an error, show the traceback instead of one line")
    return parser


def _json_target_problem(path: str) -> str | None:
    """Why ``--json PATH`` cannot be written (None if it can), found by opening it for appending, which
    leaves an existing file as it is; a file the probe had to create is removed again."""
    target = Path(path)
    if target.is_dir():
        return f"{path} is a folder; expected the path of a file to write"
    if not target.resolve().parent.is_dir():
        return f"the folder of {path} does not exist"
    existed = target.exists()
    try:
        with open(target, "a", encoding="utf-8"):
            pass
    except OSError as error:
        return f"{path} cannot be written ({error.strerror or error})"
    if not existed:
        target.unlink(missing_ok=True)
    return None


def _video_folder_problem(folder: Path) -> str | None:
    """Why ``--video DIR`` cannot hold the videos (None if it can): a file, or a folder (or the nearest
    existing folder above it, where it would be made) this process cannot write into. An unnamed temporary
    file probes it, so nothing is left behind."""
    if folder.exists() and not folder.is_dir():
        return f"{folder} is a file, not a folder"
    existing = folder.resolve()
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        return f"{existing} is a file, not a folder"
    try:
        tempfile.TemporaryFile(dir=existing).close()
    except OSError as error:
        return f"{folder} cannot be written ({error.strerror or error})"
    return None


@dataclass(frozen=True)
class _Evaluated:
    """One policy of the command: its row name, where it comes from, and the scenario overrides it runs with."""

    name: str
    overrides: dict[str, Any]
    run: Any = None  # a SavedRun or ExportedActors, or None for a reference policy (``name``)
    policy_kwargs: dict[str, Any] | None = None  # a reference law's make_policies arguments (``gains``)

    @property
    def row(self) -> str:
        """Its row in the table and the JSON: a law with tuned gains is another row than with its defaults."""
        return f"{self.name} (tuned)" if (self.policy_kwargs or {}).get("gains") == "tuned" else self.name

    def source(self) -> PolicySource:
        """What :func:`evaluate_policy` runs: the reference's name, or the run's policies (a fresh model read,
        as each comparison reads it)."""
        return self.name if self.run is None else self.run.policy_source()

    @property
    def video_name(self) -> str:
        """The policy part of its video files: a run's folder name, so that two runs' videos do not collide."""
        return self.name if self.run is None else self.run.run_dir.resolve().name


@dataclass(frozen=True)
class ExportedActors:
    """A BenchMARL export folder seen as a run by this command: its scenario, row label, action convention and
    per-agent policies (:class:`~ee_formation_env.baselines.learned.benchmarl_task.BenchmarlActors`)."""

    run_dir: Path
    actors: Any

    @classmethod
    def load(cls, folder: str | Path) -> "ExportedActors":
        from ee_formation_env.baselines.learned.benchmarl_task import load_benchmarl_policy

        return cls(Path(folder), load_benchmarl_policy(folder))

    @property
    def scenario(self) -> Any:
        return self.actors.scenario

    @property
    def scenario_name(self) -> str:
        scenario = self.actors.scenario
        return str(scenario.get("name", "scenario of the export")) if isinstance(scenario, dict) else str(scenario)

    @property
    def label(self) -> str:
        return f"learned (benchmarl, {self.actors.options.mode})"

    def env_overrides(self) -> dict[str, Any]:
        return self.actors.env_overrides()

    def policy_source(self) -> Callable[[Any], dict[str, Any]]:
        return self.actors.policy_factory()


def _policies(policy: str, parser: argparse.ArgumentParser, overrides: dict[str, Any], gains: str = "default"
              ) -> list[_Evaluated]:
    """The policies ``--policy`` names, each with the scenario overrides it is evaluated with: a run's
    policy also with the env settings of its action convention (``SavedRun.env_overrides``); ``gains``
    (``--gains``): the laws' defaults or their tuned sets."""
    def law(name: str) -> _Evaluated:
        tuned = gains == "tuned" and name in REFERENCE_CONTROLLERS
        return _Evaluated(name, overrides, policy_kwargs={"gains": "tuned"} if tuned else None)

    if policy == "all":
        return [law(name) for name in POLICIES]
    if policy in POLICIES:
        return [law(policy)]
    if gains != "default":
        parser.error("--gains: applies to the reference laws, not to a run's policy")
    if not Path(policy).is_dir() and (os.sep in policy or "/" in policy or Path(policy).exists()):
        parser.error(f"--policy: {policy!r}: no such folder (a train.py run folder or a BenchMARL export folder)"
                     if not Path(policy).exists() else f"--policy: {policy!r} is a file, not a run folder")
    if not Path(policy).is_dir():
        parser.error(f"--policy: unknown policy {policy!r}; available: {list(POLICIES)}, 'all', a train.py "
                     "run folder (holding config.json and model/) or a BenchMARL export folder (actor.json)")
    if (Path(policy) / "actor.json").is_file():
        require(["torchrl", "benchmarl"], "torchrl", "--policy with a BenchMARL export folder")
        run: Any = ExportedActors.load(policy)
        overrides = {**run.actors.overrides, **overrides}  # the task's, then the command's
    else:
        from ee_formation_env.baselines.learned.policy import SavedRun

        run = SavedRun.load(policy, "--policy")
    own = run.env_overrides()
    for key, value in own.items():
        if key in overrides and overrides[key] != value:
            raise ValueError(f"--set: {key}: the run's policy acts with {key} {value} (it trained so); it cannot "
                             "be evaluated with another value")
    return [_Evaluated(run.label, {**overrides, **own}, run)]


def _check_policies(scenario: Any, evaluated: Sequence[_Evaluated]) -> None:
    """Build each policy once on the scenario, so that what would refuse it mid-evaluation refuses it now: the
    scenario's own checks, a law on a gravity-compensated scenario, a run's model that does not load or whose
    sizes do not fit the team."""
    groups: dict[str, list[_Evaluated]] = {}
    for policy in evaluated:
        groups.setdefault(json.dumps(policy.overrides, sort_keys=True, default=str), []).append(policy)
    for group in groups.values():
        with ee_formation_env.parallel_env(scenario, **group[0].overrides) as env:
            for policy in group:
                source = policy.source()
                if isinstance(source, str):
                    make_policies(source, env, **(policy.policy_kwargs or {}))
                else:
                    source(env)


def main(argv: Sequence[str] | None = None, prog: str = "python -m ee_formation_env.baselines.evaluate") -> int:
    parser = build_parser(prog)
    args = parser.parse_args(argv)
    # Every argument is checked before the first episode runs and before any file or folder is made.
    if args.episodes < 1:
        parser.error(f"--episodes: expected an integer >= 1, got {args.episodes}")
    if not (math.isfinite(args.tolerance) and args.tolerance > 0):
        parser.error(f"--tolerance: expected an edge accuracy > 0 m, got {args.tolerance}")
    if args.seed < 0:
        parser.error(f"--seed: expected an integer >= 0, got {args.seed}")
    if args.json:
        problem = _json_target_problem(args.json)
        if problem:
            parser.error(f"--json: {problem}")
    if args.video is not None:
        require(["imageio"], "video", "--video")
        problem = _video_folder_problem(args.video)
        if problem:
            parser.error(f"--video: {problem}")
    try:
        evaluated = _policies(args.policy, parser, parse_key_values(args.set), args.gains)
        run = evaluated[0].run
        if args.scenario is not None:
            scenario = scenario_name = args.scenario
        elif run is not None:  # the scenario as saved with the run, not as its file is now
            scenario, scenario_name = run.scenario, run.scenario_name
        else:
            scenario = scenario_name = DEFAULT_SCENARIO
        _check_policies(scenario, evaluated)
    except (ValueError, TypeError) as error:
        if args.debug:
            raise
        parser.error(str(error))
    if args.video is not None:
        args.video.mkdir(parents=True, exist_ok=True)
    print(f"scenario {scenario_name}, {args.episodes} episodes from seed {args.seed}, tolerance {args.tolerance} m"
          + (f", policy of {args.policy}" if run is not None else ""), flush=True)

    def progress(name: str, seed: int, metrics: EpisodeMetrics) -> None:
        outcome = "success" if metrics.success else ("fault: " + metrics.physics_fault if metrics.physics_fault
                                                      else "no success")
        print(f"  {name}: episode {seed - args.seed + 1}/{args.episodes} (seed {seed}) {outcome}", file=sys.stderr,
              flush=True)

    def round_started(name: str, seeds: list[int]) -> None:
        first, last = seeds[0] - args.seed + 1, seeds[-1] - args.seed + 1
        print(f"  {name}: running episodes {first}-{last}/{args.episodes} together ...", file=sys.stderr, flush=True)

    quiet = args.quiet
    # A run's row is "learned", as in its comparison.json; the table shows its label.
    results = {"learned" if policy.run is not None else policy.row: evaluate_policy(
        scenario, policy.source(), args.episodes, args.seed, args.tolerance, policy.overrides,
        policy_kwargs=policy.policy_kwargs, video_dir=args.video, on_episode=None if quiet else progress,
        on_round=None if quiet else round_started, name=policy.row, video_name=policy.video_name)
        for policy in evaluated}
    print(format_table({run.label if run is not None else key: value for key, value in results.items()}))
    if args.video is not None:
        count = len(evaluated) * args.episodes
        print(f"wrote {count} video{'' if count == 1 else 's'} to {args.video.resolve()}")
    if args.json:
        record = {"scenario": scenario_name, "episodes": args.episodes, "seed": args.seed,
                  "overrides": evaluated[0].overrides}
        if run is not None:
            record.update(run=str(run.run_dir), learned_label=run.label)
        write_text(Path(args.json), json.dumps({**record, "results": results}, indent=2, default=float))
        print(f"wrote {Path(args.json).resolve()}")
    return 0


if __name__ == "__main__":
    from ee_formation_env.baselines.cli_errors import report_errors

    sys.exit(report_errors(main, "--debug" in sys.argv))
