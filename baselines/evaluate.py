"""Evaluate reference policies on seeded episodes and print a metrics table.

    ee-formation evaluate --scenario planar_square --policy adaptive_jacobian --episodes 10 --seed 0
    ee-formation evaluate --scenario spatial_tetrahedron --policy all --json results.json
    ee-formation evaluate --policy adaptive_jacobian --episodes 2 --video videos   # one MP4 per episode

(``python -m ee_formation_env.baselines.evaluate`` is the same command.)

Episode ``k`` uses reset seed ``seed + k``, so every policy sees the same initial states. Metrics are
defined in :mod:`ee_formation_env.baselines.metrics` (the same module ``train.py`` uses).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

import ee_formation_env
from ee_formation_env.baselines import POLICIES, make_policies
from ee_formation_env.baselines.extras import require
from ee_formation_env.baselines.metrics import (DEFAULT_EVALUATION_COPIES, DEFAULT_POSITION_TOLERANCE, EpisodeMetrics,
                                                format_table, metric_definitions, run_episode, run_episodes, summarize)
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
    ``_``, leading dots are dropped (no ``..``, no hidden files), at most ``max_length`` characters."""
    stem = re.sub(r"[^A-Za-z0-9_.-]", "_", str(name)).lstrip(".")[:max_length]
    return stem or fallback


def video_path(video_dir: Path | str, scenario: str, policy: str, seed: int) -> Path:
    """Where an episode's video goes: ``video_dir/<scenario>-<policy>-seed<k>`` (the writer adds ``.mp4`` or
    ``.gif``), scenario and policy names made safe by :func:`file_stem`, so it is always inside ``video_dir``."""
    return Path(video_dir) / f"{file_stem(scenario)}-{file_stem(policy, 'policy')}-seed{int(seed)}"


def evaluate_policy(scenario: Any, policy: str, episodes: int, seed: int,
                    position_tolerance: float = DEFAULT_POSITION_TOLERANCE, overrides: dict | None = None,
                    policy_kwargs: dict | None = None, video_dir: Path | None = None,
                    on_episode: Callable[[str, int, EpisodeMetrics], None] | None = None,
                    on_round: Callable[[str, list[int]], None] | None = None) -> dict[str, Any]:
    """Summary (see :func:`ee_formation_env.baselines.metrics.summarize`) of ``policy`` over seeded episodes.

    ``video_dir``: also write one video per episode there (``<scenario>-<policy>-seed<k>.mp4``, or ``.gif``; the
    names made safe by :func:`file_stem`, so that a scenario's ``name`` cannot put it elsewhere), rendered as
    ``rgb_array``. ``on_episode(policy, seed, metrics)`` is called after each episode. Without videos, the
    episodes run together on the batched env (:func:`~ee_formation_env.baselines.metrics.run_episodes`) in
    rounds of at most :data:`~ee_formation_env.baselines.metrics.DEFAULT_EVALUATION_COPIES` seeds, each on a
    fresh env as ``run_episodes`` itself makes them: ``on_round(policy, seeds)`` is called as a round starts and
    ``on_episode`` for each of its episodes once they have all ended.
    """
    if video_dir is None:  # the episodes together on the batched env: the same metrics, bit for bit
        seeds = [seed + k for k in range(episodes)]
        results = []
        for start in range(0, len(seeds), DEFAULT_EVALUATION_COPIES):
            chunk = seeds[start:start + DEFAULT_EVALUATION_COPIES]
            if on_round is not None:
                on_round(policy, chunk)
            chunk_results = run_episodes(scenario, policy, chunk, position_tolerance=position_tolerance,
                                         overrides=overrides, policy_kwargs=policy_kwargs)
            results += chunk_results
            if on_episode is not None:
                for episode_seed, metrics in zip(chunk, chunk_results):
                    on_episode(policy, episode_seed, metrics)
        summary = summarize(results)
        summary["per_episode"] = [r.as_dict() for r in results]
        return summary
    results = []
    with ee_formation_env.parallel_env(scenario, render_mode="rgb_array", **(overrides or {})) as env:
        policies = make_policies(policy, env, **(policy_kwargs or {}))
        for k in range(episodes):
            video = EpisodeVideo(env)
            metrics = run_episode(env, policies, seed=seed + k, position_tolerance=position_tolerance,
                                  on_reset=video.capture, on_step=video.capture)
            video.write(video_path(video_dir, env.scenario.name, policy, seed + k))
            results.append(metrics)
            if on_episode is not None:
                on_episode(policy, seed + k, metrics)
    summary = summarize(results)
    summary["per_episode"] = [r.as_dict() for r in results]
    return summary


def _overrides(pairs: Sequence[str]) -> dict[str, Any]:
    overrides = {}
    for pair in pairs:
        key, separator, value = pair.partition("=")
        if not separator:
            raise ValueError(f"--set: expected KEY=VALUE (VALUE in JSON), got {pair!r}")
        try:
            overrides[key] = json.loads(value)
        except json.JSONDecodeError:
            overrides[key] = value
    return overrides


def build_parser(prog: str = "python -m ee_formation_env.baselines.evaluate") -> argparse.ArgumentParser:
    """The command's flags (every one with its help)."""
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="table columns (mean over episodes unless said otherwise):\n"
                                            + metric_definitions())
    parser.add_argument("--scenario", default="planar_square", help="built-in name or YAML/JSON file")
    parser.add_argument("--policy", default="all", help=f"one of {list(POLICIES)} or 'all'")
    parser.add_argument("--episodes", type=int, default=10, help="episodes per policy (default 10)")
    parser.add_argument("--seed", type=int, default=0,
                        help="reset seed of the first episode; episode k uses seed + k (default 0)")
    parser.add_argument("--tolerance", type=float, default=DEFAULT_POSITION_TOLERANCE,
                        help="edge-length accuracy (m) that counts as success")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                        help="scenario overrides, VALUE in JSON, e.g. --set torque_limits=1e6 frame_skip=1")
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    parser.add_argument("--video", metavar="DIR", type=Path,
                        help="also write one video per episode into DIR (MP4, or GIF without imageio-ffmpeg; "
                             "needs the 'video' extra)")
    parser.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    parser.add_argument("--debug", action="store_true", help="on an error, show the traceback instead of one line")
    return parser


def main(argv: Sequence[str] | None = None, prog: str = "python -m ee_formation_env.baselines.evaluate") -> int:
    parser = build_parser(prog)
    args = parser.parse_args(argv)
    # Every argument is checked before the first episode runs.
    if args.episodes < 1:
        parser.error("--episodes: expected an integer >= 1")
    if not (math.isfinite(args.tolerance) and args.tolerance > 0):
        parser.error(f"--tolerance: expected an edge accuracy > 0 m, got {args.tolerance}")
    if args.seed < 0:
        parser.error(f"--seed: expected an integer >= 0, got {args.seed}")
    names = list(POLICIES) if args.policy == "all" else [args.policy]
    for name in names:
        if name not in POLICIES:
            parser.error(f"--policy: unknown policy {name!r}; available: {list(POLICIES)} or 'all'")
    if args.json and not Path(args.json).resolve().parent.is_dir():
        parser.error(f"--json: the folder of {args.json} does not exist")
    if args.video is not None:
        require(["imageio"], "video", "--video")
        if args.video.exists() and not args.video.is_dir():
            parser.error(f"--video: {args.video} is a file, not a folder")
    try:
        overrides = _overrides(args.set)
        ee_formation_env.parallel_env(args.scenario, **overrides).close()  # the scenario validates, or a clear error
    except (ValueError, TypeError) as error:
        if args.debug:
            raise
        parser.error(str(error))
    if args.video is not None:
        args.video.mkdir(parents=True, exist_ok=True)
    print(f"scenario {args.scenario}, {args.episodes} episodes from seed {args.seed}, tolerance {args.tolerance} m",
          flush=True)

    def progress(name: str, seed: int, metrics: EpisodeMetrics) -> None:
        outcome = "success" if metrics.success else ("fault: " + metrics.physics_fault if metrics.physics_fault
                                                      else "no success")
        print(f"  {name}: episode {seed - args.seed + 1}/{args.episodes} (seed {seed}) {outcome}", file=sys.stderr,
              flush=True)

    def round_started(name: str, seeds: list[int]) -> None:
        first, last = seeds[0] - args.seed + 1, seeds[-1] - args.seed + 1
        print(f"  {name}: running episodes {first}-{last}/{args.episodes} together ...", file=sys.stderr, flush=True)

    quiet = args.quiet
    results = {name: evaluate_policy(args.scenario, name, args.episodes, args.seed, args.tolerance, overrides,
                                     video_dir=args.video, on_episode=None if quiet else progress,
                                     on_round=None if quiet else round_started) for name in names}
    print(format_table(results))
    if args.video is not None:
        print(f"wrote {len(names) * args.episodes} videos to {args.video.resolve()}")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as handle:
            json.dump({"scenario": args.scenario, "episodes": args.episodes, "seed": args.seed,
                       "overrides": overrides, "results": results}, handle, indent=2, default=float)
        print(f"wrote {Path(args.json).resolve()}")
    return 0


if __name__ == "__main__":
    from ee_formation_env.baselines.cli_errors import report_errors

    sys.exit(report_errors(main, "--debug" in sys.argv))
