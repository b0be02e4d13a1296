"""The documentation's generated tables agree with the code, so that they cannot go stale.

Each generated table sits in a docs page between ``<!-- generated: NAME -->`` and ``<!-- end generated -->``;
on a mismatch the test prints the block to paste. The README keeps only links, the built-in table and the
quick start, checked here too.
"""

from __future__ import annotations

import re
from dataclasses import fields
from pathlib import Path

import pytest

from ee_formation_env.baselines.learned.config import TrainConfig
from ee_formation_env.baselines.learned.recipes import recipes_table

import ee_formation_env
from ee_formation_env.baselines.metrics import metric_definitions
from ee_formation_env.baselines.reference.tuned import tuned_gains_table
from ee_formation_env.scenario import Scenario, _default, scenario_keys_table

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
README = ROOT / "README.md"


def _inline_rst(text: str) -> str:
    """reStructuredText inline markup of one cell as Markdown: roles and ``literals`` to `code`, pipes escaped."""
    text = re.sub(r":\w+:`~?([^`]+)`", r"``\1``", text)
    parts = re.split(r"(``[^`]+``)", text)
    return "".join(f"`{part[2:-2]}`" if part.startswith("``") else part.replace("|", "\\|") for part in parts)


def rst_simple_table_to_markdown(table: str) -> str:
    """A reStructuredText simple table (one line per row) as a Markdown table."""
    lines = [line for line in table.strip("\n").splitlines()]
    border = lines[0]
    spans = [(match.start(), match.end()) for match in re.finditer(r"=+", border)]

    def cells(line: str) -> list[str]:
        bounds = [start for start, _ in spans] + [None]
        return [line[bounds[k]:bounds[k + 1]].strip() for k in range(len(spans))]

    header, *rows = [line for line in lines if not re.fullmatch(r"[= ]+", line)]
    out = ["| " + " | ".join(cells(header)) + " |", "|" + "---|" * len(spans)]
    out += ["| " + " | ".join(_inline_rst(cell) for cell in cells(row)) + " |" for row in rows]
    return "\n".join(out)


GENERATED = {
    "scenario_keys_table": ("scenarios.md", lambda: rst_simple_table_to_markdown(scenario_keys_table())),
    "train_flags": ("training.md", lambda: TrainConfig.flags_table()),
    "recipes": ("training.md", lambda: recipes_table()),
    "metric_definitions": ("results.md", lambda: metric_definitions(markdown=True)),
    "tuned_gains": ("controllers.md", lambda: tuned_gains_table()),
}


def _generated_block(page: str, name: str) -> str:
    text = (DOCS / page).read_text(encoding="utf-8")
    match = re.search(rf"<!-- generated: {name} -->\n(.*?)\n<!-- end generated -->", text, re.S)
    assert match, f"docs/{page} has no generated block {name!r}"
    return match.group(1).strip()


@pytest.mark.parametrize("name", sorted(GENERATED))
def test_generated_tables_match_the_code(name):
    page, make = GENERATED[name]
    expected = make().strip()
    assert _generated_block(page, name) == expected, (
        f"docs/{page} is stale; replace its {name} block with:\n\n{expected}\n")


def test_metric_definitions_have_one_home_the_training_page_links_to_it():
    """train.py's comparison.md has the evaluation's columns: the training page points to their one table."""
    training = (DOCS / "training.md").read_text(encoding="utf-8")
    assert "<!-- generated: metric_definitions -->" not in training
    assert "[Results](results.md#metrics)" in training
    assert _generated_block("results.md", "metric_definitions") == metric_definitions(markdown=True).strip()


def _key_rows(page: str) -> dict[str, str]:
    rows = {}
    for line in (DOCS / page).read_text(encoding="utf-8").splitlines():
        match = re.match(r"\| `(\w+)` \| ([^|]*) \|", line)
        if match and match.group(1) in {spec.name for spec in fields(Scenario)}:
            rows.setdefault(match.group(1), match.group(2).strip())
    return rows


def test_scenarios_page_lists_every_scenario_key():
    assert {spec.name for spec in fields(Scenario)} - {"name"} <= set(_key_rows("scenarios.md"))


@pytest.mark.parametrize("key", ["physics_hz", "initial_q_noise", "joint_damping", "max_joint_velocity",
                                 "singularity_threshold"])
def test_scenarios_page_numeric_defaults_match_the_dataclass(key):
    value = _key_rows("scenarios.md")[key].split()[0]
    assert float(value) == _default(key)


def test_generated_table_has_a_row_per_key():
    table = scenario_keys_table()
    for spec in fields(Scenario):
        if spec.name != "name":
            assert f"``{spec.name}``" in table


def test_every_builtin_scenario_is_shown_with_its_image():
    page = (DOCS / "scenarios.md").read_text(encoding="utf-8")
    readme = README.read_text(encoding="utf-8")
    for name in ee_formation_env.BUILTIN_SCENARIOS:
        assert f"figures/scenario_{name}.png" in page
        assert (DOCS / "figures" / f"scenario_{name}.png").is_file()
        assert f"`{name}`" in readme


def test_readme_quick_start_is_the_ci_test_command():
    """.ci/run's step 1 is exactly the README's test command, and the README stays short."""
    command = 'pip install torch==2.13.0 && pip install -e ".[test,train]" && python -m pytest -q'
    readme = README.read_text(encoding="utf-8")
    assert command in readme
    assert command in (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert 'pip install torch==2.13.0 && pip install -e ".[train]" && python train.py' in readme
    assert len(readme.splitlines()) <= 150


def test_every_page_is_in_the_navigation():
    nav = (ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    for page in DOCS.glob("*.md"):
        assert f": {page.name}" in nav, f"docs/{page.name} is not in mkdocs.yml's nav"


def test_the_api_reference_shows_field_defaults_as_values_not_private_helper_calls():
    """mkdocstrings renders a dataclass field's default from its source: the docs' griffe extension turns
    ``_key("distance", ...)`` (and ``_option``) into the value, so no signature shows a private call."""
    griffe = pytest.importorskip("griffe")
    import importlib.util

    spec = importlib.util.spec_from_file_location("griffe_layout", DOCS / "hooks" / "griffe_layout.py")
    hooks = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hooks)
    loaded = griffe.load("ee_formation_env.scenario", search_paths=[str(ROOT)],
                         extensions=griffe.load_extensions(hooks.PublicDefaults))
    members = loaded["Scenario"].members
    assert str(members["formation"].value) == "'distance'"
    assert str(members["reward"].value) == "RewardConfig()" and str(members["controller_gains"].value) == "None"
    assert not [name for name, member in members.items()
                if getattr(member, "value", None) is not None and str(member.value).startswith("_")]


#: The most lines a rendered docs page may have (``--8<--`` snippets expanded): a page past it is cut down to its
#: rules and current figures, the history moving to the lab's notes (studies/notes/).
MAX_PAGE_LINES = 400
#: Pages the limit does not hold for, each with the reason.
LONG_PAGES = {
    "api.md": "generated from the docstrings by mkdocstrings",
    "scoreboard-tables.md": "only the board's generated tables (a few lines of prose, held below)",
}
#: The most lines of prose (outside the generated blocks) a page of LONG_PAGES's generated tables may have.
MAX_TABLES_PAGE_PROSE = 12
#: The most lines docs/*.md may have in all (snippets expanded, the headline's generated tables included; the page of
#: the board's per-scenario tables, data rather than prose, left out).
MAX_DOCS_LINES = 3_500
_SNIPPET = re.compile(r'^--8<-- "([^"]+)"$', re.M)
_GENERATED_BLOCK = re.compile(r"<!-- generated: [\w-]+ -->\n.*?<!-- end generated -->", re.S)


def _rendered(page: Path) -> str:
    """The page's Markdown with its ``--8<--`` snippets expanded (paths relative to the repository)."""
    return _SNIPPET.sub(lambda match: (ROOT / match.group(1)).read_text(encoding="utf-8").rstrip("\n"),
                        page.read_text(encoding="utf-8"))


def test_every_docs_page_stays_short():
    lines = {page.name: len(_rendered(page).splitlines()) for page in sorted(DOCS.glob("*.md"))}
    too_long = {name: count for name, count in lines.items() if count > MAX_PAGE_LINES and name not in LONG_PAGES}
    assert not too_long, f"pages over {MAX_PAGE_LINES} lines (move their history to studies/notes/): {too_long}"
    prose = len(_GENERATED_BLOCK.sub("", _rendered(DOCS / "scoreboard-tables.md")).splitlines())
    assert prose <= MAX_TABLES_PAGE_PROSE, f"docs/scoreboard-tables.md has {prose} lines outside its generated tables"
    assert set(LONG_PAGES) <= set(lines), "LONG_PAGES names a page that does not exist"
    total = sum(count for name, count in lines.items() if name != "scoreboard-tables.md")
    assert total <= MAX_DOCS_LINES, f"docs/*.md have {total} lines in all (scoreboard-tables.md left out)"


def test_the_command_tables_list_exactly_the_commands_that_exist():
    """getting-started.md lists the installed command's subcommands and the lab's, each once, as the parsers have them."""
    from ee_formation_env.baselines.cli import COMMANDS as LIBRARY_COMMANDS
    from studies.__main__ import COMMANDS as LAB_COMMANDS

    text = (DOCS / "getting-started.md").read_text(encoding="utf-8")
    library_table = text[text.index("| command | same as | what |"):].split("\n\n")[0]
    library = re.findall(r"^\| `ee-formation (\w+)", library_table, re.M)
    assert sorted(library) == sorted(LIBRARY_COMMANDS)
    lab_table = text[text.index("| lab command | what |"):].split("\n\n")[0]
    lab = [name for cell in re.findall(r"^\| (`[^|]+`) \|", lab_table, re.M) for name in re.findall(r"`([\w-]+)`", cell)]
    assert sorted(lab) == sorted(LAB_COMMANDS)
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    stale = [name for name in LAB_COMMANDS if f"ee-formation {name}" in readme + text]
    assert not stale, f"lab commands written as ee-formation commands: {stale}"
