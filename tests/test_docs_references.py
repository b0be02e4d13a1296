"""Every repository path and dotted name the documentation writes exists, so that the docs cannot point to
code that moved or never was.

What is read: the inline code of ``docs/*.md`` and of the files they include (``--8<-- "FILE"``), except the
changelog, whose entries name what existed when they were written; and the comments of the built-in
scenarios (``ee_formation_env/builtin/*.yaml``), whose references are bare words. Fenced code blocks are
examples (a user's ``my.yaml``), not references.

The rules, one per kind of word:

- **A repository path**: a word of path characters with a ``/`` whose first part is one of
  :data:`REPOSITORY_FOLDERS` (``baselines/reference/gains.py``, ``tests/``). It must exist under the
  repository root. ``<name>`` and ``*`` stand for any file name part and a final ``...`` for anything below:
  at least one file must match.
- **A generated output**: a path whose first part is one of :data:`GENERATED_OUTPUTS` (``results/``, ``runs/``)
  is written by a run, not kept in the repository: not checked.
- **Any other path** (``kuka_iiwa/model.urdf`` in ``pybullet_data``, a run's ``checkpoints/``, a relative
  ``learned/``) is not a repository path: not checked.
- **A dotted name** starting with one of :data:`PACKAGES` (``ee_formation_env.robots.ROBOTS``,
  ``studies.benchmarl_runs.run``; a call's ``(...)`` is dropped) must import: its longest importable module,
  then an attribute for each remaining part. A class or function must be named where it is defined or by a
  module that lists it in its ``__all__`` (``ee_formation_env.load_scenario``), not where it is merely imported.
- **A name placed in a file or module**: ```NAME` in `FILE.py``` needs ``NAME`` defined (not imported) in that
  file (a ``def``, ``class`` or assignment at any depth); a class, a constant or a call placed in a module,
  ```Name` (`MODULE`)```, ```NAME` (`MODULE`)``` or ```name(...)` (`MODULE`)```, needs ``NAME`` to be an
  attribute of that module (a lower-case ```key` (`MODULE`)``` is a key or a field the module documents).
- **A section reference** ``FILE, "Heading"`` (``docs/scenarios.md, "Scenario distributions"``, ``README`` for
  ``README.md``) needs that heading in that file.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import inspect
import re
import sys
import warnings
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))  # studies/ and benchmarks/ are top-level folders of the checkout

DOCS = REPO / "docs"
BUILTIN = REPO / "ee_formation_env" / "builtin"

#: Folders of the repository: a path starting with one of them must exist.
REPOSITORY_FOLDERS = ("ee_formation_env", "baselines", "studies", "benchmarks", "tests", "docs", "assets", ".ci")
#: Folders that runs write (``.gitignore``): a path starting with one of them is an output, not checked.
GENERATED_OUTPUTS = ("results", "runs")
#: Import names of the repository: a dotted name starting with one of them must resolve.
PACKAGES = ("ee_formation_env", "studies", "benchmarks")
#: Included by a docs page but not checked: its entries name what existed when they were written.
HISTORY = ("CHANGELOG.md",)

_PATH = re.compile(r"[\w.\-]+(?:/[\w.\-<>*]*)+")
_DOTTED = re.compile(rf"(?:{'|'.join(PACKAGES)})(?:\.\w+)+")
_SECTION = re.compile(r"([\w./\-]+\.md|README),\s+\"([^\"]+)\"")
_NAME_IN_FILE = re.compile(r"`(\w+)(?:\([^`]*\))?` in `([\w./\-]+\.py)`")
_NAME_IN_MODULE = re.compile(rf"`([A-Z]\w*|\w+(?=\())(?:\([^`]*\))?` \(`((?:{'|'.join(PACKAGES)})(?:\.\w+)+)`[,;)]")
_INCLUDE = re.compile(r'^--8<-- "([^"]+)"', re.M)


def _without_fences(text: str) -> str:
    return re.sub(r"^([ \t]*)```.*?^\1```[^\n]*", "", text, flags=re.M | re.S)


def placements(text: str) -> list[tuple[str, str]]:
    """The ``("in_file" | "in_module", "NAME|WHERE")`` placements a Markdown text states, fenced blocks left out."""
    text = _without_fences(text)
    return ([("in_file", f"{name}|{where}") for name, where in _NAME_IN_FILE.findall(text)]
            + [("in_module", f"{name}|{where}") for name, where in _NAME_IN_MODULE.findall(text)])


def inline_code(text: str) -> list[str]:
    """The inline code spans of a Markdown text, fenced blocks left out."""
    return re.findall(r"`([^`\n]+)`", _without_fences(text))


def yaml_comments(text: str) -> str:
    """The comments of a YAML text (what follows ``#`` on each line), one per line."""
    return "\n".join(line.split("#", 1)[1] for line in text.splitlines() if "#" in line)


def references(text: str) -> list[tuple[str, str]]:
    """The ``(kind, word)`` references in a run of text: ``"path"``, ``"dotted"`` or ``"section"`` (the word
    ``FILE|Heading``), by the module docstring's rules; other words are not references."""
    found = [("section", f"{file}|{' '.join(heading.split())}") for file, heading in _SECTION.findall(text)]
    for word in re.split(r"[\s=,;()\"'\[\]]+", text):
        word = word if word.endswith("...") else word.rstrip(".:")
        if _PATH.fullmatch(word) and word.split("/")[0] in REPOSITORY_FOLDERS:
            found.append(("path", word))
        elif (match := _DOTTED.match(word)) and "/" not in word:
            found.append(("dotted", match.group(0)))
    return found


def path_problem(word: str) -> str | None:
    """Why the repository path ``word`` does not exist, or None if it does."""
    pattern = re.sub(r"<[^>]*>", "*", word.removesuffix("...")).rstrip("/")
    if "*" in pattern:
        return None if any(REPO.glob(pattern)) else "no file matches"
    return None if (REPO / pattern).exists() else "no such file or folder"


def dotted_problem(name: str) -> str | None:
    """Why the dotted name ``name`` does not resolve (or names a class or function away from its home)."""
    parts = name.split(".")
    for split in range(len(parts), 0, -1):
        module_name = ".".join(parts[:split])
        try:
            spec = importlib.util.find_spec(module_name)
        except ModuleNotFoundError:  # a parent part is not a package
            continue
        if spec is not None:
            break
    else:
        return "no such module"
    rest = parts[split:]
    try:
        with warnings.catch_warnings():  # a deprecated alias module warns on import: naming it is no fault
            warnings.simplefilter("ignore", DeprecationWarning)
            target = importlib.import_module(module_name)
    except ModuleNotFoundError as error:  # an optional dependency (the torchrl extra) is not installed
        if error.name.split(".")[0] in PACKAGES:
            raise
        names = _top_level_names(Path(spec.origin))
        return f"{module_name} has no attribute {rest[0]!r}" if rest and rest[0] not in names else None
    for depth, attribute in enumerate(rest, start=split):
        if not hasattr(target, attribute):
            return f"{'.'.join(parts[:depth])} has no attribute {attribute!r}"
        target = getattr(target, attribute)
    if rest and (inspect.isclass(target) or inspect.isfunction(target)):
        home = f"{target.__module__}.{target.__qualname__}"
        public = len(rest) == 1 and rest[0] in getattr(sys.modules[module_name], "__all__", ())
        if home != name and not public:
            return f"defined as {home}"
    return None


def _top_level_names(source: Path) -> set[str]:
    """The names a module's source defines or imports at its top level (read without importing it)."""
    names: set[str] = set()
    for node in ast.parse(source.read_text(encoding="utf-8")).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names.update(target.id for target in targets if isinstance(target, ast.Name))
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update((alias.asname or alias.name).split(".")[0] for alias in node.names)
    return names


def in_file_problem(reference: str) -> str | None:
    name, file = reference.split("|")
    if path_problem(file):
        return f"no such file {file}"
    return None if name in _defined_names(REPO / file) else f"{file} does not define {name}"


def _defined_names(source: Path) -> set[str]:
    """Every name a source file defines (functions, classes, assigned names and attributes), at any depth."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(source.read_text(encoding="utf-8"))):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            names.add(node.id)
    return names


def in_module_problem(reference: str) -> str | None:
    name, module = reference.split("|")
    return dotted_problem(f"{module}.{name}") and f"{module} has no attribute {name!r}"


def section_problem(reference: str) -> str | None:
    file, heading = reference.split("|")
    path = REPO / ("README.md" if file == "README" else file)
    if not path.is_file():
        return f"no such file {file}"
    headings = {line.lstrip("#").strip() for line in path.read_text(encoding="utf-8").splitlines()
                if line.startswith("#")}
    return None if heading in headings else f"{file} has no heading {heading!r}"


PROBLEM = {"path": path_problem, "dotted": dotted_problem, "section": section_problem,
           "in_file": in_file_problem, "in_module": in_module_problem}


def markdown_references(text: str) -> list[tuple[str, str]]:
    """The references of a Markdown text: those in its inline code, and its placements."""
    return [ref for span in inline_code(text) for ref in references(span)] + placements(text)


def documentation_references() -> dict[str, list[tuple[str, str]]]:
    """Source name -> the ``(kind, word)`` references read from it (module docstring)."""
    found: dict[str, list[tuple[str, str]]] = {}
    for page in sorted(DOCS.glob("*.md")):
        text = page.read_text(encoding="utf-8")
        found[f"docs/{page.name}"] = markdown_references(text)
        for included in _INCLUDE.findall(text):
            if included not in HISTORY:
                found[included] = markdown_references((REPO / included).read_text(encoding="utf-8"))
    for scenario in sorted(BUILTIN.glob("*.yaml")):
        comments = yaml_comments(scenario.read_text(encoding="utf-8"))
        found[f"ee_formation_env/builtin/{scenario.name}"] = references(comments)
    return found


def broken_references(found: dict[str, list[tuple[str, str]]]) -> list[str]:
    """``"source: word (why)"`` for each reference in ``found`` that does not exist."""
    broken = []
    for source, refs in found.items():
        for kind, word in dict.fromkeys(refs):
            problem = PROBLEM[kind](word)
            if problem:
                broken.append(f"{source}: {word.replace('|', ', ')} ({problem})")
    return broken


def test_every_reference_in_the_docs_and_the_builtin_comments_exists():
    broken = broken_references(documentation_references())
    assert not broken, "references to nothing:\n" + "\n".join(broken)


def test_the_docs_do_have_references_to_check():
    kinds = {kind for refs in documentation_references().values() for kind, _ in refs}
    assert kinds == set(PROBLEM)


def test_generated_outputs_are_ignored_by_git_and_repository_folders_are_not():
    ignored = {line.strip().strip("/") for line in (REPO / ".gitignore").read_text(encoding="utf-8").splitlines()}
    assert set(GENERATED_OUTPUTS) <= ignored
    assert not set(REPOSITORY_FOLDERS) & ignored
    assert all((REPO / folder).is_dir() for folder in REPOSITORY_FOLDERS)


# -- the extractor itself: it finds what it should, and only that ------------------------------------------
def test_inline_code_leaves_fenced_blocks_out():
    text = "See `tests/a.py`.\n\n```yaml\nurdf: `tests/b.py`\n```\n\n    ```bash\n    `tests/c.py`\n    ```\n"
    assert inline_code(text) == ["tests/a.py"]


def test_references_classifies_words_by_the_rules():
    found = references("baselines/reference/gains.py and `runs/<name>/`, kuka_iiwa/model.urdf, learned/, "
                       "ee_formation_env.parallel_env(scenario) or studies.scoreboard; results/x.json "
                       "(docs/scenarios.md, \"Scenario distributions\") tests/... my.yaml residual.ResidualActionEnv")
    assert found == [("section", "docs/scenarios.md|Scenario distributions"),
                     ("path", "baselines/reference/gains.py"), ("dotted", "ee_formation_env.parallel_env"),
                     ("dotted", "studies.scoreboard"), ("path", "docs/scenarios.md"), ("path", "tests/...")]


@pytest.mark.parametrize("word, problem", [
    ("baselines/gains.py", "no such file or folder"),
    ("tests/baselines/learned/test_nothing.py", "no such file or folder"),
    ("ee_formation_env/builtin/<name>.json", "no file matches"),
    ("baselines/reference/gains.py", None),
    ("ee_formation_env/builtin/<name>.yaml", None),
    ("tests/...", None),
])
def test_path_problem(word, problem):
    assert path_problem(word) == problem


@pytest.mark.parametrize("name, problem", [
    ("ee_formation_env.nothing", "ee_formation_env has no attribute 'nothing'"),
    ("ee_formation_env.robots.NOTHING", "ee_formation_env.robots has no attribute 'NOTHING'"),
    ("ee_formation_env.scenario.RobotSpec", "defined as ee_formation_env.robots.RobotSpec"),
    ("ee_formation_env.robots.RobotSpec", None),
    ("ee_formation_env.robots.ROBOTS", None),
    ("ee_formation_env.load_scenario", None),
    ("ee_formation_env.scenario_sets", None),
])
def test_dotted_problem(name, problem):
    assert dotted_problem(name) == problem


def test_section_problem():
    assert section_problem("README|Quick start") is None
    assert section_problem("README|Deviations") == "README has no heading 'Deviations'"
    assert section_problem("docs/nothing.md|Format") == "no such file docs/nothing.md"


def test_placements_are_checked_where_they_say():
    text = ("Add a `RobotSpec` to `ROBOTS` in `ee_formation_env/scenario.py`; build it in "
            "`make_training_env(..., mode=...)` (`ee_formation_env.baselines.learned.residual`), or "
            "`make_training_env()` (`ee_formation_env.baselines.learned.training_env`), the `sensing` key "
            "(`ee_formation_env.sensing`).")
    assert placements(text) == [("in_file", "ROBOTS|ee_formation_env/scenario.py"),
                                ("in_module", "make_training_env|ee_formation_env.baselines.learned.residual"),
                                ("in_module", "make_training_env|ee_formation_env.baselines.learned.training_env")]
    assert in_file_problem("ROBOTS|ee_formation_env/scenario.py") == (
        "ee_formation_env/scenario.py does not define ROBOTS")
    assert in_file_problem("ROBOTS|ee_formation_env/robots.py") is None
    assert in_module_problem("make_training_env|ee_formation_env.baselines.learned.residual") == (
        "ee_formation_env.baselines.learned.residual has no attribute 'make_training_env'")
    assert in_module_problem("BatchedTrainingEnv|ee_formation_env.baselines.learned.training_env") is None


def test_a_planted_wrong_path_is_reported_with_its_source():
    found = {"docs/page.md": markdown_references("Gains: `baselines/gains.py`; outputs in `results/x.json`.")}
    assert broken_references(found) == ["docs/page.md: baselines/gains.py (no such file or folder)"]
    comments = {"ee_formation_env/builtin/x.yaml": references(yaml_comments("a: 1  # derived (baselines/gains.py).\n"))}
    assert broken_references(comments) == [
        "ee_formation_env/builtin/x.yaml: baselines/gains.py (no such file or folder)"]
