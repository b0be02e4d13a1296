"""Every Python block of docs/ and README.md runs as written, so that no snippet raises where a reader runs it.

A page's blocks run in order, in one fresh Python process (a block may use what an earlier block of its page
defined; a snippet that registers something cannot leak into other tests), from a scratch folder holding
``my_scenario.yaml`` (a copy of ``planar_square``) for the snippets that load "a file". An HTML comment on
the line before a block's fence says how to treat it:

- ``<!-- snippet: no-run (why) -->``: not run, with the reason (a training run, a fragment);
- ``<!-- snippet: raises ValueError -->``: it must raise that exception (a block that shows an error);
- ``<!-- snippet: needs MODULE -->``: run where MODULE (an optional extra) is installed, else left out.
"""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from ee_formation_env.builtin import _FILES

ROOT = Path(__file__).resolve().parent.parent
PAGES = sorted((ROOT / "docs").glob("*.md")) + [ROOT / "README.md"]
BLOCK = re.compile(r"(?:^<!-- snippet: (?P<mark>[^\n]*?) -->\n)?^(?P<indent> *)```python[^\n]*\n(?P<code>.*?)^(?P=indent)```",
                   re.S | re.M)
MARK = re.compile(r"no-run \((?P<reason>.*\S.*)\)|raises (?P<error>\w+)|needs (?P<module>[\w.]+)")


def _blocks(page: Path) -> list[tuple[int, dict[str, str], str]]:
    """(line, mark fields, dedented code) of every Python block of ``page``."""
    text = page.read_text(encoding="utf-8")
    blocks = []
    for match in BLOCK.finditer(text):
        line = text.count("\n", 0, match.start("indent")) + 1
        mark = match.group("mark")
        fields = {}
        if mark is not None:
            parsed = MARK.fullmatch(mark)
            assert parsed, f"{page.name}:{line}: unknown snippet mark {mark!r}"
            fields = {key: value for key, value in parsed.groupdict().items() if value}
        blocks.append((line, fields, textwrap.dedent(match.group("code"))))
    return blocks


def _script(page: Path) -> tuple[str, list[str]]:
    """The page's runnable blocks as one script, and what was left out (and why)."""
    parts, left_out = [], []
    for line, fields, code in _blocks(page):
        where = f"{page.name}:{line}"
        if "reason" in fields:
            left_out.append(f"{where}: {fields['reason']}")
            continue
        if "module" in fields and importlib.util.find_spec(fields["module"]) is None:
            left_out.append(f"{where}: needs {fields['module']}")
            continue
        parts.append(f"print({where!r}, flush=True)\n")
        if "error" in fields:
            parts.append("try:\n" + textwrap.indent(code, "    ") + f"except {fields['error']}:\n    pass\nelse:\n"
                         f"    raise AssertionError({where!r} + ': expected {fields['error']}')\n")
        else:
            parts.append(code)
    return "".join(parts), left_out


def test_every_python_block_is_found_and_each_mark_is_understood():
    counted = {page.name: len(_blocks(page)) for page in PAGES}
    text_counts = {page.name: page.read_text(encoding="utf-8").count("```python") for page in PAGES}
    assert counted == text_counts  # no block escapes the pattern (every one is run or marked)
    assert sum(counted.values()) > 10


def test_a_no_run_mark_needs_its_reason():
    assert MARK.fullmatch("no-run") is None and MARK.fullmatch("no-run ()") is None
    assert MARK.fullmatch("no-run (a training run)").group("reason") == "a training run"


@pytest.mark.parametrize("page", [page for page in PAGES if _blocks(page)], ids=lambda page: page.name)
def test_the_python_blocks_of_the_page_run(page, tmp_path):
    script, left_out = _script(page)
    if not script:
        pytest.skip(f"no block of {page.name} runs here: {left_out}")
    (tmp_path / "my_scenario.yaml").write_text((_FILES / "planar_square.yaml").read_text(encoding="utf-8"),
                                               encoding="utf-8")
    (tmp_path / "snippets.py").write_text(script, encoding="utf-8")
    result = subprocess.run([sys.executable, "snippets.py"], cwd=tmp_path, capture_output=True, text=True,
                            timeout=600, env=_environment())
    assert result.returncode == 0, f"{page.name}: a block failed (the last line printed is its place):\n" \
                                   f"{result.stdout[-2000:]}\n{result.stderr[-4000:]}"


def _environment() -> dict[str, str]:
    """This process's environment with the checkout first on the import path (``studies``, ``benchmarks``)."""
    import os

    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}


#: Code that trains: with worker processes started by ``spawn``, which re-imports the main script in each.
TRAINS = re.compile(r"(?<![\w.])train\(|\.learn\(|\bExperiment\(|\btrain_command\(")


def test_every_block_that_trains_keeps_its_training_under_the_main_guard():
    """A reader's script that trains at its top level would train again in every spawned worker (the run then
    stops at its start-up, saying so): each snippet that trains shows the guard."""
    unguarded = [f"{page.name}:{line}" for page in PAGES for line, _, code in _blocks(page)
                 if TRAINS.search(code) and 'if __name__ == "__main__":' not in code]
    assert not unguarded, f"training snippets without `if __name__ == \"__main__\":`: {unguarded}"
    assert sum(bool(TRAINS.search(code)) for page in PAGES for _, _, code in _blocks(page)) >= 3
