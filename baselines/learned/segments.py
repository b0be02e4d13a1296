"""The training segments of a run: ``timing.json``, the monitor files and ``learning_curve.csv``.

A run trains in one segment, or in several when it is resumed. Each segment has its own monitor file (SB3's
``VecMonitor``: one line per training episode), ``monitor.csv`` for the first and ``resumed-<k>.monitor.csv``
for the k-th resumed one, never a file that exists already: resuming appends a file, it never truncates one.
``timing.json`` lists every segment: it is written when a segment starts (``running`` true), at each of its
checkpoints (its agent steps and seconds so far) and at its end. A segment that a kill ended (SIGKILL, a crash,
a power cut) is still ``running`` in it; resuming marks it ended, ``interrupted`` saying so.
``learning_curve.csv`` is drawn from the monitor files of every segment, each from the step count it started at.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ee_formation_env.baselines.atomic_files import refused, write_text
from ee_formation_env.baselines.learned.checkpoint import write_json

TIMING = "timing.json"
FIRST_MONITOR = "monitor.csv"
#: ``interrupted`` of a segment that ended without stopping cleanly (found ``running`` by a later resume).
KILLED = "ended without a clean stop (killed or crashed); resumed from its newest checkpoint"
_SEGMENT_FIELDS = {"monitor": str, "start_agent_steps": int}


def read_timing(run_dir: Path) -> dict[str, Any]:
    """``timing.json`` of ``run_dir`` (a fresh one if there is none), checked: a JSON object whose ``segments``
    is a list of segments, each with its ``monitor`` file name and ``start_agent_steps``. A file that is not is
    a ``ValueError`` naming it and the fix."""
    path = Path(run_dir) / TIMING
    if not path.is_file():
        return {"segments": []}
    fix = (f"restore the file the run wrote, or remove it (the segments before are then no longer listed, and "
           f"learning_curve.csv starts at the resumed checkpoint)")
    try:
        timing = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ValueError(f"{path}: not valid JSON ({error}): {fix}") from None
    segments = timing.get("segments") if isinstance(timing, dict) else None
    if not isinstance(segments, list):
        raise ValueError(f"{path}: expected a JSON object with a list of 'segments': {fix}")
    for index, segment in enumerate(segments):
        for key, kind in _SEGMENT_FIELDS.items():
            value = segment.get(key) if isinstance(segment, dict) else None
            if isinstance(value, bool) or not isinstance(value, kind):
                raise ValueError(f"{path}: segments[{index}].{key}: expected {kind.__name__}, got {value!r}: {fix}")
        if Path(segment["monitor"]).name != segment["monitor"] or not segment["monitor"].endswith("monitor.csv"):
            raise ValueError(f"{path}: segments[{index}].monitor: expected a monitor file name of the run folder, "
                             f"got {segment['monitor']!r}: {fix}")
    return timing


def close_killed_segments(timing: dict[str, Any]) -> None:
    """Mark the segments that are still ``running`` (a kill ended them) as ended, ``interrupted`` :data:`KILLED`."""
    for segment in timing["segments"]:
        if segment.get("running"):
            segment.update(running=False, interrupted=KILLED)


def new_monitor_name(run_dir: Path, timing: dict[str, Any]) -> str:
    """The monitor file of the next segment: ``monitor.csv`` for the first, ``resumed-<k>.monitor.csv`` after,
    never one that exists (a segment a kill ended before ``timing.json`` listed it still has its file)."""
    index = len(timing["segments"])
    while True:
        name = FIRST_MONITOR if index == 0 else f"resumed-{index}.monitor.csv"
        if not (Path(run_dir) / name).exists():
            return name
        index += 1


def start_segment(run_dir: Path, timing: dict[str, Any], monitor: str, start_agent_steps: int) -> dict[str, Any]:
    """Append the segment that starts now to ``timing`` and write ``timing.json``; returns the segment, which
    :func:`update_segment` then updates."""
    segment = {"monitor": monitor, "start_agent_steps": int(start_agent_steps), "agent_steps": int(start_agent_steps),
               "train_seconds": 0.0, "interrupted": None, "running": True}
    timing["segments"].append(segment)
    write_timing(run_dir, timing)
    return segment


def update_segment(run_dir: Path, timing: dict[str, Any], segment: dict[str, Any], **values: Any) -> None:
    """Set ``values`` in ``segment`` (the last of ``timing``), the run's totals, and write ``timing.json``."""
    segment.update(values)
    write_timing(run_dir, timing)


def write_timing(run_dir: Path, timing: dict[str, Any]) -> None:
    """``timing.json`` with the run's totals over its segments: training seconds, the agent steps of the last."""
    segments = timing["segments"]
    timing["train_seconds"] = sum(float(s.get("train_seconds") or 0.0) for s in segments)
    if segments:
        timing["agent_steps"] = int(segments[-1].get("agent_steps", segments[-1]["start_agent_steps"]))
        timing["interrupted"] = segments[-1].get("interrupted")
    path = Path(run_dir) / TIMING
    try:
        write_json(path, timing)
    except OSError as error:  # named: a refused write says which file
        raise refused(path, error) from None


def write_learning_curve(run_dir: Path, segments: list[dict[str, Any]]) -> None:
    """``learning_curve.csv``: agent steps so far and episode return (mean over agents), per training episode,
    over every segment of the run (a resumed segment starts at its checkpoint's step count, and the episodes
    of the segment before that came after that checkpoint are dropped: training continued without them)."""
    rows: list[tuple[int, float]] = []
    for segment in segments:
        start = int(segment["start_agent_steps"])
        rows = [row for row in rows if row[0] <= start]
        monitor = Path(run_dir) / segment["monitor"]
        if not monitor.exists():
            continue
        lines = [line for line in monitor.read_text().splitlines() if line and not line.startswith("#")]
        total = start
        for line in lines[1:]:
            fields = line.split(",")
            try:
                reward, length = float(fields[0]), int(float(fields[1]))
            except (IndexError, ValueError):
                continue  # a line a kill cut short
            total += length
            rows.append((total, reward))
    write_text(Path(run_dir) / "learning_curve.csv",
               "agent_steps,episode_return\n" + "".join(f"{steps},{ret}\n" for steps, ret in rows))
