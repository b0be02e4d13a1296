"""The layering of the code, read from its imports: the env core <- its framework integrations <- the reference
controllers <- the learning tools <- the studies, benchmarks and ``train.py``; no import circle among modules."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def module_name(path: Path) -> str:
    """The import name of a source file of the checkout (``baselines/`` is ``ee_formation_env.baselines``)."""
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[0] == "baselines":
        parts = ["ee_formation_env", *parts]
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def imports(path: Path, top_level_only: bool = False) -> set[str]:
    """Every module ``path`` imports at run time (``from x import y`` counts as ``x`` and ``x.y``): function-level
    imports too, unless ``top_level_only``; never those under ``if TYPE_CHECKING:`` (annotations only)."""
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):  # drop the type-checking blocks
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING":
            node.body = []
    nodes = tree.body if top_level_only else ast.walk(tree)
    found: set[str] = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
    return found


def sources(*folders: str) -> list[Path]:
    return sorted(path for folder in folders for path in (REPO / folder).rglob("*.py"))


def imported_project_modules(path: Path, top_level_only: bool = False) -> set[str]:
    prefixes = ("ee_formation_env", "baselines", "studies", "benchmarks", "train")
    return {name for name in imports(path, top_level_only) if name.split(".")[0] in prefixes}


MAX_MODULE_LINES = 600  # a module past this is split by concept (docs/extending.md, "Where code goes")


def test_no_module_outside_the_tests_is_over_600_lines():
    long = {str(path.relative_to(REPO)): count
            for path in [*sources("ee_formation_env", "baselines", "studies", "benchmarks"), REPO / "train.py"]
            if (count := len(path.read_text().splitlines())) > MAX_MODULE_LINES}
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"


def test_the_env_core_and_its_integrations_never_import_the_baselines_or_what_stands_above():
    for path in sources("ee_formation_env"):
        above = {name for name in imported_project_modules(path)
                 if name.startswith(("ee_formation_env.baselines", "baselines", "studies", "benchmarks", "train"))}
        assert not above, f"{path.relative_to(REPO)} imports {sorted(above)}"


def test_the_reference_controllers_never_import_the_learning_tools():
    for path in [*sources("baselines/reference"), REPO / "baselines" / "__init__.py", REPO / "baselines" / "metrics.py"]:
        above = {name for name in imported_project_modules(path)
                 if name.startswith(("ee_formation_env.baselines.learned", "studies", "benchmarks", "train"))}
        assert not above, f"{path.relative_to(REPO)} imports {sorted(above)}"


def test_the_library_never_imports_studies_benchmarks_or_the_script():
    for path in sources("ee_formation_env", "baselines"):
        above = {name for name in imported_project_modules(path)
                 if name.split(".")[0] in ("studies", "benchmarks", "train", "baselines")}
        assert not above, f"{path.relative_to(REPO)} imports {sorted(above)}"


def test_no_import_circle_among_modules():
    graph: dict[str, set[str]] = {}
    for path in sources("ee_formation_env", "baselines", "studies", "benchmarks"):
        graph[module_name(path)] = imported_project_modules(path)  # lazy imports too: a circle all the same
    modules = set(graph)
    edges = {name: {target for target in targets if target in modules and target != name}
             for name, targets in graph.items()}
    for name in edges:  # a package's __init__ importing its own submodules is no circle
        edges[name] = {target for target in edges[name] if not target.startswith(name + ".")}
    state: dict[str, int] = {}

    def visit(node: str, trail: list[str]) -> None:
        state[node] = 1
        for target in sorted(edges[node]):
            if state.get(target) == 1:
                pytest.fail("import circle: " + " -> ".join([*trail[trail.index(target):], target]))
            if target not in state:
                visit(target, [*trail, target])
        state[node] = 2

    assert "ee_formation_env.validation" in graph["ee_formation_env.task"]  # the walk sees function-level imports
    for name in sorted(edges):
        if name not in state:
            visit(name, [name])


@pytest.mark.parametrize("old", ["ee_formation_env.sb3", "ee_formation_env.centralized",
                                 "ee_formation_env.torchrl_env", "ee_formation_env.benchmarl_task"])
def test_the_removed_alias_modules_are_gone(old):
    """The integrations live in ee_formation_env.integrations only (their aliases never reached a release)."""
    import importlib

    with pytest.raises(ModuleNotFoundError):
        importlib.import_module(old)


_NO_TOP_LEVEL_BASELINES = """
import sys
from ee_formation_env.baselines.cli import main
main({argv!r})
assert not [m for m in sys.modules if m == "baselines" or m.startswith("baselines.")], "a top-level baselines"
assert "ee_formation_env.baselines" in sys.modules
print("ok")
"""


@pytest.mark.parametrize("argv", [
    ["evaluate", "--policy", "gradient", "--episodes", "1", "--set", "episode_seconds=0.2"],
])
def test_documented_commands_import_no_top_level_baselines(argv, tmp_path):
    result = subprocess.run([sys.executable, "-c", _NO_TOP_LEVEL_BASELINES.format(argv=argv)], cwd=tmp_path,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    assert result.stdout.strip().endswith("ok")


def test_the_folder_is_importable_under_one_name_only():
    result = subprocess.run([sys.executable, "-c", "import baselines"], cwd=REPO, capture_output=True, text=True,
                            timeout=60)
    assert result.returncode != 0 and "ee_formation_env.baselines" in result.stderr


# A module reads another module's objects through their public API only: no ``x._name`` of another module's
# object. Each exception is another library's private API that the code has to use (none of this project's).
FOREIGN_PRIVATE_READS = {
    ("ee_formation_env/inputs.py", "sys._getframe"): "CPython's frame walk: a warning's stacklevel",
    ("baselines/learned/checkpoint.py", "model._n_updates"): "SB3 keeps its update count there; a resume sets it",
    ("baselines/learned/benchmarl_task.py", "model.mlp._empty_net"): "TorchRL's MLP layers, to export its weights",
    ("benchmarks/run.py", "model._setup_learn"): "SB3's set-up of a learn() call, timed without the learning",
}
NAMEDTUPLE_API = {"_replace", "_asdict", "_fields", "_make", "_field_defaults"}  # public despite the underscore


def own_private_names(tree: ast.Module) -> set[str]:
    """The private names a module defines: its functions and classes, its module-level names and the attributes
    its code sets on ``self``/``cls`` (another instance of its own classes may read those)."""
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store) \
                and isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"):
            names.add(node.attr)
    for node in tree.body:
        targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(
            node, ast.AnnAssign) else []
        names.update(target.id for target in targets if isinstance(target, ast.Name))
    return names


def private_reads(source: str) -> list[str]:
    """Every ``x._name`` of ``source`` (one underscore) on another module's object: ``x`` is not ``self``, ``cls``
    or ``super()``, and ``_name`` is none of the module's own private names."""
    tree = ast.parse(source)
    own = own_private_names(tree)
    found = []
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")):
            continue
        value = node.value
        if isinstance(value, ast.Name) and value.id in ("self", "cls"):
            continue
        if isinstance(value, ast.Call) and isinstance(value.func, ast.Name) and value.func.id == "super":
            continue
        if node.attr not in own and node.attr not in NAMEDTUPLE_API:
            found.append(ast.unparse(node))
    return found


def test_the_private_read_check_sees_reads_across_modules():
    source = ("class A:\n    def __init__(self):\n        self._mine = 1\n    def same(self, other):\n"
              "        return other._mine + self._mine\n"
              "def f(env):\n    return env.batch._worlds[0], super()._x, env.__dict__, result._replace()\n")
    assert private_reads(source) == ["env.batch._worlds"]


def test_no_module_reads_a_private_attribute_of_another_modules_object():
    found = {}
    for path in sources("ee_formation_env", "baselines", "studies", "benchmarks"):
        name = str(path.relative_to(REPO))
        reads = [read for read in private_reads(path.read_text()) if (name, read) not in FOREIGN_PRIVATE_READS]
        if reads:
            found[name] = sorted(set(reads))
    assert not found, f"private attributes read across modules (use or add a public API): {found}"
    unused = [key for key in FOREIGN_PRIVATE_READS
              if key[1] not in private_reads((REPO / key[0]).read_text())]
    assert not unused, f"exceptions no longer needed: {unused}"
