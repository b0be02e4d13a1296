"""The scoreboard's cell cache: one JSON file per cell, and what decides whether a cached cell may be aggregated.

A cell (``studies.scoreboard``: one scenario x method x training seed) is written when it is complete, stamped
with

- ``schema``: :data:`CELL_SCHEMA`, the layout of the record (raised when a field changes meaning or is added
  that aggregation reads);
- ``code``: the code that computed it, :func:`code_version`: the package version and a SHA-256 of the source
  and data files that decide a cell's numbers (:func:`source_files`: the package ``ee_formation_env`` with its
  ``baselines`` and ``assets``, i.e. the env, the physics, the robots, the built-in scenarios, the reference
  laws, the metrics and the training code, and ``studies/benchmarl_runs.py``, which trains the BenchMARL
  methods). Any edit to those files, a comment included, makes a new version: the hash cannot tell which
  edits change a number, and a board that mixes code silently is worse than one recomputed. The laws' tuned
  gains (``baselines/reference/tuned/``) are left out of the hash: each enters the protocol of the cells that run
  with it;
- ``protocol``: what the study itself sets for the cell (the method's definition: its gains, ``train.py`` flags
  or BenchMARL run and learning settings; every board setting that decides a cell's numbers: episodes, episode
  length, the flags every learned method gets, such as ``--quick``'s; a tuned law's tuned entry), so that
  redefining a method in ``studies/scoreboard_methods.py`` recomputes its cells while editing that file's tables or
  prose does not.

A cached cell is used only when all three match this code's (:func:`stale_reason`); otherwise it is recomputed,
or, with ``--accept-stale-cells``, aggregated as it is, and each such cell is reported in one line. A file that
does not parse or lacks a field (a truncated write by an older version, a hand edit) is reported in one line
naming it and recomputed. A learned cell's training run is stamped the same way (:func:`run_is_current`): a run
started by other code or for another definition of its method is trained again, not resumed or reused.
"""

from __future__ import annotations

import errno
import functools
import hashlib
import importlib.util
import json
from pathlib import Path
from typing import Any, Callable, Mapping

import ee_formation_env
from ee_formation_env.baselines.atomic_files import WriteRefused, make_folder, write_text

#: The layout of a cell record: raised when aggregation reads a field differently (2: the precision metrics,
#: and a protocol holding every board setting that decides a cell's numbers).
CELL_SCHEMA = 2
#: The fields every cell has (aggregation reads them).
CELL_FIELDS = ("scenario", "method", "seed", "eval_seeds", "episode_seconds", "budget", "wall_seconds", "episodes")
#: The packages whose files decide a cell's numbers, and the suffixes of those files (code, scenarios, robots).
SOURCE_PACKAGES = ("ee_formation_env", "ee_formation_env.baselines", "ee_formation_env.assets")
SOURCE_SUFFIXES = (".py", ".yaml", ".yml", ".json", ".urdf", ".xml", ".obj", ".stl", ".dae")
#: Data the code hash leaves out: the laws' tuned gains, which enter the key of the cells that use them instead
#: (``Board.protocol``), so that tuning one scenario does not make every other cell stale.
EXCLUDED_DATA = ("ee_formation_env.baselines/reference/tuned/",)
#: Study files that train a board method (beside the package): the BenchMARL runs.
STUDY_SOURCES = (Path(__file__).resolve().parent / "benchmarl_runs.py",)


def source_files() -> list[tuple[str, Path]] | None:
    """(stable name, path) of every file :func:`code_version` hashes, sorted by name; None where a package's
    files cannot be listed (an install that is not plain files). Names are relative to each package, so a
    checkout's editable install and a wheel of the same code hash alike (a wheel nests ``baselines`` inside
    ``ee_formation_env``: it is walked once, as its own package)."""
    roots = {}
    for package in SOURCE_PACKAGES:
        spec = importlib.util.find_spec(package)
        if spec is None or not spec.submodule_search_locations:
            return None
        roots[package] = Path(list(spec.submodule_search_locations)[0]).resolve()
    files = []
    for package, root in roots.items():
        nested = [other for other in roots.values() if other != root and root in other.parents]
        for path in root.rglob("*"):
            name = f"{package}/{path.relative_to(root).as_posix()}"
            if (path.is_file() and path.suffix in SOURCE_SUFFIXES and "__pycache__" not in path.parts
                    and not any(folder in path.parents for folder in nested)
                    and not name.startswith(EXCLUDED_DATA)):
                files.append((name, path))
    files += [(f"studies/{path.name}", path) for path in STUDY_SOURCES if path.is_file()]
    return sorted(files)


@functools.lru_cache(maxsize=1)
def code_version() -> dict[str, Any]:
    """``{"package": the ee-formation-env version, "source": SHA-256 (16 hex digits) of the files of
    :func:`source_files`, or None where they cannot be read}``: the code a cell is computed by."""
    files = source_files()
    source = None
    if files:
        digest = hashlib.sha256()
        try:
            for name, path in files:
                digest.update(name.encode() + b"\0" + path.read_bytes() + b"\0")
            source = digest.hexdigest()[:16]
        except OSError:
            source = None
    return {"package": ee_formation_env.__version__, "source": source}


def _describe(code: Any) -> str:
    if not isinstance(code, Mapping):
        return "unstamped code (a cell from before cells carried their code version)"
    return f"ee-formation-env {code.get('package')} (source {code.get('source') or 'not hashed'})"


def stale_reason(record: Mapping[str, Any], protocol: Mapping[str, Any]) -> str | None:
    """Why the cached cell ``record`` is not this code's result for ``protocol`` (None if it is): another
    schema, another code version, or its method defined otherwise."""
    if record.get("schema") != CELL_SCHEMA:
        return f"cell schema {record.get('schema')} (this code writes {CELL_SCHEMA})"
    if record.get("code") != code_version():
        return f"computed by {_describe(record.get('code'))}, this is {_describe(code_version())}"
    if record.get("protocol") != _plain(protocol):
        return "its method was defined otherwise when it was computed"
    return None


def record_digest(record: Mapping[str, Any]) -> str:
    """SHA-256 of a cell record without its ``digest`` (canonical JSON): written into the cell, checked on every
    read, so that an edited or damaged cell (a changed metric, seed or episode length) is never aggregated.
    Integrity against accidents, not authenticity: anyone may re-sign an edit."""
    body = {key: value for key, value in record.items() if key != "digest"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, default=float).encode()).hexdigest()


def read_cell(path: Path) -> tuple[dict[str, Any] | None, str | None]:
    """The cell record at ``path``, or None and why it cannot be used (it does not parse, lacks a field, or its
    content does not match its digest; a cell of the current schema must carry one)."""
    try:
        if Path(path).is_symlink() or not Path(path).is_file():
            return None, "not a regular file"
        record = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as error:
        return None, f"unreadable ({str(error).splitlines()[0][:120] if str(error) else type(error).__name__})"
    if not isinstance(record, dict):
        return None, f"not a cell record (a JSON {type(record).__name__})"
    missing = [field for field in CELL_FIELDS if field not in record]
    if missing or not isinstance(record.get("episodes"), list):
        return None, f"not a complete cell record (missing {missing or ['episodes as a list']})"
    if not isinstance(record.get("eval_seeds"), list) or not all(
            isinstance(seed, int) and not isinstance(seed, bool) for seed in record["eval_seeds"]):
        return None, "eval_seeds: expected a list of integers"
    if record.get("schema") == CELL_SCHEMA and record.get("digest") != record_digest(record):
        return None, "its content does not match its digest (edited or damaged after it was written)"
    return record, None


def write_cell(path: Path, record: Mapping[str, Any], protocol: Mapping[str, Any]) -> dict[str, Any]:
    """Stamp ``record`` (schema, code version, protocol, digest) and write it atomically: a complete file or
    none. A write the file system refuses (or a folder at ``path``) is a
    :class:`~ee_formation_env.baselines.atomic_files.WriteRefused` naming the cell's file."""
    stamped = {**record, "schema": CELL_SCHEMA, "code": code_version(), "protocol": _plain(protocol)}
    stamped = json.loads(json.dumps(stamped, default=float))  # as it reads back (tuples as lists, NaN kept)
    stamped["digest"] = record_digest(stamped)
    make_folder(path.parent)
    write_text(path, json.dumps(stamped, indent=1, default=float))
    record, problem = read_cell(path)
    if record is None:
        raise OSError(f"{path}: the cell written does not read back ({problem})")
    return record


def check_cell_path(path: Path) -> None:
    """A :class:`~ee_formation_env.baselines.atomic_files.WriteRefused` (an ``OSError``) naming ``path`` if a cell
    cannot be written there (a folder, or a file on its way, stands there): said before the cell is computed, not
    after, and reported by the board like any refused write."""
    path = Path(path)
    if path.is_dir() and not path.is_symlink():
        raise WriteRefused(path, errno.EISDIR, "a folder stands where the cell's file goes: move it away, then run "
                           "again")
    blocking = next((parent for parent in path.parents if parent.exists() and not parent.is_dir()), None)
    if blocking is not None:
        raise WriteRefused(path, errno.ENOTDIR, f"{blocking} is a file, where a folder is expected: move it away, "
                           "then run again")


def cached_record(path: Path, label: str, protocol: Mapping[str, Any], progress: Callable[[str], None],
                  accept_stale: bool = False) -> dict[str, Any] | None:
    """The cell at ``path`` if it is this code's result (or stale, with ``accept_stale``), else None: the cell
    is to be computed. A corrupt file, or a stale one (:func:`stale_reason`), is reported in one line naming it; a
    path no cell can be written to is refused first (:func:`check_cell_path`)."""
    check_cell_path(path)
    if path.is_file():
        record, problem = read_cell(path)
        if record is not None:
            stale = stale_reason(record, protocol)
            if stale is None:
                progress(f"cached  {label}")
                return record
            if accept_stale:
                progress(f"stale   {label}: {path}: {stale}; kept (--accept-stale-cells)")
                return record
            progress(f"stale   {label}: {path}: {stale}; recomputing")
        else:
            progress(f"corrupt {label}: {path}: {problem}; recomputing")
    return None


def cached_cell(path: Path, label: str, protocol: Mapping[str, Any], compute: Callable[[], dict[str, Any]],
                progress: Callable[[str], None], accept_stale: bool = False) -> dict[str, Any]:
    """The cell at ``path`` if it is this code's result (:func:`cached_record`), else computed now and written
    (:func:`write_cell`)."""
    record = cached_record(path, label, protocol, progress, accept_stale)
    if record is not None:
        return record
    progress(f"running {label}")
    return write_cell(path, compute(), protocol)


def run_code_path(run_dir: Path) -> Path:
    """Where a learned cell's training run records the code that trains it: a hidden file beside the run's
    folder (the folder itself is replaced when a run starts again)."""
    return run_dir.with_name(f".{run_dir.name}.code.json")


def run_is_current(run_dir: Path, protocol: Mapping[str, Any]) -> bool:
    """Whether the run in ``run_dir`` was started by this code for ``protocol`` (its :func:`run_code_path`
    says so)."""
    try:
        stamp = json.loads(run_code_path(run_dir).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return False
    return stamp == {"code": code_version(), "protocol": _plain(protocol)}


def mark_run(run_dir: Path, protocol: Mapping[str, Any]) -> None:
    """Record that this code trains the run in ``run_dir`` for ``protocol`` (before it starts, so that a stopped
    run has it)."""
    path = run_code_path(run_dir)
    make_folder(path.parent)
    write_text(path, json.dumps({"code": code_version(), "protocol": _plain(protocol)}))


def _plain(value: Any) -> Any:
    """``value`` as JSON gives it back (tuples as lists), so that a protocol compares equal to its file."""
    return json.loads(json.dumps(value, default=str))
