"""The lab's command, ``python -m studies COMMAND``: every study under one name, each with its own flags."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pytest

from studies.__main__ import COMMANDS, main

REPO = Path(__file__).resolve().parents[2]


def test_every_study_with_a_main_is_a_command_and_every_command_is_a_study():
    studies = {path.stem for path in (REPO / "studies").glob("*.py")
               if not path.stem.startswith("_") and "\ndef main(" in path.read_text(encoding="utf-8")}
    assert {module for module, _ in COMMANDS.values()} == studies


def test_a_command_runs_its_study_and_reports_bad_input_in_one_line(capsys):
    assert main(["random-scenarios", "--seeds", "0"]) == 2
    assert capsys.readouterr().err.splitlines()[-1] == "error: --seeds: expected 1 to 50, got 0"
    with pytest.raises(SystemExit) as exit_info:
        main(["sensing", "--help"])
    assert exit_info.value.code == 0
    assert "usage: python -m studies.sensing" in capsys.readouterr().out


def test_an_unknown_command_is_a_usage_error_listing_the_commands(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["fly"])
    assert exit_info.value.code == 2
    assert "scoreboard" in capsys.readouterr().err


def test_the_lab_runs_as_a_module_from_the_checkout():
    result = subprocess.run([sys.executable, "-m", "studies", "--help"], cwd=REPO, capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0
    assert all(name in result.stdout for name in COMMANDS)


class _Parsed(Exception):
    """Raised instead of parsing: carries the parser a study built."""


def test_every_flag_of_every_lab_command_has_help_text(monkeypatch):
    import importlib

    def capture(self, args=None, namespace=None):
        raise _Parsed(self)

    monkeypatch.setattr(argparse.ArgumentParser, "parse_known_args", capture)
    missing = []
    for name, (module, _) in COMMANDS.items():
        try:
            study = importlib.import_module(f"studies.{module}")
        except ImportError:  # an optional stack (benchmarl_runs: the torchrl extra) not installed here
            continue
        with pytest.raises(_Parsed) as parsed:
            study.main([])
        missing += [f"{name} {'/'.join(action.option_strings) or action.dest}"
                    for action in parsed.value.args[0]._actions if not (action.help or "").strip()]
    assert not missing, f"flags without help: {missing}"
