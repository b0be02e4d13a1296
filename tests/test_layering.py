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
